"""Benchmark: training-pair throughput of the renderer (two 512² silhouettes + augmentation per pair).

Writes docs/benchmarks/render.md. Run: ``.venv/bin/python benchmarks/bench_render.py``.
Uses a prepared case from ``data/se/cases`` when present (the procedural trees), else the tube tree of
:mod:`stages.render.phantom`; reports min and median of repeats (the machine is shared, timings are noisy).
"""

from __future__ import annotations

import datetime
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def machine() -> str:
    cpu = "unknown CPU"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
        mem = int(open("/proc/meminfo").readline().split()[1]) / 2**20
    except OSError:
        mem = float("nan")
    nproc = subprocess.run(["nproc"], capture_output=True, text=True).stdout.strip()
    return f"nproc {nproc}, {cpu}, {mem:.0f} GiB RAM, Python {platform.python_version()}"


def main() -> None:
    from stages.poses import PoseModel
    from stages.prepared_case import PreparedCase, find_cases
    from stages.render.pairs import render_pair
    from stages.render.phantom import tube_case

    found = find_cases(ROOT / "data" / "se" / "cases") if (ROOT / "data" / "se" / "cases").exists() else []
    cases = [PreparedCase.load(p) for p in found[:4]] or [tube_case(s) for s in (1, 2, 3, 4)]
    model = PoseModel.default(seed=0)
    rows = []
    for label, kw in (("2D warp 2 px RMS", dict(misalign_px=2.0, misalign_3d=0.0)),
                      ("2D warp + 3D phase (p = 0.5)", dict(misalign_px=2.0, misalign_3d=0.5))):
        rng = np.random.default_rng(0)
        for c in cases[:1]:
            render_pair(c, model, rng, size=512, **kw)  # warm-up
        rates = []
        for rep in range(5):
            n = 20
            t0 = time.perf_counter()
            for i in range(n):
                render_pair(cases[i % len(cases)], model, rng, size=512, **kw)
            rates.append(n / (time.perf_counter() - t0))
        rows.append((label, min(rates), float(np.median(rates)), max(rates)))
    faces = int(np.mean([len(c.faces) for c in cases]))
    src = "procedural trees from data/se/cases" if found else "tube test trees (stages.render.phantom)"
    lines = [
        "## Renderer: training pairs",
        "",
        f"Command: `.venv/bin/python benchmarks/bench_render.py` — {datetime.date.today().isoformat()}, {machine()}, "
        f"torch threads irrelevant (NumPy only, single process). Cases: {len(cases)} {src}, mean {faces} mesh faces. "
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
    lines.append("One process uses one core; a training data loader with 2 workers doubles the rate.")
    out = ROOT / "docs" / "benchmarks" / "render.md"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
