"""The sparse backward projection (SBP) network: two vessel masks + two cameras → sparse 3D occupancy
and centreness at 0.5 mm (paper: "Sparse backwards projection module", Eqs. 5–11).

Pipeline for one two-view pair:

1. **Active pixels** (Eq. 5): pixels whose distance to the vessel mask is below ε (the maximal vessel
   radius, given in mm and converted per view with its isocentre pixel spacing).
2. **2D features** (Eq. 6): a small U-Net per view (shared weights) at half resolution gives
   ``ENCODER_CHANNELS`` feature maps; ``I^f = EDT ⊕ features``, where EDT is the signed distance to the
   vessel boundary in mm, computed exactly at full resolution.
3. **Candidate voxels** (Eqs. 7–9): voxel-centric and coarse to fine — the 0.5 mm voxels whose centres
   project onto active pixels in *both* views (the visual hull of the active maps,
   :func:`stages.visual_hull.visual_hull`). This equals casting every active pixel's ray into the
   grid and intersecting the two views, without materialising rays.
4. **Fusion**: every candidate voxel samples ``I^f`` of both views bilinearly at its projection
   (differentiable, so the 3D loss trains the 2D encoder) and concatenates them, plus a constant
   channel for the tree side (one model for both trees, conditioned on side: the local geometry a
   voxel sees is the same for left and right trees and one model gets twice the data).
5. **Sparse residual U-Net** (:class:`stages.core.sparse.SparseUNet`) → two logits per voxel: occupancy
   and centreness (sigmoid).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from scipy import ndimage

from ..core.errors import UserError
from ..core.geometry import MIN_VIEW_SEPARATION_DEG, Camera, view_separation_deg
from ..core.sparse import SparseTensor, SparseUNet
from ..core.voxels import SparseVoxels
from ..visual_hull import visual_hull

ENCODER_CHANNELS = 12
PER_VIEW_CHANNELS = ENCODER_CHANNELS + 1  # + EDT


def signed_edt_mm(mask: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Signed distance to the vessel boundary in mm (positive inside the vessel, negative outside)."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return np.full(mask.shape, -1e3, np.float32)
    inside = ndimage.distance_transform_edt(mask)
    outside = ndimage.distance_transform_edt(~mask)
    return ((inside - outside) * spacing_mm).astype(np.float32)


def active_pixels(mask: np.ndarray, camera: Camera, eps_mm: float) -> np.ndarray:
    """Pixels within ε (mm at the isocentre) of the vessel mask (Eq. 5), the mask included."""
    mask = np.asarray(mask, bool)
    if not mask.any():
        return mask.copy()
    dist_px = ndimage.distance_transform_edt(~mask)
    return dist_px * camera.isocentre_spacing < eps_mm


def check_pair(mask_a, mask_b, cam_a: Camera, cam_b: Camera, names=("view A", "view B")) -> None:
    """Refuse inputs the network cannot use, with a message naming the problem."""
    for mask, cam, name in ((mask_a, cam_a, names[0]), (mask_b, cam_b, names[1])):
        if np.shape(mask) != (cam.rows, cam.cols):
            raise UserError(f"{name}: mask is {np.shape(mask)[0]}×{np.shape(mask)[1]} but its camera expects {cam.rows}×{cam.cols}")
    sep = view_separation_deg(cam_a, cam_b)
    if sep < MIN_VIEW_SEPARATION_DEG:
        raise UserError(f"{names[0]} and {names[1]} are only {sep:.1f}° apart (need ≥ {MIN_VIEW_SEPARATION_DEG:.0f}°): "
                        "two nearly parallel views cannot triangulate vessels")


def candidate_voxels(active_a, active_b, cam_a: Camera, cam_b: Camera, voxel_size: float = 0.5,
                     grid_offset_mm=None, half_extent_mm: float = 80.0) -> SparseVoxels:
    """Voxels whose centres project onto active pixels in both views (Eqs. 7–9).

    The hull is found on the isocentre lattice; with ``grid_offset_mm`` the same voxel indices are
    re-anchored on the lattice through that point (a shift < one voxel), so training candidates sit
    on the ground truth's own grid. The shift moves centres by < 0.45 mm, far inside the ε margin of
    the active maps, so no candidate is lost.
    """
    hull = visual_hull([active_a, active_b], [cam_a, cam_b], voxel_size=voxel_size, half_extent_mm=half_extent_mm)
    origin = hull.origin.copy()
    if grid_offset_mm is not None:
        delta = np.mod(np.asarray(grid_offset_mm, float) - origin, voxel_size)
        delta[delta > voxel_size / 2] -= voxel_size
        origin = origin + delta
    return SparseVoxels(hull.coords, voxel_size, origin, {})


class _ConvBlock(nn.Sequential):
    def __init__(self, c_in, c_out, stride=1):
        super().__init__(nn.Conv2d(c_in, c_out, 3, stride, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True),
                         nn.Conv2d(c_out, c_out, 3, 1, 1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(inplace=True))


class Encoder2d(nn.Module):
    """Small U-Net on a view: input (mask, clipped signed EDT) at full resolution, output
    ``ENCODER_CHANNELS`` maps at half resolution (fine detail kept by the exact full-resolution EDT)."""

    def __init__(self, widths=(16, 32, 48)):
        super().__init__()
        w0, w1, w2 = widths
        self.stem = _ConvBlock(2, w0, stride=2)  # 1/2
        self.down1 = _ConvBlock(w0, w1, stride=2)  # 1/4
        self.down2 = _ConvBlock(w1, w2, stride=2)  # 1/8
        self.up1 = _ConvBlock(w2 + w1, w1)
        self.up0 = _ConvBlock(w1 + w0, w0)
        self.head = nn.Conv2d(w0, ENCODER_CHANNELS, 1)

    def forward(self, x):
        s0 = self.stem(x)
        s1 = self.down1(s0)
        s2 = self.down2(s1)
        u1 = self.up1(torch.cat([F.interpolate(s2, size=s1.shape[-2:], mode="bilinear", align_corners=False), s1], 1))
        u0 = self.up0(torch.cat([F.interpolate(u1, size=s0.shape[-2:], mode="bilinear", align_corners=False), s0], 1))
        return self.head(u0)


def _sample_bilinear(image: torch.Tensor, rc: torch.Tensor, full_size: tuple[int, int]) -> torch.Tensor:
    """Sample C×h×w maps covering a full_size image at N×2 full-resolution (row, col) → N×C.

    Pixel centres at integer indices (DESIGN.md): full-resolution coordinate x maps to the normalised
    coordinate (2x + 1)/size − 1 with align_corners=False, whatever resolution the map has.
    """
    H, W = full_size
    gx = (2.0 * rc[:, 1] + 1.0) / W - 1.0
    gy = (2.0 * rc[:, 0] + 1.0) / H - 1.0
    grid = torch.stack([gx, gy], -1).view(1, 1, -1, 2).to(image.dtype)
    out = F.grid_sample(image[None], grid, mode="bilinear", padding_mode="border", align_corners=False)
    return out[0, :, 0, :].transpose(0, 1)


@dataclass
class SBPConfig:
    voxel_size: float = 0.5
    eps_mm: float = 1.5  # ~ maximal vessel radius (mm): pixels within this distance of a mask are active
    edt_clip_mm: float = 5.0
    encoder_widths: tuple = (16, 32, 48)
    unet_widths: tuple = (16, 32, 48, 64)
    unet_blocks: tuple = (1, 1, 1, 1)
    # coarsest isocentre pixel size (mm) seen in training (512² renders: 0.17–0.40 mm); coarser views
    # are upsampled by an integer factor first, since the 2D encoder's features are scale-specific
    max_pixel_mm: float = 0.4

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "SBPConfig":
        return cls(**{k: (tuple(v) if isinstance(v, list) else v) for k, v in d.items()})


@dataclass
class PairInput:
    """One two-view input prepared for the network (numpy side, no gradients needed)."""

    masks: tuple[np.ndarray, np.ndarray]
    cameras: tuple[Camera, Camera]
    edts: tuple[np.ndarray, np.ndarray]  # signed EDT in mm at full resolution
    candidates: SparseVoxels


def to_training_scale(mask, cam: Camera, max_pixel_mm: float):
    """(mask, camera) upsampled by the smallest integer factor that brings the isocentre pixel size to
    ≤ ``max_pixel_mm`` (unchanged when it already is): e.g. a 256² run at 0.53 mm → 512² at 0.27 mm.
    The binary mask is interpolated linearly and re-thresholded at ½, which keeps its boundary smooth."""
    factor = int(np.ceil(cam.isocentre_spacing / max_pixel_mm - 1e-6))
    if factor <= 1:
        return mask, cam
    up = ndimage.zoom(np.asarray(mask, np.float32), factor, order=1, mode="nearest", grid_mode=True)
    return up >= 0.5, cam.resampled(factor)


def prepare_pair(mask_a, mask_b, cam_a: Camera, cam_b: Camera, config: SBPConfig,
                 grid_offset_mm=None) -> PairInput:
    """Active pixels, exact EDTs and the candidate voxel set of a pair (no network involved)."""
    check_pair(mask_a, mask_b, cam_a, cam_b)
    (mask_a, cam_a), (mask_b, cam_b) = (to_training_scale(m, c, config.max_pixel_mm)
                                        for m, c in ((mask_a, cam_a), (mask_b, cam_b)))
    masks = (np.asarray(mask_a, bool), np.asarray(mask_b, bool))
    edts = tuple(signed_edt_mm(m, c.isocentre_spacing) for m, c in zip(masks, (cam_a, cam_b)))
    act = [active_pixels(m, c, config.eps_mm) for m, c in zip(masks, (cam_a, cam_b))]
    cands = candidate_voxels(act[0], act[1], cam_a, cam_b, config.voxel_size, grid_offset_mm)
    return PairInput(masks, (cam_a, cam_b), edts, cands)


_RUNNING_STATS = ("running_mean", "running_var", "num_batches_tracked")


class SBPNet(nn.Module):
    """2D encoder + sparse back-projection + sparse U-Net → (occupancy, centreness) logits per voxel.

    Every batch norm normalises with the statistics of the pair at hand, in training *and* at
    inference (no running averages). One training example is one pair, whose statistics vary a lot
    from pair to pair (tree size, overlap, candidate count); running averages of them made inference
    much worse than training — measured on 6 data-se pairs at step 1300: Dice 0.40 / HD95 49 mm with
    running statistics vs 0.66 / 13 mm with the pair's own — so they are not kept at all.
    """

    def __init__(self, config: SBPConfig | None = None):
        super().__init__()
        self.config = config or SBPConfig()
        self.encoder = Encoder2d(self.config.encoder_widths)
        in_ch = 2 * PER_VIEW_CHANNELS + 1
        self.unet = SparseUNet(in_ch, 2, widths=self.config.unet_widths, blocks=self.config.unet_blocks)
        for m in self.modules():
            if isinstance(m, nn.modules.batchnorm._BatchNorm):
                m.track_running_stats = False
                for name in _RUNNING_STATS:
                    setattr(m, name, None)

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        """As nn.Module's, ignoring batch-norm running statistics of older checkpoints (unused here)."""
        state_dict = {k: v for k, v in state_dict.items() if k.rsplit(".", 1)[-1] not in _RUNNING_STATS}
        return super().load_state_dict(state_dict, strict=strict, assign=assign)

    def _view_features(self, mask: np.ndarray, edt: np.ndarray, device) -> tuple[torch.Tensor, torch.Tensor]:
        clip = self.config.edt_clip_mm
        edt_t = torch.from_numpy(np.clip(edt, -clip, clip) / clip).to(device)
        x = torch.stack([torch.from_numpy(mask.astype(np.float32)).to(device), edt_t])[None]
        return self.encoder(x)[0], edt_t[None]

    def forward(self, pair: PairInput, side: str = "left") -> SparseTensor:
        device = next(self.parameters()).device
        cand = pair.candidates
        pts = torch.from_numpy(cand.world_points()).to(device=device, dtype=torch.float32)
        feats = []
        for mask, edt, cam in zip(pair.masks, pair.edts, pair.cameras):
            fmap, edt_map = self._view_features(mask, edt, device)
            rc = cam.project_torch(pts.double()).float()
            full = (cam.rows, cam.cols)
            feats.append(_sample_bilinear(edt_map, rc, full))
            feats.append(_sample_bilinear(fmap, rc, full))
        side_value = 1.0 if side == "right" else 0.0
        feats.append(torch.full((len(pts), 1), side_value, device=device))
        x = SparseTensor(torch.from_numpy(cand.coords.astype(np.int64)).to(device), torch.cat(feats, 1),
                         voxel_size=cand.voxel_size, origin=tuple(cand.origin.tolist()))
        del feats, pts, rc  # the parts are copied into x: do not hold them twice through the U-Net
        return self.unet(x)

    @torch.no_grad()
    def predict(self, pair: PairInput, side: str = "left") -> SparseVoxels:
        """Inference: occupancy and centreness probabilities on the candidate voxels."""
        was_training = self.training
        self.eval()
        try:
            if len(pair.candidates) == 0:
                feats = {"occupancy": np.zeros(0, np.float32), "centreness": np.zeros(0, np.float32)}
                return SparseVoxels(pair.candidates.coords, pair.candidates.voxel_size, pair.candidates.origin, feats)
            out = torch.sigmoid(self.forward(pair, side).feats).cpu().numpy()
        finally:
            self.train(was_training)
        return SparseVoxels(pair.candidates.coords, pair.candidates.voxel_size, pair.candidates.origin,
                            {"occupancy": out[:, 0].astype(np.float32), "centreness": out[:, 1].astype(np.float32)})


