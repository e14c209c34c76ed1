"""The ``correspondence`` 3D method: two vessel masks + two cameras → 3D centreline with radii → sparse voxels.

Reads and writes nothing (called by :mod:`stages.methods3d`, i.e. by ``reconstruct``, the held-out check
and the table scripts).

1. per view, the 2D centreline with sub-pixel points, tangents and radii (:mod:`.centreline2d`), from the
   mask and, when given, the segmenter's probability;
2. per view, partners chosen along every 2D branch in the other view (:mod:`.epipolar`, :mod:`.select`),
   A → B and B → A;
3. both ways combined: a 3D point of one direction is *confirmed* when the other direction has a 3D point
   within ``agree_mm``; unconfirmed points are kept only where their own cost is low and a confirmed point
   lies within ``unconfirmed_reach_mm`` (a vessel that overlaps another one in the other view is found by
   one direction only, next to vessels both directions found), so ghosts that one direction alone invents
   are dropped;
4. 3D polylines along the branches, smoothed, radius = geometric mean of the two views' radii at the point's
   depth (each view's pixel radius × mm per pixel at that depth);
5. tubes rasterised on the 0.5 mm grid: ``occupancy`` 1 inside, ``centreness`` 1 − d/r.

A vessel seen in one view only has no partner in the other and is dropped (there is no depth for it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..core.errors import UserError
from ..core.geometry import MIN_VIEW_SEPARATION_DEG, epipolar_frame, view_separation_deg
from ..core.voxels import SparseVoxels
from .centreline2d import Centreline2D, extract_centreline
from .select import DirectionalMatch, SelectionParams, match_both_ways

__all__ = ["TwoViewMatch", "Polyline3D", "match_views", "kept_points", "correspondence_prediction",
           "correspondence_polylines", "tubes_to_voxels",
           "voxel_prior"]

@dataclass
class Polyline3D:
    points: np.ndarray  # K×3 mm
    radius: np.ndarray  # K mm
    confirmed: np.ndarray  # K bool (found both ways)


@dataclass
class TwoViewMatch:
    """Matched centreline points of the two views (both directions, after combination)."""

    points_a: np.ndarray  # N×2 (row, col) in view A
    points_b: np.ndarray  # N×2 in view B
    points_3d: np.ndarray  # N×3 mm
    radius_mm: np.ndarray  # N
    radius_a_mm: np.ndarray  # N radius from view A alone
    radius_b_mm: np.ndarray  # N radius from view B alone
    cost: np.ndarray  # N
    confirmed: np.ndarray  # N bool
    direction: np.ndarray  # N int8: 0 = A→B, 1 = B→A
    polylines: list[Polyline3D]
    centreline_a: Centreline2D
    centreline_b: Centreline2D

    def __len__(self) -> int:
        return len(self.points_3d)


def _polylines(cl: Centreline2D, m: DirectionalMatch, keep: np.ndarray, confirmed: np.ndarray,
               max_link_mm: float, smooth: float = 1.5) -> list[Polyline3D]:
    out = []
    for sl in cl.branch_slices():
        idx = np.arange(sl.start, sl.stop)
        ok = keep[idx]
        if not ok.any():
            continue
        X = m.points_3d[idx]
        gap = np.ones(len(idx), bool)
        gap[1:] = ~(ok[1:] & ok[:-1]) | (np.linalg.norm(np.diff(np.nan_to_num(X), axis=0), axis=1) > max_link_mm)
        run = np.cumsum(gap)
        for r in np.unique(run[ok]):
            sel = idx[(run == r) & ok]
            if len(sel) < 2:
                continue
            P = m.points_3d[sel]
            rad = np.sqrt(np.maximum(m.radius_q_mm[sel], 1e-3) * np.maximum(m.radius_o_mm[sel], 1e-3))
            if len(sel) >= 3:
                P = ndimage.gaussian_filter1d(P, smooth, axis=0, mode="nearest")
                rad = ndimage.median_filter(rad, size=min(7, len(sel) | 1), mode="nearest")
            out.append(Polyline3D(P, rad, confirmed[sel]))
    return out


def _nearest_distance(points: np.ndarray, others: np.ndarray) -> np.ndarray:
    from scipy.spatial import cKDTree

    if len(others) == 0:
        return np.full(len(points), np.inf)
    return cKDTree(others).query(points, k=1)[0]


def kept_points(match: DirectionalMatch, confirmed: np.ndarray, anchors: np.ndarray, max_cost: float,
                reach_mm: float) -> np.ndarray:
    """Which matched points of one direction stay: the confirmed ones, and those the other direction did not
    find whose cost is at most ``max_cost`` and that lie within ``reach_mm`` of a confirmed point (``anchors``).

    A vessel that overlaps another in the other view is found by one direction only, but next to vessels both
    directions found; a point found one way only and far from all of them is most often an epipolar
    coincidence (real phantom, 28 pairs: of the points found one way only, 66 % of those more than 20 mm from a
    confirmed point lie > 4 mm off the held-out runs' vessels, 14–16 % of those within 5 mm)."""
    cheap = np.nan_to_num(match.cost, nan=np.inf) <= max_cost
    near = _nearest_distance(np.nan_to_num(match.points_3d, nan=1e9), anchors) <= reach_mm
    return match.matched & (confirmed | (cheap & near))


def match_views(mask_a, mask_b, cam_a, cam_b, prob_a=None, prob_b=None, *, params: SelectionParams = SelectionParams(),
                agree_mm: float = 1.5, keep_unconfirmed_cost: float = 0.5, unconfirmed_reach_mm: float = 20.0,
                centrelines=None, prior=None) -> TwoViewMatch:
    """Matched centreline points of two views (see the module docstring). ``centrelines``: precomputed
    (Centreline2D of A, of B), e.g. when the same masks are matched under several cameras. ``prior``: an
    occupancy function of 3D points that breaks ties between candidates (:func:`voxel_prior`)."""
    if np.asarray(mask_a).shape != (cam_a.rows, cam_a.cols) or np.asarray(mask_b).shape != (cam_b.rows, cam_b.cols):
        raise UserError(f"mask shapes {np.asarray(mask_a).shape} / {np.asarray(mask_b).shape} do not match the "
                        f"cameras ({cam_a.rows}×{cam_a.cols}, {cam_b.rows}×{cam_b.cols})")
    sep = view_separation_deg(cam_a, cam_b)
    if sep < MIN_VIEW_SEPARATION_DEG:
        raise UserError(f"the two views are only {sep:.1f}° apart (need ≥ {MIN_VIEW_SEPARATION_DEG:.0f}°): nearly parallel "
                        "views cannot triangulate vessels")
    if centrelines is None:
        cl_a = extract_centreline(mask_a, prob_a, source="view A")
        cl_b = extract_centreline(mask_b, prob_b, source="view B")
    else:
        cl_a, cl_b = centrelines
    frame = epipolar_frame(cam_a, cam_b)
    ab, ba = match_both_ways(cl_a, cam_a, cl_b, cam_b, params, frame, prior=prior)
    ok_ab, ok_ba = ab.matched, ba.matched
    d_ab = np.full(len(cl_a), np.inf)
    d_ba = np.full(len(cl_b), np.inf)
    d_ab[ok_ab] = _nearest_distance(ab.points_3d[ok_ab], ba.points_3d[ok_ba])
    d_ba[ok_ba] = _nearest_distance(ba.points_3d[ok_ba], ab.points_3d[ok_ab])
    conf_ab, conf_ba = d_ab <= agree_mm, d_ba <= agree_mm
    anchors = np.vstack([ab.points_3d[conf_ab], ba.points_3d[conf_ba]])
    keep_ab = kept_points(ab, conf_ab, anchors, keep_unconfirmed_cost, unconfirmed_reach_mm)
    keep_ba = kept_points(ba, conf_ba, anchors, keep_unconfirmed_cost, unconfirmed_reach_mm)
    polys = (_polylines(cl_a, ab, keep_ab, conf_ab, params.max_link_mm)
             + _polylines(cl_b, ba, keep_ba & ~conf_ba, conf_ba, params.max_link_mm))
    # B→A points that A→B confirms describe the same vessel twice; they are kept in the match list (both
    # ways are evidence for calibration) but rasterised once, from the A→B polylines
    ia, ib = np.flatnonzero(keep_ab), np.flatnonzero(keep_ba)
    return TwoViewMatch(
        points_a=np.vstack([cl_a.points[ia], ba.partner_pos[ib]]),
        points_b=np.vstack([ab.partner_pos[ia], cl_b.points[ib]]),
        points_3d=np.vstack([ab.points_3d[ia], ba.points_3d[ib]]),
        radius_mm=np.r_[np.sqrt(ab.radius_q_mm[ia] * ab.radius_o_mm[ia]), np.sqrt(ba.radius_q_mm[ib] * ba.radius_o_mm[ib])],
        radius_a_mm=np.r_[ab.radius_q_mm[ia], ba.radius_o_mm[ib]],
        radius_b_mm=np.r_[ab.radius_o_mm[ia], ba.radius_q_mm[ib]],
        cost=np.r_[ab.cost[ia], ba.cost[ib]],
        confirmed=np.r_[conf_ab[ia], conf_ba[ib]],
        direction=np.r_[np.zeros(len(ia), np.int8), np.ones(len(ib), np.int8)],
        polylines=polys, centreline_a=cl_a, centreline_b=cl_b)


def voxel_prior(vox: SparseVoxels, reach: int = 1):
    """Occupancy of a sparse prediction as a function of 3D points: the highest occupancy among the voxels
    within ``reach`` voxels of the point (0 where the prediction has none)."""
    from scipy.spatial import cKDTree

    occ = np.asarray(vox.features["occupancy"], float)
    if len(vox) == 0:
        return lambda X: np.zeros(len(X))
    tree = cKDTree(vox.coords.astype(float))

    def prior(X):
        idx = (np.asarray(X, float) - vox.origin) / vox.voxel_size
        out = np.zeros(len(idx))
        for i, nb in enumerate(tree.query_ball_point(idx, r=reach + 0.5)):
            if nb:
                out[i] = occ[nb].max()
        return out

    return prior


def tubes_to_voxels(polylines: list[Polyline3D], voxel_size: float = 0.5, origin=None, step: float = 0.2) -> SparseVoxels:
    """Rasterise tubes (polyline + radius) on a grid: voxels whose centre lies within the radius of the
    nearest centreline sample (samples every ``step`` mm along each polyline)."""
    from scipy.spatial import cKDTree

    origin = np.zeros(3) if origin is None else np.asarray(origin, float)
    pts, rad = [], []
    for pl in polylines:
        seg = np.linalg.norm(np.diff(pl.points, axis=0), axis=1)
        s = np.r_[0.0, np.cumsum(seg)]
        t = np.linspace(0.0, s[-1], max(int(np.ceil(s[-1] / step)) + 1, 2))
        pts.append(np.stack([np.interp(t, s, pl.points[:, k]) for k in range(3)], axis=1))
        rad.append(np.interp(t, s, pl.radius))
    empty = SparseVoxels(np.zeros((0, 3), np.int32), voxel_size, origin,
                         {"occupancy": np.zeros(0, np.float32), "centreness": np.zeros(0, np.float32)})
    if not pts:
        return empty
    P, R = np.concatenate(pts), np.concatenate(rad)
    reach = int(np.ceil(R.max() / voxel_size)) + 1
    g = np.arange(-reach, reach + 1)
    offs = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    centre_idx = np.rint((P - origin) / voxel_size).astype(np.int64)
    # candidate voxels: a ball of offsets around every kept sample (about one per voxel along the tube), de-duplicated
    # as one int64 key per voxel. A voxel inside a tube lies within R / voxel_size + 1 + margin voxels of the rounded
    # centre of a kept sample: margin = half the kept samples' spacing plus half a voxel's diagonal, minus one
    every = max(int(round(voxel_size / step)), 1)
    C, Rc = centre_idx[::every], R[::every]
    margin = 0.5 * every * step / voxel_size + 0.5 * np.sqrt(3.0) - 1.0
    lo = C.min(0) - reach
    span = C.max(0) + reach - lo + 1
    keys = []
    r_vox_all = np.ceil(Rc / voxel_size).astype(int) + 1
    for r_vox in np.unique(r_vox_all):
        o = offs[(offs ** 2).sum(1) <= (r_vox + margin) ** 2]
        # one ball per distinct centre voxel (tubes that overlap, e.g. the same vessel from several pairs of views,
        # share most of theirs)
        c = np.unique(C[r_vox_all == r_vox], axis=0)
        ijk = (c[:, None, :] + o[None] - lo).reshape(-1, 3)
        keys.append((ijk[:, 0] * span[1] + ijk[:, 1]) * span[2] + ijk[:, 2])
    keys = np.concatenate(keys)
    if np.prod(span) <= 1 << 26:  # de-duplicated on a bitmap of the box (≤ 64 MB): faster than sorting
        seen = np.zeros(int(np.prod(span)), bool)
        seen[keys] = True
        keys = np.flatnonzero(seen)
    else:
        keys = np.unique(keys)
    cand = np.stack([keys // (span[1] * span[2]), (keys // span[2]) % span[1], keys % span[2]], axis=1) + lo
    centres = origin + cand * voxel_size
    d, j = cKDTree(P).query(centres, k=8, distance_upper_bound=float(R.max()))
    ratio = d / np.maximum(R[np.minimum(j, len(P) - 1)], 1e-6)  # no sample within reach: d = inf
    best = ratio.min(1)
    inside = best < 1.0
    if not inside.any():
        return empty
    return SparseVoxels(cand[inside].astype(np.int32), voxel_size, origin,
                        {"occupancy": np.ones(int(inside.sum()), np.float32),
                         "centreness": np.clip(1.0 - best[inside], 0.0, 1.0).astype(np.float32)})


def correspondence_prediction(mask_a, mask_b, cam_a, cam_b, prob_a=None, prob_b=None, *, voxel_size: float = 0.5,
                              params: SelectionParams = SelectionParams(), centrelines=None):
    """The 3D method's sparse prediction (occupancy + centreness on the 0.5 mm grid). ``centrelines``: the two
    masks' precomputed 2D centrelines (:func:`match_views`), e.g. when the same masks are matched under two
    cameras."""
    polylines, _ = correspondence_polylines(mask_a, mask_b, cam_a, cam_b, prob_a, prob_b, params=params,
                                            centrelines=centrelines)
    return tubes_to_voxels(polylines, voxel_size)


def correspondence_polylines(mask_a, mask_b, cam_a, cam_b, prob_a=None, prob_b=None, *,
                             params: SelectionParams = SelectionParams(), centrelines=None):
    """The two-view 3D polylines and the number of matched centreline points of both directions (how much of the
    two views they explain); an empty mask is a clear error."""
    if not np.asarray(mask_a).any():
        raise UserError("view A's vessel mask is empty: nothing to reconstruct")
    if not np.asarray(mask_b).any():
        raise UserError("view B's vessel mask is empty: nothing to reconstruct")
    m = match_views(mask_a, mask_b, cam_a, cam_b, prob_a, prob_b, params=params, centrelines=centrelines)
    return m.polylines, len(m)
