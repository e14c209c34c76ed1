"""Benchmark: time of the four 3D metrics on one coronary-sized case at 0.5 mm → docs/benchmarks/metrics.md.

The four: Dice, clDice, Chamfer, HD95.

Builds a synthetic tree (seeded random branching tubes in a ~110 mm box, radius 0.8–2 mm, like a left
coronary tree), a prediction that differs from it (tubes shifted 0.6 mm, radii ×1.2, one branch
missing, a spurious branch added), both as SparseVoxels at 0.5 mm, and times
:func:`stages.core.metrics.metrics_3d` (the whole path: common grid, Dice, skeletons, clDice, marching
cubes, KD-trees) with 2 threads. Writes docs/benchmarks/metrics.md.

Run:  python benchmarks/bench_metrics.py [--repeats 5]
"""

from __future__ import annotations

import argparse
import datetime as dt
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from stages.core.metrics import metrics_3d  # noqa: E402
from stages.core.voxels import SparseVoxels  # noqa: E402


def random_tree(seed: int, n_branches: int = 14, box: float = 55.0):
    """Polylines (list of (points K×3, radius K)) of a random branching tree, mm around the origin."""
    rng = np.random.default_rng(seed)
    branches = []
    start = np.array([0.0, 0.0, box * 0.6])
    d0 = np.array([0.3, 0.2, -1.0])
    queue = [(start, d0 / np.linalg.norm(d0), 2.0)]
    while queue and len(branches) < n_branches:
        p, d, r = queue.pop(0)
        pts, rad = [p], [r]
        length = rng.uniform(40, 90)
        for _ in range(int(length / 0.5)):
            d = d + rng.normal(0, 0.06, 3)
            d /= np.linalg.norm(d)
            p = p + 0.5 * d
            if np.any(np.abs(p) > box):
                break
            r = max(r * 0.997, 0.8)
            pts.append(p)
            rad.append(r)
            if rng.random() < 0.02 and len(queue) < 8:
                side = np.cross(d, rng.normal(size=3))
                side /= np.linalg.norm(side)
                queue.append((p.copy(), (d + side) / np.linalg.norm(d + side), max(r * 0.75, 0.8)))
        branches.append((np.array(pts), np.array(rad)))
    return branches


def voxelise(branches, voxel_size=0.5, shift=(0, 0, 0), radius_scale=1.0) -> SparseVoxels:
    """Voxels whose centre lies within the local radius of a polyline (exact per sample point)."""
    sets = []
    for pts, rad in branches:
        pts = pts + np.asarray(shift)
        rad = rad * radius_scale
        rmax = rad.max()
        k = int(np.ceil(rmax / voxel_size)) + 1
        off = np.stack(np.meshgrid(*[np.arange(-k, k + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
        base = np.rint(pts / voxel_size).astype(np.int64)
        cand = (base[:, None, :] + off[None]).reshape(-1, 3)
        owner = np.repeat(np.arange(len(pts)), len(off))
        d = np.linalg.norm(cand * voxel_size - pts[owner], axis=1)
        sets.append(cand[d <= rad[owner]])
    coords = np.unique(np.concatenate(sets), axis=0)
    return SparseVoxels(coords, voxel_size, np.zeros(3), {"occupancy": np.ones(len(coords), np.float32)})


def make_case(seed: int = 0):
    tree = random_tree(seed)
    truth = voxelise(tree)
    pred_tree = tree[:-1] + random_tree(seed + 100, n_branches=1)
    pred = voxelise(pred_tree, shift=(0.6, -0.3, 0.2), radius_scale=1.2)
    return pred, truth


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=str(ROOT / "docs" / "benchmarks" / "metrics.md"))
    args = ap.parse_args(argv)
    from machine import machine_description

    pred, truth = make_case(0)
    metrics_3d(pred, truth, workers=2)  # warm-up (imports, caches)
    times, res = [], None
    stages = {}
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        res = metrics_3d(pred, truth, workers=2)
        times.append(time.perf_counter() - t0)
    # a visual-hull-sized prediction: the truth dilated by 4 voxels (2 mm), about 10× its volume
    from scipy import ndimage

    dense, lo = truth.to_dense(pad=5)
    big = SparseVoxels.from_dense(ndimage.binary_dilation(dense, iterations=4), 0.5, truth.origin, lo)
    big.features["occupancy"] = np.ones(len(big), np.float32)
    times_big = []
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        metrics_3d(big, truth, workers=2)
        times_big.append(time.perf_counter() - t0)
    # per-part split of one run, for the record
    from stages.core import metrics as m
    t = time.perf_counter(); grid = m.common_grid(pred, truth); stages["common grid"] = time.perf_counter() - t
    t = time.perf_counter(); m.dice(grid.pred, grid.truth); stages["Dice"] = time.perf_counter() - t
    t = time.perf_counter(); m.cldice(grid.pred, grid.truth); stages["clDice (2 skeletons)"] = time.perf_counter() - t
    t = time.perf_counter()
    sp = m.surface_points(grid.pred, grid.origin, grid.voxel_size)
    sg = m.surface_points(grid.truth, grid.origin, grid.voxel_size)
    stages["marching cubes (2)"] = time.perf_counter() - t
    t = time.perf_counter(); m.chamfer_hd95(sp, sg, workers=2); stages["KD-trees CD+HD95"] = time.perf_counter() - t
    shape = grid.pred.shape
    lines = [
        "## 3D metrics speed",
        "",
        f"Command: `python benchmarks/bench_metrics.py --repeats {args.repeats}`  ",
        f"Machine: {machine_description()} (shared with other jobs: timings are noisy, min and median given)  ",
        f"Date: {dt.date.today().isoformat()}",
        "",
        f"Case: synthetic coronary-like tree, truth {len(truth)} voxels, prediction {len(pred)} voxels at 0.5 mm, "
        f"common grid {shape[0]}×{shape[1]}×{shape[2]}; {len(sp)} + {len(sg)} surface points.",
        "",
        "| what | min s | median s | target |",
        "|---|---|---|---|",
        f"| all four metrics (`metrics_3d`, 2 workers) | {min(times):.2f} | {statistics.median(times):.2f} | ≤ 5 s |",
        f"| same, hull-sized prediction ({len(big)} voxels: truth dilated 2 mm) | {min(times_big):.2f} | "
        f"{statistics.median(times_big):.2f} | ≤ 5 s |",
        "",
        "One run split by part (s): " + ", ".join(f"{k} {v:.2f}" for k, v in stages.items()) + ".",
        "",
        f"Values on this case: Dice {res['dice']:.3f}, clDice {res['cldice']:.3f}, "
        f"CD {res['chamfer_mm']:.2f} mm, HD95 {res['hd95_mm']:.2f} mm.",
        "",
    ]
    text = "\n".join(lines)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(text)
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
