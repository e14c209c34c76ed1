"""Self-calibration (stages/calibration) with injected C-arm errors: recovered against injected geometry error → docs/benchmarks/calibration.md.

Simulated pairs: a synthetic vessel tree (stages.calibration.synthetic) seen from the C-arm angles of
the phantom's run pairs; the true cameras are the header cameras with injected per-run errors (both
runs: isocentre shift, dα, dβ, in-plane rotation, dSID, each uniform up to a fraction of the issue's
maximum ±10 mm, ±3°, ±3°, ±2°, ±20 mm); matched points are the true projections with Gaussian noise.
Calibration starts from the header cameras. Reported per error size and noise level: the gauge-free
relative geometry error before and after (stages.calibration.model.relative_geometry_error: RMS 3D
error of a 10 mm grid triangulated and similarity-aligned, in mm; relative-rotation error, deg), the
fraction of calibrations applied, and the time per pair (one thread, min and median).

    OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks.bench_calibration [--trials N] [-o docs/benchmarks/calibration.md]

With ``--phantom DIR`` (the real phantom runs, ../shared/data/phantom_xa) it instead measures the
two-view calibration from masks (:func:`stages.calibration.calibrate_masks`, each pair from its own two
runs) against the joint calibration of all 8 runs (:func:`stages.calibration.calibrate_runs`,
``static=True``): the joint model's 3D centreline, projected by the jointly calibrated cameras, gives
reference matches for every pair; their symmetric epipolar distance (mm at the isocentre) under the header
cameras and under the pair's own calibration says how much of the header inconsistency the pair
calibration removes (``-o docs/benchmarks/calibration_phantom.md``).
"""

from __future__ import annotations

import argparse
import itertools
import logging
import time
from pathlib import Path

import numpy as np

PAIRS = [  # (alpha, beta, sid) of phantom runs IM1..IM8 (README of ../shared/data/phantom_xa)
    (31.3, 0.1, 860), (-27.3, -0.1, 865), (-0.8, -23.2, 891), (0.1, 28.7, 907),
    (-26.5, -32.7, 931), (24.0, -18.8, 939), (-29.3, 25.5, 976), (30.7, 23.6, 976),
]


def run(trials: int, sizes, noises, shift: bool = True, seed: int = 0):
    from stages.calibration import calibrate_pair, relative_geometry_error
    from stages.calibration.synthetic import random_error, synthetic_matches, synthetic_tree, true_camera
    from stages.core.geometry import Camera

    logging.disable(logging.WARNING)
    pairs = list(itertools.combinations(range(8), 2))
    rows = []
    rng = np.random.default_rng(seed)
    for size in sizes:
        for t in range(trials):
            i, j = pairs[int(rng.integers(len(pairs)))]
            ha, hb = (Camera.from_carm(a, b, s, 720.0, 0.390625, 512, 512) for a, b, s in (PAIRS[i], PAIRS[j]))
            tree = synthetic_tree(seed=1000 * t + int(size * 100), step_mm=0.3)
            kw = dict(shift_mm=10.0 * size if shift else 0.0, angle_deg=3.0 * size, inplane_deg=2.0 * size,
                      sid_mm=20.0 * size)
            ta, tb = true_camera(ha, random_error(rng, **kw)), true_camera(hb, random_error(rng, **kw))
            for noise in noises:
                pa, pb = synthetic_matches(tree, ta, tb, noise_px=noise, seed=t)
                t0 = time.perf_counter()
                res = calibrate_pair(pa, pb, ha, hb, names=(f"IM{i + 1}", f"IM{j + 1}"))
                dt = time.perf_counter() - t0
                e0 = relative_geometry_error(ha, hb, ta, tb)
                e1 = relative_geometry_error(res.cam_a, res.cam_b, ta, tb)
                rows.append(dict(size=size, noise=noise, n=len(pa), applied=res.applied, seconds=dt,
                                 before_mm=e0["rms_mm"], after_mm=e1["rms_mm"], before_deg=e0["rotation_deg"],
                                 after_deg=e1["rotation_deg"],
                                 resid_after_px=res.report["residual_after"]["epipolar_px"]))
    return rows


def table(rows, title: str) -> str:
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    out = [f"### {title}", "",
           "| error size (× max) | noise px | pairs | points (median) | applied | 3D RMS mm before → after | "
           "rel. rotation RMS deg before → after | residual after px | s/pair min / median |",
           "|---|---|---|---|---|---|---|---|---|"]
    for size, noise in sorted({(r["size"], r["noise"]) for r in rows}):
        s = [r for r in rows if r["size"] == size and r["noise"] == noise]
        t = np.array([r["seconds"] for r in s])
        out.append(f"| {size:g} | {noise:g} | {len(s)} | {int(np.median([r['n'] for r in s]))} | "
                   f"{np.mean([r['applied'] for r in s]):.2f} | {rms([r['before_mm'] for r in s]):.2f} → "
                   f"{rms([r['after_mm'] for r in s]):.3f} | {rms([r['before_deg'] for r in s]):.2f} → "
                   f"{rms([r['after_deg'] for r in s]):.3f} | {np.mean([r['resid_after_px'] for r in s]):.3f} | "
                   f"{t.min():.2f} / {np.median(t):.2f} |")
    return "\n".join(out) + "\n"


