"""Dropping ghost branches: terminal branches that both views already explain with other parts of the graph.

Two views cannot tell a vessel from a *ghost*: a 3D curve on the rays of one vessel in view A and of a
different vessel in view B projects onto vessel pixels in both views, so the network and the 2D
completion (:mod:`.complete`) can both produce one. What gives a ghost away is that it adds nothing: when
the true branches are in the graph too, every point of the ghost projects, in *both* views, onto a part
of the graph that lies elsewhere in 3D. A real branch overlaps other vessels in one view along a
stretch, or in both views only at crossings, not along its whole length in both.

:func:`drop_doubly_explained` removes, one at a time and most redundant first, terminal branches
(end point → junction, or a free-standing component) whose sampled points are *explained elsewhere* in
both views: within ``radius_mm`` (at the isocentre) of the projection of a graph point more than
``separation_mm`` away along the graph (or in another component). It stops when no terminal branch is explained along at least ``max_shared``
of its length in both views. Redundancy is recomputed after each removal, so of two ghosts that explain
each other only one goes. ``max_shared`` 0.7 and ``radius_mm`` 1.5 were chosen on the tuning cases
(``benchmarks/tune_ghost_drop.py``, docs/benchmarks/ghost_drop.md).

Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .vascular import VascularGraph

__all__ = ["drop_doubly_explained"]


def _terminal_branches(g: VascularGraph) -> list[tuple[np.ndarray, np.ndarray]]:
    """(segment node path, nodes removing it drops) for each segment with a free end."""
    deg = g.degrees()
    out = []
    for seg in g.segments():
        d0, d1 = deg[seg[0]], deg[seg[-1]]
        if min(d0, d1) != 1:
            continue
        if d0 == 1 and d1 == 1:  # a free-standing component
            out.append((seg, seg))
        else:
            out.append((seg, seg[1:] if d0 >= 3 else seg[:-1]))
    return out


def _samples(g: VascularGraph, segs, step_mm: float):
    """Points every ≤ ``step_mm`` along each segment, the segment each belongs to, and the graph node it
    starts from (for geodesic distances)."""
    pts, owner, node = [], [], []
    for i, seg in enumerate(segs):
        p = g.nodes[seg]
        d = np.diff(p, axis=0)
        n = np.maximum(np.ceil(np.linalg.norm(d, axis=1) / step_mm).astype(int), 1)
        t = np.concatenate([np.arange(k) / k for k in n] + [[1.0]])
        start = np.r_[np.repeat(np.arange(len(d)), n), len(d) - 1]
        pts.append(p[start] + t[:, None] * d[start])
        owner.append(np.full(len(t), i))
        node.append(seg[start])
    return np.vstack(pts), np.concatenate(owner), np.concatenate(node)


def _overlapping_pairs(points: np.ndarray, camera, radius_mm: float) -> np.ndarray:
    """K×2 index pairs of points whose projections lie within ``radius_mm`` (isocentre) in this view."""
    uv = camera.project(points)
    idx = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
    if len(idx) < 2:
        return np.zeros((0, 2), np.int64)
    pairs = cKDTree(uv[idx]).query_pairs(radius_mm / camera.isocentre_spacing, output_type="ndarray")
    return idx[pairs].reshape(-1, 2)


def _explained_elsewhere(g: VascularGraph, node_of: np.ndarray, pairs_per_view, separation_mm: float):
    """Per view, per point: does a point more than ``separation_mm`` away *along the graph* (or in another
    component) project onto it? Geodesic, not straight-line, distance, so that a short side branch is not
    explained away by its own parent near the junction."""
    from scipy.sparse.csgraph import dijkstra

    n_points = len(node_of)
    used = np.unique(np.concatenate([node_of[p].ravel() for p in pairs_per_view] + [np.zeros(0, np.int64)]))
    out = [np.zeros(n_points, bool) for _ in pairs_per_view]
    if not len(used):
        return out
    row = np.full(len(g), -1)
    row[used] = np.arange(len(used))
    dist = dijkstra(g.adjacency(), indices=used, limit=separation_mm)  # inf beyond the limit
    for flags, pairs in zip(out, pairs_per_view):
        a, b = pairs[:, 0], pairs[:, 1]
        far = dist[row[node_of[a]], node_of[b]] > separation_mm
        flags[a[far]] = True
        flags[b[far]] = True
    return out


def drop_doubly_explained(graph: VascularGraph, views, *, radius_mm: float = 1.5, separation_mm: float = 15.0,
                          max_shared: float = 0.7, step_mm: float = 0.5, dropped: list | None = None) -> VascularGraph:
    """``graph`` without the terminal branches both views explain elsewhere (module docstring).

    ``views``: the key frame's :class:`~stages.graph.optimise.View` s (fewer than two: unchanged);
    ``dropped``, when given, receives the length (mm) of each branch removed.
    """
    cams = [v.camera for v in views]
    if len(cams) < 2:
        return graph
    g = graph
    while len(g.edges):
        segs = g.segments()
        pts, owner, node_of = _samples(g, segs, step_mm)
        pairs = [_overlapping_pairs(pts, cam, radius_mm) for cam in cams]
        shared = np.logical_and.reduce(_explained_elsewhere(g, node_of, pairs, separation_mm))
        frac = np.bincount(owner, weights=shared, minlength=len(segs)) / np.bincount(owner, minlength=len(segs))
        index = {tuple(s): i for i, s in enumerate(segs)}
        best, best_frac = None, max_shared
        for seg, drop in _terminal_branches(g):
            f = frac[index[tuple(seg)]]
            if f >= best_frac:
                best, best_frac = (seg, drop), f
        if best is None:
            break
        seg, drop = best
        if dropped is not None:
            dropped.append(float(np.linalg.norm(np.diff(g.nodes[seg], axis=0), axis=1).sum()))
        keep = np.ones(len(g), bool)
        keep[drop] = False
        g = g.subgraph(keep)
    return g
