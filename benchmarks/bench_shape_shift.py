"""Shape shift: Table 1 accuracy of the 3D methods on trees outside the generator's range, beside data-se → docs/benchmarks/shape_shift.md.

The set: :func:`stages.render.products.make_shape_shift` (longer, thinner, more tortuous trees; built when
missing). Both it and data-se's first N pairs are scored by :mod:`stages.evaluate.synthetic_pairs`; the
issue's target is Dice within 0.05 of data-se.

Run:  python benchmarks/bench_shape_shift.py [--limit 20] [--methods correspondence,sbp] [--radius-scale 1]
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

KEYS = ("dice", "cldice", "chamfer_mm", "hd95_mm")


def summarise(rows) -> dict:
    return {k: float(np.mean([r[k] for r in rows])) for k in KEYS}


def main(argv=None) -> int:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--limit", type=int, default=20, help="trees in the shape-shift set (and data-se pairs compared)")
    ap.add_argument("--methods", default="correspondence,sbp", help="3D methods (stages.methods3d names)")
    ap.add_argument("--radius-scale", type=float, default=None,
                    help="override ShapeShift.radius_scale (1.0: shape only, vessels as thick as data-se's)")
    ap.add_argument("--out", default=None, help="set folder (default data/shape_shift, or data/shape_shift_r<scale>)")
    ap.add_argument("--doc", default=None,
                    help="default docs/benchmarks/shape_shift.md, or shape_shift_r<scale>.md with --radius-scale")
    args = ap.parse_args(argv)
    import logging

    import torch

    logging.basicConfig(level=logging.INFO, format="%(message)s")

    torch.set_num_threads(1)
    from machine import machine_description
    from stages.evaluate.synthetic_pairs import evaluate_many, find_se, method_predictor

    load0 = os.getloadavg()
    from stages.anatomy import ShapeShift

    shift_params = ShapeShift() if args.radius_scale is None else ShapeShift(radius_scale=args.radius_scale)
    out = args.out or str(ROOT / "data" / ("shape_shift" if args.radius_scale is None else f"shape_shift_r{args.radius_scale:g}"))
    doc = args.doc or str(ROOT / "docs" / "benchmarks" / ("shape_shift.md" if args.radius_scale is None
                                                          else f"shape_shift_r{args.radius_scale:g}.md"))
    from stages.render.products import make_shape_shift

    shift = make_shape_shift(Path(out), args.limit, shift_params)
    methods = [m.strip() for m in args.methods.split(",") if m.strip()]
    predictors = {m: method_predictor(m) for m in methods}
    sets = {"shape shift": evaluate_many(predictors, shift, args.limit)}
    se = find_se()
    if se is not None:
        sets["data-se"] = evaluate_many(predictors, se, args.limit)
    load1 = os.getloadavg()
    lines = ["## Shape shift: trees outside the generator's range (Table 1 protocol)", "",
             f"- command: `python benchmarks/bench_shape_shift.py --limit {args.limit} --methods {args.methods}"
             + (f" --radius-scale {args.radius_scale:g}`" if args.radius_scale is not None else "`"),
             f"- machine: {machine_description()}; load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the end",
             f"- date: {dt.date.today().isoformat()}",
             f"- shape-shift set: stages.anatomy.ShapeShift (× {shift_params.scale:g} scale, radii × {shift_params.radius_scale:g}, "
             f"smooth displacement field {shift_params.waves} waves per axis of {shift_params.amplitude_mm:g} mm, wavelength "
             f"{shift_params.wavelength_mm[0]:g}–{shift_params.wavelength_mm[1]:g} mm) on seeds 5 000 000 + i, rendered like data-se", "",
             "| 3D method | set | pairs | Dice | clDice | CD (mm) | HD95 (mm) |", "|---|---|---|---|---|---|---|"]
    for m in methods:
        for name, res in sets.items():
            s = summarise(res[m])
            lines.append(f"| {m} | {name} | {len(res[m])} | {s['dice']:.3f} | {s['cldice']:.3f} | {s['chamfer_mm']:.2f} | "
                         f"{s['hd95_mm']:.2f} |")
        if "data-se" in sets:
            d = summarise(sets["shape shift"][m])["dice"] - summarise(sets["data-se"][m])["dice"]
            lines.append(f"| {m} | change | | {d:+.3f} | | | |")
    lines.append("")
    Path(doc).parent.mkdir(parents=True, exist_ok=True)
    Path(doc).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
