"""Foreshortening and overlap of vessel segments over the reachable C-arm range; the best view.

Reads/writes nothing. Angles in degrees, DICOM convention (DESIGN.md §3): α LAO+ / RAO−, β CRA+ /
CAU−; the viewing direction is the isocentre→detector axis of :func:`stages.core.geometry.carm_axes`.

* **Foreshortening** of a segment (a polyline) seen along d: ``100·(1 − L_projected / L_3D)`` %, with
  L_projected the length of its parallel projection onto the detector plane (the magnification of the
  cone beam scales every length alike and cancels).
* **Overlap**: the share (%) of the segment's 1 mm samples whose projected lumen (disc of its radius)
  touches the projected lumen of any other part of the tree, i.e. a node farther than
  ``exclude_mm`` along the tree from the segment (its own continuation and the first millimetres of
  branches leaving it are not "other vessel").
* **Best view**: the grid angle minimising foreshortening + overlap (both in %), ties to the view
  nearest AP. The grid: α −60…60°, β −45…45°, ``step_deg`` apart (5° → 25 × 19 = 475 views).
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["view_grid", "view_directions", "foreshortening", "overlap", "overlap_at", "segment_views", "carm_angles"]

ALPHA_RANGE = (-60.0, 60.0)
BETA_RANGE = (-45.0, 45.0)


def view_grid(step_deg: float = 5.0):
    alphas = np.arange(ALPHA_RANGE[0], ALPHA_RANGE[1] + 1e-9, step_deg)
    betas = np.arange(BETA_RANGE[0], BETA_RANGE[1] + 1e-9, step_deg)
    return alphas, betas


def view_directions(alphas, betas):
    """(A, B, 3) unit viewing directions d and the detector column/row axes c, r for every grid angle."""
    a = np.radians(np.asarray(alphas, float))[:, None]
    b = np.radians(np.asarray(betas, float))[None, :]
    sa, ca, sb, cb = np.sin(a), np.cos(a), np.sin(b), np.cos(b)
    one = np.ones_like(a * b)
    d = np.stack([sa * cb, -ca * cb, sb * one], -1)
    c = np.stack([ca * one, sa * one, 0 * one], -1)
    r = np.stack([sa * sb, -ca * sb, -cb * one], -1)
    return d, c, r


def carm_angles(camera) -> tuple[float, float]:
    """(α, β) of a :class:`stages.core.geometry.Camera` (its C-arm record, else from its viewing axis)."""
    if getattr(camera, "carm", None):
        return float(camera.carm["alpha"]), float(camera.carm["beta"])
    d = np.asarray(camera.R, float)[2]
    d = d / np.linalg.norm(d)
    return math.degrees(math.atan2(d[0], -d[1])), math.degrees(math.asin(np.clip(d[2], -1, 1)))


def foreshortening(points, dirs) -> np.ndarray:
    """Foreshortening (%) of polyline ``points`` (K×3) for viewing directions ``dirs`` (...×3)."""
    seg = np.diff(np.asarray(points, float), axis=0)
    length = np.linalg.norm(seg, axis=1)
    total = float(length.sum())
    shape = dirs.shape[:-1]
    if total <= 0:
        return np.zeros(shape)
    dots = seg @ dirs.reshape(-1, 3).T  # K × V
    proj = np.sqrt(np.maximum(length[:, None] ** 2 - dots ** 2, 0.0)).sum(0)
    return (100.0 * (1.0 - proj / total)).reshape(shape)


def overlap(q_points, q_radius, o_points, o_radius, cols, rows, chunk: int = 16) -> np.ndarray:
    """Overlap (%) of samples q (M×3, radius M) with other points o (N×3, radius N) per view (axes ...×3)."""
    shape = cols.shape[:-1]
    C = cols.reshape(-1, 3)
    R = rows.reshape(-1, 3)
    if len(q_points) == 0:
        return np.zeros(shape)
    if len(o_points) == 0:
        return np.zeros(shape)
    q, o = np.asarray(q_points, float), np.asarray(o_points, float)
    q_radius, o_radius = np.asarray(q_radius, float), np.asarray(o_radius, float)
    # float32: millimetre geometry needs no more, and it halves the time of the M × N × views test
    reach = ((q_radius[:, None] + o_radius[None, :]) ** 2).astype(np.float32)
    farthest = float(q_radius.max() + o_radius.max())
    out = np.empty(len(C))
    qu, qv = (q @ C.T).astype(np.float32), (q @ R.T).astype(np.float32)  # M×V
    ou, ov = (o @ C.T).astype(np.float32), (o @ R.T).astype(np.float32)  # N×V
    for v0 in range(0, len(C), chunk):
        sl = slice(v0, v0 + chunk)
        # only points projecting inside the samples' box (grown by the largest reach) in some view of the chunk
        # can touch them there: the exact test runs on those alone
        near = ((ou[:, sl] > qu[:, sl].min(0) - farthest) & (ou[:, sl] < qu[:, sl].max(0) + farthest)
                & (ov[:, sl] > qv[:, sl].min(0) - farthest) & (ov[:, sl] < qv[:, sl].max(0) + farthest)).any(1)
        du = qu[:, None, sl] - ou[None, near, sl]
        dv = qv[:, None, sl] - ov[None, near, sl]
        hit = ((du * du + dv * dv) < reach[:, near, None]).any(1)  # M × chunk
        out[sl] = 100.0 * hit.mean(0)
    return out.reshape(shape)


def resample_polyline(points, radius, step: float = 1.0):
    points = np.asarray(points, float)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    n = max(int(round(s[-1] / step)), 1) + 1
    t = np.linspace(0.0, s[-1], n)
    return np.stack([np.interp(t, s, points[:, k]) for k in range(3)], 1), np.interp(t, s, radius)


def segment_views(tree, vessel, s0: float, s1: float, step_deg: float = 5.0, exclude_mm: float = 5.0,
                  geodesic=None) -> dict:
    """Foreshortening and overlap maps of ``vessel``'s stretch [s0, s1] (mm) over the C-arm grid, and the
    best view. ``geodesic``: optional callable(node indices) → distance along the tree of every node from
    them (defaults to a Dijkstra on the tree's parent links)."""
    alphas, betas = view_grid(step_deg)
    d, c, r = view_directions(alphas, betas)
    pts, q, qr, other = _stretch(tree, vessel, s0, s1, exclude_mm, geodesic)
    fs = foreshortening(pts, d)
    ov = overlap(q, qr, tree.nodes[other], tree.radius[other], c, r)
    score = fs + ov
    prefer = score + 1e-3 * np.hypot(alphas[:, None], betas[None, :])
    i, j = np.unravel_index(int(np.argmin(prefer)), score.shape)
    return {"alphas": alphas, "betas": betas, "foreshortening": fs, "overlap": ov,
            "best": {"alpha_deg": float(alphas[i]), "beta_deg": float(betas[j]),
                     "foreshortening_percent": float(fs[i, j]), "overlap_percent": float(ov[i, j])}}


def overlap_at(tree, vessel, s0: float, s1: float, angles, exclude_mm: float = 5.0) -> list[float]:
    """Overlap (%) of ``vessel``'s stretch [s0, s1] (mm) seen from each C-arm angle (α, β) of ``angles``, as in
    :func:`segment_views`."""
    _, q, qr, other = _stretch(tree, vessel, s0, s1, exclude_mm)
    out = []
    for alpha, beta in angles:
        _, c, r = view_directions([alpha], [beta])
        out.append(float(overlap(q, qr, tree.nodes[other], tree.radius[other], c, r).ravel()[0]))
    return out


def _stretch(tree, vessel, s0: float, s1: float, exclude_mm: float, geodesic=None):
    """A vessel's stretch [s0, s1] (at least three nodes): its node positions, its samples every 1 mm with their
    radii, and the tree's nodes farther than ``exclude_mm`` from it along the tree (what can overlap it)."""
    sel = (vessel.s >= s0) & (vessel.s <= s1)
    if sel.sum() < 2:
        k = int(np.argmin(np.abs(vessel.s - 0.5 * (s0 + s1))))
        sel = np.zeros(len(vessel.s), bool)
        sel[max(k - 1, 0):k + 2] = True
    seg_nodes = vessel.nodes[sel]
    pts = tree.nodes[seg_nodes]
    dist = _tree_distance(tree, seg_nodes, exclude_mm) if geodesic is None else geodesic(seg_nodes)
    q, qr = resample_polyline(pts, tree.radius[seg_nodes], 1.0)
    return pts, q, qr, np.flatnonzero(dist > exclude_mm)


def _tree_distance(tree, sources, limit: float) -> np.ndarray:
    """Distance along the tree (edges of the rooted tree) of every node from ``sources`` (inf beyond limit + 1)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    n = len(tree.nodes)
    child = np.flatnonzero(tree.parent >= 0)
    par = tree.parent[child]
    w = np.maximum(np.linalg.norm(tree.nodes[child] - tree.nodes[par], axis=1), 1e-6)
    A = coo_matrix((np.r_[w, w], (np.r_[child, par], np.r_[par, child])), shape=(n, n)).tocsr()
    dist = dijkstra(A, indices=np.asarray(sources, np.int64), limit=limit + 1.0, min_only=True)
    return dist


def value_at(grid: dict, key: str, alpha: float, beta: float) -> float:
    """Bilinear value of a map at (α, β), clamped to the grid."""
    a, b = grid["alphas"], grid["betas"]
    m = grid[key]
    x = np.clip(np.interp(alpha, a, np.arange(len(a))), 0, len(a) - 1)
    y = np.clip(np.interp(beta, b, np.arange(len(b))), 0, len(b) - 1)
    i0, j0 = int(np.floor(x)), int(np.floor(y))
    i1, j1 = min(i0 + 1, len(a) - 1), min(j0 + 1, len(b) - 1)
    tx, ty = x - i0, y - j0
    return float((1 - tx) * (1 - ty) * m[i0, j0] + tx * (1 - ty) * m[i1, j0] + (1 - tx) * ty * m[i0, j1] + tx * ty * m[i1, j1])
