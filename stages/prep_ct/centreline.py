"""Centreline graph of a lumen: skeleton of the occupancy grid, refined onto the ridge of φ (paper Eq. 1).

φ is the signed distance to the lumen mesh (positive inside), evaluated from a k-d tree of the mesh
vertices (marching-cubes vertices are ≤ 0.1 mm apart, so the nearest vertex is within a few µm of the
nearest surface point); its sign comes from the nearest vertex's outward normal. Steps:

1. ``skimage.morphology.skeletonize`` (3D thinning) of the boolean occupancy grid (0.3 mm by default);
2. a networkx graph of 26-neighbour skeleton voxels, reduced to its minimum spanning tree (which
   removes the little triangles 26-adjacency creates) and split into segments between endpoints and
   junctions (adjacent junction voxels are one junction);
3. spur pruning: a terminal segment shorter than ``spur_factor`` × φ(junction) + ``spur_mm`` is a
   surface bump, not a vessel; removed repeatedly until none is left; tiny components are dropped;
4. segments resampled every ``step_mm``; each interior node moved onto the ridge of φ (the maximum of
   φ in the plane normal to the centreline, two-level grid search), junction nodes to the local 3D
   maximum of φ. Radius of a junction node: φ there (largest inscribed sphere); of other nodes: the
   median distance to the wall along 16 rays in the normal plane (sphere tracing of φ), which is not
   biased low by the smallest bump of a voxelised wall as the inscribed sphere is;
5. junctions closer than ``merge_factor`` × their radius are merged (e.g. a left-main trifurcation).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

log = logging.getLogger(__name__)


class SurfaceDistance:
    """Signed distance φ to a closed mesh (positive inside) from its vertices and vertex normals."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import trimesh
        from scipy.spatial import cKDTree

        mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces), process=False)
        self.vertices = np.asarray(mesh.vertices, float)
        self.normals = np.asarray(mesh.vertex_normals, float)
        self.tree = cKDTree(self.vertices)

    def __call__(self, x: np.ndarray, workers: int | None = None) -> np.ndarray:
        x = np.asarray(x, float).reshape(-1, 3)
        d, i = self.tree.query(x, workers=workers or _workers())
        sign = np.sign(np.einsum("ij,ij->i", self.vertices[i] - x, self.normals[i]))
        sign[sign == 0] = 1.0
        return d * sign

    def unsigned(self, x: np.ndarray, workers: int | None = None) -> np.ndarray:
        return self.tree.query(np.asarray(x, float).reshape(-1, 3), workers=workers or _workers())[0]


def _workers() -> int:
    """k-d tree query threads: OMP_NUM_THREADS when set (batch workers run with 1), else all cores."""
    import os

    try:
        return max(1, int(os.environ.get("OMP_NUM_THREADS", "")))
    except ValueError:
        return -1


@dataclass
class Centreline:
    nodes: np.ndarray  # N×3 world mm
    radius: np.ndarray  # N mm
    edges: np.ndarray  # E×2 int

    def graph(self):
        import networkx as nx

        g = nx.Graph()
        for i, (p, r) in enumerate(zip(self.nodes, self.radius)):
            g.add_node(i, pos=p, radius=float(r))
        g.add_edges_from(map(tuple, self.edges.tolist()))
        return g


def bifurcation_count(nodes: np.ndarray, edges: np.ndarray) -> int:
    """Σ (degree − 2) over nodes of degree ≥ 3 (a trifurcation counts 2, as two bifurcations)."""
    if len(edges) == 0:
        return 0
    deg = np.bincount(np.asarray(edges).ravel(), minlength=len(nodes))
    return int(np.sum(np.maximum(deg - 2, 0)))


