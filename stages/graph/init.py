"""Graph initialisation (paper, Methods, "Graph optimization", Eq. 14): predicted sparse volume → vascular graph.

Steps, for one key frame's prediction (a :class:`~stages.core.voxels.SparseVoxels` with features
``occupancy`` and ``centreness`` in [0, 1]):

1. threshold occupancy (≥ 0.5 by default; the graph stage uses :data:`DEFAULT_OCCUPANCY_THRESHOLD`);
2. thin the thresholded set to centreline voxels (skimage 3D thinning, Lee 1994, on the dense bounding
   box: boxes are small at 0.5 mm);
3. connect centreline voxels closer than ε (a radius graph) and keep its minimum spanning tree (Eq. 14);
4. bridge the remaining components with minimum-cost paths through the predicted volume (step cost
   = length × (1 − occupancy + floor), so paths follow the prediction through sub-threshold gaps). One
   multi-source Dijkstra from all centreline voxels labels every voxel with its nearest component
   (a geodesic Voronoi partition); the cheapest path between two adjacent regions crosses their common
   border, and Kruskal's algorithm on those inter-component paths accepts bridges in order of cost until
   one component remains or the next bridge costs more than ``bridge_max_cost``;
5. prune spurs (terminal segments shorter than a few radii), drop small leftover components;
6. refine node positions (centreness-weighted centroid across the vessel, then light smoothing along
   segments) and set node radii from the lumen: distance to the nearest voxel just outside the set.

Reads/writes nothing; :func:`init_graph` is the entry point.
"""

from __future__ import annotations

import numpy as np

from ..core.errors import UserError
from .vascular import VascularGraph

# the graph stage's threshold for the shipped networks' predictions, lower than ½ because they are
# under-confident on thin and weakly seen vessels: tuned for accuracy on cases apart from every evaluation
# (docs/benchmarks/graph_threshold.md; script: git show 4cf1374:benchmarks/tune_graph_threshold.py) with the
# 3500-step SBP; with the 7300-step one and graph completion from the views (stages.graph.complete), 0.2 has
# the highest accuracy (0.408 against 0.385–0.400 for 0.3–0.5). init_graph itself defaults
# to ½, the boundary of a calibrated occupancy.
DEFAULT_OCCUPANCY_THRESHOLD = 0.2

__all__ = ["init_graph", "EmptyPredictionError", "DEFAULT_OCCUPANCY_THRESHOLD", "spur_nodes", "prune_spurs", "smooth_along_segments", "neighbour_pairs"]


class EmptyPredictionError(UserError):
    """No voxel of a prediction reaches the occupancy threshold."""


_OFFSETS13 = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)
                       if (i, j, k) > (0, 0, 0)], np.int64)


def neighbour_pairs(coords: np.ndarray):
    """26-neighbour pairs (a, b, length in voxels) among N×3 integer voxel coordinates (each pair once)."""
    c = np.asarray(coords, np.int64)
    if not len(c):
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    lo = c.min(0) - 1
    dims = c.max(0) - lo + 2
    key = ((c[:, 0] - lo[0]) * dims[1] + (c[:, 1] - lo[1])) * dims[2] + (c[:, 2] - lo[2])
    order = np.argsort(key)
    skey = key[order]
    A, B, L = [], [], []
    for off in _OFFSETS13:
        q = key + (off[0] * dims[1] + off[1]) * dims[2] + off[2]
        pos = np.searchsorted(skey, q)
        pos = np.minimum(pos, len(skey) - 1)
        hit = skey[pos] == q
        A.append(np.flatnonzero(hit))
        B.append(order[pos[hit]])
        L.append(np.full(int(hit.sum()), np.sqrt(float(off @ off))))
    return np.concatenate(A), np.concatenate(B), np.concatenate(L)


def _components(n, a, b):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    M = coo_matrix((np.ones(len(a)), (a, b)), shape=(n, n))
    return connected_components(M, directed=False)


