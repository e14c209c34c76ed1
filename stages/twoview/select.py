"""Choosing one partner per centreline point: a labelling problem solved exactly per 2D branch.

Reads and writes nothing. For every branch of view A's centreline, a chain model (Viterbi dynamic
programme) picks for each point one of its epipolar candidates in view B, or "no partner" (the vessel is
hidden, outside view B, or missing from B's mask), minimising

* per point (unary): lumen radius disagreement between the views at the triangulated depth
  (|log r_A/r_B|), distance across the epipolar line (misalignment band), and a penalty for 3D points
  outside the tree's extent (:func:`tree_extent`: a tree is about as deep as it is wide);
* per step along the branch (pairwise): a 3D jump much longer than the 2D step allows, and a step whose
  direction disagrees with the 3D tangent the two views' 2D tangents imply (n_A × n_B, where the tangent
  planes are well conditioned);
* entering or leaving "no partner" (so the branch does not flicker between matched and unmatched).

The same runs with the views swapped (B → A); :mod:`stages.twoview.method` combines both.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from .centreline2d import Centreline2D
from ..core.chain_dp import label_chains
from ..core.geometry import epipolar_frame
from .epipolar import candidates, triangulate

__all__ = ["SelectionParams", "DirectionalMatch", "match_direction", "match_both_ways", "tree_extent"]


@dataclass(frozen=True)
class SelectionParams:
    tol_px: float = 3.0  # epipolar band half-width in view B (px)
    w_radius: float = 3.0  # per unit |log(r_A / r_B)|
    overlap_discount: float = 0.35  # share of w_radius when the partner is the wider one (overlap there)
    w_miss: float = 0.3  # per (miss / tol)^2
    far_scale: float = 1.1  # 3D points deeper than this × the tree's 2D extent from its centre are implausible
    w_far: float = 5.0  # per 10 mm beyond
    free_jump: float = 2.5  # 3D step allowed (in units of the 2D step at depth) before it costs
    w_jump: float = 0.4  # per 2D step beyond free_jump
    w_tangent: float = 1.5  # per (1 − |cos|) between the 3D step and the implied tangent
    null_cost: float = 0.9  # per point without a partner
    switch_cost: float = 2.0  # entering or leaving "no partner"
    max_link_mm: float = 3.0  # consecutive matched points farther apart are not joined
    min_conditioning: float = 0.25  # below: the vessel runs along the epipolar line, depth from neighbours
    max_fill_px: int = 12  # unmatched gaps up to this long between matched points get interpolated depth
    w_agree: float = 0.8  # partner point already serves another point of this view (see match_direction)
    agree_bonus: float = 0.3  # partner point chose this very point
    agree_px: float = 3.0
    w_prior: float = 1.5  # per unit (1 − prior occupancy) at the candidate, when a prior is given
    rounds: int = 3  # alternating selections A → B and B → A, each seeing the other's last choice


@dataclass
class DirectionalMatch:
    """The selection for every point of the query view (``partner < 0``: none)."""

    partner_pos: np.ndarray  # N×2 (row, col) in the other view (NaN without a partner)
    partner_index: np.ndarray  # N nearest centreline point of the other view (−1 without)
    points_3d: np.ndarray  # N×3 (NaN without)
    radius_q_mm: np.ndarray  # N lumen radius from the query view at the point's depth
    radius_o_mm: np.ndarray  # N lumen radius from the other view
    cost: np.ndarray  # N unary cost of the chosen candidate (NaN without)
    conditioning: np.ndarray  # N |n_A × n_B| of the chosen candidate (0: vessel along the epipolar line)

    @property
    def matched(self) -> np.ndarray:
        return np.isfinite(self.points_3d[:, 0])


def tree_extent(cl_a: Centreline2D, cam_a, cl_b: Centreline2D, cam_b, quantile: float = 99.0):
    """(centre (3,) mm, radius mm) of the vessel tree two views show: the centre is where the rays through the
    two centrelines' centroids pass closest (the centroid of a 3D curve projects near the centroid of its
    image), the radius the larger of the two views' ``quantile`` distance of centreline points from their
    centroid, in mm at the centre's depth. A tree is about as deep as it is wide, so a 3D point much deeper
    than the views' extent is a chance match of two vessels, not a vessel: on the real phantom (IM1 + IM4) the
    branches that two views matched the wrong way round reached a median depth of 0.99 × this radius from the
    centre, the points the other runs confirm at most 0.82 ×."""
    centroids = [cl.points.mean(0)[None] for cl in (cl_a, cl_b)]
    centre, _ = triangulate(cam_a, centroids[0], cam_b, centroids[1])
    radius = max(float(np.percentile(np.linalg.norm(cl.points - c, axis=1), quantile)) * float(_mm_per_px(cam, centre)[0])
                 for cl, c, cam in zip((cl_a, cl_b), centroids, (cam_a, cam_b)))
    return centre[0], radius


def _beyond_extent(X: np.ndarray, extent, scale: float, cameras) -> np.ndarray:
    """How far (mm) 3D points lie beyond ``scale`` × the tree's radius from its centre in depth, summed over the
    cameras' viewing directions (:func:`tree_extent`). Depth only: a point's position across a view is what that
    view shows, so only its depth can be implausible."""
    centre, radius = extent
    out = np.zeros(len(X))
    for cam in cameras:
        out += np.maximum(0.0, np.abs((X - centre) @ cam.view_dir) - scale * radius)
    return out


def _mm_per_px(cam, X):
    _, depth = cam.project(X, return_depth=True)
    focal = 0.5 * (cam.K[0, 0] + cam.K[1, 1])
    return depth / focal


def _tangent_plane_normals(cam, rc, tangent_rc):
    _, d0 = cam.rays(rc)
    _, d1 = cam.rays(rc + 2.0 * tangent_rc)
    n = np.cross(d0, d1)
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)


@njit(cache=True, nogil=True)
def _step_costs(X, T, cond, step_mm, starts, step_i, offset, w_jump, free_jump, w_tangent):
    """Pairwise cost of every (previous, current) candidate pair of every step ``step_i`` (flat, blocks of
    k(previous) × k(current) at ``offset``): a 3D jump longer than ``free_jump`` 2D steps, and a step whose
    direction disagrees with the 3D tangent the two views imply at either end (1 − |cos|, weighted by how
    well the tangent planes intersect). Compiled: the NumPy version's gathers over every candidate pair
    cost more than the rest of the selection."""
    out = np.empty(offset[-1])
    for e in range(len(step_i)):
        i = step_i[e]
        k0 = starts[i] - starts[i - 1]
        k1 = starts[i + 1] - starts[i]
        for r in range(k0):
            c0 = starts[i - 1] + r
            s_mm = step_mm[c0]
            for s in range(k1):
                c1 = starts[i] + s
                d0, d1, d2 = X[c1, 0] - X[c0, 0], X[c1, 1] - X[c0, 1], X[c1, 2] - X[c0, 2]
                d3 = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
                cost = w_jump * max(0.0, d3 / s_mm - free_jump)
                if d3 > 0.3 * s_mm:
                    inv = 1.0 / max(d3, 1e-9)
                    cos0 = abs(d0 * T[c0, 0] + d1 * T[c0, 1] + d2 * T[c0, 2]) * inv
                    cos1 = abs(d0 * T[c1, 0] + d1 * T[c1, 1] + d2 * T[c1, 2]) * inv
                    tang = 0.5 * (cos0 * cond[c0] + cos1 * cond[c1])
                    cost += w_tangent * (0.5 * (cond[c0] + cond[c1]) - tang)
                out[offset[e] + r * k1 + s] = cost
    return out


@dataclass
class _Candidates:
    """What a direction's selection needs that does not change between rounds: the epipolar candidates, their
    triangulation, radii, implied tangents, the unary cost without the other direction's term, and every step's
    pairwise costs (computed once per direction, not once per round)."""

    cand: object
    X: np.ndarray
    r_q: np.ndarray
    r_o: np.ndarray
    cond: np.ndarray
    unary: np.ndarray
    starts: np.ndarray
    pair_cost: np.ndarray
    pair_start: np.ndarray


def _prepare(cl_q: Centreline2D, cam_q, cl_o: Centreline2D, cam_o, params: SelectionParams, frame,
             prior=None, extent=None) -> _Candidates | None:
    n = len(cl_q)
    if n == 0 or len(cl_o) < 2:
        return None
    cand = candidates(frame, cl_q, cam_q, cl_o, cam_o, tol_px=params.tol_px)
    if len(cand) == 0:
        return None
    q_rc = cl_q.points[cand.query]
    X, _ = triangulate(cam_q, q_rc, cam_o, cand.b_pos)
    extent = extent if extent is not None else tree_extent(cl_q, cam_q, cl_o, cam_o)
    mm_q, mm_o = _mm_per_px(cam_q, X), _mm_per_px(cam_o, X)
    r_q = cl_q.radius_px[cand.query] * mm_q
    r_o = cl_o.radius_px[cand.b_index] * mm_o
    n_q = _tangent_plane_normals(cam_q, q_rc, cl_q.tangent[cand.query])
    n_o = _tangent_plane_normals(cam_o, cand.b_pos, cl_o.tangent[cand.b_index])
    T = np.cross(n_q, n_o)
    cond = np.linalg.norm(T, axis=1)
    T = T / np.maximum(cond[:, None], 1e-12)
    # a partner wider than the query point may be two vessels overlapping in the other view: cheaper
    log_ratio = np.log(np.maximum(r_o, 1e-3) / np.maximum(r_q, 1e-3))
    unary = (params.w_radius * np.where(log_ratio > 0, params.overlap_discount * log_ratio, -log_ratio)
             + params.w_miss * (cand.miss_px / params.tol_px) ** 2
             + params.w_far * _beyond_extent(X, extent, params.far_scale, (cam_q, cam_o)) / 10.0)
    if prior is not None:
        unary = unary + params.w_prior * (1.0 - np.clip(prior(X), 0.0, 1.0))
    step_mm = mm_q  # the query branch is resampled at 1 px
    starts = np.searchsorted(cand.query, np.arange(n + 1))
    counts = np.diff(starts)
    # the pairwise costs of every step (point i−1 → i of a branch), all candidate pairs at once
    step_i = np.flatnonzero(np.r_[False, cl_q.branch[1:] == cl_q.branch[:-1]])
    offset = np.r_[0, np.cumsum(counts[step_i - 1] * counts[step_i])]
    pair_cost = _step_costs(X, T, cond, step_mm, starts, step_i, offset, params.w_jump, params.free_jump,
                            params.w_tangent)
    pair_start = np.zeros(n, np.int64)
    pair_start[step_i] = offset[:-1]
    return _Candidates(cand, X, r_q, r_o, cond, unary, starts, pair_cost, pair_start)


def match_direction(cl_q: Centreline2D, cam_q, cl_o: Centreline2D, cam_o, params: SelectionParams = SelectionParams(),
                    frame=None, reverse: DirectionalMatch | None = None,
                    prior=None, prepared: _Candidates | None = None) -> DirectionalMatch:
    """Select partners in view ``o`` for every centreline point of view ``q`` (module docstring).

    ``reverse``: the current selection the other way (``o`` → ``q``). A candidate whose partner point chose
    another point of ``q`` costs ``w_agree`` more, one whose partner chose this very point ``agree_bonus`` less:
    uniqueness (one point of B serves one point of A) and both-way agreement as a soft term, so a branch of
    A that borrowed the partner of another branch moves to its own.

    ``prior``: optional function of N×3 points → occupancy in [0, 1] (e.g. the SBP network's prediction); a
    candidate where it is low costs up to ``w_prior`` more. ``prepared``: this direction's candidates from an
    earlier round (:func:`_prepare`, with the same prior), so that only the other direction's term is new."""
    n = len(cl_q)
    res = DirectionalMatch(np.full((n, 2), np.nan), -np.ones(n, int), np.full((n, 3), np.nan), np.full(n, np.nan),
                           np.full(n, np.nan), np.full(n, np.nan), np.zeros(n))
    if prepared is None:
        prepared = _prepare(cl_q, cam_q, cl_o, cam_o, params, frame or epipolar_frame(cam_q, cam_o), prior)
    if prepared is None:
        return res
    cand, X, r_q, r_o, cond, unary = prepared.cand, prepared.X, prepared.r_q, prepared.r_o, prepared.cond, prepared.unary
    starts = prepared.starts
    q_rc = cl_q.points[cand.query]
    if reverse is not None:
        back = reverse.partner_pos[cand.b_index]  # where the partner's own choice lies in view q
        chose = np.isfinite(back[:, 0])
        dist = np.linalg.norm(np.nan_to_num(back) - q_rc, axis=1)
        unary = unary + np.where(chose, np.where(dist <= params.agree_px, -params.agree_bonus, params.w_agree), 0.0)
    # Viterbi over (candidates…, no partner) along every branch, all branches in one compiled pass
    branches = cl_q.branch_slices()
    chosen = label_chains(np.r_[[sl.start for sl in branches], n], starts, unary, prepared.pair_cost,
                          prepared.pair_start,
                          null_unary=np.full(n, params.null_cost), switch_cost=params.switch_cost)
    has = np.flatnonzero(chosen >= 0)
    c = starts[has] + chosen[has]
    res.partner_pos[has] = cand.b_pos[c]
    res.partner_index[has] = cand.b_index[c]
    res.points_3d[has] = X[c]
    res.radius_q_mm[has] = r_q[c]
    res.radius_o_mm[has] = r_o[c]
    res.cost[has] = unary[c]
    res.conditioning[has] = cond[c]
    rays = cam_q.rays(cl_q.points)
    for sl in branches:
        _interpolate_depth(res, np.arange(sl.start, sl.stop), cam_q, cl_q, cam_o, params, rays)
    return res


def _interpolate_depth(res: DirectionalMatch, idx: np.ndarray, cam_q, cl_q: Centreline2D, cam_o, params: SelectionParams,
                       rays):
    """Along one branch: where the vessel runs along the epipolar line (poor conditioning) or a short gap has
    no partner, place the point on its own ray at the depth interpolated between well-conditioned matched
    neighbours (triangulation is ill-posed there; the branch's continuity is not). ``rays``: (origins,
    directions) of every point of ``cl_q``."""
    X = res.points_3d[idx]
    matched = np.isfinite(X[:, 0])
    anchor = matched & (res.conditioning[idx] >= params.min_conditioning)
    if anchor.sum() < 2:
        return
    origins, dirs = rays[0][idx], rays[1][idx]
    lam = np.einsum("ij,ij->i", np.nan_to_num(X) - origins, dirs)
    k = np.arange(len(idx))
    ka = k[anchor]
    inside = (k > ka[0]) & (k < ka[-1]) & ~anchor
    if not inside.any():
        return
    # the gap (in points) to the nearest anchors on each side
    nxt = ka[np.searchsorted(ka, k[inside])]
    prv = ka[np.searchsorted(ka, k[inside]) - 1]
    unmatched_gap = ~matched[inside] & ((nxt - prv) > params.max_fill_px)
    target = k[inside][~unmatched_gap]
    if not len(target):
        return
    lam_t = np.interp(target, ka, lam[anchor])
    new = origins[target] + lam_t[:, None] * dirs[target]
    # only where the interpolated point stays near what the neighbours imply (no jump across a fold)
    i_global = idx[target]
    was = np.isfinite(res.points_3d[i_global, 0])
    res.points_3d[i_global] = new
    res.partner_pos[i_global] = cam_o.project(new)
    r_q = cl_q.radius_px[i_global] * _mm_per_px(cam_q, new)
    res.radius_q_mm[i_global] = r_q
    res.radius_o_mm[i_global] = np.where(was, res.radius_o_mm[i_global], r_q)
    res.cost[i_global] = np.where(was, res.cost[i_global], params.null_cost)
    res.conditioning[i_global] = np.where(was, res.conditioning[i_global], 0.0)


def match_both_ways(cl_a: Centreline2D, cam_a, cl_b: Centreline2D, cam_b, params: SelectionParams = SelectionParams(),
                    frame=None, prior=None) -> tuple[DirectionalMatch, DirectionalMatch]:
    """A → B and B → A, alternated ``params.rounds`` times, each round seeing the other's previous choice."""
    frame = frame or epipolar_frame(cam_a, cam_b)
    extent = tree_extent(cl_a, cam_a, cl_b, cam_b) if len(cl_a) and len(cl_b) else None
    # the candidates and their fixed costs are the same every round: prepared once per direction
    prep_ab = _prepare(cl_a, cam_a, cl_b, cam_b, params, frame, prior, extent)
    prep_ba = _prepare(cl_b, cam_b, cl_a, cam_a, params, frame, prior, extent)
    ab = match_direction(cl_a, cam_a, cl_b, cam_b, params, frame, prepared=prep_ab)
    ba = match_direction(cl_b, cam_b, cl_a, cam_a, params, frame, prepared=prep_ba)
    for _ in range(params.rounds - 1):
        ab, ba = (match_direction(cl_a, cam_a, cl_b, cam_b, params, frame, reverse=ba, prepared=prep_ab),
                  match_direction(cl_b, cam_b, cl_a, cam_a, params, frame, reverse=ab, prepared=prep_ba))
    return ab, ba
