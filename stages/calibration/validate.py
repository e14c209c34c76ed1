"""The calibration's accuracy, measured: recovered against injected C-arm errors on simulated pairs, the
3D reconstruction on rendered pairs with injected header errors before and after calibration, and on the
real phantom each pair's own calibration against the joint calibration of all its runs.

Reads: nothing for :func:`injected_errors` (synthetic trees at the phantom's C-arm angles); data-se
(``pairs.zarr`` and its prepared cases) for :func:`reconstruction_under_errors`; the phantom's ``*.dcm`` runs
for :func:`pair_vs_joint`. Writes nothing: all return rows (``benchmarks/bench_calibration.py`` turns them
into docs/benchmarks/calibration.md, calibration_reconstruction.md and calibration_phantom.md).
"""

from __future__ import annotations

import itertools
import logging
import os
import time

import numpy as np

__all__ = ["PHANTOM_CARM", "ERROR_MAX", "injected_errors", "absolute_error",
           "reconstruction_under_errors", "reconstruction_tables",
           "pair_vs_joint"]

PHANTOM_CARM = [  # (alpha, beta, sid) of phantom runs IM1..IM8 (README of ../shared/data/phantom_xa)
    (31.3, 0.1, 860), (-27.3, -0.1, 865), (-0.8, -23.2, 891), (0.1, 28.7, 907),
    (-26.5, -32.7, 931), (24.0, -18.8, 939), (-29.3, 25.5, 976), (30.7, 23.6, 976),
]
# the injected error at size 1: per axis isocentre shift mm, dα and dβ deg, in-plane deg, SID mm
ERROR_MAX = {"shift_mm": 10.0, "angle_deg": 3.0, "inplane_deg": 2.0, "sid_mm": 20.0}


def injected_errors(trials: int, sizes, noises, shift: bool = True, seed: int = 0) -> list[dict]:
    """Per error size, ``trials`` random phantom run pairs whose true cameras are the header cameras with
    uniform errors in both runs up to ``size`` × (±10 mm isocentre shift unless not ``shift``, ±3° dα and dβ,
    ±2° in-plane, ±20 mm SID); per noise level (px) the pair is calibrated from the headers on the true
    projections of a synthetic tree plus noise. A row per calibration: gauge-free 3D RMS error (mm) and
    relative-rotation error (deg) before and after, applied, residual after (px), seconds."""
    from ..core.geometry import Camera
    from . import calibrate_pair, relative_geometry_error
    from .synthetic import random_error, synthetic_matches, synthetic_tree, true_camera

    logging.disable(logging.WARNING)
    pairs = list(itertools.combinations(range(len(PHANTOM_CARM)), 2))
    rows = []
    rng = np.random.default_rng(seed)
    for size in sizes:
        for t in range(trials):
            i, j = pairs[int(rng.integers(len(pairs)))]
            ha, hb = (Camera.from_carm(a, b, s, 720.0, 0.390625, 512, 512) for a, b, s in (PHANTOM_CARM[i], PHANTOM_CARM[j]))
            tree = synthetic_tree(seed=1000 * t + int(size * 100), step_mm=0.3)
            kw = {key: size * v for key, v in ERROR_MAX.items()} | ({} if shift else {"shift_mm": 0.0})
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


def absolute_error(cam_a, cam_b, true_a, true_b) -> dict:
    """RMS 3D error (mm) of points triangulated with (cam_a, cam_b) from their true projections, with no
    alignment (``abs_mm``): a 5 mm grid in a 100 mm cube at the isocentre, as :func:`relative_geometry_error`
    uses. With run A true this is what a Dice against the truth sees. It includes the one gauge freedom that
    fixing A leaves, a scale about A's source (depth along A's rays: the length of the baseline, which two
    images cannot observe); ``scaled_mm`` is the error left after the best such scale (``scale``)."""
    from .model import triangulate

    g = np.arange(-50.0, 50.01, 10.0)
    X = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    Y = triangulate(cam_a, cam_b, true_a.project(X), true_b.project(X))
    ok = np.all(np.isfinite(Y), axis=1)
    a, b = Y[ok] - cam_a.source, X[ok] - cam_a.source
    k = float(np.sum(a * b) / np.sum(a * a))
    rms = lambda d: float(np.sqrt(np.mean(np.sum(d ** 2, 1))))  # noqa: E731
    return {"abs_mm": rms(a - b), "scaled_mm": rms(k * a - b), "scale": k}


