"""Benchmark: what a wider SBP network would cost on this machine (inference budget of issue #7: ≤ 3 s and
≤ 2 GB per pair at 0.5 mm; training step time).

The half-width network of training stages 1–8 (0.9 M parameters) plateaued with more pairs
(docs/MODEL_CARD.md), so the next step was a wider one (shipped since stage 9: the 2x wide one, widened
from the trained half-width weights), and from scratch on a GPU
(`autocar train --encoder-widths … --unet-widths … --unet-blocks …`). Before spending GPU hours on it,
this measures, for a few wider architectures with random weights (the compute does not depend on the
weights), on the first ``--limit`` pairs of data-se with the default 2 px misalignment of view B:
parameters, inference time per pair (candidates + network, median and max), the peak resident memory of
a process that runs only that architecture, and the time of one training step (forward, Eq. 11 loss,
backward) on one pair. Each architecture runs in its own process so its peak memory is its own.

Run:  python benchmarks/bench_sbp_capacity.py [--limit 10] [--threads 2]
Writes docs/benchmarks/sbp_capacity.md. Missing data-se: says so and exits 0.
"""

from __future__ import annotations

import argparse
import json
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

# name → SBPConfig fields (the half-width network of stages 1–8 first)
ARCHITECTURES = {
    "half width": {"encoder_widths": [16, 32, 48], "unet_widths": [16, 32, 48, 64], "unet_blocks": [1, 1, 1, 1]},
    "1.5x wide": {"encoder_widths": [24, 48, 64], "unet_widths": [24, 48, 72, 96], "unet_blocks": [1, 1, 1, 1]},
    "2x wide (shipped)": {"encoder_widths": [32, 64, 96], "unet_widths": [32, 64, 96, 128],
                          "unet_blocks": [1, 1, 1, 1]},
    "2x wide, 2 blocks": {"encoder_widths": [32, 64, 96], "unet_widths": [32, 64, 96, 128],
                          "unet_blocks": [2, 2, 2, 2]},
}


def measure(name: str, data: Path, limit: int, threads: int, misalign_px: float) -> dict:
    """One architecture, in this process: returns its figures."""
    import numpy as np
    import torch

    from se_eval import se_pairs
    from stages.sbp.loss import align_targets, sbp_loss
    from stages.sbp.model import SBPConfig, SBPNet, prepare_pair

    torch.set_num_threads(threads)
    torch.manual_seed(0)
    model = SBPNet(SBPConfig.from_dict({**SBPConfig().as_dict(), **ARCHITECTURES[name]}))
    params = sum(p.numel() for p in model.parameters())
    times, voxels, first = [], [], None
    for p in se_pairs(data, limit, misalign_px):
        t0 = time.perf_counter()
        pair = prepare_pair(p.mask_a, p.mask_b, p.cam_a, p.cam_b, model.config)
        model.predict(pair, side=p.case.side)
        times.append(time.perf_counter() - t0)
        voxels.append(len(pair.candidates))
        if first is None:
            first = (pair, p)
    rss_inference = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    # one training step on the first pair (after one warm-up step)
    pair, p = first
    model.train()
    opt = torch.optim.AdamW(model.parameters(), lr=1e-4)
    steps = []
    for _ in range(3):
        t0 = time.perf_counter()
        out = model(pair, p.case.side)
        targets = align_targets(pair.candidates, p.truth)
        loss, _ = sbp_loss(out.feats, targets)
        opt.zero_grad()
        loss.backward()
        opt.step()
        steps.append(time.perf_counter() - t0)
    return {"name": name, "parameters": int(params), "median_s": float(statistics.median(times)),
            "max_s": float(max(times)), "median_voxels": int(np.median(voxels)), "pairs": len(times),
            "peak_rss_inference_mb": float(rss_inference), "train_step_s": float(statistics.median(steps[1:])),
            "peak_rss_training_mb": float(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024)}


def main(argv=None) -> int:
    from se_eval import add_se_arguments, se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_se_arguments(ap)
    ap.set_defaults(limit=10)
    ap.add_argument("--only", default=None, help=argparse.SUPPRESS)  # internal: measure one architecture
    args = ap.parse_args(argv)
    data = se_or_say(args.data)
    if data is None:
        return 0
    if args.only:
        print("RESULT " + json.dumps(measure(args.only, data, args.limit, args.threads, args.misalign_px)))
        return 0

    from machine import write_section

    rows = []
    for name in ARCHITECTURES:
        cmd = [sys.executable, __file__, "--only", name, "--limit", str(args.limit), "--threads", str(args.threads),
               "--misalign-px", str(args.misalign_px), "--data", str(data)]
        proc = subprocess.run(cmd, capture_output=True, text=True)
        line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
        if proc.returncode or not line:
            raise SystemExit(f"{name}: measurement failed:\n{proc.stderr[-2000:]}")
        rows.append(json.loads(line[0][7:]))
        r = rows[-1]
        print(f"{name}: {r['parameters'] / 1e6:.2f} M parameters, inference median {r['median_s']:.2f} s "
              f"(max {r['max_s']:.2f}), {r['peak_rss_inference_mb']:.0f} MB; training step {r['train_step_s']:.2f} s",
              flush=True)
    base = rows[0]
    lines = ["| architecture (encoder / U-Net widths / blocks) | parameters | inference median (max) | peak memory, "
             "inference | training step, one pair | peak memory, training |", "|---|---|---|---|---|---|"]
    for r in rows:
        a = ARCHITECTURES[r["name"]]
        arch = (f"{r['name']}: {','.join(map(str, a['encoder_widths']))} / {','.join(map(str, a['unet_widths']))} / "
                f"{','.join(map(str, a['unet_blocks']))}")
        lines.append(f"| {arch} | {r['parameters'] / 1e6:.2f} M | {r['median_s']:.2f} s ({r['max_s']:.2f} s) | "
                     f"{r['peak_rss_inference_mb']:.0f} MB | {r['train_step_s']:.2f} s "
                     f"(×{r['train_step_s'] / base['train_step_s']:.1f}) | {r['peak_rss_training_mb']:.0f} MB |")
    fits = [r["name"] for r in rows if r["median_s"] <= 3.0 and r["peak_rss_inference_mb"] <= 2048]
    body = (f"First {base['pairs']} pairs of data-se (median {base['median_voxels']} candidate voxels), view B with a "
            f"{args.misalign_px:g} px RMS misalignment, random weights, {args.threads} torch threads, "
            "each architecture in its own process. Training step: forward, Eq. 11 loss, backward and AdamW update "
            "on the first pair (median of two after a warm-up).\n\n" + "\n".join(lines) + "\n\n"
            "Within the inference budget of issue #7 (median ≤ 3 s per pair, ≤ 2 GB): "
            f"{', '.join(fits) or 'none'}. "
            "The largest trees take longer than the median: the shipped network's maximum over all 90 pairs is in "
            "docs/benchmarks/sbp_se.md.\n")
    write_section("sbp_capacity", "What a wider SBP network costs on this machine",
                  "python benchmarks/bench_sbp_capacity.py", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
