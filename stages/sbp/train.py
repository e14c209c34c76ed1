"""Stage ``train``: fit the SBP network on synthetic two-view pairs rendered online.

Reads: prepared cases (``autocar.prepared-case`` zarr artefacts, a folder of them) and a pose model
(``autocar.pose-model``; ``default`` for the built-in clinical model, ``uniform`` for the L7 ablation).
Writes, in the run folder ``-o RUN``:

* ``checkpoint.pt`` — model, optimiser, step, config (every ``ckpt_every`` steps, on interrupt, at the end;
  written atomically); ``--resume`` continues from it with the same data order;
* ``model.pt`` — the final weights + config only (what inference loads; small);
* ``log.csv`` — one row per step (loss terms, candidate recall, voxels, seconds) and ``loss.png``;
* ``val.json`` / ``val.csv`` — validation Dice/clDice/CD/HD95 on held-out cases at each ``val_every``.

Data order is a pure function of (seed, step, rank): pair ``i`` of rank ``r`` uses
``numpy.random.default_rng([seed, r, i])`` — a resumed or repeated run sees exactly the same pairs.
With ``mask_noise`` > 0 (``--mask-noise``), that share of the pairs gets segmenter-style mask errors
(:mod:`stages.render.mask_noise`) drawn from a second stream, ``default_rng([seed, r, i, 1])``, so the
poses, placement and truth of pair ``i`` stay the same; with ``unet_masks`` > 0 (``--unet-masks``), from the
same stream, that share of the pairs gets the 2D segmenter's masks of simulated XA frames of the pair
(:mod:`stages.render.segmenter_masks`); validation pairs always use exact silhouettes.

Distributed data-parallel: launch with ``torchrun --nproc_per_node N -m stages.sbp.train ...`` (or
``autocar train`` under torchrun); gloo on CPU, NCCL on GPU. Gradients are averaged across ranks and
rank 0 writes the files.
"""

from __future__ import annotations

import csv
import json
import logging
import math
import os
import signal
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
import torch

from ..core.artefacts import atomic_path, load_torch_file
from ..core.errors import UserError
from ..core.figures import save_png
from ..core.voxels import SparseVoxels
from .loss import align_targets, sbp_loss, skeleton_labels
from .model import SBPConfig, SBPNet, embed_weights, is_widening, prepare_pair

log = logging.getLogger(__name__)


@dataclass
class TrainConfig:
    steps: int = 2000
    lr: float = 2e-3
    weight_decay: float = 1e-5
    accum: int = 1  # gradient accumulation: pairs per optimiser step (per rank)
    ckpt_every: int = 50
    val_every: int = 250
    val_pairs: int = 8
    seed: int = 0
    size: int = 512
    misalign_px: float = 2.0
    misalign_3d: float = 0.1
    mask_noise: float = 0.0  # probability that a pair's two masks get segmenter-style errors (stages.render.mask_noise)
    unet_masks: float = 0.0  # probability that a pair's two masks are the U-Net's masks of XA frames (stages.render.segmenter_masks)
    pose_model: str = "default"
    threads: int = 0  # 0: leave torch's default
    device: str = "auto"  # "auto" (the rank's CUDA device when there is one, else the CPU), "cpu" or "cuda"
    workers: int = 0  # processes rendering pairs ahead of the network (0: render in the training process)
    refresh_every: int = 0  # re-scan the case folder every N steps for cases added meanwhile (0: never)
    init: str = ""  # start from these weights (model.pt or checkpoint.pt) instead of a random initialisation
    skeleton_recall_weight: float = 0.0  # weight of the skeleton-recall term (stages.sbp.loss); 0: Eq. 11 only
    model: dict = field(default_factory=lambda: SBPConfig().as_dict())
    # architecture fields asked for explicitly (e.g. {"unet_widths": (32, 64, 96, 128)}): they override
    # ``model`` for a fresh network and must agree with the weights being continued (--init, --resume)
    architecture: dict = field(default_factory=dict)


