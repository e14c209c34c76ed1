"""Ablation on data-re: the shipped pipeline with and without graph completion from the 2D views.

Uses Table 2's L8 reconstructions (``out/table2/L8``, reconstructed here only if that cache is missing or
stale): ``graph-opt`` is rerun on each case's predictions with ``complete=False`` and with the default
completion (stages/graph/complete.py), and both are scored as Table 2 scores them. Per-case means, then
paired over the cases (Wilcoxon signed-rank). The completion's gate was chosen on the tuning cases
(``tune_graph_completion.py``), not here.

Run:  python benchmarks/bench_graph_completion_re.py [--data data/re] [--out out/table2]
Writes docs/benchmarks/graph_completion_re.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

COLUMNS = [("coverage", "coverage ↑", 3), ("EPE", "EPE (mm) ↓", 2), ("accuracy", "accuracy ↑", 3),
           ("centreline", "3D centreline error (mm) ↓", 2), ("branches", "branches from 2D per key frame", 1)]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "re"))
    ap.add_argument("--out", default=str(ROOT / "out" / "table2"), help="Table 2's reconstruction cache")
    args = ap.parse_args(argv)

    from scipy.stats import wilcoxon

    from machine import write_section
    from re_eval import case_jobs, re_cases_or_say, run_case
    from tune_graph_threshold import score_settings

    cases = re_cases_or_say(Path(args.data))
    if not cases:
        return 0
    settings = {"without completion": {"complete": False}, "with completion (shipped)": {"complete": True}}
    per_case = {name: [] for name in settings}
    refused = []
    for job in case_jobs([("L8", "sbp", None)], cases, args.out):
        res = run_case(job)
        if "refused" in res:
            refused.append(res["case"])
            continue
        scores = score_settings(Path(job[4]), Path(job[3]), settings)
        for name in settings:
            per_case[name].append(np.nanmean(np.asarray(scores[name], float), 0))
        print(res["case"], {n: np.round(per_case[n][-1], 3).tolist() for n in settings}, flush=True)

    off, on = (np.asarray(per_case[n]) for n in settings)
    lines = ["| L8 graph-opt | " + " | ".join(c[1] for c in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    for name, arr in zip(settings, (off, on)):
        lines.append(f"| {name} | " + " | ".join(f"{arr[:, i].mean():.{c[2]}f}" for i, c in enumerate(COLUMNS)) + " |")
    paired = []
    for i, (label, _, digits) in enumerate(COLUMNS[:4]):
        d = on[:, i] - off[:, i]
        p = wilcoxon(on[:, i], off[:, i]).pvalue
        paired.append(f"{label} {d.mean():+.{digits}f} (higher on {int((d > 0).sum())} of {len(d)} cases, p = {p:.2g})")
    body = (f"{len(off)} data-re cases ({len(refused)} refused by the pipeline: {', '.join(refused) or 'none'}), "
            "shipped SBP weights, our segmentation and key frames, Table 2's scoring (60 simulator centreline nodes "
            "per key-frame pair; 3D centreline error against the simulator's tree at the midpoint of the two frames). "
            "Means over cases of the per-case means over key-frame pairs.\n\n" + "\n".join(lines) +
            "\n\nWith minus without, paired over the cases (Wilcoxon signed-rank): " + "; ".join(paired) + ".\n")
    write_section("graph_completion_re", "Graph completion from the 2D views: ablation on data-re",
                  "python benchmarks/bench_graph_completion_re.py", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
