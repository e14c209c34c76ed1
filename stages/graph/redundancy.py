"""Dropping ghost branches: terminal branches that both views already explain with other parts of the graph,
and far pieces that one view explains with the tree.

Two views cannot tell a vessel from a *ghost*: a 3D curve on the rays of one vessel in view A and of a
different vessel in view B projects onto vessel pixels in both views, so the network and the 2D
completion (:mod:`.complete`) can both produce one. What gives a ghost away is that it adds nothing: when
the true branches are in the graph too, every point of the ghost projects, in *both* views, onto a part
of the graph that lies elsewhere in 3D. A real branch overlaps other vessels in one view along a
stretch, or in both views only at crossings, not along its whole length in both.

:func:`drop_doubly_explained` removes, most redundant first, terminal branches (end point → junction, or
a free-standing component) whose sampled points are *explained elsewhere* in both views: within
``radius_mm`` (at the isocentre) of the projection of a graph point more than ``separation_mm`` away
along the graph (or in another component). It stops when no terminal branch is explained along at least
``max_shared`` of its length in both views. A branch is re-checked against what is still kept just
before it goes, so of two ghosts that explain each other only one goes. ``radius_mm`` was chosen on the tuning
cases (docs/benchmarks/ghost_drop.md; the script: ``git show 4cf1374:benchmarks/tune_ghost_drop.py``), ``max_shared``
there first (0.7) and then on the real phantom's connected trees, scored on the runs each pair leaves out: 0.5 takes
their distance from 1.62 to 1.50 mm for 0.007 of coverage (docs/TWOVIEW.md).

:func:`drop_unsupported_branches` then removes terminal branches the network hardly predicted (few of their
points near a voxel of occupancy ≥ ½: they come from low-occupancy voxels kept by the graph threshold, or from
the 2D completion) when one view already explains them elsewhere. On the tuning cases such branches lay
mostly more than 3 mm from the true tree and dropping them raised accuracy a little
(docs/benchmarks/unsupported_drop.md), but on data-re it lowered it (docs/benchmarks/graph_completion_re.md),
so ``graph-opt`` runs it only when asked (``--drop-unsupported``). An unpredicted branch that is the only
explanation of its pixels in both views always stays, since it may be a vessel the network missed.

A piece that floats far from the main tree (no chain of gaps ≤ ``FAR_PIECE_MM`` reaches it, the quality
check's criterion) is the same kind of ghost when one view alone already explains it by the tree: it adds
a second depth for pixels the tree covers. :func:`drop_far_explained_pieces` removes such pieces; a far
piece both views show on their own, a vessel the reconstruction detached, stays.

:func:`drop_faint_pieces` removes the pieces apart from the main tree that are not filled with contrast: where a
view's image shows the piece much fainter, per millimetre of lumen radius, than the tree's vessels (tubing,
fittings, edges that a segmenter takes for vessels; on the real phantom almost every piece left apart from the
tree after the joining was one).

:func:`drop_stubs` removes the pieces apart from the main tree that are only a few lumen diameters long: the joining
found no path to attach them, and they are too short to have a direction or a profile.

:func:`drop_catheter_runs` removes the guiding catheter's long straight stretch from a free end that enters the
field of view (the 3D rule of :mod:`stages.core.catheter`): every view shows it, so it is no ghost, but it is
not a coronary either.

Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..core.catheter import catheter_runs
from .vascular import VascularGraph

__all__ = ["drop_doubly_explained", "drop_unsupported_branches", "drop_far_explained_pieces", "drop_faint_pieces",
           "drop_catheter_runs", "drop_stubs", "FAR_PIECE_MM", "FAINT_CONTRAST_RATIO"]

# a piece farther than this from the main tree (by a chain of shorter gaps) is suspect (stages.quality flags it)
FAR_PIECE_MM = 10.0
# a far piece fainter than this share of the tree's vessels of its calibre, in some view, is not contrast-filled
FAINT_CONTRAST_RATIO = 0.5


def _terminal_branches(g: VascularGraph, segs) -> list[tuple[int, np.ndarray]]:
    """(index in ``segs``, nodes removing it drops) for each of ``g``'s segments with a free end."""
    deg = g.degrees()
    out = []
    for i, seg in enumerate(segs):
        d0, d1 = deg[seg[0]], deg[seg[-1]]
        if min(d0, d1) != 1:
            continue
        if d0 == 1 and d1 == 1:  # a free-standing component
            out.append((i, seg))
        else:
            out.append((i, seg[1:] if d0 >= 3 else seg[:-1]))
    return out


def _samples(g: VascularGraph, segs, step_mm: float):
    """Points every ≤ ``step_mm`` along each segment (segment by segment, in order), the segment each
    belongs to, and the graph node it starts from (for geodesic distances)."""
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


