"""Graph completion from the 2D views: vessel branches the 3D prediction missed, triangulated along
epipolar lines (between the first two views; further views vet the depths).

A 3D prediction misses branches both 2D masks show: the network's occupancy stays under the graph threshold
on thin and faint ones; the correspondence method finds no partner for a branch that the other view shows
only inside another vessel's band (overlapping it in projection), since that view's skeleton follows the
other vessel. For each view ``s`` (the other being ``t``):

1. the centreline pixels of ``s`` that the graph's projection does not explain (farther than
   ``cover_px``) are grouped into 8-connected pieces; a piece touching an explained pixel is *anchored*
   there, at the graph point whose projection is nearest — a point of the tree, not of a piece more than
   ``FAR_PIECE_MM`` from it (a ghost graph-opt may drop next, which branches grown on it would keep). A
   catheter or guide wire (the strict 2D rule of :mod:`stages.core.catheter`) is not walked: it crosses
   ``t``'s vessels and would become a ghost;
2. each piece is walked from its anchor as a tree of pixel paths (the longest path first, side paths
   anchored on it), every ``stride`` pixels;
3. along the ray of every walked pixel, the depths whose projection into ``t`` lies on ``t``'s
   centreline (within ``match_px``) are the candidates — one per crossing of the epipolar line with a
   ``t`` vessel, more along a vessel it runs parallel to. With further views (a third run …), a depth that
   projects into one of them farther than :data:`GATE_PX` from its vessels is no candidate: most of the
   crossings of two views' epipolar lines with the wrong vessel are not on a third view's vessels (data-re
   with a third run, 6 cases: EPE 2.94 → 2.72 mm, recon → truth 3.13 → 2.86 mm);
4. a Viterbi pass picks one candidate per pixel: unary cost = distance to ``t``'s centreline (px) plus
   how little the prediction believed in the voxel there (1 − occupancy), pairwise cost = 3D step beyond
   what the pixel step allows (a continuous vessel), start cost = distance from the anchor;
5. with a graded occupancy (a network's probabilities), a path whose chosen voxels have a mean occupancy
   under ``min_occupancy`` is dropped: on the tuning cases most of those were ghosts, the epipolar line
   crossing the wrong vessel (docs/benchmarks/graph_completion.md). Tubes of one occupancy level (the
   correspondence method's, drawn around the points it matched) carry no belief about what they did not
   match, so they veto nothing;
6. the chosen 3D path, cut where it jumps, lightly smoothed, joins the graph at its anchor (unless it
   would be a spur by :func:`~stages.graph.init.prune_spurs`' rule); radii come from the mask's distance
   transform at the pixel, scaled to mm at the point's depth.

Unanchored pieces (a branch the segmentation cut off) are triangulated too when long enough and the
prediction is graded (with tubes alone nothing ties them to the tree: on the real phantom they became
far pieces), and join as their own components. A path that is not added leaves the next round (up to ``max_rounds``), where the
pixels it crossed are walked again from their own anchors: side paths are not lost with it. View ``s`` =
first view, then the second with the completed graph, so each branch is added once.

Reads/writes nothing; :func:`complete_from_views` is the entry point.
"""

from __future__ import annotations

import numpy as np

from ..twoview.centreline2d import catheter_pixels
from .redundancy import FAR_PIECE_MM
from .vascular import VascularGraph

__all__ = ["complete_from_views"]

# a further view (a third run …) rules out a candidate that projects farther than this (px) from its vessels
GATE_PX = 3.0
_OFFSETS = np.array([(-1, -1), (-1, 0), (-1, 1), (0, -1), (0, 1), (1, -1), (1, 0), (1, 1)])


def _pixel_index(pix: np.ndarray, shape) -> np.ndarray:
    img = -np.ones(shape, np.int64)
    img[pix[:, 0], pix[:, 1]] = np.arange(len(pix))
    return img


def _neighbours(pix: np.ndarray, index_img: np.ndarray):
    """(i, j) pairs of 8-connected pixels (each pair once in each direction)."""
    H, W = index_img.shape
    out_i, out_j = [], []
    for dr, dc in _OFFSETS:
        r, c = pix[:, 0] + dr, pix[:, 1] + dc
        ok = (r >= 0) & (r < H) & (c >= 0) & (c < W)
        j = np.full(len(pix), -1)
        j[ok] = index_img[r[ok], c[ok]]
        hit = j >= 0
        out_i.append(np.flatnonzero(hit))
        out_j.append(j[hit])
    return np.concatenate(out_i), np.concatenate(out_j)