def is_widening(narrow: SBPConfig, wide: SBPConfig) -> bool:
    """True when ``wide`` has the same levels and blocks as ``narrow`` and no narrower layer."""
    def at_least(a, b):
        return len(a) == len(b) and all(x >= y for x, y in zip(a, b))

    same = {k: v for k, v in narrow.as_dict().items() if k not in ("encoder_widths", "unet_widths")}
    return (same == {k: wide.as_dict()[k] for k in same} and at_least(wide.encoder_widths, narrow.encoder_widths)
            and at_least(wide.unet_widths, narrow.unet_widths))


def _concatenated_inputs(key: str, config: SBPConfig) -> list[int] | None:
    """Channel counts of the tensors concatenated into the layer ``key`` (None: a single input tensor).

    Widening moves the second part of a concatenation, so its old channels must be placed after the
    first part's new width, not right after its old width."""
    w0, w1, w2 = config.encoder_widths
    if key == "encoder.up1.0.weight":
        return [w2, w1]
    if key == "encoder.up0.0.weight":
        return [w1, w0]
    parts = key.split(".")  # e.g. unet.dec.<decoder>.<block>.conv1.weight
    if parts[:2] == ["unet", "dec"] and parts[3] == "0" and parts[4:] in (["conv1", "weight"],
                                                                           ["shortcut", "0", "weight"], ["weight"]):
        level = len(config.unet_widths) - 1 - int(parts[2])  # decoder i brings level L-1-i up to level L-2-i
        return [config.unet_widths[level - 1], config.unet_widths[level - 1]]  # upsampled features, skip
    return None


