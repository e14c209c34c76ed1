"""What the dense baselines share: the fixed cube they predict in, ground truth resampled onto it,
and upsampling of their coarse predictions to the 0.5 mm lattice the metrics and the SBP model use.

Reads and writes nothing on disk.

* **The cube**: ±80 mm around the isocentre (the search box of :func:`stages.visual_hull.visual_hull`
  and of the SBP candidates), cut into ``n``³ cells of ``voxel_size`` mm; cell ``ijk`` has its centre at
  ``−80 + (ijk + ½)·voxel_size``. The prepared trees of data/train_cases and data-se reach at most
  73.5 mm from the isocentre (measured over all 173 cases); training adds ≤ 10 mm of translation,
  so the rare voxel beyond the cube counts as a miss in the loss (never dropped silently).
* **Coarse targets**: occupancy and centreness of a coarse cell = the mean over the 0.5 mm label voxels
  whose centres fall in it (partial volume), so the loss of :func:`stages.sbp.loss.sbp_loss` applies
  as is, with every cell of the cube a "candidate".
* **Upsampling**: coarse probabilities are interpolated trilinearly at the centres of the 0.5 mm
  lattice (through the isocentre, or re-anchored through ``grid_offset_mm`` as the SBP candidates are)
  and kept where occupancy ≥ 0.5. Only cells near a cell ≥ 0.5 are visited — a trilinear value can only
  reach 0.5 if one of its 8 corners does — so a dense 0.5 mm cube is never built.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch.nn as nn
from scipy import ndimage

from ..core.voxels import SparseVoxels

CUBE_HALF_MM = 80.0
FINE_MM = 0.5
HEAD_PRIOR = -4.0  # initial logit of both heads (sigmoid ≈ 0.018)


def norm(channels: int, dims: int = 3):
    """Instance norm with a learned scale and shift — what batch norm computes on the one-pair batches
    these baselines train on, but the same in evaluation. (Batch norm's running averages over pairs
    of very different trees left a trained dense model predicting nothing in eval mode: max occupancy
    0.007 where the batch statistics of the very pair gave 1.0.)"""
    return (nn.InstanceNorm3d if dims == 3 else nn.InstanceNorm2d)(channels, affine=True)


@dataclass(frozen=True)
class CubeGrid:
    """``n``³ cells of ``voxel_size`` mm covering ±``half_extent`` mm around the isocentre."""

    n: int
    voxel_size: float
    half_extent: float = CUBE_HALF_MM

    def __post_init__(self):
        if abs(self.n * self.voxel_size - 2 * self.half_extent) > 1e-6:
            raise ValueError(f"{self.n} cells of {self.voxel_size} mm do not span ±{self.half_extent} mm")

    @property
    def origin(self) -> np.ndarray:
        """World position (mm) of the centre of cell (0, 0, 0)."""
        return np.full(3, -self.half_extent + self.voxel_size / 2)

    def centres(self) -> np.ndarray:
        """n³×3 cell centres in world mm, in C order of the (i, j, k) array axes."""
        g = self.origin[0] + self.voxel_size * np.arange(self.n)
        return np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)

    def cell_of(self, points) -> np.ndarray:
        """Integer cell index of world points (may fall outside 0..n−1)."""
        return np.floor((np.asarray(points, float) + self.half_extent) / self.voxel_size).astype(np.int64)


def coarse_targets(truth: SparseVoxels, grid: CubeGrid) -> dict:
    """The labels averaged onto the cube's cells, in the form :func:`stages.sbp.loss.sbp_loss` takes.

    ``occupancy``/``centreness``: flat arrays of n³ cell means; label mass outside the cube is reported as
    ``missed_*`` (in cell units) and enters the Dice denominators.
    """
    n = grid.n
    occ = np.asarray(truth.features["occupancy"], np.float32)
    cen = np.asarray(truth.features["centreness"], np.float32)
    cell = grid.cell_of(truth.world_points())
    inside = np.all((cell >= 0) & (cell < n), axis=1)
    flat = np.ravel_multi_index(tuple(cell[inside].T), (n, n, n))
    share = (truth.voxel_size / grid.voxel_size) ** 3  # one label voxel's fraction of a cell
    t_occ = (np.bincount(flat, occ[inside], minlength=n ** 3) * share).astype(np.float32)
    t_cen = (np.bincount(flat, cen[inside], minlength=n ** 3) * share).astype(np.float32)
    total = float(occ.sum()) * share
    missed = float(occ[~inside].sum()) * share
    return {"occupancy": t_occ, "centreness": t_cen, "missed_occupancy": missed,
            "missed_centreness": float(cen[~inside].sum()) * share, "truth_positive": total,
            "candidate_recall": 1.0 - missed / total if total > 0 else 1.0}


def fine_anchor(grid: CubeGrid, grid_offset_mm=None, fine: float = FINE_MM) -> np.ndarray:
    """Origin of the output 0.5 mm lattice: the cube's corner, moved by < half a voxel onto the lattice
    through ``grid_offset_mm`` when given (as :func:`stages.sbp.model.candidate_voxels` does)."""
    anchor = np.full(3, -grid.half_extent)
    if grid_offset_mm is not None:
        delta = np.mod(np.asarray(grid_offset_mm, float) - anchor, fine)
        delta[delta > fine / 2] -= fine
        anchor = anchor + delta
    return anchor


def upsample_to_sparse(prob: np.ndarray, grid: CubeGrid, names=("occupancy", "centreness"), grid_offset_mm=None,
                       fine: float = FINE_MM, threshold: float = 0.5) -> SparseVoxels:
    """C×n×n×n coarse probabilities (channel 0 = occupancy) → the 0.5 mm voxels whose trilinearly
    interpolated occupancy is ≥ ``threshold``, with every channel interpolated as a feature."""
    prob = np.asarray(prob, np.float32)
    k = int(round(grid.voxel_size / fine))
    if abs(k * fine - grid.voxel_size) > 1e-6:
        raise ValueError(f"cell size {grid.voxel_size} mm is not a multiple of {fine} mm")
    anchor = fine_anchor(grid, grid_offset_mm, fine)
    # cells that can hold a fine point ≥ threshold: within one cell of a cell ≥ threshold, plus one more
    # for the (< half fine voxel) shift of the re-anchored lattice
    near = ndimage.binary_dilation(prob[0] >= threshold, iterations=2)
    cells = np.argwhere(near).astype(np.int64)
    if len(cells) == 0:
        return SparseVoxels(np.zeros((0, 3), np.int32), fine, anchor, {nm: np.zeros(0, np.float32) for nm in names})
    sub = np.stack(np.meshgrid(*(np.arange(k),) * 3, indexing="ij"), -1).reshape(-1, 3)
    coords = (cells[:, None, :] * k + sub[None]).reshape(-1, 3)
    u = ((anchor + coords * fine) - grid.origin) / grid.voxel_size  # continuous cell index
    occ = ndimage.map_coordinates(prob[0], u.T, order=1, mode="nearest")
    keep = occ >= threshold
    coords, u = coords[keep], u[keep]
    feats = {names[0]: occ[keep].astype(np.float32)}
    for c, nm in enumerate(names[1:], start=1):
        feats[nm] = ndimage.map_coordinates(prob[c], u.T, order=1, mode="nearest").astype(np.float32)
    return SparseVoxels(coords, fine, anchor, feats)