def _mst_edges(points: np.ndarray, eps: float, weight=None):
    """Edges of the minimum spanning forest of the ε radius graph on the points (Eq. 14)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import minimum_spanning_tree
    from scipy.spatial import cKDTree

    pairs = cKDTree(points).query_pairs(eps, output_type="ndarray")
    if not len(pairs):
        return np.zeros((0, 2), np.int64)
    w = np.linalg.norm(points[pairs[:, 0]] - points[pairs[:, 1]], axis=1)
    if weight is not None:  # prefer edges through confident (central) voxels
        w = w * (1.5 - 0.5 * 0.5 * (weight[pairs[:, 0]] + weight[pairs[:, 1]]))
    n = len(points)
    T = minimum_spanning_tree(coo_matrix((w, (pairs[:, 0], pairs[:, 1])), shape=(n, n)).tocsr()).tocoo()
    return np.stack([T.row, T.col], 1).astype(np.int64)


def _bridge(vox_coords, occ, seeds, seed_comp, voxel_size, max_cost, floor):
    """Minimum-cost paths joining components (geodesic Voronoi + Kruskal).

    ``seeds``: indices (into vox_coords) of centreline voxels, ``seed_comp`` their component labels.
    Returns a list of voxel-index paths, each running from a seed of one component to a seed of another.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    a, b, L = neighbour_pairs(vox_coords)
    n = len(vox_coords)
    step = 1.0 - 0.5 * (occ[a] + occ[b]) + floor
    w = L * voxel_size * step
    G = coo_matrix((np.r_[w, w], (np.r_[a, b], np.r_[b, a])), shape=(n, n)).tocsr()
    dist, pred, src = dijkstra(G, directed=True, indices=seeds, min_only=True, return_predecessors=True,
                               limit=max_cost)
    comp_of_voxel = np.full(n, -1, np.int64)
    reached = src >= 0
    seed_label = np.full(n, -1, np.int64)
    seed_label[seeds] = seed_comp
    comp_of_voxel[reached] = seed_label[src[reached]]
    ca, cb = comp_of_voxel[a], comp_of_voxel[b]
    cross = (ca >= 0) & (cb >= 0) & (ca != cb)
    if not cross.any():
        return []
    ea, eb = a[cross], b[cross]
    cost = dist[ea] + w[cross] + dist[eb]
    ok = cost <= max_cost
    ea, eb, cost = ea[ok], eb[ok], cost[ok]
    order = np.argsort(cost, kind="stable")
    parent = {}

    def find(x):
        while parent.get(x, x) != x:
            parent[x] = parent.get(parent[x], parent[x])
            x = parent[x]
        return x

    paths = []
    for k in order:
        u, v = int(ea[k]), int(eb[k])
        ru, rv = find(int(comp_of_voxel[u])), find(int(comp_of_voxel[v]))
        if ru == rv:
            continue
        parent[ru] = rv
        left = [u]
        while pred[left[-1]] >= 0:
            left.append(int(pred[left[-1]]))
        right = [v]
        while pred[right[-1]] >= 0:
            right.append(int(pred[right[-1]]))
        paths.append(np.asarray(left[::-1] + right, np.int64))
    return paths


def spur_nodes(g: VascularGraph, min_length_mm: float = 2.5, radius_factor: float = 2.5) -> np.ndarray:
    """Per node, whether it lies on a spur: a terminal segment (end point → junction) shorter than max(min_length,
    factor × junction radius), its end point included, its junction not."""
    deg = g.degrees()
    drop = np.zeros(len(g), bool)
    for seg in g.segments():
        d0, d1 = deg[seg[0]], deg[seg[-1]]
        if {d0 >= 3, d1 >= 3} != {True, False} or min(d0, d1) != 1:
            continue
        junction = seg[0] if d0 >= 3 else seg[-1]
        length = np.linalg.norm(np.diff(g.nodes[seg], axis=0), axis=1).sum()
        if length < max(min_length_mm, radius_factor * g.radius[junction]):
            drop[seg[1:] if junction == seg[0] else seg[:-1]] = True
    return drop


def prune_spurs(g: VascularGraph, min_length_mm: float = 2.5, radius_factor: float = 2.5, passes: int = 4) -> VascularGraph:
    """Remove the spurs (:func:`spur_nodes`), again where removing one leaves another, up to ``passes`` times."""
    for _ in range(passes):
        drop = spur_nodes(g, min_length_mm, radius_factor)
        if not drop.any():
            break
        g = g.subgraph(~drop)
    return g


