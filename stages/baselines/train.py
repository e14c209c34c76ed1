"""Training of the Table 1 baselines on the same online-rendered pairs as the SBP network.

``python -m stages.baselines.train --model dense|concat --steps N --out DIR [--resume] [--cases data/train_cases]``

Reads: prepared cases (``data/train_cases``), a pose model (``default`` clinical or ``uniform``).
Writes, in ``DIR``:

* ``checkpoint.pt`` — model, optimiser, step, config (every ``ckpt_every`` steps, on SIGTERM/interrupt,
  at the end; atomic); ``--resume`` continues it with the same data order;
* ``log.csv`` — one row per step: loss terms (as :func:`stages.sbp.loss.sbp_loss` reports them), the
  fraction of label mass inside the cube, lr, seconds;
* ``model.pt`` — float16 inference weights with a meta dict (steps, seconds, seed, budget); with
  ``--ship`` also copied to ``stages/weights/baseline_<model>.pt``.

Data are those of :mod:`stages.sbp.train`: the same case loading and train/validation split, the same pose
model, the same misalignment augmentation and the same seed scheme — pair ``i`` uses
``numpy.random.default_rng([seed, 0, i])`` and the same :func:`stages.render.pairs.render_pair` call as
:func:`stages.sbp.train.make_example`, so step ``i`` sees the very pair SBP training sees at its step ``i``
(SBP's own candidate set is not built: the baselines predict on a fixed cube). Targets: the case's
labels (shifted with the pair) averaged onto the baseline's cells (:func:`.common.coarse_targets`).
"""

from __future__ import annotations

import argparse
import csv
import json
import logging
import math
import signal
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import torch

from ..core.errors import UserError
from ..sbp.loss import sbp_loss
from ..sbp.train import TrainConfig, _save_checkpoint, load_cases, pose_model_by_name, shifted_labels, split_cases
from . import build, default_weights, save_weights
from .common import coarse_targets

log = logging.getLogger(__name__)
CLI_FIELDS = ("steps", "lr", "weight_decay", "ckpt_every", "seed", "size", "misalign_px", "misalign_3d", "pose_model",
              "threads", "budget")
LOG_FIELDS = ["step", "loss", "dice_occ", "bce_occ", "dice_cen", "bce_cen", "candidate_recall", "lr", "seconds"]


@dataclass
class BaselineTrainConfig(TrainConfig):
    """:class:`stages.sbp.train.TrainConfig` (steps, lr, seed, size, misalignment, pose model, …) plus the
    baseline's architecture; ``model`` holds that architecture's config dict."""

    arch: str = "dense"
    ckpt_every: int = 25
    budget: str = ""  # free text recorded in the weights' meta (e.g. "35 min wall, nice 19, 1 thread")
    model: dict = field(default_factory=dict)


def render_example(case, pose_model, rng, cfg: TrainConfig):
    """The pair :func:`stages.sbp.train.make_example` renders from the same ``rng``, and its shifted labels."""
    from ..render.pairs import render_pair

    sample = render_pair(case, pose_model, rng, size=cfg.size, misalign_px=cfg.misalign_px, misalign_3d=cfg.misalign_3d)
    return sample, shifted_labels(case, sample["translation"])


def loss_on_pair(net, sample: dict, truth, side: str):
    """Eq. 11 of the paper on the baseline's cells (every cell a candidate)."""
    x = net.prepare(sample["mask_a"], sample["mask_b"], sample["camera_a"], sample["camera_b"], side)
    logits = net(x)[0].flatten(1).T  # n³×2, C order like the targets
    return sbp_loss(logits, coarse_targets(truth, net.grid))


def _lr(cfg: TrainConfig, s: int) -> float:
    """Linear warm-up over the first tenth (≤ 50 steps), then cosine decay to 0."""
    warm = min(50, cfg.steps // 10 + 1)
    if s < warm:
        return cfg.lr * (s + 1) / warm
    return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, (s - warm) / max(1, cfg.steps - warm))))


