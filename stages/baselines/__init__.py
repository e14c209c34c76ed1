"""Learned baselines of the paper's Table 1, trained on the same data and poses as SBP.

* ``dense`` (:mod:`.dense`, L2-style): masks back-projected with the cameras into a dense 2 mm grid,
  a small dense 3D U-Net;
* ``concat`` (:mod:`.concat`, L1-style): 2D features of both views concatenated and lifted to a 3D
  grid by a learned decoder, without camera geometry.

Reads: weights files ``stages/weights/baseline_<arch>.pt`` (written by :mod:`.train`: float16 state
dict, ``arch``, ``config``, ``meta``). Writes: nothing; :func:`predict` returns a
:class:`~stages.core.voxels.SparseVoxels` at 0.5 mm (occupancy ≥ 0.5) for :func:`stages.core.metrics.metrics_3d`.
"""

from __future__ import annotations

from pathlib import Path

import torch

from ..core.artefacts import atomic_path, load_torch_file
from ..core.errors import UserError
from ..core.voxels import SparseVoxels
from ..sbp.model import check_pair
from .common import upsample_to_sparse
from .concat import ConcatBaseline, ConcatConfig
from .dense import DenseBaseline, DenseConfig

ARCHS = {"dense": (DenseBaseline, DenseConfig), "concat": (ConcatBaseline, ConcatConfig)}
WEIGHTS_DIR = Path(__file__).resolve().parents[1] / "weights"

__all__ = ["ARCHS", "build", "predict", "save_weights", "load_baseline", "default_weights"]


def build(arch: str, config: dict | None = None):
    if arch not in ARCHS:
        raise UserError(f"unknown baseline {arch!r} (choose from {', '.join(ARCHS)})")
    net_cls, cfg_cls = ARCHS[arch]
    return net_cls(cfg_cls.from_dict(config) if config else cfg_cls())


def default_weights(arch: str) -> Path:
    return WEIGHTS_DIR / f"baseline_{arch}.pt"


@torch.no_grad()
def predict(model, mask_a, mask_b, cam_a, cam_b, side: str = "left", grid_offset_mm=None) -> SparseVoxels:
    """Occupancy and centreness at 0.5 mm (voxels with occupancy ≥ 0.5) for one two-view pair."""
    check_pair(mask_a, mask_b, cam_a, cam_b)
    was_training = model.training
    model.eval()
    try:
        prob = torch.sigmoid(model(model.prepare(mask_a, mask_b, cam_a, cam_b, side)))[0].numpy()
    finally:
        model.train(was_training)
    return upsample_to_sparse(prob, model.grid, grid_offset_mm=grid_offset_mm)


def save_weights(path, model, meta: dict) -> Path:
    """Inference weights: float16 state dict + arch + config + metadata (well under 2 MB)."""
    state = {k: (v.half() if v.is_floating_point() else v) for k, v in model.state_dict().items()}
    with atomic_path(path) as tmp:
        torch.save({"arch": model.arch, "state_dict": state, "config": model.config.as_dict(), "meta": meta}, tmp)
    return Path(path)


def load_baseline(path):
    """A baseline from a weights file (:func:`save_weights`) or a training checkpoint, in eval mode."""
    path = Path(path)
    blob = load_torch_file(path, " (train a baseline with `python -m stages.baselines.train`)")
    if "arch" in blob and "state_dict" in blob:
        model, state = build(blob["arch"], blob["config"]), blob["state_dict"]
    elif "model" in blob and "config" in blob and "arch" in blob["config"]:
        model, state = build(blob["config"]["arch"], blob["config"]["model"]), blob["model"]
    else:
        raise UserError(f"{path}: not an autocar baseline weights or checkpoint file")
    model.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    model.eval()
    return model


