"""Compare two SBP weights files on data-se, pair by pair: is a newly trained network better?

Both networks predict every pair (ground-truth silhouettes, view B with the default 2 px RMS
misalignment, seeded per pair, so both see the same inputs) and are scored with
:func:`stages.core.metrics.metrics_3d`. Reported per metric: both means, the mean paired difference, on how
many pairs the second is better, and the Wilcoxon signed-rank p-value; and each network's median
inference time. Use it after `make train-wide` or any fine-tuning, before replacing the shipped weights.

Run:  python training/compare_sbp_se.py A.pt B.pt [--limit N] [--mask-noise] [--doc NAME]
(--mask-noise: both masks with segmenter-style errors, seeded per pair, instead of exact silhouettes.)
Prints the table; with --doc also writes docs/benchmarks/NAME.md. Uses the data-se loop of
stages/evaluate/synthetic_pairs.py (the one Table 1 uses). Missing data-se: says so and exits 0.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

# metric, label, higher is better
METRICS = [("dice", "Dice", True), ("cldice", "clDice", True), ("chamfer_mm", "Chamfer (mm)", False),
           ("hd95_mm", "HD95 (mm)", False)]


def paired_table(rows_a: list[dict], rows_b: list[dict], name_a: str, name_b: str) -> str:
    """Markdown table of the paired comparison (rows in the same pair order)."""
    from scipy.stats import wilcoxon

    lines = [f"| metric | {name_a} | {name_b} | difference (B − A) | B better on | Wilcoxon p |",
             "|---|---|---|---|---|---|"]
    for key, label, higher in METRICS:
        a = np.array([r[key] for r in rows_a], float)
        b = np.array([r[key] for r in rows_b], float)
        ok = np.isfinite(a) & np.isfinite(b)
        d = b[ok] - a[ok]
        better = np.mean(d > 0) if higher else np.mean(d < 0)
        p = wilcoxon(a[ok], b[ok]).pvalue if np.any(d != 0) else 1.0
        lines.append(f"| {label} | {a[ok].mean():.3f} | {b[ok].mean():.3f} | {d.mean():+.3f} | {better:.0%} "
                     f"| {p:.2g} |")
    return "\n".join(lines)


def main(argv=None) -> int:
    from stages.evaluate.synthetic_pairs import add_se_arguments, evaluate_many, sbp_predictor, se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("weights_a", help="first weights (e.g. stages/weights/sbp.pt, the shipped ones)")
    ap.add_argument("weights_b", help="second weights (e.g. out/train_sbp_wide/model.pt)")
    add_se_arguments(ap)
    ap.add_argument("--mask-noise", action="store_true",
                    help="give both networks masks with segmenter-style errors (stages.render.mask_noise, seeded per pair)")
    ap.add_argument("--doc", default=None, help="also write docs/benchmarks/<doc>.md")
    args = ap.parse_args(argv)
    data = se_or_say(args.data)
    if data is None:
        return 0
    import torch

    from stages.sbp.train import load_weights

    torch.set_num_threads(args.threads)
    models = {"A": load_weights(args.weights_a), "B": load_weights(args.weights_b)}
    rows = evaluate_many({k: sbp_predictor(m) for k, m in models.items()}, data, args.limit, args.misalign_px,
                         workers=args.threads, verbose=False, mask_noise=args.mask_noise)
    table = paired_table(rows["A"], rows["B"], f"A: `{args.weights_a}`", f"B: `{args.weights_b}`")
    times = {k: statistics.median(r["seconds"] for r in rows[k]) for k in rows}
    masks = "ground-truth silhouettes with segmenter-style errors" if args.mask_noise else "ground-truth silhouettes"
    body = (f"{len(rows['A'])} pairs of data-se, {masks}, view B with a {args.misalign_px:g} px RMS "
            f"misalignment (seeded per pair), {args.threads} torch threads.\n\n{table}\n\n"
            f"Median inference per pair: A {times['A']:.2f} s, B {times['B']:.2f} s.\n")
    print(body)
    if args.doc:
        from machine import write_section

        cmd = f"python training/compare_sbp_se.py {args.weights_a} {args.weights_b}"
        if args.limit:
            cmd += f" --limit {args.limit}"
        if args.mask_noise:
            cmd += " --mask-noise"
        write_section(args.doc, f"Paired comparison on data-se: {args.weights_b} against {args.weights_a}", cmd, body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