def _samples_by_segment(owner: np.ndarray, n_segments: int) -> list[np.ndarray]:
    """Indices of each segment's samples (:func:`_samples` emits them segment by segment)."""
    bounds = np.r_[0, np.cumsum(np.bincount(owner, minlength=n_segments))]
    return [np.arange(bounds[i], bounds[i + 1]) for i in range(n_segments)]


def _polyline_length(g: VascularGraph, seg: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(g.nodes[seg], axis=0), axis=1).sum())


def _overlapping_pairs(points: np.ndarray, camera, radius_mm: float) -> np.ndarray:
    """K×2 index pairs of points whose projections lie within ``radius_mm`` (isocentre) in this view."""
    uv = camera.project(points)
    idx = np.flatnonzero(np.all(np.isfinite(uv), axis=1))
    if len(idx) < 2:
        return np.zeros((0, 2), np.int64)
    pairs = cKDTree(uv[idx]).query_pairs(radius_mm / camera.isocentre_spacing, output_type="ndarray")
    return idx[pairs].reshape(-1, 2)


def _far_partners(g: VascularGraph, node_of: np.ndarray, pairs: np.ndarray, separation_mm: float, chunk: int = 256):
    """Sparse symmetric P×P matrix marking the overlapping point pairs (``pairs``) that lie more than
    ``separation_mm`` apart *along the graph* (or in different components). Geodesic, not straight-line,
    distance, so that a short side branch is not explained away by its own parent near the junction."""
    from scipy.sparse import csr_matrix
    from scipy.sparse.csgraph import dijkstra

    n = len(node_of)
    far_a, far_b = [], []
    if len(pairs):
        src = node_of[pairs[:, 0]]
        used = np.unique(src)
        row = np.full(len(g), -1)
        row[used] = np.arange(len(used))
        adjacency = g.adjacency()
        for lo in range(0, len(used), chunk):  # chunks bound the dense (sources × nodes) distance block
            dist = dijkstra(adjacency, indices=used[lo:lo + chunk], limit=separation_mm)  # inf beyond the limit
            sel = np.flatnonzero((row[src] >= lo) & (row[src] < lo + chunk))
            far = dist[row[src[sel]] - lo, node_of[pairs[sel, 1]]] > separation_mm
            far_a.append(pairs[sel[far], 0])
            far_b.append(pairs[sel[far], 1])
    a = np.concatenate(far_a + [np.zeros(0, np.int64)])
    b = np.concatenate(far_b + [np.zeros(0, np.int64)])
    ones = np.ones(2 * len(a), np.float32)
    return csr_matrix((ones, (np.r_[a, b], np.r_[b, a])), shape=(n, n))


def drop_doubly_explained(graph: VascularGraph, views, *, radius_mm: float = 1.5, separation_mm: float = 15.0,
                          max_shared: float = 0.5, step_mm: float = 0.5, dropped: list | None = None) -> VascularGraph:
    """``graph`` without the terminal branches both views explain elsewhere (module docstring).

    ``views``: the key frame's :class:`~stages.graph.optimise.View` s (fewer than two: unchanged);
    ``dropped``, when given, receives the length (mm) of each branch removed.

    Works in passes: the point overlaps are found once per pass; terminal branches are then visited from
    the most explained down and each is re-checked against what is still kept before it goes (removing a
    branch only lowers the others' scores). A branch at a junction that lost a branch in this pass waits
    for the next pass, where the junction's remaining segments have merged.
    """
    cams = [v.camera for v in views]
    if len(cams) < 2:
        return graph
    g = graph
    while len(g.edges):
        segs = g.segments()
        pts, owner, node_of = _samples(g, segs, step_mm)
        partners = [_far_partners(g, node_of, _overlapping_pairs(pts, cam, radius_mm), separation_mm) for cam in cams]
        samples_of = _samples_by_segment(owner, len(segs))
        alive = np.ones(len(pts), np.float32)

        def shared_fraction(i):
            s = samples_of[i]
            return float(np.logical_and.reduce([(m[s] @ alive) > 0 for m in partners]).mean())

        candidates = []
        for i, drop in _terminal_branches(g, segs):
            f = shared_fraction(i)
            if f >= max_shared:
                candidates.append((f, i, segs[i], drop))
        keep = np.ones(len(g), bool)
        touched: set[int] = set()
        for _, i, seg, drop in sorted(candidates, key=lambda c: -c[0]):
            junction = {int(seg[0]), int(seg[-1])} - set(map(int, drop))
            if junction & touched or shared_fraction(i) < max_shared:
                continue
            alive[samples_of[i]] = 0.0
            keep[drop] = False
            touched |= junction
            if dropped is not None:
                dropped.append(_polyline_length(g, seg))
        if keep.all():
            break
        g = g.subgraph(keep)
    return g