def load_cases(folder, skip=()) -> list:
    """Prepared cases under ``folder`` (or a single case path), sorted by name; paths in ``skip`` are
    left out (used to pick up only new cases while training)."""
    from ..core.prepared_case import PreparedCase, find_cases
    from ..render.pairs import RENDER_MESH_CACHE, simplified_for_rendering

    folder = Path(folder)
    paths = [folder] if folder.suffix == ".zarr" else find_cases(folder)
    if not paths and not skip:
        raise UserError(f"{folder}: no prepared cases (*.zarr of kind autocar.prepared-case); run `autocar prep-ct` first")
    skip = {str(p) for p in skip}
    # training renders thousands of silhouettes: decimated meshes keep that at ~20 ms a view; they are
    # cached beside the cases, so only the first run on a folder pays the decimation (~1 s a tree)
    cache = (folder.parent if folder.suffix == ".zarr" else folder) / RENDER_MESH_CACHE
    return [simplified_for_rendering(PreparedCase.load(p), cache_dir=cache) for p in paths if str(p) not in skip]


def is_validation_case(case_id: str, val_fraction: float = 0.1) -> bool:
    """Deterministic, order-free split: a case validates when its id hashes into the first bucket.

    Hashing the id (not the position in a sorted list) keeps every case on the same side of the split
    when more cases are added while a run trains.
    """
    import zlib

    return zlib.crc32(case_id.encode()) % 1000 < int(round(1000 * val_fraction))


def split_cases(cases: list, val_fraction: float = 0.1):
    """(train, validation) lists; with no hashed validation case, the last case by id validates."""
    if len(cases) < 2:
        return cases, []
    val = [c for c in cases if is_validation_case(c.case_id, val_fraction)]
    if not val:
        val = sorted(cases, key=lambda c: c.case_id)[-1:]
    val_ids = {id(c) for c in val}
    return [c for c in cases if id(c) not in val_ids], val


def pose_model_by_name(name: str):
    from ..poses import PoseModel

    if name == "default":
        return PoseModel.default(seed=0)
    if name == "uniform":
        return PoseModel.uniform_sphere(seed=0)
    return PoseModel.load(name)


_SKELETONS: dict = {}  # (case_id, side) → skeleton_labels of its labels (labels never change while training)


def shifted_labels(case, translation, with_skeleton: bool = False) -> SparseVoxels:
    lab = case.labels
    features = dict(lab.features)
    if with_skeleton:
        key = (case.case_id, case.side)  # the two trees of a case share its id
        if key not in _SKELETONS:
            _SKELETONS[key] = skeleton_labels(lab)
        features["skeleton"] = _SKELETONS[key]
    return SparseVoxels(lab.coords, lab.voxel_size, lab.origin + np.asarray(translation, float), features)


def make_example(case, pose_model, rng, cfg: TrainConfig, model_cfg: SBPConfig, noise_rng=None):
    """Render a pair of ``case`` and build the network input and aligned targets.

    With ``noise_rng``, the two masks get segmenter-style errors with probability ``cfg.mask_noise``, or
    else become the U-Net's masks of XA frames of the pair with probability ``cfg.unet_masks`` (both
    drawn from ``noise_rng`` alone, so the pair itself is the same with or without them)."""
    from ..render.pairs import render_pair

    sample = render_pair(case, pose_model, rng, size=cfg.size, misalign_px=cfg.misalign_px, misalign_3d=cfg.misalign_3d)
    if noise_rng is not None and cfg.mask_noise > 0 and noise_rng.random() < cfg.mask_noise:
        from ..render.mask_noise import corrupt_mask

        sample["mask_a"] = corrupt_mask(sample["mask_a"], noise_rng)
        sample["mask_b"] = corrupt_mask(sample["mask_b"], noise_rng)
    elif noise_rng is not None and cfg.unet_masks > 0 and noise_rng.random() < cfg.unet_masks:
        from ..render.segmenter_masks import segmenter_masks

        sample["mask_a"], sample["mask_b"] = segmenter_masks(sample, case, noise_rng)
    truth = shifted_labels(case, sample["translation"], with_skeleton=cfg.skeleton_recall_weight > 0)
    pair = prepare_pair(sample["mask_a"], sample["mask_b"], sample["camera_a"], sample["camera_b"], model_cfg,
                        grid_offset_mm=truth.origin)
    return pair, truth, sample


