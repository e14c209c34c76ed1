"""Benchmark: held-out-view check on the real phantom runs, SBP beside the hull → docs/benchmarks/heldout_sbp.md.

All 28 pairs of the eight phantom runs, each method on the same U-Net masks, scored in the six other runs
(:mod:`stages.evaluate.heldout`); then `autocar reconstruct IM1 IM4` end to end, with its stage timings.

Run:  python benchmarks/bench_heldout.py [--pairs N] [--weights F] [--methods visual-hull,sbp,L2=dense]
Also writes out/heldout/<method>.json. Missing phantom data: says so.
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PHANTOM = ROOT.parent / "shared" / "data" / "phantom_xa"
DEFAULT_METHODS = "visual-hull,sbp"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(PHANTOM))
    ap.add_argument("--pairs", type=int, default=None, help="only the first N run pairs")
    ap.add_argument("--weights", default=None, help="SBP weights (default: shipped)")
    ap.add_argument("--methods", default=DEFAULT_METHODS, help="rows NAME=METHOD[:WEIGHTS] (stages.methods3d)")
    ap.add_argument("--side", default="left", help="tree side the SBP network is conditioned on")
    ap.add_argument("--out", default=str(ROOT / "out" / "heldout"))
    args = ap.parse_args(argv)
    data = Path(args.data)
    if len(list(data.glob("*.dcm"))) < 3:
        print(f"{data}: phantom runs not found. Nothing measured.")
        return 0

    from machine import write_section
    from stages.evaluate.end_to_end import parse_rows
    from stages.evaluate.heldout import compare_tables, load_views, method_on_views, summary_line
    from stages.reconstruct import reconstruct

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    views = load_views(data, seg_method="unet")
    pairs = list(itertools.combinations(range(len(views)), 2))[: args.pairs]
    results, seconds = {}, {}
    for name, method, weights in parse_rows(args.methods, args.weights):
        results[name], seconds[name] = method_on_views(views, pairs, method, weights, args.side)
        (out / f"{name}.json").write_text(json.dumps(results[name], indent=1))
        print(f"{name}: {summary_line(results[name])}", flush=True)

    names = [v.name for v in views]
    run_a, run_b = data / f"{names[0]}.dcm", data / f"{names[min(3, len(names) - 1)]}.dcm"
    summary = reconstruct(run_a, run_b, out / "reconstruct", weights=args.weights, side=args.side)
    timing = ", ".join(f"{k} {v:.1f} s" for k, v in summary["timings"])

    lines, per_pair = compare_tables(results, seconds, names, pairs)
    body = (f"{len(names)} real static-phantom runs, {len(pairs)} pairs × {len(names) - 2} held-out views; masks: the "
            f"shipped U-Net on each run's full-contrast frame; ε = 3 mm; SBP side `{args.side}` (the phantom's tree "
            f"side is not in its headers). Coverage is recall-like, distance precision-like (see stages/evaluate/heldout.py). "
            f"Runs whose table moved are placed on {names[0]}'s table first (header table positions). "
            f"Per-row JSON: `{out.relative_to(ROOT) if out.is_relative_to(ROOT) else out}/<method>.json`.\n\n"
            + "\n".join(lines) + "\n\n"
            f"`autocar reconstruct {run_a.name} {run_b.name}` (its default method, {summary['method']}) ran end to end: "
            f"{len(summary['pairs'])} "
            f"key-frame pair(s), warnings: {len(summary['warnings'])}; stage timings: {timing}.\n\n"
            "Per pair (mean over its held-out views):\n\n" + "\n".join(per_pair) + "\n")
    cmd = "python benchmarks/bench_heldout.py" + (f" --pairs {args.pairs}" if args.pairs else "") + (
        f" --methods {args.methods}" if args.methods != DEFAULT_METHODS else "") + (
        f" --weights {args.weights}" if args.weights else "")
    write_section("heldout_sbp", "Held-out-view check on the real phantom: SBP vs visual hull", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
