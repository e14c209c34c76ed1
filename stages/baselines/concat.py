"""L1-style baseline of Table 1: 2D features of both views concatenated and lifted to 3D without geometry.

Reads: two vessel masks (H×W bool) and the tree side — the cameras are ignored on purpose.
Writes: nothing itself; :func:`stages.baselines.predict` returns a :class:`~stages.core.voxels.SparseVoxels`
at 0.5 mm and :mod:`stages.baselines.train` writes the weights.

Each mask is area-averaged to 128² and, with a constant side plane, goes through a shared strided 2D
CNN (128² → 8², 64 channels). The two feature maps are concatenated along channels (view A first), a
1×1 convolution mixes them into ``depth``·``c3`` channels that are reshaped into a ``c3``×8×8×8 volume,
and 3D transposed convolutions grow it to 64³ cells of 2.5 mm over the same ±80 mm cube as the dense
baseline. Where a vessel lies in 3D must be learned from the images alone: there is no camera input,
which is exactly what this baseline is meant to show.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F

from ..core.geometry import Camera
from .common import HEAD_PRIOR, CubeGrid, norm


@dataclass
class ConcatConfig:
    image: int = 128
    widths2d: tuple = (16, 32, 64, 64)
    c3: int = 32
    widths3d: tuple = (32, 16, 8)
    n: int = 64
    voxel_size: float = 2.5

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "ConcatConfig":
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def _conv2d(c_in, c_out, stride):
    return nn.Sequential(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), norm(c_out, 2), nn.ReLU(inplace=True))


def _up3d(c_in, c_out):
    return nn.Sequential(nn.ConvTranspose3d(c_in, c_out, 4, 2, 1, bias=False), norm(c_out), nn.ReLU(inplace=True),
                         nn.Conv3d(c_out, c_out, 3, 1, 1, bias=False), norm(c_out), nn.ReLU(inplace=True))


class ConcatBaseline(nn.Module):
    """Two masks (1×2×2×S×S: view, (mask, side)) → (occupancy, centreness) logits (1×2×n³)."""

    arch = "concat"

    def __init__(self, config: ConcatConfig | None = None):
        super().__init__()
        cfg = self.config = config or ConcatConfig()
        self.grid = CubeGrid(cfg.n, cfg.voxel_size)
        layers, c = [], 2
        for w in cfg.widths2d:  # each stride-2 layer halves the image
            layers.append(_conv2d(c, w, 2))
            c = w
        self.encoder = nn.Sequential(*layers)
        self.side2d = cfg.image // 2 ** len(cfg.widths2d)
        ups = len(cfg.widths3d)
        if self.side2d * 2 ** ups != cfg.n:
            raise ValueError(f"{cfg.image}² images give {self.side2d}² maps; {ups} doublings do not reach {cfg.n}³")
        self.lift = nn.Conv2d(2 * c, cfg.c3 * self.side2d, 1)
        dec, c = [], cfg.c3
        for w in cfg.widths3d:
            dec.append(_up3d(c, w))
            c = w
        self.decoder = nn.Sequential(*dec)
        self.head = nn.Conv3d(c, 2, 1)
        nn.init.constant_(self.head.bias, HEAD_PRIOR)  # vessels fill far below 1 % of the cube: start there

    def prepare(self, mask_a, mask_b, cam_a: Camera | None = None, cam_b: Camera | None = None,
                side: str = "left") -> torch.Tensor:
        s = self.config.image
        views = []
        for m in (mask_a, mask_b):
            t = torch.from_numpy(np.asarray(m, np.float32))[None, None]
            small = F.interpolate(t, size=(s, s), mode="area")[0, 0]  # vessel fraction per pixel
            views.append(torch.stack([small, torch.full_like(small, 1.0 if side == "right" else 0.0)]))
        return torch.stack(views)[None]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        b = x.shape[0]
        feats = self.encoder(x.flatten(0, 1))  # both views through the shared encoder
        feats = feats.view(b, 2 * feats.shape[1], self.side2d, self.side2d)
        vol = self.lift(feats).view(b, self.config.c3, self.side2d, self.side2d, self.side2d)
        return self.head(self.decoder(vol))
