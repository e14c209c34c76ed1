"""Visual-hull baseline: the voxels whose projections fall on the vessel in every view.

Reads: two (or more) binary vessel masks (H×W, True = vessel) and their :class:`~stages.core.geometry.Camera`.
Writes (via :func:`save_prediction` in :mod:`stages.evaluate`): an ``autocar.sparse-prediction``
artefact with ``occupancy`` = 1.0 for every hull voxel.

Method (voxel-centric, coarse to fine, so it never holds a dense 0.5 mm grid):

1. The search box is a cube of ±``half_extent_mm`` (80 mm) around the isocentre, on the 0.5 mm grid
   whose voxel centres include the isocentre (origin = −half_extent). It is split into coarse cells
   of ``2**levels`` voxels.
2. For every view the Euclidean distance transform of the mask's complement gives, per pixel, the
   distance (px) to the nearest vessel pixel. A cell survives a view if the distance at the projection
   of its centre is at most the radius of its footprint: the projected radius of the cell's bounding
   sphere (half diagonal × magnification at the cell's depth / detector spacing) plus √2/2 px for the
   nearest-pixel lookup. This test is conservative: no cell containing a hull voxel is dropped.
3. Survivors are split into 8 children and tested again, down to single voxels, where the test is
   exact: the voxel's centre projects (nearest pixel, pixel centres at integer indices) onto a vessel
   pixel in every view. Projections outside an image count as background.

The result is a :class:`~stages.core.voxels.SparseVoxels` at ``voxel_size`` mm.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .core.geometry import Camera
from .core.voxels import SparseVoxels

__all__ = ["visual_hull", "project_to_mask"]


def _lookup(mask_or_dist: np.ndarray, rc: np.ndarray, outside):
    """Values at the nearest pixel of each (row, col); ``outside`` where off the image or NaN."""
    h, w = mask_or_dist.shape
    r = np.rint(rc[:, 0])
    c = np.rint(rc[:, 1])
    ok = np.isfinite(r) & np.isfinite(c) & (r >= 0) & (r < h) & (c >= 0) & (c < w)
    out = np.full(len(rc), outside, dtype=mask_or_dist.dtype)
    out[ok] = mask_or_dist[r[ok].astype(np.int64), c[ok].astype(np.int64)]
    return out


def _footprint_px(cam: Camera, depth: np.ndarray, radius_mm: float) -> np.ndarray:
    """Projected size in pixels of a sphere of ``radius_mm`` at the given depth (max over both axes)."""
    focal = max(cam.K[0, 0], cam.K[1, 1])
    # r·f/(z − r) bounds the image of a sphere on the axis; ×1.05 covers the off-axis stretch of a
    # sphere's ellipse within the ±10° a C-arm image spans.
    return 1.05 * radius_mm * focal / np.maximum(depth - radius_mm, 1e-3)


def visual_hull(masks, cameras, voxel_size: float = 0.5, half_extent_mm: float = 80.0,
                levels: int = 4, chunk: int = 2_000_000) -> SparseVoxels:
    """Voxels of ``voxel_size`` mm whose centres project onto the vessel in every view.

    ``masks``: sequence of H×W boolean arrays; ``cameras``: matching :class:`Camera` list.
    ``levels``: number of refinement steps (coarse cell = 2**levels voxels).
    """
    masks = [np.asarray(m, bool) for m in masks]
    if len(masks) != len(cameras) or len(masks) < 1:
        raise ValueError("one camera per mask is needed")
    for m, cam in zip(masks, cameras):
        if m.shape != (cam.rows, cam.cols):
            raise ValueError(f"mask shape {m.shape} does not match its camera ({cam.rows}, {cam.cols})")
    # distance (px) to the nearest vessel pixel; an empty mask gives +inf everywhere
    dists = []
    for m in masks:
        if m.any():
            dists.append(ndimage.distance_transform_edt(~m).astype(np.float32))
        else:
            dists.append(np.full(m.shape, np.inf, np.float32))
    vs = float(voxel_size)
    n_vox = int(np.ceil(2 * half_extent_mm / vs)) + 1  # voxel centres from −E to +E
    origin = np.full(3, -half_extent_mm)
    cell = 2 ** levels
    n_cell = int(np.ceil(n_vox / cell))
    g = np.arange(n_cell)
    cells = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3).astype(np.int64)
    size = cell
    while True:
        # cell = block of size³ voxels starting at cells*size; keep only those inside the box
        start = cells * size
        cells = cells[np.all(start < n_vox, axis=1)]
        if size == 1:
            keep = np.ones(len(cells), bool)
            for lo in range(0, len(cells), chunk):
                pts = origin + cells[lo:lo + chunk] * vs
                k = keep[lo:lo + chunk]
                for m, cam in zip(masks, cameras):
                    k &= _lookup(m, cam.project(pts), False)
                keep[lo:lo + chunk] = k
            cells = cells[keep]
            break
        centre_idx = cells * size + (size - 1) / 2.0
        keep = np.ones(len(cells), bool)
        half_diag = np.sqrt(3) * size * vs / 2.0
        for lo in range(0, len(cells), chunk):
            pts = origin + centre_idx[lo:lo + chunk] * vs
            k = keep[lo:lo + chunk]
            for dist, cam in zip(dists, cameras):
                rc, depth = cam.project(pts, return_depth=True)
                reach = _footprint_px(cam, depth, half_diag) + np.sqrt(0.5)
                k &= _lookup(dist, rc, np.float32(np.inf)) <= reach
            keep[lo:lo + chunk] = k
        cells = cells[keep]
        # children: 8 sub-cells of half the size
        size //= 2
        octs = np.stack(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij"), -1).reshape(-1, 3)
        cells = (cells[:, None, :] * 2 + octs[None]).reshape(-1, 3)
    coords = cells.astype(np.int32)
    return SparseVoxels(coords, vs, origin, {"occupancy": np.ones(len(coords), np.float32)})


def project_to_mask(points: np.ndarray, camera: Camera, dilate_px: int = 0) -> np.ndarray:
    """Binary image (camera.rows × camera.cols) of the nearest pixels hit by projected world points."""
    out = np.zeros((camera.rows, camera.cols), bool)
    rc = camera.project(np.asarray(points, float).reshape(-1, 3))
    r = np.rint(rc[:, 0])
    c = np.rint(rc[:, 1])
    ok = np.isfinite(r) & np.isfinite(c) & (r >= 0) & (r < camera.rows) & (c >= 0) & (c < camera.cols)
    out[r[ok].astype(np.int64), c[ok].astype(np.int64)] = True
    if dilate_px > 0:
        out = ndimage.binary_dilation(out, iterations=int(dilate_px))
    return out