def embed_weights(wide: SBPNet, narrow: SBPNet) -> SBPNet:
    """Copy ``narrow``'s weights into the wider network ``wide`` so that it computes exactly the same
    occupancy and centreness (function-preserving widening), and return ``wide``.

    Every layer keeps the narrow network's channels as its leading channels. The extra channels keep
    ``wide``'s random initialisation on their inputs, and their weights into the old channels (and into
    the heads) are zero, so at first they change nothing; training then grows them from there. This
    lets a wider network start from the shipped weights instead of from scratch. Batch norms normalise
    each channel on its own, so the extra channels do not disturb the old ones' statistics either.
    """
    if not is_widening(narrow.config, wide.config):
        raise ValueError(f"{wide.config} is not a widening of {narrow.config}")
    old_state, new_state = narrow.state_dict(), wide.state_dict()
    with torch.no_grad():
        for key, new in new_state.items():
            old = old_state[key].to(new.dtype)
            if old.shape == new.shape:
                new.copy_(old)
                continue
            # axes: Conv2d (out, in, h, w); sparse conv (kernel offsets, in, out); norms and biases (out,)
            out_axis, in_axis = {4: (0, 1), 3: (2, 1), 1: (0, None)}[new.dim()]
            index: list = [slice(None)] * new.dim()
            index[out_axis] = slice(0, old.shape[out_axis])
            if in_axis is None:
                new[tuple(index)] = old
                continue
            new[tuple(index)] = 0.0  # extra inputs feed nothing into the old outputs
            old_parts = _concatenated_inputs(key, narrow.config) or [old.shape[in_axis]]
            new_parts = _concatenated_inputs(key, wide.config) or [new.shape[in_axis]]
            if sum(old_parts) != old.shape[in_axis] or len(old_parts) != len(new_parts):
                raise ValueError(f"{key}: cannot place {old.shape[in_axis]} input channels in {new.shape[in_axis]}")
            starts = np.cumsum([0] + new_parts[:-1])
            index[in_axis] = torch.from_numpy(np.concatenate([s + np.arange(n) for s, n in zip(starts, old_parts)]))
            new[tuple(index)] = old
    return wide
