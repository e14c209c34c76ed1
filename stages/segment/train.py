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

Frames catching the bolus arriving or washing out (vessel area < 80 % of the best-filled frame of the
same scene) are drawn ``partial_weight`` times as often as the others: they are the faint, hard frames.
``init``: start from shipped-format weights (fine-tuning; their ``train`` info is kept under ``"init"``);
a checkpoint, when present, takes precedence (resuming).
"""

from __future__ import annotations

import logging
import math
import time
from pathlib import Path

import numpy as np

from .weights import DEFAULT_WEIGHTS, load_model  # DEFAULT_WEIGHTS re-exported

log = logging.getLogger(__name__)

__all__ = ["train", "export_weights", "sampling_weights", "main", "DEFAULT_WEIGHTS"]


def _loss(logits, target):
    import torch
    from torch.nn import functional as F

    bce = F.binary_cross_entropy_with_logits(logits, target)
    p = torch.sigmoid(logits)
    inter = (p * target).sum()
    dice = 1 - (2 * inter + 1) / (p.sum() + target.sum() + 1)
    return bce + dice


def sampling_weights(masks: np.ndarray, frames_per_scene: int = 4, partial_weight: float = 1.0) -> np.ndarray:
    """Per-frame sampling probabilities: frames of a scene come in consecutive groups of
    ``frames_per_scene`` (:func:`stages.segment.data.build_split`); a non-empty frame whose vessel area is
    < 80 % of its scene's best-filled frame (bolus arriving / washing out) weighs ``partial_weight``."""
    area = masks.reshape(len(masks), -1).sum(1).astype(float)
    group = np.arange(len(masks)) // frames_per_scene
    best = np.array([area[group == g].max() for g in group])
    partial = (area > 0) & (area < 0.8 * best)
    w = np.where(partial, float(partial_weight), 1.0)
    return w / w.sum()


def export_weights(model, path, threshold: float = 0.5, info: dict | None = None) -> Path:
    import torch

    from ..core.artefacts import atomic_path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    payload = {"state_dict": {k: v.detach().clone() for k, v in model.state_dict().items()},
               "config": model.config(), "threshold": float(threshold), "train": info or {}}
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)
    return path


def train(data="data/seg", ckpt="out/seg/ckpt.pt", weights=DEFAULT_WEIGHTS, steps: int = 6000, batch: int = 8,
          crop: int = 256, lr: float = 3e-3, max_minutes: float = 40.0, seed: int = 0, threads: int = 1,
          log_every: int = 25, ckpt_every: int = 50, init=None, partial_weight: float = 1.0,
          frames_per_scene: int = 4) -> dict:
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
    prob = sampling_weights(masks, frames_per_scene, partial_weight)
    init_info = None
    if init is not None:
        base, _, init_info = load_model(init)
        model = UNet2D(**base.config())
        model.load_state_dict(base.state_dict())
        log.info("initialised from %s (%s)", init, init_info)
    else:
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
        # uniform draws keep the random stream of the runs before weighted sampling existed
        idx = rng.integers(len(frames), size=batch) if partial_weight == 1 else rng.choice(len(frames), size=batch, p=prob)
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
        run_loss.append(loss.item())
        if step % log_every == 0:
            log.info("step %d loss %.4f lr %.2e %.1f min", step, np.mean(run_loss), opt.param_groups[0]["lr"],
                     (time.time() - t0) / 60)
            run_loss = []
        if step % ckpt_every == 0 or step >= steps:
            from ..core.artefacts import atomic_path

            with atomic_path(ckpt) as tmp:
                torch.save({"model": model.state_dict(), "opt": opt.state_dict(), "torch_rng": g.get_state(),
                            "np_rng": rng.bit_generator.state, "step": step, "elapsed": time.time() - t0}, tmp)
    info = {"steps": step, "batch": batch, "crop": crop, "seconds": round(time.time() - t0, 1),
            "frames": int(len(frames)), "seed": seed, "lr": lr, "partial_weight": partial_weight}
    if init_info is not None:
        info["init"] = init_info
    model.eval()
    export_weights(model, weights, 0.5, info)
    log.info("wrote %s after %d steps (%.1f min)", weights, step, (time.time() - t0) / 60)
    return info


def main(argv=None) -> dict:
    """python -m stages.segment.train [--minutes M] [--steps N] [--init WEIGHTS] ... (``make train-seg``)."""
    import argparse

    ap = argparse.ArgumentParser(prog="python -m stages.segment.train", description=main.__doc__)
    ap.add_argument("--data", default="data/seg")
    ap.add_argument("--ckpt", default="out/seg/ckpt.pt", help="resumable checkpoint (log next to it: train.log)")
    ap.add_argument("--weights", default=str(DEFAULT_WEIGHTS), help="where the final weights go")
    ap.add_argument("--init", default=None, help="start from these weights (fine-tuning)")
    ap.add_argument("--minutes", type=float, default=40.0, help="wall-time budget")
    ap.add_argument("--steps", type=int, default=6000)
    ap.add_argument("--batch", type=int, default=8)
    ap.add_argument("--lr", type=float, default=3e-3)
    ap.add_argument("--partial-weight", type=float, default=1.0, help="sampling weight of partially filled frames")
    ap.add_argument("--seed", type=int, default=0)
    a = ap.parse_args(argv)
    log_dir = Path(a.ckpt).parent
    log_dir.mkdir(parents=True, exist_ok=True)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s",
                        handlers=[logging.FileHandler(log_dir / "train.log"), logging.StreamHandler()])
    return train(data=a.data, ckpt=a.ckpt, weights=a.weights, steps=a.steps, batch=a.batch, lr=a.lr,
                 max_minutes=a.minutes, seed=a.seed, init=a.init, partial_weight=a.partial_weight)


if __name__ == "__main__":
    main()