def _score(pred, truth) -> dict:
    from ..core.metrics import metrics_3d
    from ..core.voxels import SparseVoxels

    occ = SparseVoxels(pred.coords, pred.voxel_size, pred.origin,
                       {"occupancy": np.asarray(pred.features["occupancy"], np.float32)})
    m = metrics_3d(occ, truth, workers=1)
    return {k: float(m[k]) for k in ("dice", "cldice", "chamfer_mm", "hd95_mm")}


def reconstruction_under_errors(data, limit: int | None, sizes=(0.25, 0.5, 1.0), methods=("correspondence", "sbp"),
                                seed: int = 0, misalign_px: float = 2.0, verbose: bool = False) -> list[dict]:
    """The 3D reconstruction of data-se pairs (Table 1's protocol, :func:`stages.evaluate.synthetic_pairs.se_pairs`:
    masks rendered with the true cameras) when run B's header camera is off, with and without calibration.

    Per pair and error size ``s``: a header error for run B only, uniform up to ``s`` × :data:`ERROR_MAX` per
    component (seeded by ``[seed, pair, 1000·s]``), turned into B's header camera by
    :func:`stages.calibration.synthetic.header_camera`.
    Run A keeps its true camera: it is the calibration's reference (the gauge it holds fixed), so the
    reconstruction stays in the truth's frame and is scored against the truth directly. One freedom is left
    even so: a scale of the scene about A's source (depth along A's rays, i.e. the baseline length) changes
    no image, so two views cannot observe it, and a 1 % scale moves the heart ~7 mm in depth.
    :func:`stages.calibration.calibrate_masks` corrects B from the two masks, applied as ``autocar
    reconstruct`` applies it (a refused correction or a :class:`UserError` keeps the header).

    Per method of :mod:`stages.methods3d`: Dice, clDice, Chamfer, HD95 (:func:`stages.core.metrics.metrics_3d`)
    with the true cameras (``free_*``, once per pair), the header cameras (``uncal_*``) and the calibrated
    ones (``cal_*``); the last two also with that depth gauge removed (``*_depth`` keys: the prediction
    scaled about A's source by :func:`absolute_error`'s ``scale``, an oracle from the true cameras). A row
    per pair × size × method, with the calibration's seconds, whether it was applied, and the geometry
    error before and after: gauge-free (:func:`relative_geometry_error` against the true pair) and in the
    truth's frame (:func:`absolute_error`). ``data`` may also be an iterable of
    :class:`~stages.evaluate.synthetic_pairs.SEPair` (``limit`` and ``misalign_px`` then unused).
    """
    from ..core.errors import UserError
    from ..core.voxels import SparseVoxels
    from ..evaluate.synthetic_pairs import se_pairs
    from ..methods3d import load_predictor
    from . import calibrate_masks, relative_geometry_error
    from .synthetic import header_camera, random_error

    logging.disable(logging.WARNING)
    predictors = {m: load_predictor(m) for m in methods}
    rows = []
    pairs = se_pairs(data, limit, misalign_px=misalign_px) if isinstance(data, (str, os.PathLike)) else data
    for p in pairs:
        def run(method, cam_b, scale=None):
            t0 = time.perf_counter()
            pred = predictors[method](p.mask_a, p.mask_b, p.cam_a, cam_b, p.case.side)
            dt = time.perf_counter() - t0
            sc = _score(pred, p.truth)
            if scale is not None:  # also scored with the depth gauge removed: scaled about A's source
                src = p.cam_a.source
                sc.update({f"{k}_depth": v for k, v in _score(SparseVoxels(
                    pred.coords, pred.voxel_size * scale, src + scale * (pred.origin - src), pred.features),
                    p.truth).items()})
            return sc, dt

        free = {m: run(m, p.cam_b) for m in methods}
        for size in sizes:
            err = random_error(np.random.default_rng([seed, p.index, round(1000 * size)]),
                               **{key: size * v for key, v in ERROR_MAX.items()})
            head_b = header_camera(p.cam_b, err)
            t0 = time.perf_counter()
            try:
                cal = calibrate_masks(p.mask_a, p.mask_b, p.cam_a, head_b)
                applied, cam_b = cal.applied, (cal.cam_b if cal.applied else head_b)
                note = "; ".join(cal.report["warnings"])
                shift = cal.report["proposed_correction"].get("shift_mm_norm", float("nan"))
            except UserError as exc:
                applied, cam_b, note, shift = False, head_b, str(exc), float("nan")
            dt = time.perf_counter() - t0
            e0 = relative_geometry_error(p.cam_a, head_b, p.cam_a, p.cam_b)
            e1 = relative_geometry_error(p.cam_a, cam_b, p.cam_a, p.cam_b)
            a0, a1 = absolute_error(p.cam_a, head_b, p.cam_a, p.cam_b), absolute_error(p.cam_a, cam_b, p.cam_a, p.cam_b)
            for m in methods:
                uncal, t_u = run(m, head_b, a0["scale"])
                calm, t_c = run(m, cam_b, a1["scale"]) if applied else (uncal, t_u)
                row = dict(pair=p.index, case_id=p.case.case_id, size=size, method=m, applied=applied, seconds=dt,
                           proposed_shift_mm=shift, note=note, before_mm=e0["rms_mm"], after_mm=e1["rms_mm"],
                           before_deg=e0["rotation_deg"], after_deg=e1["rotation_deg"], error=dict(err),
                           abs_before_mm=a0["abs_mm"], abs_after_mm=a1["abs_mm"], scaled_before_mm=a0["scaled_mm"],
                           scaled_after_mm=a1["scaled_mm"],
                           recon_seconds=free[m][1] + t_u + t_c)
                for prefix, sc in (("free", free[m][0]), ("uncal", uncal), ("cal", calm)):
                    row.update({f"{prefix}_{key}": v for key, v in sc.items()})
                rows.append(row)
                if verbose:
                    print(f"pair {p.index} size {size:g} {m}: Dice {row['free_dice']:.3f} / {row['uncal_dice']:.3f} / "
                          f"{row['cal_dice']:.3f} (free / header / calibrated), geometry {e0['rms_mm']:.2f} → "
                          f"{e1['rms_mm']:.2f} mm, {e0['rotation_deg']:.2f} → {e1['rotation_deg']:.2f}°, "
                          f"{'applied' if applied else 'refused'}, {dt:.1f} s", flush=True)
    return rows