def extract_centreline(occupancy: np.ndarray, occ_affine: np.ndarray, phi: SurfaceDistance, *,
                       step_mm: float = 0.5, spur_factor: float = 1.0, spur_mm: float = 0.5,
                       min_component_mm: float = 3.0, merge_factor: float = 1.0) -> Centreline:
    import networkx as nx
    from scipy.spatial import cKDTree
    from skimage.morphology import skeletonize

    # crop to the occupied box to keep the thinning cheap
    nz = np.argwhere(occupancy)
    lo, hi = nz.min(0), nz.max(0) + 1
    sk = skeletonize(occupancy[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
    vox = np.argwhere(sk) + lo
    if len(vox) < 2:
        raise ValueError("skeletonisation found no centreline (lumen too small, or a perfectly grid-aligned "
                         "straight rod of even width, which 3D thinning erases)")
    world = vox @ occ_affine[:3, :3].T + occ_affine[:3, 3]

    # 26-neighbour graph weighted by world length; the MST drops the diagonal shortcuts
    pairs = cKDTree(vox).query_pairs(np.sqrt(3) + 1e-3, output_type="ndarray")
    g = nx.Graph()
    g.add_nodes_from(range(len(vox)))
    w = np.linalg.norm(world[pairs[:, 0]] - world[pairs[:, 1]], axis=1)
    g.add_weighted_edges_from(zip(pairs[:, 0].tolist(), pairs[:, 1].tolist(), w.tolist()))
    g = nx.minimum_spanning_tree(g)

    # drop tiny components (specks of skeleton)
    for comp in list(nx.connected_components(g)):
        length = sum(d["weight"] for _, _, d in g.subgraph(comp).edges(data=True))
        if length < min_component_mm:
            g.remove_nodes_from(comp)
    if g.number_of_nodes() < 2:
        raise ValueError("no centreline left after removing specks")

    segments = _segments(g)
    # spur pruning, repeated: removing a spur can turn its junction into a plain path point
    for _ in range(10):
        removed = False
        deg = dict(g.degree())
        for seg in segments:
            a, b = seg[0], seg[-1]
            if (deg[a] == 1) == (deg[b] == 1):
                continue  # not a terminal segment (or an isolated line)
            junction = b if deg[a] == 1 else a
            length = float(np.linalg.norm(np.diff(world[seg], axis=0), axis=1).sum())
            r = max(float(phi(world[junction])[0]), 0.0)
            if length < spur_factor * r + spur_mm:
                g.remove_nodes_from([n for n in seg if n != junction])
                removed = True
        if not removed:
            break
        segments = _segments(g)

    # resample, refine on the ridge of φ
    node_pos: list[np.ndarray] = []
    key_index: dict[int, int] = {}
    edges: list[tuple[int, int]] = []

    def key_node(n):
        if n not in key_index:
            key_index[n] = len(node_pos)
            node_pos.append(world[n])
        return key_index[n]

    interior_ids: list[int] = []
    tangents: list[np.ndarray] = []
    for seg in segments:
        pts = world[seg]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        n_int = max(int(round(s[-1] / step_mm)) - 1, 0)
        a = key_node(seg[0])
        prev = a
        if n_int > 0:
            t = np.linspace(0, s[-1], n_int + 2)[1:-1]
            # smooth the voxel staircase before resampling (moving average over ~1 mm)
            k = 2
            sm = pts.copy()
            if len(pts) > 2 * k + 1:
                ker = np.ones(2 * k + 1) / (2 * k + 1)
                for ax in range(3):
                    padded = np.concatenate([np.full(k, pts[0, ax]), pts[:, ax], np.full(k, pts[-1, ax])])
                    sm[:, ax] = np.convolve(padded, ker, mode="valid")
            res = np.stack([np.interp(t, s, sm[:, ax]) for ax in range(3)], axis=1)
            tang = np.gradient(np.concatenate([pts[:1], res, pts[-1:]]), axis=0)[1:-1]
            for p, tg in zip(res, tang):
                idx = len(node_pos)
                node_pos.append(p)
                interior_ids.append(idx)
                tangents.append(tg / max(np.linalg.norm(tg), 1e-9))
                edges.append((prev, idx))
                prev = idx
        b = key_node(seg[-1])
        if b != prev:
            edges.append((prev, b))
    nodes = np.asarray(node_pos, float)
    edges_arr = np.asarray(edges, np.int64).reshape(-1, 2)

    if interior_ids:
        ids = np.asarray(interior_ids)
        nodes[ids] = _ridge_in_plane(nodes[ids], np.asarray(tangents), phi)
    key_ids = np.asarray(sorted(key_index.values()))
    deg = np.bincount(edges_arr.ravel(), minlength=len(nodes))
    junctions = key_ids[deg[key_ids] >= 3]
    if len(junctions):
        nodes[junctions] = _ridge_3d(nodes[junctions], phi)
    radius = np.maximum(phi(nodes), 0.0)
    # lumen radius of path and end nodes: median wall distance over rays in the normal plane (the
    # inscribed-sphere radius φ is biased low by the smallest bump of a voxelised wall); junctions keep φ
    tang = np.zeros_like(nodes)
    np.add.at(tang, edges_arr[:, 0], nodes[edges_arr[:, 1]] - nodes[edges_arr[:, 0]])
    np.add.at(tang, edges_arr[:, 1], nodes[edges_arr[:, 1]] - nodes[edges_arr[:, 0]])
    ok = (deg <= 2) & (np.linalg.norm(tang, axis=1) > 1e-9)
    if ok.any():
        t = tang[ok] / np.linalg.norm(tang[ok], axis=1, keepdims=True)
        radius[ok] = _ray_radius(nodes[ok], t, phi, radius[ok])
    nodes, radius, edges_arr = _merge_close_junctions(nodes, radius, edges_arr, merge_factor)
    return Centreline(nodes, radius, edges_arr)


def _segments(g) -> list[list[int]]:
    """Chains of graph nodes between key nodes (degree ≠ 2); cycles become one segment."""
    deg = dict(g.degree())
    key = {n for n, d in deg.items() if d != 2}
    segs, seen = [], set()
    for k in key:
        for nb in g.neighbors(k):
            if (k, nb) in seen:
                continue
            chain = [k, nb]
            prev, cur = k, nb
            while cur not in key:
                nxt = [x for x in g.neighbors(cur) if x != prev]
                if not nxt:
                    break
                prev, cur = cur, nxt[0]
                chain.append(cur)
            seen.add((chain[-1], chain[-2]))
            seen.add((k, nb))
            segs.append(chain)
    return segs


def _plane_basis(t: np.ndarray):
    a = np.where(np.abs(t[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    e1 = np.cross(t, a)
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(t, e1)
    return e1, e2


def _ridge_in_plane(p: np.ndarray, t: np.ndarray, phi: SurfaceDistance, rounds=((0.3, 7), (0.1, 7), (0.03, 7))):
    """Move each point to the maximum of φ on a grid in the plane normal to its tangent (coarse→fine)."""
    e1, e2 = _plane_basis(t)
    p = p.copy()
    for half, n in rounds:
        u = np.linspace(-half, half, n)
        uu, vv = np.meshgrid(u, u, indexing="ij")
        off = uu.reshape(-1)[None, :, None] * e1[:, None, :] + vv.reshape(-1)[None, :, None] * e2[:, None, :]
        cand = p[:, None, :] + off
        val = phi(cand.reshape(-1, 3)).reshape(len(p), -1)
        best = np.argmax(val, axis=1)
        p = cand[np.arange(len(p)), best]
    return p


def _ray_radius(p: np.ndarray, t: np.ndarray, phi: SurfaceDistance, start: np.ndarray, n_rays: int = 16,
                iterations: int = 8) -> np.ndarray:
    """Median distance to the wall along ``n_rays`` rays in the normal plane, found by sphere tracing φ."""
    e1, e2 = _plane_basis(t)
    ang = np.linspace(0, 2 * np.pi, n_rays, endpoint=False)
    dirs = np.cos(ang)[None, :, None] * e1[:, None, :] + np.sin(ang)[None, :, None] * e2[:, None, :]
    dist = np.repeat(np.maximum(start, 0.0)[:, None], n_rays, axis=1)
    for _ in range(iterations):
        x = p[:, None, :] + dist[..., None] * dirs
        step = phi(x.reshape(-1, 3)).reshape(dist.shape)
        dist = dist + step  # φ is a distance: never steps through the wall from inside
    return np.median(dist, axis=1)


def _ridge_3d(p: np.ndarray, phi: SurfaceDistance, rounds=((0.4, 9), (0.1, 7), (0.025, 7))):
    p = p.copy()
    for half, n in rounds:
        u = np.linspace(-half, half, n)
        off = np.stack(np.meshgrid(u, u, u, indexing="ij"), -1).reshape(-1, 3)
        cand = p[:, None, :] + off[None]
        val = phi(cand.reshape(-1, 3)).reshape(len(p), -1)
        p = cand[np.arange(len(p)), np.argmax(val, axis=1)]
    return p


def _merge_close_junctions(nodes, radius, edges, factor):
    """Contract paths between two junctions shorter than ``factor`` × (r1 + r2) into one node."""
    import networkx as nx

    g = nx.Graph()
    g.add_nodes_from(range(len(nodes)))
    g.add_edges_from(map(tuple, edges.tolist()))
    changed = True
    while changed:
        changed = False
        junc = [n for n, d in g.degree() if d >= 3]
        jset = set(junc)
        for j in junc:
            if j not in g:
                continue
            # walk each branch from j until a key node; if it is a junction close by, contract
            for nb in list(g.neighbors(j)):
                path = [j, nb]
                while path[-1] not in jset and g.degree(path[-1]) == 2 and len(path) < 50:
                    nxt = [x for x in g.neighbors(path[-1]) if x != path[-2]]
                    path.append(nxt[0])
                end = path[-1]
                if end == j or end not in jset or g.degree(end) < 3:
                    continue
                length = np.linalg.norm(np.diff(nodes[path], axis=0), axis=1).sum()
                if length < factor * (radius[j] + radius[end]):
                    keep = j
                    for n in path[1:]:
                        for x in list(g.neighbors(n)):
                            if x != keep and x not in path:
                                g.add_edge(keep, x)
                        g.remove_node(n)
                    nodes[keep] = nodes[path].mean(axis=0)
                    changed = True
                    break
            if changed:
                break
    keep = np.asarray(sorted(g.nodes()))
    remap = -np.ones(len(nodes), np.int64)
    remap[keep] = np.arange(len(keep))
    e = np.asarray([(remap[a], remap[b]) for a, b in g.edges()], np.int64).reshape(-1, 2)
    return nodes[keep], radius[keep], e
