"""Measure dropping unpredicted branches (stages.graph.redundancy.drop_unsupported_branches) on cases never
evaluated on, and choose what counts as the network's support.

Same tuning set and reconstructions as ``tune_graph_threshold.py`` (data/re_tuning, seeds
:data:`stages.render.products.SEED_RE_TUNING` +, shipped SBP weights, our segmentation and key frames).
``graph-opt`` (with completion and ghost dropping) is rerun on each case's predictions without the step and
with it at several settings — (occupancy a supporting voxel needs, fraction of a branch that must be
supported, reach in mm) — and scored with the paper's coverage / EPE / accuracy plus the 3D centreline
error against the simulator's tree. The setting is chosen for accuracy. The step is opt-in
(``graph-opt --drop-unsupported``): on data-re it did not help (``bench_graph_completion_re.py``).

Run:  python benchmarks/tune_unsupported_drop.py [--cases 6] [--settings 0.5:0.1:0.75,0.2:0.1:0.75,...]
Writes out/tune_graph/ (reconstructions, shared with the other graph tunings) and
docs/benchmarks/unsupported_drop.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

KEYS = ("occupancy", "min_support", "reach_mm")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6, help="tuning cases (seeds SEED_RE_TUNING + 0 … n−1)")
    ap.add_argument("--settings",
                    default="0.5:0.1:0.75,0.5:0.1:1.0,0.5:0.2:0.75,0.2:0.1:0.75,0.3:0.15:0.75,0.7:0.1:0.75",
                    help="occupancy:min_support:reach_mm triples to try")
    ap.add_argument("--data", default=str(ROOT / "data" / "re_tuning"))
    ap.add_argument("--out", default=str(ROOT / "out" / "tune_graph"))
    args = ap.parse_args(argv)
    grid = [tuple(float(v) for v in t.split(":")) for t in args.settings.split(",")]

    from machine import write_section
    from tune_graph_completion import OFF, report_settings
    from tune_graph_threshold import score_tuning_cases

    from stages.graph.redundancy import drop_unsupported_branches

    default = tuple(drop_unsupported_branches.__kwdefaults__[k] for k in KEYS)
    settings = {OFF: {"drop_unsupported": False}}
    settings.update({f"occupancy ≥ {o:g}, support < {s:g}, reach {r:g} mm": {
        "drop_unsupported": True, "unsupported_kw": dict(zip(KEYS, (o, s, r)))} for o, s, r in grid})
    cases, scores = score_tuning_cases(Path(args.data), Path(args.out), args.cases, settings)

    def label_of(n):
        is_default = n != OFF and tuple(settings[n]["unsupported_kw"][k] for k in KEYS) == default
        return "off" if n == OFF else f"on, {n}" + (" (default)" if is_default else "")

    body = report_settings(cases, scores, label_of, "dropping unpredicted branches",
                           (6, "branches dropped per key frame"), ", graph completion and ghost dropping on")
    cmd = "python benchmarks/tune_unsupported_drop.py" + "".join(
        f" --{k} {getattr(args, k)}" for k in ("cases", "settings") if getattr(args, k) != ap.get_default(k))
    write_section("unsupported_drop", "Dropping branches the network did not predict, measured on held-apart cases",
                  cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