def _network_support(points: np.ndarray, voxels, occupancy: float, reach_mm: float) -> np.ndarray:
    """Per point: is a predicted voxel with occupancy ≥ ``occupancy`` within ``reach_mm``?"""
    if voxels is None or len(voxels) == 0 or "occupancy" not in voxels.features:
        return np.zeros(len(points), bool)
    keep = np.asarray(voxels.features["occupancy"]) >= occupancy
    if not keep.any():
        return np.zeros(len(points), bool)
    d, _ = cKDTree(voxels.world_points()[keep]).query(points, distance_upper_bound=reach_mm)
    return np.isfinite(d)


def drop_unsupported_branches(graph: VascularGraph, views, voxels, *, min_support: float = 0.1,
                              min_explained: float = 0.5, occupancy: float = 0.5, reach_mm: float = 0.75,
                              radius_mm: float = 1.5, separation_mm: float = 15.0, step_mm: float = 0.5,
                              dropped: list | None = None) -> VascularGraph:
    """``graph`` without terminal branches that the network hardly predicted and one view explains elsewhere.

    A terminal branch (or free-standing piece) goes when fewer than ``min_support`` of its points lie within
    ``reach_mm`` of a predicted voxel with occupancy ≥ ``occupancy`` *and* at least ``min_explained`` of them
    project, in one of the views, onto a part of the graph more than ``separation_mm`` away along it (as in
    :func:`drop_doubly_explained`). Such branches come from low-occupancy voxels or from paths traced in the 2D
    views; on the tuning cases most of them lay > 3 mm from the true tree. Passes until none goes.
    """
    cams = [v.camera for v in views]
    g = graph
    while len(g.edges):
        segs = g.segments()
        pts, owner, node_of = _samples(g, segs, step_mm)
        supported = _network_support(pts, voxels, occupancy, reach_mm)
        explained = [np.asarray(_far_partners(g, node_of, _overlapping_pairs(pts, cam, radius_mm),
                                              separation_mm).sum(1)).ravel() > 0 for cam in cams]
        samples_of = _samples_by_segment(owner, len(segs))
        keep = np.ones(len(g), bool)
        touched: set[int] = set()
        for i, drop in _terminal_branches(g, segs):
            s = samples_of[i]
            best_view = max((e[s].mean() for e in explained), default=0.0)
            if supported[s].mean() >= min_support or best_view < min_explained:
                continue
            junction = {int(segs[i][0]), int(segs[i][-1])} - set(map(int, drop))
            if junction & touched:  # its junction changes this pass: look again next pass
                continue
            keep[drop] = False
            touched |= junction
            if dropped is not None:
                dropped.append(_polyline_length(g, segs[i]))
        if keep.all():
            break
        g = g.subgraph(keep)
    return g


def _far_pieces(graph: VascularGraph, far_mm: float):
    """(label per node, length per piece, the far pieces' labels, mask of the main tree's nodes): a piece is far
    when no chain of gaps ≤ ``far_mm`` joins it to the main tree (:meth:`VascularGraph.pieces`)."""
    label, lengths, gaps, order = graph.pieces(far_mm)
    far = [c for c in order[1:] if gaps[c] > far_mm]
    return label, lengths, far, np.isin(label, [c for c in order if gaps[c] <= far_mm])


def drop_far_explained_pieces(graph: VascularGraph, views, *, far_mm: float = FAR_PIECE_MM, min_explained: float = 0.7,
                              radius_mm: float = 1.5, step_mm: float = 0.5, dropped: list | None = None) -> VascularGraph:
    """``graph`` without the pieces that float far from the main tree and that one view already explains by it.

    A piece no chain of gaps ≤ ``far_mm`` joins to the main tree (:meth:`VascularGraph.pieces`) goes when, in
    at least one view, ``min_explained`` of its points project within ``radius_mm`` (isocentre) of the main
    tree's projection: that view shows nothing the tree does not already explain, so the piece is a second
    depth for the tree's own pixels — a ghost. On data-re with the SBP network (2026-12-04, the 20 cases'
    tracked graphs, 154 far pieces; docs/benchmarks/far_pieces.md) 134 far pieces were ghosts (median 27 mm
    from the true tree); this rule takes 124 of them (96 % of their length) and 7 of the 20 true ones, all
    3.8 mm stubs. A far piece both views show on their own (a vessel the reconstruction detached) stays.
    """
    if not views or not len(graph):
        return graph
    label, lengths, far, main = _far_pieces(graph, far_mm)
    if not far:
        return graph
    tree_pts = graph.subgraph(main).sample(step_mm)[0]
    keep = np.ones(len(graph), bool)
    for c in far:
        members = label == c
        pts = graph.subgraph(members).sample(step_mm)[0]
        for v in views:
            cam = v.camera
            d, _ = cKDTree(cam.project(tree_pts)).query(cam.project(pts))
            if np.mean(d * cam.isocentre_spacing <= radius_mm) >= min_explained:
                keep[members] = False
                if dropped is not None:
                    dropped.append(float(lengths[c]))
                break
    return graph if keep.all() else graph.subgraph(keep)


