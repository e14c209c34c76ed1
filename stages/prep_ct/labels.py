"""Sparse training labels around a lumen: occupancy (paper Eq. 4) and centreness (paper Eq. 3).

The voxels lie on the world-aligned lattice of ``voxel_mm`` (0.5 mm default) whose index (0, 0, 0) is
the world origin shifted to the case's bounding box, i.e. voxel centres sit at multiples of
``voxel_mm`` in world mm (LPS), so labels of all cases share one lattice. Kept: every voxel whose
centre is inside the lumen plus a band of outside voxels within ``band_mm`` of the wall (negatives).

* occupancy o(x) = 1 if φ(x) > 0 (inside the lumen) else 0                              (Eq. 4)
* centreness c(x) = φ(x) / (φ(x) + d_cl(x)) inside, 0 outside                            (Eq. 3)
  with φ the signed distance to the lumen wall (positive inside) and d_cl the distance to the
  centreline polyline: 1 on the centreline, 0 on the wall.
"""

from __future__ import annotations

import numpy as np

from ..core.voxels import SparseVoxels


def densify_polyline(nodes: np.ndarray, edges: np.ndarray, step: float = 0.05) -> np.ndarray:
    """Points along every centreline edge, at most ``step`` apart (for distance-to-centreline queries)."""
    nodes = np.asarray(nodes, float)
    if len(edges) == 0:
        return nodes.copy()
    a, b = nodes[edges[:, 0]], nodes[edges[:, 1]]
    n = np.maximum(np.ceil(np.linalg.norm(b - a, axis=1) / step).astype(int), 1)
    seg = np.repeat(np.arange(len(edges)), n + 1)
    t = np.concatenate([np.linspace(0, 1, k + 1) for k in n])
    return a[seg] + t[:, None] * (b[seg] - a[seg])


_BIAS = 1 << 20  # lattice indices are |i| < 2^20 (±524 m at 0.5 mm)


def _encode(idx: np.ndarray) -> np.ndarray:
    """One int64 key per lattice index triple (np.unique on keys is far faster than on rows)."""
    b = idx.astype(np.int64) + _BIAS
    return (b[:, 0] << 42) | (b[:, 1] << 21) | b[:, 2]


def _decode(key: np.ndarray) -> np.ndarray:
    mask = (1 << 21) - 1
    return np.stack([(key >> 42) & mask, (key >> 21) & mask, key & mask], axis=1) - _BIAS


def centreness(phi_values: np.ndarray, d_centreline: np.ndarray) -> np.ndarray:
    """Eq. 3: φ/(φ + d_cl) where φ > 0, else 0 (both arrays in mm)."""
    phi_values = np.asarray(phi_values, float)
    d = np.asarray(d_centreline, float)
    out = np.zeros(len(phi_values), np.float32)
    inside = phi_values > 0
    out[inside] = phi_values[inside] / (phi_values[inside] + d[inside])
    return np.clip(out, 0.0, 1.0)


def sparse_labels(phi, nodes: np.ndarray, radius: np.ndarray, edges: np.ndarray, *, voxel_mm: float = 0.5,
                  band_mm: float = 1.0) -> SparseVoxels:
    """SparseVoxels with features occupancy (uint8) and centreness (float32) around a lumen.

    ``phi`` is a callable giving the signed distance (positive inside) at N×3 world points.
    """
    from scipy.spatial import cKDTree

    dense_cl = densify_polyline(nodes, np.asarray(edges).reshape(-1, 2), 0.05)
    # radius along the densified centreline (nearest node's radius), for the candidate boxes
    r_cl = np.asarray(radius, float)[cKDTree(nodes).query(dense_cl)[1]]
    # candidate voxels: lattice points within r + band + one voxel of a centreline point
    stride = max(1, int(round(voxel_mm / 0.05)))  # one box per voxel length of centreline
    sub, r_sub = dense_cl[::stride], r_cl[::stride]
    reach = r_sub + band_mm + voxel_mm
    order = np.argsort(reach)
    keys = []
    for chunk in np.array_split(order, max(1, len(order) // 2000)):
        k = int(np.ceil(reach[chunk].max() / voxel_mm))
        off = np.stack(np.meshgrid(*[np.arange(-k, k + 1)] * 3, indexing="ij"), -1).reshape(-1, 3)
        base = np.rint(sub[chunk] / voxel_mm).astype(np.int64)
        idx = (base[:, None, :] + off[None]).reshape(-1, 3)
        owner = np.repeat(chunk, len(off))
        near = np.linalg.norm(idx * voxel_mm - sub[owner], axis=1) <= reach[owner]
        keys.append(_encode(idx[near]))
    idx = _decode(np.unique(np.concatenate(keys)))
    x = idx * voxel_mm
    ph = phi(x)
    keep = ph > -band_mm
    idx, x, ph = idx[keep], x[keep], ph[keep]
    d_cl = cKDTree(dense_cl).query(x)[0]
    occ = (ph > 0).astype(np.uint8)
    cen = centreness(ph, d_cl)
    lo = idx.min(axis=0)
    return SparseVoxels((idx - lo).astype(np.int32), voxel_mm, lo * voxel_mm,
                        {"occupancy": occ, "centreness": cen})