def _walk_paths(members: np.ndarray, adj: dict, root: int) -> list[tuple[int | None, list[int]]]:
    """Decompose the BFS tree of ``members`` from ``root`` into paths, longest first.

    Returns [(parent pixel or None, [pixels…])]; each path after the first starts next to a pixel of an
    earlier one (its parent)."""
    parent = {root: None}
    order = [root]
    for p in order:  # BFS (order grows while iterating)
        for q in adj.get(p, ()):
            if q not in parent:
                parent[q] = p
                order.append(q)
    children: dict[int, list[int]] = {}
    for p in order[1:]:
        children.setdefault(parent[p], []).append(p)
    height = {}
    for p in reversed(order):
        height[p] = 1 + max((height[c] for c in children.get(p, ())), default=0)
    paths = []
    starts = [(None, root)]
    while starts:
        par, p = starts.pop(0)
        path = [p]
        while children.get(p):
            kids = sorted(children[p], key=lambda c: -height[c])
            starts.extend((p, k) for k in kids[1:])
            p = kids[0]
            path.append(p)
        paths.append((par, path))
    return paths


class _OccupancyLookup:
    """Occupancy of the sparse prediction at world points (0 outside the candidate set)."""

    def __init__(self, voxels):
        self.ok = voxels is not None and len(voxels) and "occupancy" in voxels.features
        self.graded = False
        if not self.ok:
            return
        # a belief (the network's probabilities) can veto a path; one level only (tubes drawn around the points
        # a geometric method matched) says nothing about what it did not match
        self.graded = bool(np.ptp(np.asarray(voxels.features["occupancy"], float)) > 0)
        self.vs, self.origin = voxels.voxel_size, voxels.origin
        c = voxels.coords.astype(np.int64)
        self.lo = c.min(0)
        self.dims = c.max(0) - self.lo + 1
        key = np.ravel_multi_index((c - self.lo).T, self.dims)
        order = np.argsort(key)
        self.keys, self.occ = key[order], np.asarray(voxels.features["occupancy"], float)[order]

    def __call__(self, points: np.ndarray) -> np.ndarray:
        out = np.zeros(points.shape[:-1])
        if not self.ok:
            return out
        ijk = np.rint((points - self.origin) / self.vs).astype(np.int64) - self.lo
        inside = np.all((ijk >= 0) & (ijk < self.dims), axis=-1)
        key = np.ravel_multi_index(tuple(ijk[inside].T), self.dims)
        pos = np.clip(np.searchsorted(self.keys, key), 0, len(self.keys) - 1)
        hit = self.keys[pos] == key
        vals = np.zeros(len(key))
        vals[hit] = self.occ[pos[hit]]
        out[inside] = vals
        return out


def _candidates(cam_s, pix, depths, dist_t, cam_t, occ_lookup, match_px, max_per_pixel, occ_weight, gates=()):
    """Per pixel: candidate 3D points on its ray, with unary costs. ``gates``: (camera, distance map to its
    vessel mask, px) of further views; a candidate that projects into one of them farther than GATE_PX from its
    vessels is no candidate."""
    from scipy import ndimage

    o, d = cam_s.rays(pix.astype(float))
    X = o[:, None, :] + depths[None, :, None] * d[:, None, :]  # n×T×3
    rc = cam_t.project(X.reshape(-1, 3))
    dist = ndimage.map_coordinates(dist_t, np.nan_to_num(rc, nan=-1e6).T, order=1, mode="constant", cval=1e6)
    dist = dist.reshape(len(pix), len(depths))
    for cam_g, dist_g in gates:
        rc_g = cam_g.project(X.reshape(-1, 3))
        off = ndimage.map_coordinates(dist_g, np.nan_to_num(rc_g, nan=-1e6).T, order=1, mode="constant", cval=0.0)
        off = np.where(cam_g.in_image(rc_g) & np.isfinite(rc_g).all(1), off, 0.0).reshape(dist.shape)
        dist = np.where(off > GATE_PX, np.inf, dist)
    occ = occ_lookup(X)
    cost = dist + occ_weight * (1.0 - occ)
    out = []
    for i in range(len(pix)):  # (points, unary cost, occupancy) per pixel
        ok = dist[i] <= match_px
        if not ok.any():
            out.append((np.zeros((0, 3)), np.zeros(0), np.zeros(0)))
            continue
        # one candidate per run of matching depths (its cheapest), plus every 4th sample of long runs
        idx = np.flatnonzero(ok)
        runs = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
        pick = []
        for r in runs:
            pick.append(r[np.argmin(cost[i, r])])
            if len(r) > 8:
                pick.extend(r[::4])
        pick = np.unique(pick)
        if len(pick) > max_per_pixel:
            pick = pick[np.argsort(cost[i, pick])[:max_per_pixel]]
        out.append((X[i, pick], cost[i, pick], occ[i, pick]))
    return out


