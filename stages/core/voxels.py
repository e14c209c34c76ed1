"""Sparse voxel sets on disk and in NumPy: integer coordinates on a regular grid plus per-voxel features.

This is the storage form shared by every stage (DESIGN.md §4): ground-truth labels written by
``prep-ct``, network predictions, visual hulls. (The torch sparse tensor used *inside* networks lives
in :mod:`stages.core.sparse`.)

A voxel with integer index ``ijk`` has its centre at world position ``origin + ijk * voxel_size`` (mm,
LPS). Coordinates are N×3 int32; features are named N-vectors (or N×C arrays).

In a zarr group the layout is::

    <group>/coords            N×3 int32
    <group>/<feature name>    N or N×C
    <group>.attrs             {"voxel_size_mm": float, "origin_mm": [x, y, z], "features": [...]}
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass
class SparseVoxels:
    coords: np.ndarray  # N×3 int32 voxel indices
    voxel_size: float  # mm, isotropic
    origin: np.ndarray  # (3,) world position of index (0, 0, 0), mm
    features: dict[str, np.ndarray] = field(default_factory=dict)

    def __post_init__(self):
        self.coords = np.asarray(self.coords, dtype=np.int32).reshape(-1, 3)
        self.origin = np.asarray(self.origin, dtype=float).reshape(3)
        self.voxel_size = float(self.voxel_size)
        for name, values in self.features.items():
            if len(values) != len(self.coords):
                raise ValueError(f"feature {name!r} has {len(values)} rows for {len(self.coords)} voxels")

    def __len__(self) -> int:
        return len(self.coords)

    def subset(self, keep) -> "SparseVoxels":
        """The voxels selected by a boolean mask or index array, with their features, on the same grid."""
        keep = np.asarray(keep)
        return SparseVoxels(self.coords[keep], self.voxel_size, self.origin,
                            {k: np.asarray(v)[keep] for k, v in self.features.items()})

    # ------------------------------------------------------------------ geometry
    def world_points(self) -> np.ndarray:
        """N×3 voxel centres in world mm."""
        return self.origin + self.coords.astype(float) * self.voxel_size

    @classmethod
    def from_world_points(cls, points, voxel_size: float, origin=None, features=None) -> "SparseVoxels":
        """Snap world points to the grid (nearest voxel centre); duplicates are kept, caller decides."""
        points = np.asarray(points, dtype=float).reshape(-1, 3)
        origin = np.zeros(3) if origin is None else np.asarray(origin, dtype=float)
        coords = np.rint((points - origin) / voxel_size).astype(np.int32)
        return cls(coords, voxel_size, origin, dict(features or {}))

    # ------------------------------------------------------------------ dense conversion
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """Inclusive (min, max) integer index of the set."""
        return self.coords.min(axis=0), self.coords.max(axis=0)

    def to_dense(self, feature: str | None = None, pad: int = 0, fill=0):
        """Dense array over the bounding box (+pad). Returns (array, index offset of array[0,0,0])."""
        lo, hi = self.bounds()
        lo = lo - pad
        shape = tuple((hi + pad - lo + 1).tolist())
        values = np.ones(len(self), dtype=bool) if feature is None else self.features[feature]
        dense = np.full(shape + values.shape[1:], fill, dtype=values.dtype)
        idx = self.coords - lo
        dense[idx[:, 0], idx[:, 1], idx[:, 2]] = values
        return dense, lo

    @classmethod
    def from_dense(cls, mask, voxel_size: float, origin, offset=(0, 0, 0), features=None) -> "SparseVoxels":
        """Active voxels of a dense boolean mask; ``features`` maps names to dense arrays sampled at them."""
        mask = np.asarray(mask, dtype=bool)
        idx = np.argwhere(mask)
        feats = {name: np.asarray(arr)[tuple(idx.T)] for name, arr in (features or {}).items()}
        return cls(idx + np.asarray(offset, dtype=np.int64), voxel_size, origin, feats)

    # ------------------------------------------------------------------ storage
    def write_to_group(self, group) -> None:
        """Store into a (writable) zarr group: coords, one array per feature, grid attributes."""
        group.create_array("coords", data=self.coords)
        for name, values in self.features.items():
            group.create_array(name, data=np.asarray(values))
        group.attrs.update({
            "voxel_size_mm": self.voxel_size,
            "origin_mm": self.origin.tolist(),
            "features": list(self.features),
        })

    @classmethod
    def read_from_group(cls, group) -> "SparseVoxels":
        attrs = dict(group.attrs)
        feats = {name: group[name][...] for name in attrs.get("features", [])}
        return cls(group["coords"][...], attrs["voxel_size_mm"], np.asarray(attrs["origin_mm"]), feats)
