"""Training loop of the 2D vessel segmenter (``make train-seg``).

Reads: simulated frames ``data/seg/train/*.npz`` (:mod:`stages.segment.data`; rendered first when
missing). Writes: a resumable checkpoint ``out/seg/ckpt.pt`` (model, optimiser, step, RNG state), a
log ``out/seg/train.log`` and, at the end, the shipped weights ``stages/weights/seg.pt``::

    {"state_dict": ..., "config": {"widths": [...], "stem": ...}, "threshold": 0.5,
     "train": {"steps", "batch", "crop", "seconds", "frames", "seed"}}

Loss: binary cross-entropy + soft Dice on batches of ``batch`` random ``crop``² crops
(:func:`stages.segment.augment.augment_batch`), Adam with a cosine learning-rate decay over ``steps``
or ``max_minutes`` of wall time, whichever runs out first (training stops there); one thread by
default (the machine is shared).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

__all__ = ["train", "export_weights", "DEFAULT_WEIGHTS"]

DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "seg.pt"


def _loss(logits, target):
    import torch
    from torch.nn import functional as F

    bce = F.binary_cross_entropy_with_logits(logits, target)
    p = torch.sigmoid(logits)
    inter = (p * target).sum()
    dice = 1 - (2 * inter + 1) / (p.sum() + target.sum() + 1)
    return bce + dice


def export_weights(model, path, threshold: float = 0.5, info: dict | None = None) -> Path:
    import torch

    from ..artefacts import atomic_path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
               "config": model.config(), "threshold": float(threshold), "train": info or {}}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def train(data="data/seg", ckpt="out/seg/ckpt.pt", weights=DEFAULT_WEIGHTS, steps: int = 6000, batch: int = 8,
          crop: int = 256, lr: float = 3e-3, max_minutes: float = 40.0, seed: int = 0, threads: int = 1,
          log_every: int = 25, ckpt_every: int = 50) -> dict:
    import torch

    from .augment import augment_batch
    from .data import build_split, load_split
    from .model import UNet2D

    torch.set_num_threads(threads)
    data = Path(data)
    if not any((data / "train").glob("*.npz")):
        build_split(data, split="train")
    frames, masks, _ = load_split(data / "train")
    log.info("training frames: %d of %s, vessel fraction %.3f", len(frames), frames.shape[1:], masks.mean())
    model = UNet2D()
    opt = torch.optim.Adam(model.parameters(), lr=lr)
    g = torch.Generator().manual_seed(seed)
    rng = np.random.default_rng(seed)
    step, elapsed = 0, 0.0
    ckpt = Path(ckpt)
    if ckpt.exists():
        st = torch.load(ckpt, weights_only=False)
        model.load_state_dict(st["model"])
        opt.load_state_dict(st["opt"])
        g.set_state(st["torch_rng"])
        rng.bit_generator.state = st["np_rng"]
        step, elapsed = st["step"], st["elapsed"]
        log.info("resumed at step %d (%.1f min)", step, elapsed / 60)
    ckpt.parent.mkdir(parents=True, exist_ok=True)
    t0 = time.time() - elapsed
    model.train()
    run_loss = []
    while step < steps and (time.time() - t0) < max_minutes * 60:
        idx = rng.integers(len(frames), size=batch)
        x = torch.from_numpy(frames[idx].astype(np.float32))[:, None]
        y = torch.from_numpy(masks[idx].astype(np.float32))[:, None]
        xa, ya = augment_batch(x, y, g, crop=crop)
        # cosine decay to 3 % of lr over whichever budget (steps or wall time) runs out first
        frac = min(max(step / steps, (time.time() - t0) / (max_minutes * 60)), 1.0)
        for group in opt.param_groups:
            group["lr"] = lr * (0.03 + 0.97 * 0.5 * (1 + math.cos(math.pi * frac)))
        loss = _loss(model(xa), ya)
        opt.zero_grad()
        loss.backward()
        opt.step()
        step += 1
        run_loss.append(float(loss))
        if step % log_every == 0:
            log.info("step %d loss %.4f lr %.2e %.1f min", step, np.mean(run_loss), opt.param_groups[0]["lr"],
                     (time.time() - t0) / 60)
            run_loss = []
        if step % ckpt_every == 0 or step >= steps:
            from ..artefacts import atomic_path

            with atomic_path(ckpt) as tmp:
                torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "torch_rng": g.get_state(),
                            "np_rng": rng.bit_generator.state, "step": step, "elapsed": time.time() - t0}, tmp)
    info = {"steps": step, "batch": batch, "crop": crop, "seconds": round(time.time() - t0, 1),
            "frames": int(len(frames)), "seed": seed}
    model.eval()
    export_weights(model, weights, 0.5, info)
    log.info("wrote %s after %d steps (%.1f min)", weights, step, (time.time() - t0) / 60)
    return info


if __name__ == "__main__":  # python -m stages.segment.train [max_minutes [steps]]
    import sys

    Path("out/seg").mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s",
                        handlers=[logging.FileHandler("out/seg/train.log"), logging.StreamHandler()])
    train(max_minutes=float(sys.argv[1]) if len(sys.argv) > 1 else 40.0,
          steps=int(sys.argv[2]) if len(sys.argv) > 2 else 6000)
