"""Benchmark: a learned Table 1 baseline (dense back-projection L2, or concatenation L1) on data-se.

Same evaluation as benchmarks/bench_sbp_se.py (the shared loop of benchmarks/se_eval.py): every pair
of ``data/se/pairs.zarr``, ground-truth silhouettes, view B re-rendered with the default 2 px RMS TPS
misalignment seeded per pair, the baseline's 0.5 mm prediction scored by
:func:`stages.metrics.metrics_3d`.

Run:  python benchmarks/bench_baselines_se.py --model dense|concat [--weights FILE] [--limit N]
Writes docs/benchmarks/baseline_<model>_se.md and the per-case JSON ``--json`` (default
out/baselines/<model>_se.json: rows + aggregate + parameters). Missing data-se or weights: says so,
exits 0.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

TITLES = {"dense": "L2-style dense back-projection (2 mm, 3D U-Net)",
          "concat": "L1-style channel concatenation (no geometry)"}


def _rel(path: Path):
    full = Path(path).resolve()
    return full.relative_to(ROOT) if full.is_relative_to(ROOT) else path


def main(argv=None) -> int:
    from se_eval import add_se_arguments, se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", choices=sorted(TITLES), required=True)
    ap.add_argument("--weights", default=None, help="default: stages/weights/baseline_<model>.pt")
    add_se_arguments(ap)
    ap.add_argument("--json", default=None, help="per-case JSON (default out/baselines/<model>_se.json)")
    args = ap.parse_args(argv)
    from se_eval import METRIC_KEYS, baseline_predictor, evaluate_se

    data = se_or_say(args.data)
    if data is None:
        return 0
    import torch

    from machine import write_section
    from stages.artefacts import write_json
    from stages.baselines import default_weights, load_baseline
    from stages.errors import UserError
    from stages.evaluate import aggregate

    torch.set_num_threads(args.threads)
    weights = Path(args.weights) if args.weights else default_weights(args.model)
    try:
        model = load_baseline(weights)
    except UserError as exc:
        print(f"{exc}. Nothing measured.")
        return 0
    if model.arch != args.model:
        print(f"{weights}: a {model.arch} baseline, not {args.model}. Nothing measured.")
        return 0
    rows = evaluate_se(baseline_predictor(model), data, args.limit, args.misalign_px, workers=args.threads)
    agg = aggregate(rows, list(METRIC_KEYS))
    meta = torch.load(weights, map_location="cpu", weights_only=False).get("meta", {})
    params = {"model": args.model, "weights": str(weights), "misalign_px": args.misalign_px, "pairs": len(rows),
              "training": {k: meta.get(k) for k in ("steps", "seconds", "seed", "budget")}}
    out_json = Path(args.json) if args.json else ROOT / "out" / "baselines" / f"{args.model}_se.json"
    write_json(out_json, {"rows": rows, "aggregate": agg, "parameters": params})

    lines = ["| metric | mean ± sd | median | n | undefined |", "|---|---|---|---|---|"]
    for k in METRIC_KEYS:
        a = agg[k]
        f = "{:.2f}" if k.endswith("_mm") else "{:.3f}"
        if a["mean"] is None:
            lines.append(f"| {k} | n/a | | 0 | {a['n_undefined']} |")
            continue
        lines.append(f"| {k} | {f.format(a['mean'])} ± {f.format(a['sd'] or 0)} | {f.format(a['median'])} | "
                     f"{a['n']} | {a['n_undefined']} |")
    times = [r["seconds"] for r in rows]
    body = (f"Weights: `{_rel(weights)}` "
            f"({meta.get('steps')} steps, {meta.get('seconds')} s of training; {meta.get('budget') or 'budget not recorded'}). "
            f"{len(rows)} pairs of data-se, ground-truth silhouettes, view B with a {args.misalign_px:g} px RMS TPS "
            f"misalignment (seeded per pair), {args.threads} torch threads. Per-case numbers: `{_rel(out_json)}`.\n\n"
            + "\n".join(lines) + "\n\n"
            f"Inference per pair (back-projection or 2D encoding + network + upsampling to 0.5 mm): min {min(times):.2f} s, "
            f"median {statistics.median(times):.2f} s. undefined: Chamfer/HD95 of an empty prediction.\n")
    cmd = f"python benchmarks/bench_baselines_se.py --model {args.model}" + (
        f" --weights {args.weights}" if args.weights else "") + (f" --limit {args.limit}" if args.limit else "")
    write_section(f"baseline_{args.model}_se", f"{TITLES[args.model]} on data-se (Table 1)", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