def smooth_along_segments(g: VascularGraph, iterations: int = 3, alpha: float = 0.5) -> VascularGraph:
    """Laplacian smoothing of degree-2 nodes (junctions and end points stay put)."""
    if not len(g.edges):
        return g
    from scipy.sparse import coo_matrix

    n = len(g)
    e = g.edges
    A = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    deg = np.asarray(A.sum(1)).ravel()
    move = deg == 2
    X = g.nodes.copy()
    for _ in range(iterations):
        mean = (A @ X) / np.maximum(deg, 1)[:, None]
        X[move] = (1 - alpha) * X[move] + alpha * mean[move]
    return g.copy(nodes=X)


def _fill_missing(g: VascularGraph, values: np.ndarray, iterations: int = 50) -> np.ndarray:
    """Fill NaN node values by repeated neighbour averaging along edges (then the global median)."""
    v = values.copy()
    if not np.isnan(v).any():
        return v
    e = g.edges
    for _ in range(iterations):
        bad = np.isnan(v)
        if not bad.any() or not len(e):
            break
        s = np.zeros(len(v))
        c = np.zeros(len(v))
        for i, j in ((0, 1), (1, 0)):
            ok = ~np.isnan(v[e[:, j]])
            np.add.at(s, e[ok, i], v[e[ok, j]])
            np.add.at(c, e[ok, i], 1)
        upd = bad & (c > 0)
        if not upd.any():
            break
        v[upd] = s[upd] / c[upd]
    v[np.isnan(v)] = np.nanmedian(values) if np.isfinite(values).any() else 1.0
    return v


def _refine_centres(g: VascularGraph, vox_points: np.ndarray, weight: np.ndarray, reach: float) -> np.ndarray:
    """Move degree-2 nodes to the weighted centroid of nearby voxels, across the vessel only."""
    from scipy.spatial import cKDTree

    X = g.nodes.copy()
    deg = g.degrees()
    idx = np.flatnonzero(deg == 2)
    if not len(idx):
        return X
    # tangent of each degree-2 node from its two neighbours
    nb = [[] for _ in range(len(g))]
    for a, b in g.edges:
        nb[a].append(b)
        nb[b].append(a)
    t = np.array([X[nb[i][1]] - X[nb[i][0]] for i in idx])
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-9)
    tree = cKDTree(vox_points)
    lists = tree.query_ball_point(X[idx], reach)
    for row, (i, members) in enumerate(zip(idx, lists)):
        if not members:
            continue
        m = np.asarray(members)
        w = weight[m]
        if w.sum() <= 0:
            continue
        c = (w[:, None] * vox_points[m]).sum(0) / w.sum()
        d = c - X[i]
        d -= (d @ t[row]) * t[row]
        X[i] = X[i] + d
    return X


