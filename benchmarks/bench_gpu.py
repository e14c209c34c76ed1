"""Optional: the SBP network's inference and training step on a CUDA GPU against the CPU, on one pair.

AutoCAR never needs a GPU; this measures what one buys for training, which is what limits the network
(issue #7: the loss gains are flat per pair on this machine's CPU budget). One synthetic two-view pair
(:mod:`stages.graph.synthetic`: a 10-branch tree rendered into two 512² views 60° apart, the shipped
weights' configuration) is prepared once; then, on each device:

* inference: ``SBPNet.predict`` (median of 5 after a warm-up);
* a training step: forward, Dice + BCE loss (:func:`stages.sbp.loss.sbp_loss`) against the tree's own
  occupancy/centreness, backward (median of 5 after a warm-up).

Rendering training pairs is CPU work outside the network (about a second per pair here) and parallelises
over processes, so the network step is what a GPU changes.

Run:  python benchmarks/bench_gpu.py [--threads 2] [--no-write]
Writes docs/benchmarks/gpu.md when a CUDA device is present (else prints the CPU figures only).
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def synthetic_pair(seed: int = 3):
    """(PairInput, targets) of a synthetic tree: targets as :func:`stages.sbp.loss.align_targets` gives."""
    from scipy.spatial import cKDTree

    from stages.geometry import Camera
    from stages.graph.synthetic import render_mask, synthetic_tree
    from stages.sbp.model import SBPConfig, prepare_pair

    tree = synthetic_tree(seed=seed, n_side=10, main_length=120.0)
    cams = [Camera.from_carm(a, b, 1000.0, 750.0, 0.3, 512, 512) for a, b in ((30.0, 20.0), (-30.0, -5.0))]
    masks = [render_mask(tree, c) > 0 for c in cams]
    pair = prepare_pair(masks[0], masks[1], cams[0], cams[1], SBPConfig())
    pts, rad = tree.sample(0.25)
    d, i = cKDTree(pts).query(pair.candidates.world_points())
    inside = d <= rad[i]
    centre = np.clip(1.0 - d / np.maximum(rad[i], 1e-6), 0.0, 1.0) * inside
    targets = {"occupancy": inside.astype(np.float32), "centreness": centre.astype(np.float32),
               "missed_occupancy": 0.0, "missed_centreness": 0.0, "candidate_recall": 1.0}
    return pair, targets


def time_device(model, pair, targets, device: str, repeats: int = 5) -> dict:
    """Median inference and training-step seconds (+ peak GPU memory) of ``model`` on ``device``."""
    import torch

    from stages.sbp.loss import sbp_loss

    model = model.to(device)
    sync = torch.cuda.synchronize if device == "cuda" else (lambda: None)

    def infer():
        model.predict(pair)
        sync()

    def step():
        model.train()
        model.zero_grad(set_to_none=True)
        out = model(pair)
        loss, _ = sbp_loss(out.feats, targets)
        loss.backward()
        sync()

    res = {}
    for name, fn in (("inference_s", infer), ("train_step_s", step)):
        if device == "cuda":
            torch.cuda.reset_peak_memory_stats()
        fn()  # warm-up (CUDA kernels, allocator)
        times = []
        for _ in range(repeats):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        res[name] = float(np.median(times))
        if device == "cuda":
            res[name[:-2] + "_peak_gb"] = torch.cuda.max_memory_allocated() / 1e9
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    ap.add_argument("--no-write", action="store_true", help="print only")
    args = ap.parse_args(argv)

    import torch

    from stages.train import load_weights

    torch.set_num_threads(args.threads)
    t = time.perf_counter()
    pair, targets = synthetic_pair()
    prep_s = time.perf_counter() - t
    model = load_weights()
    rows = {"cpu": time_device(model, pair, targets, "cpu")}
    gpu = torch.cuda.get_device_name(0) if torch.cuda.is_available() else None
    if gpu:
        rows["cuda"] = time_device(model, pair, targets, "cuda")
    print(f"{len(pair.candidates)} candidate voxels; pair preparation {prep_s:.2f} s; {rows}")
    if not gpu or args.no_write:
        return 0

    from machine import write_section

    c, g = rows["cpu"], rows["cuda"]
    lines = ["| device | inference (s) | training step (s) | training pairs/s (network only) | peak GPU memory (GB) |",
             "|---|---|---|---|---|",
             f"| CPU, {args.threads} threads | {c['inference_s']:.3f} | {c['train_step_s']:.3f} | "
             f"{1 / c['train_step_s']:.2f} | – |",
             f"| {gpu} | {g['inference_s']:.3f} | {g['train_step_s']:.3f} | {1 / g['train_step_s']:.1f} | "
             f"{g['train_step_peak_gb']:.2f} |"]
    body = (f"One synthetic two-view pair (10-branch tree, two 512² views 60° apart), {len(pair.candidates)} candidate "
            f"voxels at 0.5 mm, shipped SBP weights; medians of 5 after a warm-up. Preparing the pair (masks → EDTs → "
            f"candidate voxels, CPU) took {prep_s:.2f} s; rendering a training pair is CPU work of the same order and "
            "runs in other processes, so the network step is what a GPU changes.\n\n" + "\n".join(lines) +
            f"\n\nTraining step speed-up: {c['train_step_s'] / g['train_step_s']:.0f}×; "
            f"inference: {c['inference_s'] / g['inference_s']:.0f}×.")
    print(write_section("gpu", "SBP network on a GPU (optional)", "python benchmarks/bench_gpu.py", body))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
