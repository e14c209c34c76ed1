"""Benchmark: SBP inference time, memory and accuracy on data-se (Table 1's L8 row) → docs/benchmarks/sbp_se.md.

Table 1's protocol (:mod:`stages.evaluate.synthetic_pairs`), plus per pair the inference time, the active
voxels against the dense grid of the same extent and the process's peak memory; the largest pair is then
predicted alone in a fresh process (``--single-pair I``): one pair's peak memory, not the loop's.

Run:  python benchmarks/bench_sbp_se.py [--weights FILE] [--limit N] [--doc NAME]. Missing data-se: exits 0.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

PAPER = {"dice": 0.80, "cldice": 0.93, "chamfer_mm": 1.27, "hd95_mm": 3.57}


def main(argv=None) -> int:
    from stages.evaluate.synthetic_pairs import add_se_arguments, evaluate_se, sbp_predictor, se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_se_arguments(ap)
    ap.add_argument("--weights", default=None, help="weights or checkpoint (default: the shipped stages/weights/sbp.pt)")
    ap.add_argument("--doc", default="sbp_se", help="section name: writes docs/benchmarks/<name>.md")
    ap.add_argument("--single-pair", type=int, default=None,
                    help="only predict pair I and print its time, voxels and the process's peak memory (JSON)")
    args = ap.parse_args(argv)
    data = se_or_say(args.data)
    if data is None:
        return 0
    if args.single_pair is not None:
        return single_pair(data, args)

    import numpy as np
    import torch

    from machine import peak_rss_mb, write_section
    from stages.core.errors import UserError
    from stages.sbp.train import load_weights

    torch.set_num_threads(args.threads)
    try:
        model = load_weights(args.weights)
    except UserError as exc:
        print(f"{exc}. Nothing measured.")
        return 0
    rss0_mb = peak_rss_mb()

    rows = evaluate_se(sbp_predictor(model), data, args.limit, args.misalign_px, workers=args.threads)
    n = len(rows)
    times = [r["seconds"] for r in rows]
    voxels = [r["voxels"] for r in rows]
    ratios = [r["dense_ratio"] for r in rows]
    peak_mb = peak_rss_mb()

    def stat(key):
        vals = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
        return (statistics.mean(vals), statistics.pstdev(vals), statistics.median(vals), len(vals)) if vals else None

    lines = ["| metric | ours: mean ± sd | median | pairs | paper (AutoCAR, L8) |", "|---|---|---|---|---|"]
    for key, name in (("dice", "Dice"), ("cldice", "clDice"), ("chamfer_mm", "Chamfer (mm)"), ("hd95_mm", "HD95 (mm)")):
        s = stat(key)
        lines.append(f"| {name} | {s[0]:.3f} ± {s[1]:.3f} | {s[2]:.3f} | {s[3]} | {PAPER[key]} |" if s else f"| {name} | n/a | | 0 | {PAPER[key]} |")
    weights = args.weights or "stages/weights/sbp.pt (shipped)"
    body = (f"Weights: `{weights}`. {n} pairs of data-se, ground-truth silhouettes, view B with a "
            f"{args.misalign_px:g} px RMS TPS misalignment (seeded per pair), {args.threads} torch threads.\n\n"
            + "\n".join(lines) + "\n\n"
            f"Inference per pair (candidate voxels + network): min {min(times):.2f} s, median {statistics.median(times):.2f} s, "
            f"max {max(times):.2f} s. Active voxels: median {int(statistics.median(voxels))}, i.e. "
            f"{statistics.median(ratios) * 100:.1f} % of the dense grid of the same extent (median ratio 1 : "
            f"{1 / statistics.median(ratios):.0f}). Peak resident memory of the whole process: {peak_mb:.0f} MB "
            f"(before the first pair {rss0_mb:.0f} MB).\n")
    largest = max(rows, key=lambda r: r["voxels"])
    alone = largest_pair_alone(largest["pair"], args)
    body += (f"\nThe largest pair (pair {largest['pair']}, {largest['voxels']} candidate voxels) predicted alone in a "
             f"fresh process: {alone['seconds']:.2f} s, peak resident memory {alone['peak_mb']:.0f} MB (weights and "
             f"Python included; {alone['before_mb']:.0f} MB before the pair).\n")
    cmd = "python benchmarks/bench_sbp_se.py" + (f" --weights {args.weights}" if args.weights else "") + (
        f" --limit {args.limit}" if args.limit else "")
    write_section(args.doc, "SBP network on data-se (Table 1, AutoCAR row)", cmd, body)
    print(body)
    return 0


def largest_pair_alone(index: int, args) -> dict:
    """Run ``--single-pair index`` in a fresh process and return its JSON line."""
    import json
    import subprocess

    cmd = [sys.executable, __file__, "--single-pair", str(index), "--threads", str(args.threads),
           "--misalign-px", str(args.misalign_px)]
    cmd += ["--weights", args.weights] if args.weights else []
    cmd += ["--data", args.data] if args.data else []
    out = subprocess.run(cmd, check=True, capture_output=True, text=True).stdout
    return json.loads(out.strip().splitlines()[-1])


def single_pair(data, args) -> int:
    """Predict one pair of data-se and print {seconds, voxels, before_mb, peak_mb} as one JSON line."""
    import itertools
    import json
    import time

    import torch

    from machine import peak_rss_mb
    from stages.evaluate.synthetic_pairs import se_pairs
    from stages.sbp.model import prepare_pair
    from stages.sbp.train import load_weights

    torch.set_num_threads(args.threads)
    p = next(itertools.islice(se_pairs(data, args.single_pair + 1, args.misalign_px), args.single_pair, None))
    model = load_weights(args.weights)
    before = peak_rss_mb()
    t0 = time.perf_counter()
    pair = prepare_pair(p.mask_a, p.mask_b, p.cam_a, p.cam_b, model.config)
    model.predict(pair, side=p.case.side)
    print(json.dumps({"seconds": time.perf_counter() - t0, "voxels": len(pair.candidates), "before_mb": before,
                      "peak_mb": peak_rss_mb()}))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
