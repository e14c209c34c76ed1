"""Measure ghost-branch dropping (stages.graph.redundancy) on cases never evaluated on, and choose how
much of a terminal branch both views must explain elsewhere before it goes.

Same tuning set and reconstructions as ``tune_graph_threshold.py`` (data/re_tuning, seeds
:data:`stages.render.products.SEED_RE_TUNING` +, shipped SBP weights, our segmentation and key frames).
``graph-opt`` (with completion) is rerun on each case's predictions without dropping and with it at
several values of ``max_shared``, and scored with the paper's coverage / EPE / accuracy plus the 3D
centreline error against the simulator's tree. The value is chosen for accuracy, among the settings
that do not worsen the 3D centreline error.

Run:  python benchmarks/tune_ghost_drop.py [--cases 6] [--shared 0.5,0.6,0.7,0.9] [--radius 1.5]
Writes out/tune_graph/ (reconstructions, shared with the other graph tunings) and
docs/benchmarks/ghost_drop.md.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6, help="tuning cases (seeds SEED_RE_TUNING + 0 … n−1)")
    ap.add_argument("--shared", default="0.5,0.6,0.7,0.9", help="max_shared values to try")
    ap.add_argument("--radius", default="1.5", help="radius_mm values to try (every pair with --shared)")
    ap.add_argument("--data", default=str(ROOT / "data" / "re_tuning"))
    ap.add_argument("--out", default=str(ROOT / "out" / "tune_graph"))
    args = ap.parse_args(argv)
    grid = [(float(m), float(r)) for m in args.shared.split(",") for r in args.radius.split(",")]

    from machine import write_section
    from tune_graph_completion import OFF, report_settings
    from tune_graph_threshold import score_tuning_cases

    from stages.graph.redundancy import drop_doubly_explained

    default = (drop_doubly_explained.__kwdefaults__["max_shared"], drop_doubly_explained.__kwdefaults__["radius_mm"])
    settings = {OFF: {"drop_ghosts": False}}
    settings.update({f"max_shared {m:g}, radius {r:g} mm": {"drop_ghosts": True,
                                                            "ghost_kw": {"max_shared": m, "radius_mm": r}}
                     for m, r in grid})
    cases, scores = score_tuning_cases(Path(args.data), Path(args.out), args.cases, settings)

    def label_of(n):
        is_default = n != OFF and settings[n]["ghost_kw"] == dict(zip(("max_shared", "radius_mm"), default))
        return "off" if n == OFF else f"on, {n}" + (" (default)" if is_default else "")

    body = report_settings(cases, scores, label_of, "ghost dropping", (5, "branches dropped per key frame"),
                           ", graph completion on")
    cmd = "python benchmarks/tune_ghost_drop.py" + "".join(
        f" --{k} {getattr(args, k)}" for k in ("cases", "shared", "radius") if getattr(args, k) != ap.get_default(k))
    write_section("ghost_drop", "Dropping ghost branches, measured on held-apart cases", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
