"""A small tubular test tree built directly as a prepared case (no CT pipeline), for tests and benchmarks.

Reads/writes nothing. :func:`tube_case` makes a watertight lumen mesh by a boolean union
(manifold3d) of spheres and cone frusta along a few random branches, its centreline graph, and
labels (occupancy from the distance to the centreline segments, a band of outside voxels), placed
around a heart frame near the isocentre like the procedural trees of ``prep-ct``. Real prepared
cases come from ``autocar prep-ct``; this keeps the renderer's tests independent of that stage.
"""

from __future__ import annotations

import numpy as np

__all__ = ["tube_case"]


def _rotation_to(z: np.ndarray) -> np.ndarray:
    z = z / np.linalg.norm(z)
    a = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(a, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.stack([x, y, z], 1)  # columns: local x, y, z in world


def tube_case(seed: int = 0, n_branches: int = 4, segments: int = 20, step: float = 4.0, voxel: float = 0.5):
    """A PreparedCase of a random little tree (main branch of ~80 mm plus side branches)."""
    import manifold3d as m3d

    from ..core.prepared_case import PreparedCase
    from ..core.voxels import SparseVoxels

    rng = np.random.default_rng(seed)
    heart_c = np.array([10.0, -20.0, -10.0]) + rng.normal(0, 3, 3)
    axis = np.array([0.5, -0.55, -0.67])
    axis /= np.linalg.norm(axis)
    nodes, radius, edges = [], [], []

    def branch(p0, d, r0, n, parent_node):
        p = np.array(p0, float)
        for i in range(n):
            d = d + 0.25 * rng.standard_normal(3)
            d /= np.linalg.norm(d)
            p = p + step * d
            nodes.append(p.copy())
            radius.append(max(r0 * (1 - 0.45 * (i + 1) / n), 0.6))
            edges.append((parent_node, len(nodes) - 1))
            parent_node = len(nodes) - 1

    root = heart_c - 35 * axis + np.array([0, 0, 10.0])
    nodes.append(root)
    radius.append(2.0)
    branch(root, axis + np.array([0.3, 0, 0]), 2.0, 20, 0)
    for _ in range(n_branches - 1):
        i = int(rng.integers(3, 16))
        branch(nodes[i], rng.standard_normal(3), radius[i] * 0.7, 10, i)
    nodes_a, radius_a, edges_a = np.array(nodes), np.array(radius), np.array(edges, np.int32)
    parts = [m3d.Manifold.sphere(float(r), segments).translate(tuple(p)) for p, r in zip(nodes_a, radius_a)]
    for a, b in edges_a:
        pa, pb = nodes_a[a], nodes_a[b]
        L = float(np.linalg.norm(pb - pa))
        R = _rotation_to(pb - pa)
        M = np.hstack([R, pa[:, None]])
        parts.append(m3d.Manifold.cylinder(L, float(radius_a[a]), float(radius_a[b]), segments).transform(M.tolist()))
    mesh = m3d.Manifold.batch_boolean(parts, m3d.OpType.Add).to_mesh()
    V = np.asarray(mesh.vert_properties)[:, :3].astype(np.float32)
    F = np.asarray(mesh.tri_verts).astype(np.int32)
    # labels: distance to the segments vs interpolated radius, on a 0.5 mm grid around the tree
    lo = V.min(0) - 2.0
    hi = V.max(0) + 2.0
    origin = np.floor(lo / voxel) * voxel
    shape = np.ceil((hi - origin) / voxel).astype(int) + 1
    best = np.full(tuple(shape), np.inf, dtype=np.float32)  # signed distance to the lumen (negative inside)
    for a, b in edges_a:
        pa, pb = nodes_a[a], nodes_a[b]
        pad = max(radius_a[a], radius_a[b]) + 2.0
        i0 = np.maximum(np.floor((np.minimum(pa, pb) - pad - origin) / voxel).astype(int), 0)
        i1 = np.minimum(np.ceil((np.maximum(pa, pb) + pad - origin) / voxel).astype(int) + 1, shape)
        sub = np.stack(np.meshgrid(*[np.arange(i0[k], i1[k]) for k in range(3)], indexing="ij"), -1)
        X = origin + sub * voxel
        d = pb - pa
        t = np.clip(((X - pa) @ d) / (d @ d), 0, 1)
        dist = np.sqrt((((X - (pa + t[..., None] * d))) ** 2).sum(-1))
        r = radius_a[a] + t * (radius_a[b] - radius_a[a])
        view = best[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]]
        np.minimum(view, (dist - r).astype(np.float32), out=view)
    keep = best < 1.5
    g = np.argwhere(keep)
    occ = (best[keep] <= 0).astype(np.uint8)
    centreness = np.clip(-best[keep], 0, None).astype(np.float32)
    labels = SparseVoxels(g, voxel, origin, {"occupancy": occ, "centreness": centreness})
    return PreparedCase(case_id=f"tube{seed}", side="left", vertices=V, faces=F, nodes=nodes_a, radius=radius_a,
                        edges=edges_a, labels=labels, source={"synthetic": "tube_case", "seed": seed},
                        heart={"centre": heart_c.tolist(), "long_axis": axis.tolist()})