def example_at(index: int, train_cases: list, pose_model, cfg: TrainConfig, model_cfg: SBPConfig, rank: int):
    """Training pair number ``index`` of ``rank`` as (side, pair, truth), or (None, reason, None) when it is
    unusable. A pure function of (seed, rank, index), wherever it runs: a resumed run, or one with
    rendering workers, sees exactly the same pairs."""
    rng = np.random.default_rng([cfg.seed, rank, index])
    noise_rng = np.random.default_rng([cfg.seed, rank, index, 1])  # its own stream: the pair does not depend on it
    case = train_cases[int(rng.integers(len(train_cases)))]
    try:
        pair, truth, _ = make_example(case, pose_model, rng, cfg, model_cfg, noise_rng=noise_rng)
    except UserError as exc:  # e.g. a tree that does not fit the field of view
        return None, str(exc), None
    return case.side, pair, truth


_WORKER: dict = {}  # a rendering worker's cases, pose model and configs (loaded once per process)


def _worker_init(cases_dir: str, cfg: TrainConfig, rank: int) -> None:
    torch.set_num_threads(1)
    cases = load_cases(cases_dir)
    _WORKER.update(train_cases=split_cases(cases)[0], pose_model=pose_model_by_name(cfg.pose_model), cfg=cfg,
                   model_cfg=SBPConfig.from_dict(cfg.model), rank=rank)


def _worker_example(index: int):
    w = _WORKER
    return example_at(index, w["train_cases"], w["pose_model"], w["cfg"], w["model_cfg"], w["rank"])


class PairPrefetcher:
    """Renders training pairs ``start, start+1, …`` in ``workers`` processes, ``2 × workers`` ahead, and hands
    them back in order (each is :func:`example_at`, so the data order does not depend on the workers).
    Rendering is CPU work of about a second per pair; on a GPU the network step is ~0.1 s, so without
    workers the GPU would mostly wait."""

    def __init__(self, cases_dir, cfg: TrainConfig, rank: int, start: int, workers: int):
        import multiprocessing as mp
        from concurrent.futures import ProcessPoolExecutor

        # spawn, not fork: the parent may hold CUDA state and torch thread pools that a fork would copy
        self.pool = ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn"), initializer=_worker_init,
                                        initargs=(str(cases_dir), cfg, rank))
        self.ahead = 2 * workers
        self.next_submit = start
        self.pending: dict = {}

    def get(self, index: int):
        while self.next_submit < index + self.ahead:
            self.pending[self.next_submit] = self.pool.submit(_worker_example, self.next_submit)
            self.next_submit += 1
        return self.pending.pop(index).result()

    def close(self) -> None:
        self.pool.shutdown(wait=False, cancel_futures=True)


def resolve_device(name: str) -> torch.device:
    """``auto`` → this rank's CUDA device (``LOCAL_RANK``) when CUDA is available, else the CPU."""
    if name not in ("auto", "cpu", "cuda"):
        raise UserError(f"--device must be auto, cpu or cuda, not {name!r}")
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise UserError("--device cuda: no CUDA device is available to torch here")
    return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")) % torch.cuda.device_count())


def _dist_info():
    import torch.distributed as dist

    if dist.is_available() and dist.is_initialized():
        return dist.get_rank(), dist.get_world_size()
    return 0, 1


def _maybe_init_distributed():
    import torch.distributed as dist

    if int(os.environ.get("WORLD_SIZE", "1")) > 1 and not dist.is_initialized():
        backend = "nccl" if torch.cuda.is_available() else "gloo"
        dist.init_process_group(backend=backend)
    return _dist_info()


def _save_checkpoint(path: Path, model, optimiser, step: int, cfg: TrainConfig, extra=None):
    state = {"model": model.state_dict(), "optimiser": optimiser.state_dict(), "step": step,
             "config": asdict(cfg), "extra": extra or {}}
    with atomic_path(path) as tmp:
        torch.save(state, tmp)


