"""Ablation on data-re: the shipped pipeline with and without its two graph-opt additions, graph
completion from the 2D views and ghost-branch dropping, and with the opt-in third, dropping branches the
network did not predict.

Uses Table 2's L8 reconstructions (``out/table2/L8``, reconstructed here only if that cache is missing or
stale): ``graph-opt`` is rerun on each case's predictions with none of them, with completion only
(stages/graph/complete.py), with completion and ghost dropping (stages/graph/redundancy.py; shipped) and
with the opt-in third step too (``drop_unsupported=True``), and each is scored as Table 2 scores them. Per-case means, then paired over the cases
(Wilcoxon signed-rank): each addition against the setting without it. The additions' parameters were
chosen on the tuning cases (``tune_graph_completion.py``, ``tune_ghost_drop.py``,
``tune_unsupported_drop.py``), not here.

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
           ("centreline", "3D centreline error (mm) ↓", 2), ("branches", "branches from 2D per key frame", 1),
           ("ghosts", "ghost branches dropped per key frame", 1),
           ("unsupported", "unpredicted branches dropped per key frame", 1)]


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
    settings = {"none": {"complete": False, "drop_ghosts": False, "drop_unsupported": False},
                "completion only": {"complete": True, "drop_ghosts": False, "drop_unsupported": False},
                "completion + ghost dropping (shipped)": {"complete": True, "drop_ghosts": True,
                                                          "drop_unsupported": False},
                "+ dropping unpredicted branches (opt-in)": {"complete": True, "drop_ghosts": True,
                                                             "drop_unsupported": True}}
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

    arrays = {name: np.asarray(per_case[name]) for name in settings}
    lines = ["| L8 graph-opt | " + " | ".join(c[1] for c in COLUMNS) + " |", "|---" * (len(COLUMNS) + 1) + "|"]
    for name, arr in arrays.items():
        lines.append(f"| {name} | " + " | ".join(f"{arr[:, i].mean():.{c[2]}f}" for i, c in enumerate(COLUMNS)) + " |")
    names = list(settings)
    paired = []
    for base, new, what in ((names[0], names[1], "Completion (completion only − none)"),
                            (names[1], names[2], "Ghost dropping (shipped − completion only)"),
                            (names[2], names[3], "Dropping unpredicted branches (opt-in − shipped)")):
        parts = []
        for i, (label, _, digits) in enumerate(COLUMNS[:4]):
            d = arrays[new][:, i] - arrays[base][:, i]
            p = wilcoxon(arrays[new][:, i], arrays[base][:, i]).pvalue if np.any(d != 0) else 1.0
            parts.append(f"{label} {d.mean():+.{digits}f} (higher on {int((d > 0).sum())} of {len(d)} cases, "
                         f"p = {p:.2g})")
        paired.append(f"{what}: " + "; ".join(parts) + ".")
    n_cases = len(arrays[names[0]])
    body = (f"{n_cases} data-re cases ({len(refused)} refused by the pipeline: {', '.join(refused) or 'none'}), "
            "shipped SBP weights, our segmentation and key frames, Table 2's scoring (60 simulator centreline nodes "
            "per key-frame pair; 3D centreline error against the simulator's tree at the midpoint of the two frames). "
            "Means over cases of the per-case means over key-frame pairs.\n\n" + "\n".join(lines) +
            "\n\nPaired over the cases (Wilcoxon signed-rank):\n\n" + "\n".join(f"- {p}" for p in paired) + "\n")
    write_section("graph_completion_re", "Graph completion and ghost dropping: ablation on data-re",
                  "python benchmarks/bench_graph_completion_re.py", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