def _viterbi(cands, steps_mm, anchor, slack: float, step_weight: float, anchor_weight: float):
    """Cheapest sequence of one candidate per pixel (see the module docstring); returns indices."""
    cost = cands[0][1].copy()
    if anchor is not None:
        cost = cost + anchor_weight * np.maximum(np.linalg.norm(cands[0][0] - anchor, axis=1) - slack, 0.0)
    back = []
    for i in range(1, len(cands)):
        jump = np.linalg.norm(cands[i][0][None, :, :] - cands[i - 1][0][:, None, :], axis=2)
        excess = np.maximum(jump - slack - steps_mm[i], 0.0)
        total = cost[:, None] + step_weight * excess
        back.append(np.argmin(total, axis=0))
        cost = total[back[-1], np.arange(total.shape[1])] + cands[i][1]
    choice = [int(np.argmin(cost))]
    for b in reversed(back):
        choice.append(int(b[choice[-1]]))
    return choice[::-1]


def _smooth(points: np.ndarray, iterations: int = 3) -> np.ndarray:
    """(¼, ½, ¼) smoothing of a polyline's interior points; both ends stay where they are."""
    p = points.copy()
    for _ in range(iterations):
        if len(p) < 3:
            break
        q = p.copy()
        q[1:-1] = 0.25 * p[:-2] + 0.5 * p[1:-1] + 0.25 * p[2:]
        p = q
    return p


def _triangulate_path(path, start_point, start_node, pix, cam_s, cam_t, depths, dist_t, occ_lookup, depth, edt_s,
                      nodes, radius, edges, added, *, gates, match_px, stride, max_per_pixel, occ_weight, step_weight,
                      anchor_weight, max_jump_mm, min_occupancy, spur_mm, spur_radius_factor):
    """Steps 3–6 of the module docstring for one pixel path of view s: appends its nodes, radii and edges
    (attached to ``start_node`` when given) and returns {pixel: node} for the pixels up to where it was cut
    (each with its nearest walked pixel's node), or None when the path is not added."""
    walk = path[::stride] if len(path) > stride else path
    cands = _candidates(cam_s, pix[walk], depths, dist_t, cam_t, occ_lookup, match_px, max_per_pixel, occ_weight,
                        gates)
    keep = [k for k, cd in enumerate(cands) if len(cd[1])]
    if len(keep) < 2:
        return None
    cands = [cands[k] for k in keep]
    walk = [walk[k] for k in keep]
    # allowed 3D step between kept pixels: their pixel distance at the graph's depth, foreshortening aside
    px_mm = float(np.median(depth)) / cam_s.K[0, 0]
    gaps = np.r_[0.0, np.linalg.norm(np.diff(pix[walk], axis=0), axis=1)] * px_mm
    choice = _viterbi(cands, gaps, start_point, slack=1.0, step_weight=step_weight, anchor_weight=anchor_weight)
    pts = np.array([cands[k][0][ch] for k, ch in enumerate(choice)])
    occ_path = np.array([cands[k][2][ch] for k, ch in enumerate(choice)])
    if occ_lookup.graded and occ_path.mean() < min_occupancy:
        return None  # the network does not back this path at all: most such paths are ghosts
    if start_point is not None and np.linalg.norm(pts[0] - start_point) > max_jump_mm + 2.0:
        return None  # no continuation of the anchor: a ghost would join here
    jumps = np.flatnonzero(np.linalg.norm(np.diff(pts, axis=0), axis=1) > max_jump_mm + gaps[1:])
    end = jumps[0] + 1 if len(jumps) else len(pts)
    pts, walk = pts[:end], walk[:end]
    if len(pts) < 2:
        return None
    pts = _smooth(pts)
    if start_node is not None:
        # a short side path would be a spur: the same rule as init_graph's spur pruning
        length = np.linalg.norm(pts[0] - start_point) + np.linalg.norm(np.diff(pts, axis=0), axis=1).sum()
        degree = np.count_nonzero(np.vstack(edges) == start_node)
        r_start = np.concatenate(radius)[start_node]
        if degree >= 2 and length < max(spur_mm, spur_radius_factor * r_start):
            return None
    _, zt = cam_s.project(pts, return_depth=True)
    rad = (edt_s[pix[walk, 0], pix[walk, 1]] if edt_s is not None else np.ones(len(pts))) * zt / cam_s.K[0, 0]
    idx = sum(len(x) for x in nodes) + np.arange(len(pts))
    nodes.append(pts)
    radius.append(np.maximum(rad, 0.3))
    chain = np.stack([idx[:-1], idx[1:]], 1)
    if start_node is not None:
        chain = np.vstack([[start_node, idx[0]], chain])
    edges.append(chain)
    added.append({"nodes": idx, "pixels": len(walk), "occupancy": float(occ_path.mean()),
                  "anchored": start_node is not None,
                  "cost": float(np.mean([cands[k][1][ch] for k, ch in enumerate(choice)]))})
    # every pixel of the path up to its last kept one: side paths may leave it between walked pixels
    position = {p: i for i, p in enumerate(path)}
    covered = path[:position[walk[-1]] + 1]
    walked_at = np.array([position[w] for w in walk])
    nearest = np.abs(np.arange(len(covered))[:, None] - walked_at[None, :]).argmin(1)
    return {int(p): int(idx[k]) for p, k in zip(covered, nearest)}


