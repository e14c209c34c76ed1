"""Benchmark: the renderer's training-pair throughput (two 512² silhouettes + augmentation) → docs/benchmarks/render.md.

Run: ``.venv/bin/python benchmarks/bench_render.py``. Cases: prepared cases from ``data/se/cases`` when present
(the procedural trees), else the tube trees of :mod:`stages.render.phantom`.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import repeat_timing, write_section  # noqa: E402


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # --help; no options
    from stages.core.errors import UserError
    from stages.core.prepared_case import PreparedCase, find_cases
    from stages.poses import PoseModel
    from stages.render.pairs import render_pair, simplified_for_rendering
    from stages.render.phantom import tube_case

    refused = [0]

    def attempt(case, rng, **kw):
        # a tree that fits no drawn placement is refused after 20 tries; training skips it and pays the time
        try:
            render_pair(case, model, rng, size=512, **kw)
        except UserError:
            refused[0] += 1

    found = find_cases(ROOT / "data" / "se" / "cases") if (ROOT / "data" / "se" / "cases").exists() else []
    full = [PreparedCase.load(p) for p in found[:4]] or [tube_case(s) for s in (1, 2, 3, 4)]
    # what training renders: meshes decimated to ≤ 60k faces (stages.render.pairs.simplified_for_rendering)
    cases = [simplified_for_rendering(c) for c in full]
    model = PoseModel.default(seed=0)
    rows = []
    for label, use, kw in (("2D warp 2 px RMS", cases, dict(misalign_px=2.0, misalign_3d=0.0)),
                           ("2D warp + 3D phase (p = 0.5)", cases, dict(misalign_px=2.0, misalign_3d=0.5)),
                           ("2D warp 2 px RMS, full prep-ct mesh", full, dict(misalign_px=2.0, misalign_3d=0.0))):
        rng = np.random.default_rng(0)
        attempt(use[0], rng, **kw)  # warm-up
        times = repeat_timing(lambda: [attempt(use[i % len(use)], rng, **kw) for i in range(20)], 5, warmup=0)["times"]
        rates = [20 / t for t in times]
        rows.append(f"| {label} | {min(rates):.1f} | {np.median(rates):.1f} | {max(rates):.1f} | ≥ 10 on 2 cores |")
    src = "procedural trees from data/se/cases" if found else "tube test trees (stages.render.phantom)"
    body = (f"Torch threads irrelevant (NumPy only, single process). Cases: {len(cases)} {src}, mean "
            f"{int(np.mean([len(c.faces) for c in cases]))} mesh faces as rendered in training (decimated from "
            f"{int(np.mean([len(c.faces) for c in full]))}). One pair = pose pair from the default pose model, placement "
            "translation ±10 mm, in-plane jitter ±8 px, two 512² silhouettes (exact triangle raster of the lumen mesh), "
            "TPS warp of view b. 5 repeats of 20 pairs; the machine is shared with other jobs, so min/median/max are given.\n\n"
            "| augmentation | pairs/s min | median | max | target |\n|---|---|---|---|---|\n" + "\n".join(rows) +
            f"\n\nPairs refused because the tree fits no drawn placement (counted in the time): {refused[0]}.\n\n"
            "One process uses one core; a training data loader with 2 workers doubles the rate.")
    print(write_section("render", "Renderer: training pairs", ".venv/bin/python benchmarks/bench_render.py", body).read_text())


if __name__ == "__main__":
    main()
