"""Benchmark: the SBP network on the synthetic evaluation set (data-se, paper Table 1, AutoCAR row).

For every pair of ``data/se/pairs.zarr`` the two ground-truth silhouettes are used, view B re-rendered
with the default temporal-misalignment augmentation (2 px RMS TPS warp, seeded per pair), the network
predicts occupancy on its sparse candidate set and :func:`stages.metrics.metrics_3d` scores it against
the case's labels (Dice, clDice, Chamfer, HD95). Also measured per pair: inference time (candidates +
network), the number of active voxels against the dense grid of the same extent, and the process's
peak resident memory.

Run:  python benchmarks/bench_sbp_se.py [--weights FILE] [--limit N] [--pose-model default|uniform]
Writes docs/benchmarks/sbp_se.md (or docs/benchmarks/<--doc>.md). Missing data-se: says so and exits 0.
"""

from __future__ import annotations

import argparse
import os
import resource
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

PAPER = {"dice": 0.80, "cldice": 0.93, "chamfer_mm": 1.27, "hd95_mm": 3.57}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "se"))
    ap.add_argument("--weights", default=None, help="weights or checkpoint (default: the shipped stages/weights/sbp.pt)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--misalign-px", type=float, default=2.0)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--doc", default="sbp_se", help="section name: writes docs/benchmarks/<name>.md")
    args = ap.parse_args(argv)
    data = Path(args.data)
    if not (data / "pairs.zarr").exists():
        print(f"{data / 'pairs.zarr'} not found: run `make data-se` first. Nothing measured.")
        return 0

    import numpy as np
    import torch

    from machine import write_section
    from stages.metrics import metrics_3d
    from stages.prepared_case import PreparedCase
    from stages.render.augment import random_warp
    from stages.render.pairs import load_pair_shard
    from stages.render.raster import rasterise_mask
    from stages.sbp.model import prepare_pair
    from stages.train import load_weights
    from stages.voxels import SparseVoxels

    from stages.errors import UserError

    torch.set_num_threads(args.threads)
    try:
        model = load_weights(args.weights)
    except UserError as exc:
        print(f"{exc}. Nothing measured.")
        return 0
    shard = load_pair_shard(data / "pairs.zarr")
    cases = shard["attrs"]["cases"]
    n = len(shard["mask_a"]) if args.limit is None else min(args.limit, len(shard["mask_a"]))
    rows, times, ratios, voxels = [], [], [], []
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    for i in range(n):
        case_path = Path(cases[int(shard["case_index"][i])])
        if not case_path.is_absolute() and not case_path.exists():
            case_path = data / case_path
        case = PreparedCase.load(case_path)
        t = np.asarray(shard["translation"][i], float)
        cam_a, cam_b = shard["cameras_a"][i], shard["cameras_b"][i]
        mask_a = shard["mask_a"][i].astype(bool)
        mask_b = shard["mask_b"][i].astype(bool)
        if args.misalign_px > 0:
            rng = np.random.default_rng([1_000_000, i])
            size = mask_b.shape[0]
            warp = random_warp(rng, size, size, args.misalign_px)
            V = case.vertices.astype(float) + t
            mask_b = rasterise_mask(V, case.faces, cam_b, offset_rc=warp.displacement(np.nan_to_num(cam_b.project(V))))
        truth = SparseVoxels(case.labels.coords, case.labels.voxel_size, case.labels.origin + t, case.labels.features)
        t0 = time.perf_counter()
        pair = prepare_pair(mask_a, mask_b, cam_a, cam_b, model.config)
        pred = model.predict(pair, side=case.side)
        times.append(time.perf_counter() - t0)
        lo, hi = pair.candidates.bounds()
        ratios.append(len(pair.candidates) / float(np.prod(hi - lo + 1)))
        voxels.append(len(pair.candidates))
        occ = SparseVoxels(pred.coords, pred.voxel_size, pred.origin, {"occupancy": pred.features["occupancy"]})
        rows.append(metrics_3d(occ, truth))
        print(f"pair {i}: dice {rows[-1]['dice']:.3f} cldice {rows[-1]['cldice']:.3f} "
              f"cd {rows[-1]['chamfer_mm']:.2f} hd95 {rows[-1]['hd95_mm']:.2f} ({times[-1]:.1f} s, {voxels[-1]} voxels)", flush=True)
    peak_mb = (resource.getrusage(resource.RUSAGE_SELF).ru_maxrss) / 1024

    def stat(key):
        vals = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
        return (statistics.mean(vals), statistics.pstdev(vals), statistics.median(vals), len(vals)) if vals else None

    lines = ["| metric | ours: mean ± sd | median | pairs | paper (AutoCAR, L8) |", "|---|---|---|---|---|"]
    for key, name in (("dice", "Dice"), ("cldice", "clDice"), ("chamfer_mm", "Chamfer (mm)"), ("hd95_mm", "HD95 (mm)")):
        s = stat(key)
        lines.append(f"| {name} | {s[0]:.3f} ± {s[1]:.3f} | {s[2]:.3f} | {s[3]} | {PAPER[key]} |" if s else f"| {name} | n/a | | 0 | {PAPER[key]} |")
    weights = args.weights or "stages/weights/sbp.pt (shipped)"
    body = (f"Weights: `{weights}`. {n} pairs of data-se, ground-truth silhouettes, view B with a "
            f"{args.misalign_px:g} px RMS TPS misalignment (seeded per pair), {args.threads} torch threads.\n\n"
            + "\n".join(lines) + "\n\n"
            f"Inference per pair (candidate voxels + network): min {min(times):.2f} s, median {statistics.median(times):.2f} s, "
            f"max {max(times):.2f} s. Active voxels: median {int(statistics.median(voxels))}, i.e. "
            f"{statistics.median(ratios) * 100:.1f} % of the dense grid of the same extent (median ratio 1 : "
            f"{1 / statistics.median(ratios):.0f}). Peak resident memory of the whole process: {peak_mb:.0f} MB "
            f"(before the first pair {rss0 / 1024:.0f} MB).\n")
    cmd = "python benchmarks/bench_sbp_se.py" + (f" --weights {args.weights}" if args.weights else "") + (
        f" --limit {args.limit}" if args.limit else "")
    write_section(args.doc, "SBP network on data-se (Table 1, AutoCAR row)", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
