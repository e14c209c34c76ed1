"""Benchmark: the visual-hull baseline on the synthetic evaluation set (data-se, paper Table 1).

For every two-view pair of ``data/se/pairs.zarr`` (``autocar.render-pairs``, written by ``make data-se``)
the visual hull of the two ground-truth silhouettes is reconstructed at 0.5 mm
(:func:`stages.visual_hull.visual_hull`) and scored against the case's ``labels/`` (shifted by the
pair's recorded translation) with :func:`stages.metrics.metrics_3d`: Dice, clDice, Chamfer, HD95.
Writes docs/benchmarks/visual_hull_se.md (mean ± sd, median over pairs; the paper's visual hull:
Dice 0.19, clDice 0.26, CD 12.6 mm, HD95 33.1 mm) and, with ``--out``, the per-pair metric tables via
:func:`stages.evaluate.write_metrics`.

Run:  python benchmarks/bench_visual_hull_se.py [--data data/se] [--limit N] [--misalign-px 2] [--out out/vh_se]
If the data set is missing it says so and exits 0 without touching the docs.
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import statistics
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None) -> int:
    from se_eval import add_se_arguments, evaluate_se, hull_predictor, se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_se_arguments(ap, misalign_px=0.0)
    ap.add_argument("--out", default=None, help="also write per-pair tables OUT.{zarr,json,csv,md}")
    ap.add_argument("--doc", default=str(ROOT / "docs" / "benchmarks" / "visual_hull_se.md"))
    args = ap.parse_args(argv)
    data = se_or_say(args.data)
    if data is None:
        return 0

    from bench_metrics import machine
    from stages.evaluate import aggregate, write_metrics

    rows = evaluate_se(hull_predictor(), data, args.limit, args.misalign_px, workers=args.threads)
    n = len(rows)
    t_hull = [r["seconds"] for r in rows]
    t_metric = [r["metric_seconds"] for r in rows]
    agg = aggregate(rows, ["dice", "cldice", "tprec", "tsens", "chamfer_mm", "hd95_mm"])
    if args.out:
        write_metrics(args.out, rows, agg, inputs=[str(data / "pairs.zarr")], parameters={"method": "visual hull"})

    def cell(k, paper):
        a = agg[k]
        f = (lambda v: f"{v:.2f}") if k.endswith("_mm") else (lambda v: f"{v:.3f}")
        return f"| {k} | {f(a['mean'])} ± {f(a['sd'] or 0)} | {f(a['median'])} | {a['n']} | {paper} |"

    cmd = "python benchmarks/bench_visual_hull_se.py" + (f" --limit {args.limit}" if args.limit else "") + (
        f" --misalign-px {args.misalign_px:g}" if args.misalign_px else "")
    lines = [
        "## Visual-hull baseline on data-se",
        "",
        f"Command: `{cmd}`  ",
        f"Machine: {machine()} (shared; timings noisy)  ",
        f"Date: {dt.date.today().isoformat()}",
        "",
        f"Data: {data} — {n} two-view pairs, ground-truth silhouettes"
        + (f" (view B with a {args.misalign_px:g} px RMS TPS misalignment)" if args.misalign_px else "")
        + ", 0.5 mm common grid. "
        "Reconstruction: voxels whose centres project onto the vessel in both views (stages/visual_hull.py).",
        "",
        "| metric | mean ± sd | median | n | paper (visual hull) |",
        "|---|---|---|---|---|",
        cell("dice", "0.19"), cell("cldice", "0.26"), cell("tprec", "–"), cell("tsens", "–"),
        cell("chamfer_mm", "12.6"), cell("hd95_mm", "33.1"),
        "",
        f"Time per pair: hull min {min(t_hull):.2f} s, median {statistics.median(t_hull):.2f} s; "
        f"metrics min {min(t_metric):.2f} s, median {statistics.median(t_metric):.2f} s. "
        f"Hull size median {int(statistics.median([r['voxels'] for r in rows]))} voxels.",
        "",
    ]
    text = "\n".join(lines)
    Path(args.doc).parent.mkdir(parents=True, exist_ok=True)
    Path(args.doc).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