def drop_faint_pieces(graph: VascularGraph, views, *, min_ratio: float = FAINT_CONTRAST_RATIO,
                      dropped: list | None = None) -> VascularGraph:
    """``graph`` without the pieces apart from the main tree that some view's image shows much fainter than the
    tree's vessels.

    An angiogram shows the coronaries by their iodine: a vessel's contrast (:attr:`View.contrast`, the attenuation
    along the ray) grows with its width at a given filling (Beer–Lambert), so the contrast per millimetre of lumen
    radius is about the same on every filled vessel. A piece not connected to the main tree (the longest piece)
    whose median contrast per millimetre of radius in a view is below ``min_ratio`` × the main tree's median
    contrast per millimetre of radius there is not filled with contrast: tubing, a fitting or an edge that the
    segmenter took for a vessel. Views without an image say nothing. On the real phantom's 56 three-run
    reconstructions the pieces left apart from the tree were 53 such structures (0.00–0.38 × the tree's contrast
    per millimetre in their faintest view) and one vessel the joining left detached (0.72–1.76 × in every view).
    ``dropped`` receives the length (mm) of every piece removed."""
    from scipy.ndimage import map_coordinates

    if not len(graph) or not any(v.image is not None for v in views):
        return graph
    label, lengths, _, order = graph.pieces(0.0)
    if len(order) < 2:
        return graph
    main = label == order[0]
    radius = np.maximum(graph.radius, 1e-3)
    keep = np.ones(len(graph), bool)
    for v in views:
        if v.image is None:
            continue
        rc = v.camera.project(graph.nodes)
        inside = np.isfinite(rc).all(axis=1) & v.camera.in_image(rc)
        per_mm = np.full(len(graph), np.nan)  # every node's contrast at its projection per mm of radius
        per_mm[inside] = map_coordinates(v.contrast, rc[inside].T, order=1) / radius[inside]
        tree = per_mm[main]
        if np.isfinite(tree).sum() < 3 or not np.nanmedian(tree) > 0:
            continue
        faint = min_ratio * np.nanmedian(tree)
        for c in np.unique(label[~main & keep]):
            members = label == c
            piece = per_mm[members]
            if np.isfinite(piece).sum() >= 3 and np.nanmedian(piece) < faint:
                keep[members] = False
                if dropped is not None:
                    dropped.append(float(lengths[c]))
    return graph if keep.all() else graph.subgraph(keep)


def drop_stubs(graph: VascularGraph, *, min_diameters: float = 4.0, dropped: list | None = None) -> VascularGraph:
    """``graph`` without the pieces apart from the main tree shorter than ``min_diameters`` × their lumen diameter.

    A fragment that short has no direction to be joined to the tree by and no lumen profile to grade, and the
    joining, which graph-opt runs first (unless ``--no-join``), found no path along the vessels to attach it: nothing
    vouches for it. On the real
    phantom's 28 pairs the two far pieces the other rules left were 4.8 and 4.4 mm long, 28 and 64 mm from the tree,
    3.6 and 1.8 diameters long; of its 70 sets of four runs one kept a 5.3 mm piece 9.5 mm from the tree, which the
    far-piece rules do not judge (the phantom is one tree). ``dropped`` receives the length (mm) of every piece
    removed."""
    if not len(graph):
        return graph
    label, lengths, _, order = graph.pieces(0.0)  # every piece but the longest is judged
    keep = np.ones(len(graph), bool)
    for c in order[1:]:
        members = label == c
        if lengths[c] < min_diameters * 2.0 * float(np.median(graph.radius[members])):
            keep[members] = False
            if dropped is not None:
                dropped.append(float(lengths[c]))
    return graph if keep.all() else graph.subgraph(keep)


def drop_catheter_runs(graph: VascularGraph, views, *, dropped: list | None = None) -> VascularGraph:
    """``graph`` without its catheter-like stretches (:func:`stages.core.catheter.catheter_runs`: long,
    straight, from a free end that enters the field of view): the guiding catheter is a real 3D object that
    every view shows, so matching and joining keep it, but it is not a coronary. Junction nodes stay.
    ``dropped`` receives the length (mm) of every stretch removed."""
    if not len(graph) or not views:
        return graph
    runs = catheter_runs(graph, [v.camera for v in views])
    if not runs:
        return graph
    keep = np.ones(len(graph), bool)
    deg = graph.degrees()
    for nodes, length, _ in runs:
        keep[nodes[deg[nodes] <= 2]] = False
        if dropped is not None:
            dropped.append(float(length))
    return graph.subgraph(keep)