def _complete_one_view(graph: VascularGraph, vs, vt, occ_lookup, *, cover_px, min_px, min_free_px, depth_margin_mm,
                       depth_step_mm, max_rounds, added, **path_kw):
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    cam_s, cam_t = vs.camera, vt.camera
    pix = np.rint(np.asarray(vs.centreline_rc)).astype(np.int64)
    if not len(pix) or not len(vt.centreline_rc) or not len(graph):
        return graph
    shape = (cam_s.rows, cam_s.cols)
    samples, _ = graph.sample(0.5)
    proj = cam_s.project(samples)
    ok = np.all(np.isfinite(proj), 1)
    samples, proj = samples[ok], proj[ok]
    d, near = cKDTree(proj).query(pix)
    explained = d <= cover_px
    if explained.all():
        return graph
    sample_node = cKDTree(graph.nodes)  # graph point → nearest graph node, for attaching
    # paths grow from the tree only: a piece far from it may be a ghost (tubing, a catheter's pairing) that
    # graph-opt drops next, and branches grown on it would keep it
    label, _, gaps, _ = graph.pieces(FAR_PIECE_MM)
    anchorable = (gaps[label] <= FAR_PIECE_MM)[sample_node.query(samples)[1]][near]
    # depth range of the search: the graph's depths along the rays of view s, with a margin
    _, depth = cam_s.project(samples, return_depth=True)
    depths = np.arange(depth.min() - depth_margin_mm, depth.max() + depth_margin_mm, depth_step_mm)
    depths = depths[depths > 0]
    # distance (px) to view t's centreline, and mask EDT of view s for radii
    dist_t = vt.centreline_distance.astype(np.float32)
    edt_s = vs.depth_in_mask

    index_img = _pixel_index(pix, shape)
    ii, jj = _neighbours(pix, index_img)
    nodes, radius, edges = [graph.nodes], [graph.radius], [graph.edges]
    node_of = {}  # pixel of an added path → the node it was triangulated into (or its nearest walked pixel's)
    # a catheter (or a guide wire) is not walked: it crosses the other view's vessels and would become a ghost
    catheter = catheter_pixels(index_img >= 0)
    rejected = catheter[pix[:, 0], pix[:, 1]]
    # Rounds: a path that fails (a catheter or wire crossing several branches, a ghost) takes its pixels out
    # of the next round, so the branches it crossed are walked again from their own anchors instead of being
    # lost with it; pixels an added path explains anchor the next round's paths.
    for _ in range(max_rounds):
        done = explained.copy()
        done[list(node_of)] = True
        pending = ~done & ~rejected
        if not pending.any():
            break
        rejected_before, added_before = int(rejected.sum()), len(node_of)
        inner = pending[ii] & pending[jj]
        n = len(pix)
        _, lab = connected_components(coo_matrix((np.ones(inner.sum()), (ii[inner], jj[inner])), shape=(n, n)),
                                      directed=False)
        adj: dict[int, list[int]] = {}
        for a, b in zip(ii[inner], jj[inner]):
            adj.setdefault(int(a), []).append(int(b))
        # a pending pixel next to a pixel the tree or an added path explains: an anchor
        touch = pending[ii] & done[jj] & (anchorable[jj] | ~explained[jj])
        anchor_of = {}
        for a, b in zip(ii[touch], jj[touch]):
            anchor_of.setdefault(int(a), int(b))
        for c in np.unique(lab[pending]):
            members = np.flatnonzero(lab == c)
            anchored = [m for m in members if m in anchor_of]
            # a free piece needs the prediction's belief: matched along the other view's centreline alone,
            # nothing ties it to the tree
            free_ok = occ_lookup.graded and len(members) >= min_free_px
            if len(members) < min_px or not (anchored or free_ok):
                rejected[members] = True
                continue
            if anchored:
                root = anchored[0]
                b = anchor_of[root]
                root_node = node_of.get(b)
                if root_node is None:
                    root_point = samples[near[b]]
                    root_node = int(sample_node.query(root_point)[1])
                else:
                    root_point = np.vstack(nodes)[root_node]
            else:
                deg = {m: len(adj.get(int(m), ())) for m in members}
                root = int(min(members, key=lambda m: deg[m]))
                root_point, root_node = None, None
            for parent, path in _walk_paths(members, adj, int(root)):
                if parent is None:
                    start_point, start_node = root_point, root_node
                else:
                    start_node = node_of.get(parent)
                    if start_node is None:  # its parent path failed: next round, from its own anchor
                        continue
                    start_point = np.vstack(nodes)[start_node]
                path_nodes = _triangulate_path(path, start_point, start_node, pix, cam_s, cam_t, depths, dist_t,
                                               occ_lookup, depth, edt_s, nodes, radius, edges, added, **path_kw)
                if path_nodes is None:
                    rejected[path] = True
                else:
                    node_of.update(path_nodes)
        if int(rejected.sum()) == rejected_before and len(node_of) == added_before:
            break
    if len(nodes) == 1:
        return graph
    all_nodes = np.vstack(nodes)
    ids = np.r_[graph.node_id, graph.node_id.max() + 1 + np.arange(len(all_nodes) - len(graph))] if len(graph) else None
    return VascularGraph(all_nodes, np.concatenate(radius), np.vstack(edges), ids)