def phantom(folder) -> str:
    from stages.calibration import calibrate_masks, calibrate_runs, pair_residual
    from stages.calibration.runs import _centreline_maps, _model_points, _voted
    from stages.heldout import load_views

    logging.disable(logging.WARNING)
    views = load_views(folder)
    names = [v.name for v in views]
    t0 = time.perf_counter()
    cams, rep = calibrate_runs([v.mask for v in views], [v.camera for v in views], names, static=True,
                               fovs=[v.fov for v in views])
    t_joint = time.perf_counter() - t0
    dm = _centreline_maps([v.mask for v in views])
    part = names.index(rep["partner_run"])
    model = _voted(_model_points([views[0].mask, views[part].mask], [cams[0], cams[part]], 0), cams, dm,
                   exclude=(0, part))
    out = [f"Joint calibration of the {len(views)} runs (reference {rep['reference_run']}, model partner "
           f"{rep['partner_run']}, {len(model)} model points): {t_joint:.0f} s.", "",
           "| run | shift mm | in-plane ° | dα ° | dβ ° | dSID mm | chamfer mm before → after |", "|---|---|---|---|---|---|---|"]
    for n in names:
        c = rep["corrections"][n]
        b, a = rep["residual_before"][n]["chamfer_mm"], rep["residual_after"][n]["chamfer_mm"]
        out.append(f"| {n} | {c['shift_mm_norm']:.2f} | {c['inplane_deg']:+.2f} | {c['dalpha_deg']:+.2f} | "
                   f"{c['dbeta_deg']:+.2f} | {c['dsid_mm']:+.1f} | {b:.2f} → {a:.2f} |")
    out += ["", "| pair | applied | shift mm | epipolar residual mm vs joint: header → pair calibration | s |",
            "|---|---|---|---|---|"]
    res = []
    for i, j in itertools.combinations(range(len(views)), 2):
        xa, xb = cams[i].project(model), cams[j].project(model)
        ok = views[i].camera.in_image(xa) & views[j].camera.in_image(xb)
        t0 = time.perf_counter()
        cal = calibrate_masks(views[i].mask, views[j].mask, views[i].camera, views[j].camera, names=(names[i], names[j]))
        dt = time.perf_counter() - t0
        r0 = pair_residual(views[i].camera, views[j].camera, xa[ok], xb[ok])["epipolar_mm"]
        r1 = pair_residual(views[i].camera, cal.cam_b, xa[ok], xb[ok])["epipolar_mm"]
        res.append((r0, r1, dt))
        out.append(f"| {names[i]}+{names[j]} | {'yes' if cal.applied else 'no'} | "
                   f"{cal.report['corrections'][names[j]]['shift_mm_norm']:.2f} | {r0:.2f} → {r1:.2f} | {dt:.2f} |")
    r = np.array(res)
    out += ["", f"All {len(r)} pairs: header {r[:, 0].mean():.2f} mm mean ({np.median(r[:, 0]):.2f} median) → "
            f"pair calibration {r[:, 1].mean():.2f} mm mean ({np.median(r[:, 1]):.2f} median); "
            f"{r[:, 2].min():.2f} / {np.median(r[:, 2]):.2f} s per pair (min / median)."]
    return "\n".join(out) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=12)
    ap.add_argument("--sizes", type=float, nargs="+", default=[0.25, 0.5, 1.0])
    ap.add_argument("--noises", type=float, nargs="+", default=[0.0, 0.25, 0.5])
    ap.add_argument("-o", "--output", type=Path, default=None)
    ap.add_argument("--phantom", type=Path, default=None, help="Folder of the phantom runs: pair vs joint calibration.")
    args = ap.parse_args(argv)
    if args.phantom is not None:
        text = phantom(args.phantom)
    else:
        parts = []
        for shift, title in ((True, "All injected errors (isocentre shift, angles, in-plane, SID) in both runs"),
                             (False, "Without the isocentre shift (angles, in-plane, SID in both runs)")):
            rows = run(args.trials, args.sizes, args.noises, shift=shift)
            parts.append(table(rows, title))
        text = "\n".join(parts)
    print(text)
    if args.output:
        from stages.core.artefacts import atomic_path

        with atomic_path(args.output) as tmp:
            Path(tmp).write_text(text)

if __name__ == "__main__":
    main()
