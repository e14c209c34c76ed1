"""Benchmark: time of the four 3D metrics on one coronary-sized case at 0.5 mm → docs/benchmarks/metrics.md.

Dice, clDice, Chamfer and HD95 (:func:`stages.core.metrics.metrics_3d`, the whole path: common grid, skeletons,
marching cubes, KD-trees) with 2 threads, on a synthetic tree and a prediction that differs from it (tubes
shifted 0.6 mm, radii ×1.2, one branch missing, a spurious one added), and on a hull-sized prediction.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import min_median, repeat_timing, timed, write_section  # noqa: E402
from stages.core.metrics import metrics_3d  # noqa: E402
from stages.core.voxels import SparseVoxels  # noqa: E402


def random_tree(seed: int, n_branches: int = 14, box: float = 55.0):
    """Polylines (list of (points K×3, radius K)) of a random branching tree, mm around the origin."""
    rng, branches, d0 = np.random.default_rng(seed), [], np.array([0.3, 0.2, -1.0])
    queue = [(np.array([0.0, 0.0, box * 0.6]), d0 / np.linalg.norm(d0), 2.0)]
    while queue and len(branches) < n_branches:
        p, d, r = queue.pop(0)
        pts, rad = [p], [r]
        for _ in range(int(rng.uniform(40, 90) / 0.5)):
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


def voxelise(branches, shift=(0, 0, 0), radius_scale=1.0) -> SparseVoxels:
    """The tree's tubes on the 0.5 mm grid (the correspondence method's tube rasteriser), fully occupied."""
    from stages.twoview.method import Polyline3D, tubes_to_voxels

    tubes = [Polyline3D(pts + np.asarray(shift), rad * radius_scale, np.ones(len(pts), bool)) for pts, rad in branches]
    v = tubes_to_voxels(tubes, 0.5)
    return SparseVoxels(v.coords, v.voxel_size, v.origin, {"occupancy": np.ones(len(v), np.float32)})


def make_case(seed: int = 0):
    """(prediction, truth): the tree, and the tree with its last branch swapped, shifted, radii × 1.2."""
    tree = random_tree(seed)
    return voxelise(tree[:-1] + random_tree(seed + 100, n_branches=1), shift=(0.6, -0.3, 0.2), radius_scale=1.2), voxelise(tree)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args(argv)
    from scipy import ndimage

    from stages.core import metrics as m

    pred, truth = make_case(0)
    res = metrics_3d(pred, truth, workers=2)  # warm-up (imports, caches)
    times = repeat_timing(lambda: metrics_3d(pred, truth, workers=2), args.repeats, warmup=0)["times"]
    # a visual-hull-sized prediction: the truth dilated by 4 voxels (2 mm), about 10× its volume
    dense, lo = truth.to_dense(pad=5)
    big = SparseVoxels.from_dense(ndimage.binary_dilation(dense, iterations=4), 0.5, truth.origin, lo)
    big.features["occupancy"] = np.ones(len(big), np.float32)
    times_big = repeat_timing(lambda: metrics_3d(big, truth, workers=2), args.repeats, warmup=0)["times"]
    # per-part split of one run, for the record
    grid, t_grid = timed(m.common_grid, pred, truth)
    parts = {"common grid": t_grid, "Dice": timed(m.dice, grid.pred, grid.truth)[1],
             "clDice (2 skeletons)": timed(m.cldice, grid.pred, grid.truth)[1]}
    (sp, sg), parts["marching cubes (2)"] = timed(lambda: [m.surface_points(g, grid.origin, grid.voxel_size)
                                                          for g in (grid.pred, grid.truth)])
    parts["KD-trees CD+HD95"] = timed(m.chamfer_hd95, sp, sg, workers=2)[1]
    shape = grid.pred.shape
    body = f"""Machine shared with other jobs: timings are noisy, min and median given.

Case: synthetic coronary-like tree, truth {len(truth)} voxels, prediction {len(pred)} voxels at 0.5 mm, common grid
{shape[0]}×{shape[1]}×{shape[2]}; {len(sp)} + {len(sg)} surface points.

| what | min s | median s | target |
|---|---|---|---|
| all four metrics (`metrics_3d`, 2 workers) | {min_median(times)} | ≤ 5 s |
| same, hull-sized prediction ({len(big)} voxels: truth dilated 2 mm) | {min_median(times_big)} | ≤ 5 s |

One run split by part (s): {", ".join(f"{k} {v:.2f}" for k, v in parts.items())}.

Values on this case: Dice {res['dice']:.3f}, clDice {res['cldice']:.3f}, CD {res['chamfer_mm']:.2f} mm, HD95 {res['hd95_mm']:.2f} mm.
"""
    print(write_section("metrics", "3D metrics speed", f"python benchmarks/bench_metrics.py --repeats {args.repeats}",
                        body).read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