def complete_from_views(graph: VascularGraph, views, voxels=None, *, cover_px: float = 3.0, match_px: float = 1.5,
                        stride: int = 2, min_px: int = 8, min_free_px: int = 30, depth_margin_mm: float = 30.0,
                        depth_step_mm: float = 0.5, max_per_pixel: int = 12, occ_weight: float = 2.0,
                        step_weight: float = 4.0, anchor_weight: float = 2.0, max_jump_mm: float = 4.0,
                        min_occupancy: float = 0.05, spur_mm: float = 2.5, spur_radius_factor: float = 2.5,
                        max_rounds: int = 3, added: list | None = None) -> VascularGraph:
    """``graph`` plus the branches both views show and it lacks (see the module docstring).

    ``views``: the key frame's :class:`~stages.graph.optimise.View` s (two needed; otherwise the graph is
    returned unchanged; the first two are walked and matched, any further one vets the candidate depths);
    ``voxels``: its sparse prediction (occupancy breaks ties between candidates and gates paths; without it every
    path is kept). ``added``, when given, receives one dict per added path
    (its node indices, walked pixels, mean occupancy, whether anchored, mean unary cost).
    """
    if len(views) < 2 or not len(graph):
        return graph
    look = _OccupancyLookup(voxels)
    kw = dict(cover_px=cover_px, match_px=match_px, stride=stride, min_px=min_px, min_free_px=min_free_px,
              depth_margin_mm=depth_margin_mm, depth_step_mm=depth_step_mm, max_per_pixel=max_per_pixel,
              occ_weight=occ_weight, step_weight=step_weight, anchor_weight=anchor_weight, max_jump_mm=max_jump_mm,
              min_occupancy=min_occupancy, spur_mm=spur_mm, spur_radius_factor=spur_radius_factor,
              max_rounds=max_rounds, added=[] if added is None else added)
    gates = [(v.camera, v.mask_distance) for v in views[2:] if v.mask is not None]
    g = _complete_one_view(graph, views[0], views[1], look, gates=gates, **kw)
    return _complete_one_view(g, views[1], views[0], look, gates=gates, **kw)
