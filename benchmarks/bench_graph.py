"""Benchmark: graph optimisation time per key frame (target ≤ 2 s on 2 cores) → docs/benchmarks/graph.md.

The paper reports ~6 s per key frame on a GPU. Case: :func:`stages.graph.synthetic.moving_case` (a coronary-sized
tree through 4 key frames of smooth motion, a noisy prediction and two masks each). Timed: the whole graph
optimisation, (frames_to_inputs + optimise_frames) / key frames; also the accuracy against the known truth.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("MKL_NUM_THREADS", "2")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import min_median, timed, write_section  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args(argv)
    import torch  # noqa: F401  (import cost kept out of the timings)

    from stages.graph.optimise import optimise_frames
    from stages.graph.stage import frames_to_inputs
    from stages.graph.synthetic import moving_case, tracking_errors

    tree, frames, truths = moving_case()
    K = len(frames)
    optimise_frames(frames_to_inputs(frames[:2]))  # warm-up (imports, first-call costs)
    inits, opts = [], []
    for _ in range(args.repeats):
        fin, t_init = timed(frames_to_inputs, frames)
        tracked, t_opt = timed(optimise_frames, fin)
        inits.append(t_init / K)
        opts.append(t_opt / K)
    total = [a + b for a, b in zip(inits, opts)]
    rows = [f"| kf{k} | {e['nodes']} | {e['bifurcations']} / {e['true_bifurcations']} | {e['dist_mean']:.2f} | "
            f"{e['dist_p95']:.2f} | {e['correspondence']:.2f} | {e['radius_median']:.2f} |"
            for k, e in enumerate(tracking_errors(tracked.graphs, truths))]
    body = f"""
Case: synthetic coronary-sized tree ({tree.length():.0f} mm of centreline, {len(tree.bifurcations())} bifurcations,
radii 0.7–2 mm), {K} key frames of smooth motion (up to 9° rotation, 3.5 mm bend, 3 mm translation); per frame a
noisy sparse prediction of ~{int(np.mean([len(f.voxels) for f in frames]))} voxels at 0.5 mm and two 512² masks. Threads: OMP 2; the L-BFGS runs torch
single-threaded on purpose (tensors are small; on this loaded machine 2 torch threads were ~20× slower).
The machine is shared with other jobs, so timings are noisy: min and median of {args.repeats} repeats.

| per key frame | min s | median s |
|---|---|---|
| **graph optimisation, total** (target ≤ 2 s) | {min_median(total, '**{:.2f}**')} |
| graph initialisation + 2D centrelines | {min_median(inits)} |
| tracking (matching + L-BFGS + radius fusion) | {min_median(opts)} |

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
