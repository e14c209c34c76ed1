"""Benchmark: the renderer's training-pair throughput (two 512² silhouettes + augmentation) → docs/benchmarks/render.md.

Writes docs/benchmarks/render.md. Run: ``.venv/bin/python benchmarks/bench_render.py``.
Uses a prepared case from ``data/se/cases`` when present (the procedural trees), else the tube tree of
:mod:`stages.render.phantom`; reports min and median of repeats (the machine is shared, timings are noisy).
"""

from __future__ import annotations

import datetime
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main() -> None:
    from machine import machine_description
    from stages.poses import PoseModel
    from stages.core.prepared_case import PreparedCase, find_cases
    from stages.core.errors import UserError
    from stages.render.pairs import render_pair, simplified_for_rendering

    refused = [0]

    def attempt(case, rng, **kw):
        # a tree that fits no drawn placement is refused after 20 tries; training skips it and pays the time
        try:
            render_pair(case, model, rng, size=512, **kw)
        except UserError:
            refused[0] += 1
    from stages.render.phantom import tube_case

    found = find_cases(ROOT / "data" / "se" / "cases") if (ROOT / "data" / "se" / "cases").exists() else []
    full = [PreparedCase.load(p) for p in found[:4]] or [tube_case(s) for s in (1, 2, 3, 4)]
    # what training renders: meshes decimated to ≤ 60k faces (stages.render.pairs.simplified_for_rendering)
    cases = [simplified_for_rendering(c) for c in full]
    model = PoseModel.default(seed=0)
    rows = []
    for label, kw in (("2D warp 2 px RMS", dict(misalign_px=2.0, misalign_3d=0.0)),
                      ("2D warp + 3D phase (p = 0.5)", dict(misalign_px=2.0, misalign_3d=0.5)),
                      ("2D warp 2 px RMS, full prep-ct mesh", dict(misalign_px=2.0, misalign_3d=0.0, _full=True))):
        use = full if kw.pop("_full", False) else cases
        rng = np.random.default_rng(0)
        for c in use[:1]:
            attempt(c, rng, **kw)  # warm-up
        rates = []
        for rep in range(5):
            n = 20
            t0 = time.perf_counter()
            for i in range(n):
                attempt(use[i % len(use)], rng, **kw)
            rates.append(n / (time.perf_counter() - t0))
        rows.append((label, min(rates), float(np.median(rates)), max(rates)))
    faces = int(np.mean([len(c.faces) for c in cases]))
    faces_full = int(np.mean([len(c.faces) for c in full]))
    src = "procedural trees from data/se/cases" if found else "tube test trees (stages.render.phantom)"
    lines = [
        "## Renderer: training pairs",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_render.py` — {datetime.date.today().isoformat()}, {machine_description()}, "
        f"torch threads irrelevant (NumPy only, single process). Cases: {len(cases)} {src}, mean {faces} mesh faces as rendered in training (decimated from {faces_full}). "
        "One pair = pose pair from the default pose model, placement translation ±10 mm, in-plane jitter ±8 px, "
        "two 512² silhouettes (exact triangle raster of the lumen mesh), TPS warp of view b. "
        "5 repeats of 20 pairs; the machine is shared with other jobs, so min/median/max are given.",
        "",
        "| augmentation | pairs/s min | median | max | target |",
        "|---|---|---|---|---|",
    ]
    for label, lo, med, hi in rows:
        lines.append(f"| {label} | {lo:.1f} | {med:.1f} | {hi:.1f} | ≥ 10 on 2 cores |")
    lines.append("")
    lines.append(f"Pairs refused because the tree fits no drawn placement (counted in the time): {refused[0]}.")
    lines.append("")
    lines.append("One process uses one core; a training data loader with 2 workers doubles the rate.")
    out = ROOT / "docs" / "benchmarks" / "render.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
