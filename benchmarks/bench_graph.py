"""Benchmark: graph optimisation time per key frame (target ≤ 2 s on 2 cores) → docs/benchmarks/graph.md.

The paper reports ~6 s per key frame on a GPU.

Case: a synthetic coronary-sized tree (:func:`stages.graph.synthetic.synthetic_tree`, 120 mm main branch and
10 side branches), moved through 4 key frames by a smooth cardiac-like motion (rotation up to 9°, bend up
to 3.5 mm, translation up to 3 mm), each frame given as a noisy sparse prediction at 0.5 mm (occupancy,
centreness) plus two 512² vessel masks from C-arm cameras (LAO 30/CRA 20, RAO 35/CAU 15).

Timed per key frame, the whole graph optimisation: graph initialisation of the frame's prediction
(threshold, thinning, MST, bridging, spurs, radii), 2D centreline extraction of its masks, and its share of
the tracking (3D + 2D Algorithm-1 matching and L-BFGS of the deformation graph, radius fusion) — i.e.
(time of frames_to_inputs + optimise_frames) / number of key frames. Also reports the accuracy against
the known truth. Writes docs/benchmarks/graph.md.

Run:  python benchmarks/bench_graph.py [--repeats 3]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("MKL_NUM_THREADS", "2")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import write_section  # noqa: E402


def make_case(seed: int = 7, n_frames: int = 4):
    from stages.core.geometry import Camera
    from stages.graph.io import PredictionFrame
    from stages.graph.synthetic import render_mask, smooth_warp, synthetic_tree, voxelise_prediction

    tree = synthetic_tree(seed, n_side=10, main_length=120.0)
    cams = {"a": Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512),
            "b": Camera.from_carm(-35, -15, 1100, 750, 0.3, 512, 512)}
    frames, truths = [], []
    phase = np.linspace(0, 1, n_frames)
    for k, s in enumerate(phase):
        t = tree.copy(nodes=smooth_warp(tree.nodes, tree.nodes.mean(0), angle_deg=9 * s, bend_mm=3.5 * s,
                                        translation=(1.5 * s, -1.0 * s, 2.5 * s)))
        truths.append(t)
        frames.append(PredictionFrame(f"kf{k}", voxelise_prediction(t, noise=0.05, seed=k),
                                      {v: render_mask(t, c) for v, c in cams.items()}, cams))
    return tree, frames, truths


def run_once(frames):
    from stages.graph.optimise import optimise_frames
    from stages.graph.stage import frames_to_inputs

    t0 = time.perf_counter()
    fin = frames_to_inputs(frames)
    t1 = time.perf_counter()
    tracked = optimise_frames(fin)
    t2 = time.perf_counter()
    return fin, tracked, t1 - t0, t2 - t1


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    import torch  # noqa: F401  (import cost kept out of the timings)
    from scipy.spatial import cKDTree

    tree, frames, truths = make_case()
    K = len(frames)
    run_once(frames[:2])  # warm-up (imports, first-call costs)
    per_frame, inits, opts = [], [], []
    result = None
    for _ in range(args.repeats):
        fin, tracked, t_init, t_opt = run_once(frames)
        per_frame.append((t_init + t_opt) / K)
        inits.append(t_init / K)
        opts.append(t_opt / K)
        result = (fin, tracked)
    fin, tracked = result
    n_vox = int(np.mean([len(f.voxels) for f in frames]))
    rows = []
    ref_idx = cKDTree(truths[0].nodes).query(tracked.graphs[0].nodes)[1]
    for k, (g, t) in enumerate(zip(tracked.graphs, truths)):
        d = cKDTree(t.sample(0.1)[0]).query(g.nodes)[0]
        corr = np.linalg.norm(g.nodes - t.nodes[ref_idx], axis=1)
        r_err = np.abs(g.radius - t.radius[cKDTree(t.nodes).query(g.nodes)[1]])
        rows.append(f"| kf{k} | {len(g)} | {len(g.bifurcations())} / {len(t.bifurcations())} | {d.mean():.2f} | "
                    f"{np.percentile(d, 95):.2f} | {corr.mean():.2f} | {np.median(r_err):.2f} |")
    body = f"""
Case: synthetic coronary-sized tree ({tree.length():.0f} mm of centreline, {len(tree.bifurcations())} bifurcations,
radii 0.7–2 mm), {K} key frames of smooth motion (up to 9° rotation, 3.5 mm bend, 3 mm translation); per frame a
noisy sparse prediction of ~{n_vox} voxels at 0.5 mm and two 512² masks. Threads: OMP 2; the L-BFGS runs torch
single-threaded on purpose (tensors are small; on this loaded machine 2 torch threads were ~20× slower).
The machine is shared with other jobs, so timings are noisy: min and median of {args.repeats} repeats.

| per key frame | min s | median s |
|---|---|---|
| **graph optimisation, total** (target ≤ 2 s) | **{min(per_frame):.2f}** | **{statistics.median(per_frame):.2f}** |
| graph initialisation + 2D centrelines | {min(inits):.2f} | {statistics.median(inits):.2f} |
| tracking (matching + L-BFGS + radius fusion) | {min(opts):.2f} | {statistics.median(opts):.2f} |

Accuracy of the tracked graphs against the known truth (mm; correspondence = each tracked node vs the true
position of the truth node it started from in key frame kf0, so sliding along vessels counts as error; it
grows along the chain of key frames because each frame-to-frame registration can slide a little). Where more
bifurcations are found than exist, synthetic branches pass within ~0.5 mm of each other and merge at 0.5 mm
voxels (checked for seed 7: three branches 0.34–0.54 mm apart), a true junction of the voxelised input:

| key frame | nodes | bifurcations (found / true) | mean dist. to true centreline | p95 | mean correspondence error | median radius error |
|---|---|---|---|---|---|---|
""" + "\n".join(rows) + "\n"
    path = write_section("graph", "Graph optimisation speed (per key frame)", "python benchmarks/bench_graph.py "
                         f"--repeats {args.repeats}", body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
