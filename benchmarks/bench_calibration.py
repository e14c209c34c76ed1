"""Self-calibration (stages/calibration) with injected C-arm errors: recovered against injected geometry error → docs/benchmarks/calibration.md.

The runs are stages/calibration/validate.py's (method in docs/CALIBRATION.md); ``--phantom DIR`` (the real
phantom runs) measures instead each pair's calibration from masks against the joint calibration of all 8
runs (``-o docs/benchmarks/calibration_phantom.md``); ``--reconstruction [--pairs N]`` reconstructs data-se pairs
with an injected header error in run B, before and after calibration → docs/benchmarks/calibration_reconstruction.md.

    OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks.bench_calibration [--trials N] [-o docs/benchmarks/calibration.md]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from stages.calibration.validate import (injected_errors, pair_vs_joint, reconstruction_tables,
                                        reconstruction_under_errors)


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
    res = pair_vs_joint(folder)
    rep = res["joint"]
    out = [f"Joint calibration of the {len(res['names'])} runs (reference {rep['reference_run']}, model partner "
           f"{rep['partner_run']}, {res['model_points']} model points): {res['joint_seconds']:.0f} s.", "",
           "| run | shift mm | in-plane ° | dα ° | dβ ° | dSID mm | chamfer mm before → after |", "|---|---|---|---|---|---|---|"]
    for n in res["names"]:
        c = rep["corrections"][n]
        out.append(f"| {n} | {c['shift_mm_norm']:.2f} | {c['inplane_deg']:+.2f} | {c['dalpha_deg']:+.2f} | "
                   f"{c['dbeta_deg']:+.2f} | {c['dsid_mm']:+.1f} | {rep['residual_before'][n]['chamfer_mm']:.2f} → "
                   f"{rep['residual_after'][n]['chamfer_mm']:.2f} |")
    out += ["", "| pair | applied | shift mm | epipolar residual mm vs joint: header → pair calibration | s |",
            "|---|---|---|---|---|"]
    out += [f"| {p['a']}+{p['b']} | {'yes' if p['applied'] else 'no'} | {p['shift_mm']:.2f} | {p['header_mm']:.2f} → "
            f"{p['pair_mm']:.2f} | {p['seconds']:.2f} |" for p in res["pairs"]]
    r = np.array([(p["header_mm"], p["pair_mm"], p["seconds"]) for p in res["pairs"]])
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
    ap.add_argument("--reconstruction", action="store_true", help="data-se reconstructions under injected errors")
    ap.add_argument("--pairs", type=int, default=20, help="--reconstruction: the first N data-se pairs")
    ap.add_argument("--methods", nargs="+", default=["correspondence", "sbp"], help="--reconstruction: 3D methods")
    ap.add_argument("--data", default=None, help="--reconstruction: data-se folder (default data/se)")
    args = ap.parse_args(argv)
    if args.reconstruction:
        from benchmarks.machine import load_average, write_section
        from stages.evaluate.synthetic_pairs import se_or_say

        if (data := se_or_say(args.data)) is not None:
            rows = reconstruction_under_errors(data, args.pairs, args.sizes, args.methods, verbose=True)
            body = reconstruction_tables(rows, args.sizes, args.methods) + f"\nWhile measuring: {load_average()}.\n"
            cmd = "OMP_NUM_THREADS=1 .venv/bin/python -m benchmarks.bench_calibration " + " ".join(
                argv or sys.argv[1:])
            print(body, "→", write_section("calibration_reconstruction", "Reconstruction with an injected header "
                                           "error in run B, before and after calibration (data-se)", cmd, body))
        return
    if args.phantom is not None:
        text = phantom(args.phantom)
    else:
        text = "\n".join(table(injected_errors(args.trials, args.sizes, args.noises, shift=shift), title) for shift, title in (
            (True, "All injected errors (isocentre shift, angles, in-plane, SID) in both runs"),
            (False, "Without the isocentre shift (angles, in-plane, SID in both runs)")))
    print(text)
    if args.output:
        from stages.core.artefacts import atomic_path

        with atomic_path(args.output) as tmp:
            Path(tmp).write_text(text)


if __name__ == "__main__":
    main()
