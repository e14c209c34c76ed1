"""L2-style baseline of Table 1: dense back-projection into a 2 mm grid and a small dense 3D U-Net.

Reads: two vessel masks (H×W bool) and their :class:`~stages.core.geometry.Camera`, plus the tree side.
Writes: nothing itself; :func:`stages.baselines.predict` returns a :class:`~stages.core.voxels.SparseVoxels`
at 0.5 mm (occupancy ≥ 0.5, features occupancy and centreness) and :mod:`stages.baselines.train`
writes the weights.

Every cell of the fixed ±80 mm cube (:class:`stages.baselines.common.CubeGrid`, 80³ cells of 2 mm)
is projected into both views with the pair's cameras; at the projection it reads, per view, the
signed distance to the vessel boundary (mm, clipped to ±5 mm and scaled to ±1) and the mask, both
bilinearly. With a side channel (0 left, 1 right) that makes 5 input channels on a dense grid — the
back-projected volume of the paper's dense baseline — which a 3-level 3D U-Net (widths 8/16/32/32)
turns into occupancy and centreness logits per 2 mm cell. Unlike SBP there is no learned 2D encoder
and no sparsity: the cost is set by the cube, and 2 mm cells cannot resolve vessels much thinner than
a cell (the resolution argument of the paper for sparse 0.5 mm voxels).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from scipy import ndimage

from ..core.geometry import Camera
from ..sbp.model import signed_edt_mm
from .common import HEAD_PRIOR, CubeGrid, norm

IN_CHANNELS = 5  # (EDT, mask) per view + side


@dataclass
class DenseConfig:
    n: int = 80
    voxel_size: float = 2.0
    edt_clip_mm: float = 5.0
    widths: tuple = (8, 16, 32, 32)

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, d: dict) -> "DenseConfig":
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


def backproject(mask: np.ndarray, camera: Camera, grid: CubeGrid, edt_clip_mm: float = 5.0) -> np.ndarray:
    """2×n×n×n: (clipped signed EDT / clip, mask) of one view read at every cell centre's projection.

    Cells projecting off the image (or behind the source) read "far from any vessel": −1 and 0.
    """
    mask = np.asarray(mask, bool)
    edt = np.clip(signed_edt_mm(mask, camera.isocentre_spacing), -edt_clip_mm, edt_clip_mm) / edt_clip_mm
    rc = camera.project(grid.centres())
    rc = np.where(np.isfinite(rc), rc, -1e6).T  # behind the source: off the image
    shape = (grid.n,) * 3
    e = ndimage.map_coordinates(edt.astype(np.float32), rc, order=1, mode="constant", cval=-1.0).reshape(shape)
    m = ndimage.map_coordinates(mask.astype(np.float32), rc, order=1, mode="constant", cval=0.0).reshape(shape)
    return np.stack([e, m]).astype(np.float32)


def _block(c_in, c_out, stride=1):
    return nn.Sequential(nn.Conv3d(c_in, c_out, 3, stride, 1, bias=False), norm(c_out), nn.ReLU(inplace=True))


class DenseBaseline(nn.Module):
    """Back-projected volume (1×5×n³) → 3D U-Net → (occupancy, centreness) logits (1×2×n³)."""

    arch = "dense"

    def __init__(self, config: DenseConfig | None = None):
        super().__init__()
        self.config = config or DenseConfig()
        self.grid = CubeGrid(self.config.n, self.config.voxel_size)
        w0, w1, w2, w3 = self.config.widths
        # one convolution at full resolution on each side: the 80³ level dominates the cost
        self.enc0 = _block(IN_CHANNELS, w0)
        self.enc1 = nn.Sequential(_block(w0, w1, 2), _block(w1, w1))
        self.enc2 = nn.Sequential(_block(w1, w2, 2), _block(w2, w2))
        self.enc3 = nn.Sequential(_block(w2, w3, 2), _block(w3, w3))
        self.dec2 = _block(w3 + w2, w2)
        self.dec1 = _block(w2 + w1, w1)
        self.squeeze0 = nn.Conv3d(w1, w0, 1)
        self.dec0 = _block(w0, w0)
        self.head = nn.Conv3d(w0, 2, 1)
        nn.init.constant_(self.head.bias, HEAD_PRIOR)  # vessels fill far below 1 % of the cube: start there

    def prepare(self, mask_a, mask_b, cam_a: Camera, cam_b: Camera, side: str = "left") -> torch.Tensor:
        g, clip = self.grid, self.config.edt_clip_mm
        side_ch = np.full((1,) + (g.n,) * 3, 1.0 if side == "right" else 0.0, np.float32)
        x = np.concatenate([backproject(mask_a, cam_a, g, clip), backproject(mask_b, cam_b, g, clip), side_ch])
        return torch.from_numpy(x)[None]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        def up(t, like):
            return F.interpolate(t, size=like.shape[-3:], mode="trilinear", align_corners=False)

        s0 = self.enc0(x)
        s1 = self.enc1(s0)
        s2 = self.enc2(s1)
        s3 = self.enc3(s2)
        d2 = self.dec2(torch.cat([up(s3, s2), s2], 1))
        d1 = self.dec1(torch.cat([up(d2, s1), s1], 1))
        d0 = self.dec0(up(self.squeeze0(d1), s0) + s0)
        return self.head(d0)