def train(cases_dir, run_dir, cfg: BaselineTrainConfig, resume: bool = False, ship: bool = False) -> dict:
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    run_dir = Path(run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    train_cases, val_cases = split_cases(load_cases(cases_dir))
    pose_model = pose_model_by_name(cfg.pose_model)
    torch.manual_seed(cfg.seed)
    model = build(cfg.arch, cfg.model or None)
    cfg.model = model.config.as_dict()
    optimiser = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step, seconds_before = 0, 0.0
    ckpt = run_dir / "checkpoint.pt"
    if resume:
        if not ckpt.exists():
            raise UserError(f"{ckpt}: nothing to resume from")
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        if state["config"].get("arch") != cfg.arch:
            raise UserError(f"{ckpt}: a {state['config'].get('arch')} checkpoint, not {cfg.arch}")
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        step = int(state["step"])
        seconds_before = float(state.get("extra", {}).get("seconds", 0.0))
        log.info("resumed from %s at step %d", ckpt, step)
    log_path = run_dir / "log.csv"
    if not resume or not log_path.exists():
        with open(log_path, "w", newline="") as fh:
            csv.writer(fh).writerow(LOG_FIELDS)
    stop = {"flag": False}
    old = signal.signal(signal.SIGTERM, lambda *_: stop.update(flag=True))
    t_start = time.time()

    def seconds():
        return seconds_before + time.time() - t_start

    model.train()
    try:
        while step < cfg.steps and not stop["flag"]:
            t0 = time.time()
            lr = _lr(cfg, step)
            for g in optimiser.param_groups:
                g["lr"] = lr
            rng = np.random.default_rng([cfg.seed, 0, step])  # the SBP scheme, rank 0, accum 1
            case = train_cases[int(rng.integers(len(train_cases)))]
            try:
                sample, truth = render_example(case, pose_model, rng, cfg)
            except UserError as exc:  # e.g. a tree that does not fit the field of view
                log.warning("step %d: skipping pair: %s", step, exc)
                step += 1
                continue
            optimiser.zero_grad(set_to_none=True)
            loss, parts = loss_on_pair(model, sample, truth, case.side)
            loss.backward()
            optimiser.step()
            step += 1
            parts.update(step=step, lr=lr, seconds=time.time() - t0)
            with open(log_path, "a", newline="") as fh:
                csv.writer(fh).writerow([step] + [f"{parts[k]:.6g}" for k in LOG_FIELDS[1:]])
            if step % 10 == 0:
                log.info("step %d/%d loss %.4f dice_occ %.3f (%.2f s)", step, cfg.steps, parts["loss"],
                         parts["dice_occ"], parts["seconds"])
            if step % cfg.ckpt_every == 0:
                _save_checkpoint(ckpt, model, optimiser, step, cfg, {"seconds": seconds()})
    except KeyboardInterrupt:
        stop["flag"] = True
    finally:
        signal.signal(signal.SIGTERM, old)
        _save_checkpoint(ckpt, model, optimiser, step, cfg, {"seconds": seconds()})
    summary = {"arch": cfg.arch, "step": step, "steps": cfg.steps, "interrupted": stop["flag"],
               "seconds": round(seconds(), 1), "train_cases": len(train_cases), "val_cases": len(val_cases)}
    if step >= cfg.steps:
        meta = {"steps": step, "seconds": summary["seconds"], "seed": cfg.seed, "budget": cfg.budget,
                "pose_model": cfg.pose_model, "train_cases": len(train_cases), "train": asdict(cfg)}
        save_weights(run_dir / "model.pt", model, meta)
        if ship:
            save_weights(default_weights(cfg.arch), model, meta)
    return summary


def main(argv=None):
    p = argparse.ArgumentParser(description="Train a Table 1 baseline (dense back-projection or concatenation).")
    p.add_argument("--model", choices=["dense", "concat"], required=True)
    p.add_argument("--out", required=True, help="run folder (checkpoint.pt, log.csv, model.pt)")
    p.add_argument("--cases", default="data/train_cases")
    p.add_argument("--resume", action="store_true")
    p.add_argument("--ship", action="store_true", help="also write stages/weights/baseline_<model>.pt at the end")
    defaults = asdict(BaselineTrainConfig())
    for f in CLI_FIELDS:
        p.add_argument(f"--{f.replace('_', '-')}", type=type(defaults[f]), default=defaults[f])
    args = p.parse_args(argv)
    cfg = BaselineTrainConfig(arch=args.model, **{f: getattr(args, f) for f in CLI_FIELDS})
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    print(json.dumps(train(args.cases, args.out, cfg, resume=args.resume, ship=args.ship)))


if __name__ == "__main__":
    main()