def reconstruction_tables(rows, sizes, methods) -> str:
    """Markdown of :func:`reconstruction_under_errors`'s rows: per size × method the reconstruction figures
    (means over pairs), per size the calibration's geometry (RMS over pairs) and time."""
    rms = lambda v: float(np.sqrt(np.mean(np.square(v))))  # noqa: E731
    keys = ("dice", "chamfer_mm", "hd95_mm")
    out = ["Means over pairs: error-free / header / calibrated; *no depth*: header / calibrated with the depth "
           "gauge removed (scaled about A's source; docs/CALIBRATION.md).", "",
           "| size | method | pairs | Dice | Dice, no depth | CD mm | CD, no depth | HD95 mm | HD95, no depth | "
           "cal / free: Dice, CD, HD95 | same, no depth |", "|---|---|---|---|---|---|---|---|---|---|---|"]
    for size, m in ((size, m) for size in sizes for m in methods):
        s = [r for r in rows if r["size"] == size and r["method"] == m]
        f = {k: [np.mean([r[c + k] for r in s]) for c in ("free_", "uncal_", "cal_")] for k in keys}
        d = {k: [np.mean([r[c + k + "_depth"] for r in s]) for c in ("uncal_", "cal_")] for k in keys}
        cells = [" / ".join(f"{v:.3f}" if k == "dice" else f"{v:.2f}" for v in g[k]) for k in keys for g in (f, d)]
        cells += [" / ".join(f"{g[k][-1] / f[k][0]:.2f}" for k in keys) for g in (f, d)]
        out.append(f"| {size:g} | {m} | {len(s)} | " + " | ".join(cells) + " |")
    out += ["", "Calibration, RMS over pairs, before → after (truth frame: no alignment; no depth: after the best "
            "scale about A's source):", "",
            "| size | pairs | applied | gauge-free mm | rel. rotation ° | truth frame mm | truth frame, no depth mm | "
            "s/calibration min / median |", "|---|---|---|---|---|---|---|---|"]
    for size in sizes:
        s = [r for r in rows if r["size"] == size and r["method"] == methods[0]]
        cells = [f"{rms([r[k + 'before' + u] for r in s]):.2f} → {rms([r[k + 'after' + u] for r in s]):.2f}"
                 for k, u in (("", "_mm"), ("", "_deg"), ("abs_", "_mm"), ("scaled_", "_mm"))]
        out.append(f"| {size:g} | {len(s)} | {np.mean([r['applied'] for r in s]):.2f} | " + " | ".join(cells) +
                   f" | {np.min([r['seconds'] for r in s]):.2f} / {np.median([r['seconds'] for r in s]):.2f} |")
    return "\n".join(out) + "\n"


