"""The segmenter's weights file: where the shipped one lives and how a weights file becomes a network.

Reads: a weights file in the shipped format (``stages/weights/seg.pt`` by default, written by
:func:`stages.segment.train.export_weights`). Writes nothing. Both inference
(:mod:`stages.segment.infer`) and fine-tuning (:mod:`stages.segment.train`) load weights through
:func:`load_model`; neither imports the other. torch is imported on first load, not on import.
"""

from __future__ import annotations

import functools
from pathlib import Path

from ..core.errors import UserError

__all__ = ["DEFAULT_WEIGHTS", "load_model"]

DEFAULT_WEIGHTS = Path(__file__).resolve().parent.parent / "weights" / "seg.pt"


@functools.lru_cache(maxsize=4)
def _load(path: str):
    import torch

    from .model import UNet2D

    try:
        payload = torch.load(path, map_location="cpu", weights_only=False)
        model = UNet2D(**payload["config"])
        model.load_state_dict(payload["state_dict"])
    except (OSError, RuntimeError, KeyError) as exc:
        raise UserError(f"{path}: cannot load segmentation weights ({type(exc).__name__}: {exc})") from None
    model.eval()
    return model, float(payload.get("threshold", 0.5)), dict(payload.get("train", {}))


def load_model(weights=None):
    """(model, threshold, training info) from ``weights`` (default: the shipped ``stages/weights/seg.pt``)."""
    path = Path(weights) if weights else DEFAULT_WEIGHTS
    if not path.exists():
        raise UserError(f"{path}: no segmentation weights; train them with `make train-seg`")
    return _load(str(path.resolve()))