def _thinned_voxels(idx: np.ndarray) -> np.ndarray:
    """Indices (K×3, raster order) of the 3D thinning of the voxels at ``idx`` (N×3, non-negative), each
    26-connected piece thinned in its own box.

    The same skeleton as thinning their whole bounding box at once: thinning removes a voxel by looking at its
    26 neighbours only, so separate pieces never affect each other, and a box keeps the order in which a piece's
    voxels are visited. The tubes fill well under 1 % of their bounding box, so the boxes are far less work."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from skimage.morphology import skeletonize

    idx = np.asarray(idx, np.int64)
    if not len(idx):
        return np.zeros((0, 3), np.int64)
    # the 26-neighbour pairs, found by looking each voxel's 13 forward neighbours up among the sorted voxel keys
    span = idx.max(0) + 3

    def key(p):  # one int64 per voxel; the +1 keeps the neighbours at −1 apart from real voxels
        return ((p[:, 0] + 1) * span[1] + p[:, 1] + 1) * span[2] + p[:, 2] + 1

    keys = key(idx)
    order = np.argsort(keys)
    sorted_keys = keys[order]
    pairs = []
    for off in np.argwhere(np.ones((3, 3, 3), bool))[14:] - 1:  # the 13 offsets after (0, 0, 0) in raster order
        k = key(idx + off)
        pos = np.minimum(np.searchsorted(sorted_keys, k), len(keys) - 1)
        hit = sorted_keys[pos] == k
        pairs.append(np.stack([np.flatnonzero(hit), order[pos[hit]]]))
    pairs = np.concatenate(pairs, axis=1)
    n, label = connected_components(coo_matrix((np.ones(pairs.shape[1]), tuple(pairs)), shape=(len(idx),) * 2),
                                    directed=False)
    found = []
    by_piece = np.argsort(label, kind="stable")
    for members in np.split(by_piece, np.cumsum(np.bincount(label, minlength=n))[:-1]):
        p = idx[members]
        lo = p.min(0)
        piece = np.zeros(tuple((p.max(0) - lo + 1).tolist()), bool)
        piece[tuple((p - lo).T)] = True
        found.append(np.argwhere(skeletonize(piece)) + lo)
    out = np.concatenate(found)
    return out[np.lexsort(out.T[::-1])]  # raster order, as np.argwhere over the whole volume gives it


def init_graph(voxels, *, occupancy_threshold: float = 0.5, epsilon_mm: float | None = None,
               bridge_max_cost: float = 4.0, bridge_min_occupancy: float = 0.05, bridge_floor: float = 0.05,
               spur_length_mm: float = 2.5, spur_radius_factor: float = 2.5, min_component_mm: float = 4.0,
               refine: bool = True, smooth_iterations: int = 3, allow_empty: bool = False) -> VascularGraph:
    """Vascular graph of one predicted sparse volume (see the module docstring for the steps).

    ``voxels``: SparseVoxels with ``occupancy`` (and optionally ``centreness``) in [0, 1].
    ``epsilon_mm``: radius-graph reach (default 1.75 voxels: the 26-neighbourhood).
    ``bridge_max_cost``: largest accepted bridge cost (≈ mm of path through empty prediction).
    Raises :class:`EmptyPredictionError` when no voxel reaches the threshold, unless ``allow_empty``
    (then an empty graph is returned).
    """
    from scipy.spatial import cKDTree

    if "occupancy" not in voxels.features:
        raise UserError("prediction has no 'occupancy' feature")
    occ = np.asarray(voxels.features["occupancy"], float)
    # centreness is documented in [0, 1]; clip so other scalings (e.g. a distance in mm) cannot flip weights
    cen = np.clip(np.asarray(voxels.features.get("centreness", occ), float), 0.0, 1.0)
    vs = voxels.voxel_size
    fg = occ >= occupancy_threshold
    if not fg.any():
        if allow_empty:
            return VascularGraph.empty()
        top = float(occ.max()) if len(occ) else float("nan")
        raise EmptyPredictionError(
            f"no voxel has occupancy ≥ {occupancy_threshold} (of {len(occ)} voxels, the highest is {top:.3g}): "
            "nothing to build a vascular graph from")
    eps = 1.75 * vs if epsilon_mm is None else float(epsilon_mm)

    # ---- 2. thinning on the dense bounding box of the thresholded set
    fc = voxels.coords[fg].astype(np.int64)
    lo = fc.min(0) - 1
    shape = tuple((fc.max(0) + 2 - lo).tolist())
    dense = np.zeros(shape, bool)
    dense[tuple((fc - lo).T)] = True
    sk_idx = _thinned_voxels(fc - lo)
    if not len(sk_idx):  # a blob thinner than the thinning can keep: use its voxel nearest the centroid
        sk_idx = (fc - lo)[[np.argmin(np.linalg.norm(fc - fc.mean(0), axis=1))]]
    sk_coords = sk_idx + lo
    # radii: distance to the nearest voxel just outside the thresholded set (its face neighbours)
    grown = dense.copy()  # face neighbours of the set: the first voxels outside it
    grown[1:] |= dense[:-1]
    grown[:-1] |= dense[1:]
    grown[:, 1:] |= dense[:, :-1]
    grown[:, :-1] |= dense[:, 1:]
    grown[:, :, 1:] |= dense[:, :, :-1]
    grown[:, :, :-1] |= dense[:, :, 1:]
    outside = np.argwhere(grown & ~dense) + lo
    origin = voxels.origin

    # ---- 3. ε radius graph on the centreline voxels → minimum spanning forest (Eq. 14)
    # centreline voxels as indices into the candidate set used for bridging
    cand = occ >= min(bridge_min_occupancy, occupancy_threshold)
    cand_coords = voxels.coords[cand].astype(np.int64)
    cand_occ, cand_cen = occ[cand], cen[cand]
    key_lo = cand_coords.min(0)
    dims = cand_coords.max(0) - key_lo + 1

    def keys(c):
        return ((c[:, 0] - key_lo[0]) * dims[1] + (c[:, 1] - key_lo[1])) * dims[2] + (c[:, 2] - key_lo[2])

    korder = np.argsort(keys(cand_coords))
    sorted_keys = keys(cand_coords)[korder]
    sk_in_cand = korder[np.searchsorted(sorted_keys, keys(sk_coords))]
    sk_pts = origin + sk_coords * vs
    edges = _mst_edges(sk_pts, eps, weight=cand_cen[sk_in_cand])

    # ---- 4. bridge components by minimum-cost paths through the prediction
    ncomp, label = _components(len(sk_pts), edges[:, 0], edges[:, 1])
    node_of_cand = {int(c): i for i, c in enumerate(sk_in_cand)}
    node_cand = list(sk_in_cand)
    edge_list = [tuple(e) for e in edges.tolist()]
    if ncomp > 1:
        for path in _bridge(cand_coords, cand_occ, sk_in_cand, label, vs, bridge_max_cost, bridge_floor):
            prev = None
            for c in path.tolist():
                if c not in node_of_cand:
                    node_of_cand[c] = len(node_cand)
                    node_cand.append(c)
                cur = node_of_cand[c]
                if prev is not None and prev != cur:
                    edge_list.append((prev, cur))
                prev = cur
    node_cand = np.asarray(node_cand, np.int64)
    pts = origin + cand_coords[node_cand] * vs
    e = np.asarray(edge_list, np.int64).reshape(-1, 2)
    if len(e):
        e = np.unique(np.sort(e, axis=1), axis=0)
        e = e[e[:, 0] != e[:, 1]]
    # bridges may close loops with the MST; a final spanning forest keeps the result a tree
    if len(e):
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import minimum_spanning_tree

        w = np.maximum(np.linalg.norm(pts[e[:, 0]] - pts[e[:, 1]], axis=1), 1e-6)
        T = minimum_spanning_tree(coo_matrix((w, (e[:, 0], e[:, 1])), shape=(len(pts),) * 2).tocsr()).tocoo()
        e = np.stack([T.row, T.col], 1).astype(np.int64)
    radius = np.full(len(pts), np.nan)
    in_fg = cand_occ[node_cand] >= occupancy_threshold
    bd_out = cKDTree(origin + outside * vs)

    def lumen_radius(p):
        # the nearest of the many first-outside voxel centres lies just beyond the wall; measured on
        # voxelised tubes this is unbiased to ~0.05 mm at 0.5 mm voxels (the last inside voxel is ~0.2 short)
        return bd_out.query(p)[0]

    radius[in_fg] = lumen_radius(pts[in_fg])
    g = VascularGraph(pts, radius, e)
    g = g.copy(radius=_fill_missing(g, g.radius))

    # ---- 5. spurs and small leftovers
    g = prune_spurs(g, spur_length_mm, spur_radius_factor)
    ncomp, label = _components(len(g), g.edges[:, 0], g.edges[:, 1])
    if ncomp > 1:
        seg_len = np.linalg.norm(g.nodes[g.edges[:, 0]] - g.nodes[g.edges[:, 1]], axis=1)
        comp_len = np.bincount(label[g.edges[:, 0]], weights=seg_len, minlength=ncomp)
        big = comp_len >= min_component_mm
        if not big.any():
            big[np.argmax(comp_len)] = True
        g = g.subgraph(big[label])

    # ---- 6. sub-voxel centres, smoothing, radii at the final positions
    if refine and len(g.edges):
        X = _refine_centres(g, origin + cand_coords * vs, cand_occ * cand_cen ** 2, reach=max(vs * 1.5, 0.75))
        g = g.copy(nodes=X)
    g = smooth_along_segments(g, smooth_iterations)
    r = np.maximum(lumen_radius(g.nodes), 0.5 * vs)
    r = np.where(in_fg[g.node_id], r, g.radius)  # bridge nodes keep radii interpolated along the graph
    return VascularGraph(g.nodes, r, g.edges)