def save_weights(path: Path, model: SBPNet, meta: dict) -> Path:
    """Inference weights: float16 state dict (on the CPU, whatever trained it) + config + metadata (a few MB)."""
    state = {k: (v.half() if v.is_floating_point() else v).cpu() for k, v in model.state_dict().items()}
    with atomic_path(path) as tmp:
        torch.save({"state_dict": state, "config": model.config.as_dict(), "meta": meta}, tmp)
    return path


SHIPPED_WEIGHTS = Path(__file__).parent.parent / "weights" / "sbp.pt"


def read_weights(path) -> tuple[SBPConfig, dict]:
    """(network configuration, state dict) of a weights file (model.pt, sbp.pt) or a training checkpoint."""
    path = Path(path)
    blob = load_torch_file(path)
    if "state_dict" in blob:
        return SBPConfig.from_dict(blob["config"]), blob["state_dict"]
    if "model" in blob and "config" in blob:
        return SBPConfig.from_dict(blob["config"]["model"]), blob["model"]
    raise UserError(f"{path}: not an autocar SBP weights or checkpoint file")


def load_weights(path=None) -> SBPNet:
    """The shipped model (default) or a weights / checkpoint file."""
    if path is None:
        path = SHIPPED_WEIGHTS
        if not path.exists():
            raise UserError(f"{path}: the shipped SBP weights are missing (run `make train`)")
    config, state = read_weights(path)
    model = SBPNet(config)
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    model.eval()
    return model


def validate(model: SBPNet, val_cases, pose_model, cfg: TrainConfig) -> dict:
    """Dice/clDice/CD/HD95 on ``cfg.val_pairs`` fixed pairs of the validation cases."""
    from ..core.metrics import metrics_3d

    model_cfg = model.config
    rows = []
    for i in range(cfg.val_pairs):
        case = val_cases[i % len(val_cases)]
        for attempt in range(5):  # a pose pair can be unusable (views < 10° apart, tree off the image)
            rng = np.random.default_rng([cfg.seed, 999_999, i, attempt])
            try:
                pair, truth, _ = make_example(case, pose_model, rng, cfg, model_cfg)
                break
            except UserError as exc:
                log.warning("validation pair %d, attempt %d: %s", i, attempt, exc)
        else:
            continue
        pred = model.predict(pair, side=case.side)
        pred_occ = SparseVoxels(pred.coords, pred.voxel_size, pred.origin, {"occupancy": pred.features["occupancy"]})
        rows.append(metrics_3d(pred_occ, truth))
    keys = ("dice", "cldice", "chamfer_mm", "hd95_mm")
    out = {}
    for k in keys:
        vals = [r[k] for r in rows if r.get(k) is not None and np.isfinite(r[k])]
        out[k] = float(np.mean(vals)) if vals else float("nan")
    return out


ARCHITECTURE_FIELDS = ("encoder_widths", "unet_widths", "unet_blocks")


def resolve_architecture(cfg: TrainConfig, checkpoint: Path | None = None) -> SBPConfig:
    """The network to train: the checkpoint's when resuming, else that of the ``--init`` weights, else
    ``cfg.model``; ``cfg.architecture`` overrides a fresh network's fields and must match continued weights."""
    unknown = set(cfg.architecture) - set(ARCHITECTURE_FIELDS)
    if unknown:
        raise ValueError(f"unknown architecture fields {sorted(unknown)}")
    asked = {k: tuple(int(x) for x in v) for k, v in cfg.architecture.items()}
    for k, v in asked.items():
        if not v or min(v) < 1:
            raise UserError(f"--{k.replace('_', '-')}: give positive integers, e.g. 16,32,48")
    source = checkpoint if checkpoint is not None else (Path(cfg.init) if cfg.init else None)
    base = read_weights(source)[0] if source is not None else SBPConfig.from_dict(cfg.model)
    if source is not None:
        # --init may widen the weights' network (embed_weights); a resumed run continues it as it is
        if checkpoint is None and is_widening(base, replace(base, **asked)):
            return replace(base, **asked)
        for k, v in asked.items():
            if tuple(getattr(base, k)) != v:
                hint = "" if checkpoint is not None else " (--init can only widen a network, layer by layer)"
                raise UserError(f"{source}: its network has {k.replace('_', '-')} "
                                f"{','.join(map(str, getattr(base, k)))}, not {','.join(map(str, v))} as asked{hint}")
        return base
    out = replace(base, **asked)
    if len(out.unet_blocks) != len(out.unet_widths):
        raise UserError(f"--unet-blocks gives {len(out.unet_blocks)} levels, --unet-widths {len(out.unet_widths)}: "
                        "give one block count per U-Net level")
    return out


