"""Joining the pieces of a key frame's graph into one tree along the vessels both views show.

A coronary tree is one connected object, yet the 3D step leaves it in pieces: near junctions and crossings the
two views' centrelines are hard to pair, so the stretches between well-matched vessels are missing. The
missing stretch is still in both images. Every 3D point on it projects onto a vessel in every view, so it
lies inside the views' *vessel hull* (the points whose projections fall on vessel pixels in all views), and
near the views' centrelines.

:func:`join_pieces_through_views` finds those stretches as minimal paths:

1. the hull is sampled on a grid (``step_mm``) around the graph: a grid point belongs to it when, in every
   view, its projection lies within ``tol_mm`` of the vessel mask (millimetres at the isocentre, so a
   zoomed-out view is not looser than the others; at least :data:`MIN_TOL_PX`); its cost per mm is
   ``1 + Σ_views (distance to that view's centreline) / tolerance``, so paths follow the vessels' middles;
2. one Dijkstra search from every piece at once (each grid point learns its nearest piece and the geodesic
   cost to it) gives, for every two pieces whose search regions touch, the cheapest path between them;
3. the pieces are joined in order of that cost (Kruskal's minimum spanning tree over the pieces), each path
   accepted only while it is short (``max_path_mm``) and not much longer than the gap it closes
   (``max_detour`` × the straight distance + 2 grid steps): a long detour through the hull runs through
   the ghost regions where two different vessels' rays cross;
4. an accepted path joins the nearest nodes of the two pieces, smoothed, with radii interpolated between
   its ends.

A ghost piece (one vessel's rays in view A crossing another vessel's in view B) may be joined too; the
redundancy rules that run next (:mod:`.redundancy`) drop a terminal branch whose every point both views
explain with other parts of the tree, which a joined ghost now is.

Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components, dijkstra
from scipy.spatial import cKDTree

from .vascular import VascularGraph

__all__ = ["join_pieces_through_views"]

TOL_MM = 0.6  # how far from a view's vessel mask (mm at the isocentre) a path may run
MIN_TOL_PX = 1.0
# the longest path accepted: with two views a longer one runs through the ghost regions where two vessels' rays
# cross; every further view shrinks those regions, so a longer missing stretch can be restored
MAX_PATH_MM = 60.0
MAX_PATH_MM_MORE_VIEWS = 100.0
HULL_BLOCK = 1 << 21  # grid points tested at once (a few tens of MB)
_OFFSETS = np.array([(i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)])


def _coarse_cells(maps, lo: np.ndarray, shape: tuple, step_mm: float, factor: int):
    """The cells of ``factor``³ grid points that can hold a hull point: a cell goes when, in some view, its centre
    projects inside the image farther from the vessel mask than the tolerance plus the farthest any point of the
    cell can project from the centre (the projection's largest magnification over the grid's box and the image, ×√2
    for the bilinear distance map). Exact: it only drops cells no point of which passes :func:`_vessel_hull`'s test."""
    shape = np.asarray(shape)
    cshape = tuple(int(c) for c in -(-shape // factor))
    half_diag = (factor - 1) / 2 * step_mm * np.sqrt(3)
    corners = lo + np.array([[i, j, k] for i in (0, 1) for j in (0, 1) for k in (0, 1)]) * (shape - 1) * step_mm
    margins = []
    for camera, tol_px, _, _ in maps:
        _, depth = camera.project(corners, return_depth=True)
        focal = min(camera.K[0, 0], camera.K[1, 1])
        image = np.array([[r, c] for r in (-0.5, camera.rows - 0.5) for c in (-0.5, camera.cols - 0.5)])
        off_axis = float(np.max(np.hypot(image[:, 1] - camera.K[0, 2], image[:, 0] - camera.K[1, 2]))) / focal
        gain = max(camera.K[0, 0], camera.K[1, 1]) * np.sqrt(1 + off_axis ** 2) / max(float(depth.min()), 1e-6)
        margins.append(tol_px + np.sqrt(2) * half_diag * gain + 0.5)
    kept = []
    total = int(np.prod(cshape))
    for start in range(0, total, HULL_BLOCK):
        cells = np.arange(start, min(start + HULL_BLOCK, total))
        for (camera, _, off_mask, _), limit in zip(maps, margins):
            centre = lo + (np.stack(np.unravel_index(cells, cshape), 1) * factor + (factor - 1) / 2) * step_mm
            rc = camera.project(centre)
            inside = np.flatnonzero(camera.in_image(rc))
            far = ndimage.map_coordinates(off_mask, rc[inside].T, order=1, mode="nearest") > limit
            cells = np.delete(cells, inside[far])
        kept.append(cells)
    return np.concatenate(kept), cshape


def _vessel_hull(views, lo: np.ndarray, shape: tuple, step_mm: float, tol_mm: float, coarse: int = 4):
    """Flat indices of the grid points inside every view's vessels (within ``tol_mm`` of the mask, at the
    isocentre), and each one's cost per mm (1 + summed distance to the views' centrelines over that tolerance).
    Only the grid points of the ``coarse``³ cells :func:`_coarse_cells` keeps are tested (the same result,
    3–7× faster: the hull is a few per cent of the box), a block at a time, so memory stays bounded however far
    apart the pieces are."""
    maps = [(v.camera, max(MIN_TOL_PX, tol_mm / v.camera.isocentre_spacing), v.mask_distance, v.centreline_distance)
            for v in views]
    cells, cshape = _coarse_cells(maps, lo, shape, step_mm, coarse)
    offsets = np.stack(np.meshgrid(*[np.arange(coarse)] * 3, indexing="ij"), -1).reshape(-1, 3)
    kept, costs = [], []
    per_block = max(1, HULL_BLOCK // len(offsets))
    for start in range(0, len(cells), per_block):
        ijk = (np.stack(np.unravel_index(cells[start:start + per_block], cshape), 1)[:, None] * coarse + offsets).reshape(-1, 3)
        ijk = ijk[np.all(ijk < np.asarray(shape), 1)]
        idx = np.ravel_multi_index(ijk.T, shape)
        cost = np.ones(len(idx))
        for camera, tol_px, off_mask, off_line in maps:
            rc = camera.project(lo + np.stack(np.unravel_index(idx, shape), 1) * step_mm)
            inside = camera.in_image(rc)
            idx, rc, cost = idx[inside], rc[inside], cost[inside]
            keep = ndimage.map_coordinates(off_mask, rc.T, order=1, mode="nearest") <= tol_px
            idx, rc, cost = idx[keep], rc[keep], cost[keep]
            cost = cost + ndimage.map_coordinates(off_line, rc.T, order=1, mode="nearest") / tol_px
        kept.append(idx)
        costs.append(cost)
    idx, cost = np.concatenate(kept), np.concatenate(costs)
    order = np.argsort(idx, kind="stable")  # ascending, as _grid_graph looks neighbours up in it
    return idx[order], cost[order]


def _grid_graph(idx: np.ndarray, cost: np.ndarray, shape: tuple, step_mm: float):
    """Sparse 26-neighbour graph over the hull points (row i = idx[i], ``idx`` ascending); an edge costs its
    length × the mean cost per mm of its two ends. Neighbours are looked up in ``idx`` itself, not in a
    grid-sized table."""
    ijk = np.stack(np.unravel_index(idx, shape), 1)
    rows, cols, w = [], [], []
    for off in _OFFSETS:
        nb = ijk + off
        ok = np.flatnonzero(np.all((nb >= 0) & (nb < shape), axis=1))
        flat = np.ravel_multi_index(nb[ok].T, shape)
        pos = np.minimum(np.searchsorted(idx, flat), len(idx) - 1)
        j = -np.ones(len(idx), np.int64)
        j[ok] = np.where(idx[pos] == flat, pos, -1)
        has = np.flatnonzero(j >= 0)
        rows.append(has)
        cols.append(j[has])
        w.append(np.linalg.norm(off) * step_mm * 0.5 * (cost[has] + cost[j[has]]))
    r, c, ww = np.concatenate(rows), np.concatenate(cols), np.concatenate(w)
    n = len(idx)
    return coo_matrix((np.r_[ww, ww], (np.r_[r, c], np.r_[c, r])), shape=(n, n)).tocsr()


def _walk_back(pred: np.ndarray, start: int) -> list[int]:
    path = [start]
    while pred[path[-1]] >= 0:
        path.append(int(pred[path[-1]]))
    return path


def join_pieces_through_views(graph: VascularGraph, views, *, step_mm: float = 1.0, tol_mm: float = TOL_MM,
                              margin_mm: float = 10.0, max_path_mm: float | None = None, max_detour: float = 2.5,
                              joined: list | None = None) -> VascularGraph:
    """``graph`` with its pieces joined by minimal paths through every view's vessels (module docstring).
    ``max_path_mm``: by default :data:`MAX_PATH_MM` for two views, :data:`MAX_PATH_MM_MORE_VIEWS` for more.
    ``joined`` receives the length (mm) of every path added."""
    views = [v for v in views if getattr(v, "mask", None) is not None]
    if len(views) < 2 or len(graph) < 2:
        return graph
    if max_path_mm is None:
        max_path_mm = MAX_PATH_MM if len(views) == 2 else MAX_PATH_MM_MORE_VIEWS
    n_pieces, label = connected_components(graph.adjacency(), directed=False)
    if n_pieces < 2:
        return graph
    lo = graph.nodes.min(0) - margin_mm
    shape = tuple(int(s) for s in np.ceil((graph.nodes.max(0) + margin_mm - lo) / step_mm).astype(int) + 1)
    idx, cost = _vessel_hull(views, lo, shape, step_mm, tol_mm)
    if len(idx) < 2:
        return graph
    points = lo + np.stack(np.unravel_index(idx, shape), 1) * step_mm
    # the search starts from every hull point within one grid step of a graph node, labelled by its piece
    d_node, nearest_node = cKDTree(graph.nodes).query(points, distance_upper_bound=step_mm)
    seeds = np.flatnonzero(np.isfinite(d_node))
    if len(np.unique(label[nearest_node[seeds]])) < 2:
        return graph
    A = _grid_graph(idx, cost, shape, step_mm)
    dist, pred, source = dijkstra(A, indices=seeds, min_only=True, return_predecessors=True)
    reached = np.isfinite(dist)
    piece_of = np.full(len(idx), -1)
    piece_of[reached] = label[nearest_node[source[reached]]]
    # where two pieces' search regions meet: the cheapest meeting edge per pair of pieces
    A = A.tocoo()
    u, v, w = A.row, A.col, A.data
    meet = (piece_of[u] >= 0) & (piece_of[v] >= 0) & (piece_of[u] < piece_of[v])
    u, v, total = u[meet], v[meet], dist[u[meet]] + w[meet] + dist[v[meet]]
    order = np.argsort(total, kind="stable")
    _, first = np.unique((piece_of[u] * n_pieces + piece_of[v])[order], return_index=True)
    cheapest = order[first][np.argsort(total[order[first]], kind="stable")]  # one per pair, cheapest pair first
    parent = list(range(n_pieces))

    def find(x):
        while parent[x] != x:
            parent[x] = parent[parent[x]]
            x = parent[x]
        return x

    nodes, radius, edges = [graph.nodes], [graph.radius], [graph.edges]
    n_total = len(graph)
    for a, b in zip(u[cheapest].tolist(), v[cheapest].tolist()):
        p, q = int(piece_of[a]), int(piece_of[b])
        if find(p) == find(q):
            continue
        path = _walk_back(pred, a)[::-1] + _walk_back(pred, b)  # seed of p … a, b … seed of q
        end_p, end_q = int(nearest_node[path[0]]), int(nearest_node[path[-1]])
        P = np.vstack([graph.nodes[end_p], points[path], graph.nodes[end_q]])
        length = float(np.linalg.norm(np.diff(P, axis=0), axis=1).sum())
        straight = float(np.linalg.norm(graph.nodes[end_p] - graph.nodes[end_q]))
        if length > max_path_mm or length > max_detour * straight + 2 * step_mm:
            continue
        parent[find(p)] = find(q)
        inner = P[1:-1]
        if len(inner) >= 3:  # the grid's staircase, smoothed; the path's ends stay on the pieces
            inner = ndimage.gaussian_filter1d(np.vstack([P[:1], inner, P[-1:]]), 1.0, axis=0, mode="nearest")[1:-1]
        t = np.linspace(0.0, 1.0, len(inner) + 2)[1:-1]
        new = np.arange(n_total, n_total + len(inner))
        chain = np.r_[end_p, new, end_q]
        nodes.append(inner)
        radius.append((1 - t) * graph.radius[end_p] + t * graph.radius[end_q])
        edges.append(np.stack([chain[:-1], chain[1:]], 1))
        n_total += len(inner)
        if joined is not None:
            joined.append(length)
    if n_total == len(graph) and len(edges) == 1:
        return graph
    node_id = np.r_[graph.node_id, graph.node_id.max() + 1 + np.arange(n_total - len(graph))] if n_total > len(graph) \
        else graph.node_id
    return VascularGraph(np.vstack(nodes), np.concatenate(radius), np.vstack(edges), node_id)