def pair_vs_joint(folder) -> dict:
    """The joint calibration of all runs in ``folder`` (static) gives a 3D model whose projections by the
    jointly calibrated cameras are reference matches for every run pair; per pair, their symmetric epipolar
    distance (mm at the isocentre) under the header cameras and under the pair's own calibration from its
    masks. Returns the joint report, its time and model size, and a row per pair."""
    from ..evaluate.heldout import load_views
    from . import calibrate_masks, calibrate_runs, pair_residual
    from .runs import _centreline_maps, _model_points, _voted

    logging.disable(logging.WARNING)
    views = load_views(folder)
    names = [v.name for v in views]
    t0 = time.perf_counter()
    cams, rep = calibrate_runs([v.mask for v in views], [v.camera for v in views], names, static=True,
                               fovs=[v.fov for v in views])
    t_joint = time.perf_counter() - t0
    part = names.index(rep["partner_run"])
    model = _voted(_model_points([views[0].mask, views[part].mask], [cams[0], cams[part]], 0), cams,
                   _centreline_maps([v.mask for v in views]), exclude=(0, part))
    pairs = []
    for i, j in itertools.combinations(range(len(views)), 2):
        xa, xb = cams[i].project(model), cams[j].project(model)
        ok = views[i].camera.in_image(xa) & views[j].camera.in_image(xb)
        t0 = time.perf_counter()
        cal = calibrate_masks(views[i].mask, views[j].mask, views[i].camera, views[j].camera, names=(names[i], names[j]))
        dt = time.perf_counter() - t0
        pairs.append(dict(a=names[i], b=names[j], applied=cal.applied, seconds=dt,
                          shift_mm=cal.report["corrections"][names[j]]["shift_mm_norm"],
                          header_mm=pair_residual(views[i].camera, views[j].camera, xa[ok], xb[ok])["epipolar_mm"],
                          pair_mm=pair_residual(views[i].camera, cal.cam_b, xa[ok], xb[ok])["epipolar_mm"]))
    return {"names": names, "joint": rep, "joint_seconds": t_joint, "model_points": len(model), "pairs": pairs}