def lock_run_dir(run_dir: Path):
    """Hold an exclusive lock on ``run_dir/.lock`` for as long as the returned file stays open.

    A run stopped with a signal finishes its step and writes its checkpoint and log row before it exits;
    a second run started in the same folder meanwhile would get that row in its log and that checkpoint
    under its name. The lock makes the second run refuse instead. No-op where ``fcntl`` is missing.
    """
    try:
        import fcntl
    except ImportError:  # not POSIX: no lock
        return None
    fh = open(run_dir / ".lock", "w")
    try:
        fcntl.flock(fh, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        fh.close()
        raise UserError(f"{run_dir}: another training run is still writing to this folder; wait for it to "
                        "stop (or stop it), or choose another -o") from None
    return fh


def train(cases_dir, run_dir, cfg: TrainConfig, resume: bool = False, progress=None) -> dict:
    """Train (or resume) the SBP network; returns a summary dict."""
    rank, world = _maybe_init_distributed()
    run_dir = Path(run_dir)
    run_lock = None
    if rank == 0:
        run_dir.mkdir(parents=True, exist_ok=True)
        run_lock = lock_run_dir(run_dir)
    try:
        return _train(cases_dir, run_dir, cfg, resume, progress, rank, world)
    finally:  # released on errors too, so a corrected rerun in this process may use the folder
        if run_lock is not None:
            run_lock.close()


def _train(cases_dir, run_dir: Path, cfg: TrainConfig, resume, progress, rank: int, world: int) -> dict:
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    cases = load_cases(cases_dir)
    train_cases, val_cases = split_cases(cases)
    pose_model = pose_model_by_name(cfg.pose_model)
    ckpt = run_dir / "checkpoint.pt"
    if resume and not ckpt.exists():
        raise UserError(f"{ckpt}: nothing to resume from")
    model_cfg = resolve_architecture(cfg, ckpt if resume else None)
    cfg = replace(cfg, model=model_cfg.as_dict())  # what checkpoints, model.pt and the workers record
    torch.manual_seed(cfg.seed)  # after resolving: reading --init weights must not shift the initialisation
    if cfg.workers and cfg.refresh_every:
        raise UserError("--workers and --refresh-every cannot be combined: the workers load the cases once")
    device = resolve_device(cfg.device)
    model = SBPNet(model_cfg)
    if cfg.init and not resume:
        start = load_weights(cfg.init)
        if start.config == model_cfg:
            model.load_state_dict(start.state_dict())
            log.info("initialised from %s", cfg.init)
        else:  # a wider network asked for: it starts computing exactly what the weights compute
            embed_weights(model, start)
            log.info("initialised from %s, widened to encoder %s / U-Net %s", cfg.init,
                     model_cfg.encoder_widths, model_cfg.unet_widths)
    model.to(device)
    optimiser = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    step = 0
    if resume:
        state = torch.load(ckpt, map_location="cpu", weights_only=False)
        model.load_state_dict(state["model"])
        optimiser.load_state_dict(state["optimiser"])
        step = int(state["step"])
        log.info("resumed from %s at step %d", ckpt, step)
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[device] if device.type == "cuda" else None)

    def lr_at(s):  # cosine decay after a short warm-up
        warm = min(50, cfg.steps // 10 + 1)
        if s < warm:
            return cfg.lr * (s + 1) / warm
        return cfg.lr * 0.5 * (1 + math.cos(math.pi * min(1.0, (s - warm) / max(1, cfg.steps - warm))))

    interrupted = {"flag": False}

    def on_signal(signum, frame):
        interrupted["flag"] = True

    old = signal.signal(signal.SIGTERM, on_signal)
    log_path = run_dir / "log.csv"
    fields = ["step", "loss", "dice_occ", "bce_occ", "dice_cen", "bce_cen", "candidate_recall", "voxels", "lr", "seconds"]
    if cfg.skeleton_recall_weight > 0:
        fields.insert(6, "skeleton_recall")
    if rank == 0 and (not resume or not log_path.exists()):
        with open(log_path, "w", newline="") as fh:
            csv.writer(fh).writerow(fields)
    val_history = json.loads((run_dir / "val.json").read_text()) if resume and (run_dir / "val.json").exists() else []
    t_start = time.time()
    model.train()
    prefetch = PairPrefetcher(cases_dir, cfg, rank, step * cfg.accum, cfg.workers) if cfg.workers else None
    try:
        while step < cfg.steps and not interrupted["flag"]:
            t0 = time.time()
            if cfg.refresh_every and step % cfg.refresh_every == 0 and step > 0:
                new = load_cases(cases_dir, skip=[c.path for c in cases])
                if new:
                    cases += new
                    train_cases, val_cases = split_cases(cases)
                    log.info("picked up %d new case(s): %d train, %d validation", len(new), len(train_cases), len(val_cases))
            for g in optimiser.param_groups:
                g["lr"] = lr_at(step)
            optimiser.zero_grad(set_to_none=True)
            parts_acc = []
            for micro in range(cfg.accum):
                index = step * cfg.accum + micro
                side, pair, truth = (prefetch.get(index) if prefetch else
                                     example_at(index, train_cases, pose_model, cfg, model_cfg, rank))
                if side is None:
                    log.warning("skipping pair: %s", pair)
                    continue
                if len(pair.candidates) == 0:
                    continue
                targets = align_targets(pair.candidates, truth)
                out = net(pair, side=side)
                loss, parts = sbp_loss(out.feats, targets, skeleton_weight=cfg.skeleton_recall_weight)
                (loss / cfg.accum).backward()
                parts_acc.append(parts)
            if not parts_acc:  # keep ranks in lockstep: DDP needs every rank to call backward
                sum(p.sum() for p in net.parameters()).mul(0.0).backward()
            optimiser.step()
            step += 1
            if rank == 0 and parts_acc:
                row = {k: float(np.mean([p[k] for p in parts_acc])) for k in fields if k in parts_acc[0]}
                row.update(step=step, lr=lr_at(step - 1), seconds=time.time() - t0)
                with open(log_path, "a", newline="") as fh:
                    csv.writer(fh).writerow([f"{row.get(k, float('nan')):.6g}" if k != "step" else step for k in fields])
                if progress:
                    progress(step, cfg.steps, row)
            if rank == 0 and step % cfg.ckpt_every == 0:
                _save_checkpoint(ckpt, model, optimiser, step, cfg)
            if rank == 0 and val_cases and cfg.val_every and step % cfg.val_every == 0:
                val = validate(model, val_cases, pose_model, cfg)
                val_history.append({"step": step, **val})
                _write_val(run_dir, val_history)
                model.train()
    except KeyboardInterrupt:
        interrupted["flag"] = True
    finally:
        signal.signal(signal.SIGTERM, old)
        if prefetch:
            prefetch.close()
        if rank == 0:
            _save_checkpoint(ckpt, model, optimiser, step, cfg)
    summary = {"step": step, "steps": cfg.steps, "interrupted": interrupted["flag"], "seconds": time.time() - t_start,
               "train_cases": len(train_cases), "val_cases": len(val_cases), "world_size": world,
               "device": str(device), "workers": cfg.workers}
    if world > 1:
        summary["replica_max_abs_diff"] = _replica_spread(model)
    if rank == 0 and log_path.exists() and step > 0:
        plot_log(log_path, run_dir / "loss.png", pairs_per_step=cfg.accum)
    if rank == 0 and step >= cfg.steps:
        save_weights(run_dir / "model.pt", model, {"train": asdict(cfg), "summary": summary,
                                                  "val": val_history[-1] if val_history else None})
    return summary


def _replica_spread(model) -> float:
    """Largest difference of any parameter between data-parallel replicas (0 when they agree)."""
    import torch.distributed as dist

    flat = torch.cat([p.detach().reshape(-1) for p in model.parameters()]).double()
    hi, lo = flat.clone(), flat.clone()
    dist.all_reduce(hi, op=dist.ReduceOp.MAX)
    dist.all_reduce(lo, op=dist.ReduceOp.MIN)
    return float((hi - lo).max())


def _write_val(run_dir: Path, history: list[dict]) -> None:
    with atomic_path(run_dir / "val.json") as tmp:
        tmp.write_text(json.dumps(history, indent=2))
    keys = list(dict.fromkeys(k for h in history for k in h))  # union: metric names may change between runs
    with atomic_path(run_dir / "val.csv") as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(keys)
            for h in history:
                w.writerow([h.get(k, "") for k in keys])


def main(argv=None):
    """``python -m stages.sbp.train CASES RUN [--steps N ...]`` — the entry point for torchrun."""
    import argparse

    p = argparse.ArgumentParser(description="Train the SBP network (see `autocar train --help`).")
    p.add_argument("cases")
    p.add_argument("run")
    p.add_argument("--resume", action="store_true")
    for f, v in asdict(TrainConfig()).items():
        if isinstance(v, (int, float, str)):
            p.add_argument(f"--{f.replace('_', '-')}", type=type(v), default=v)
    args = p.parse_args(argv)
    cfg = TrainConfig(**{f: getattr(args, f) for f in asdict(TrainConfig()) if hasattr(args, f)})
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    print(json.dumps(train(args.cases, args.run, cfg, resume=args.resume)))



def plot_log(log_csv, png, window: int = 25, pairs_per_step=None) -> Path:
    """Loss curve of a run (per-step loss and its running mean over ``window`` steps) as a PNG.

    ``pairs_per_step`` (one per logged row, or one for all; default 1) labels runs whose later steps accumulate several
    pairs (``--accum``) and makes the title's throughput count pairs, not steps."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(open(log_csv)))
    if not rows:
        raise UserError(f"{log_csv}: empty training log")
    step = np.array([float(r["step"]) for r in rows])
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for key, colour in (("loss", "#333333"), ("dice_occ", "#cc3311"), ("dice_cen", "#0077bb")):
        v = np.array([float(r[key]) for r in rows])
        run = np.convolve(v, np.ones(window) / window, mode="valid") if len(v) >= window else v
        ax.plot(step, v, color=colour, alpha=0.2, lw=0.8)
        ax.plot(step[len(step) - len(run):], run, color=colour, lw=1.8, label=f"{key} (mean of {window})")
    seconds = np.array([float(r["seconds"]) for r in rows])
    pairs = np.broadcast_to(np.asarray(1 if pairs_per_step is None else pairs_per_step, float), (len(rows),))
    if np.all(pairs == 1):
        ax.set_xlabel("step (one two-view pair each)")
        ax.set_title(f"SBP training: {int(step.max())} steps, median {np.median(seconds):.1f} s/step "
                     f"({1 / np.median(seconds):.2f} pairs/s)", fontsize=9)
    else:
        first = int(step[np.argmax(pairs > 1)])
        ax.set_xlabel(f"optimiser step (one two-view pair each; {int(pairs.max())} pairs each from step {first})")
        ax.set_title(f"SBP training: {int(step.max())} steps, {int(pairs.sum())} logged pairs, "
                     f"{pairs.sum() / seconds.sum():.2f} pairs/s", fontsize=9)
    ax.set_ylabel("loss")
    ax.legend(fontsize=7)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return save_png(fig, png, dpi=100)


if __name__ == "__main__":
    main()
