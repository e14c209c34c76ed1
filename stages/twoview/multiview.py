"""Every view of the same tree: the correspondence method on two or more views of one cardiac phase.

Reads and writes nothing (called by :mod:`stages.methods3d`, i.e. by ``reconstruct`` with three or more runs and
by the held-out check with ``--views N``).

Two views cannot tell a vessel from a ghost: a dense tree's epipolar line crosses several vessels of the other
view, so almost every point finds some depth of near-zero cost there. A third view that sees the same phase
settles most of it, because a ghost's 3D point projects off the vessels of that view. So, for N ≥ 3 views:

1. every pair of views is matched (:func:`stages.twoview.method.match_views`: 2D centrelines, epipolar
   candidates, the labelling per 2D branch both ways), and every candidate 3D point is charged by the *other*
   views: :func:`view_evidence` is the product over them of ``exp(−d²/2σ²)``, d the distance (px) from the
   point's projection to that view's vessel mask (a view the point projects outside of says nothing), and the
   labelling pays ``w_prior`` × (1 − evidence). A ghost that the pair finds plausible is off the vessels of
   another view and loses to "no partner" or to the true depth;
2. the pairs' 3D polylines are pooled: a vessel hidden by an overlap in one pair is found by another pair;
3. a pooled point that another pair contradicts and none corroborates is dropped (:func:`drop_contradicted`):
   where a vessel runs along one pair's epipolar lines that pair may place it at a wrong depth where the other
   views happen to show some vessel too; the other pairs then place the same pixels of two of its views
   elsewhere in 3D, and no other pair puts a point near it;
4. a pooled point whose projection lies farther than ``max_off_vessel_px`` from the vessel mask of any view it
   projects into is cut out (the pair's own views are satisfied by construction; this removes what the soft
   evidence left of a ghost), and so is a point that projects outside a view's image away from where that view's
   vessels leave it (a ghost at the wrong depth can land there, where the view cannot refute it; the tree's
   vessels leave an image only through its border), and a point that fewer than three views see (it projects
   outside the others' images: only its own pair's evidence, with the two-view ambiguity) unless both directions
   of its pair agree on it.

First, every further view (the third, fourth …) is placed and checked against the first two. Its consistency is
the share of the two-view reconstruction's confirmed points (both directions found them: fewer ghosts) it sees
that project within ``max_off_vessel_px`` of its vessels; the view's image shift that brings them closest to its
centrelines (all integer shifts up to :data:`MAX_VIEW_SHIFT_PX` at once, by FFT correlation) is applied when it
raises the share by at least 0.05: a run taken minutes after the others sees the heart displaced by breathing, and
the table's residual error (data-re with a third run: shares of 0.2–0.4 rose to 0.8–1.0 with shifts of 10–25 px).
On the real phantom's runs the same tree scores 0.71–0.90, the same runs mirrored or turned (another tree) at most
0.34. A view below :data:`MIN_CONSISTENCY` (another injection, a wrong phase or geometry) is left out, and the
report says so. The shifts also measure where breathing put the heart in each run, which places the first two views'
model in depth: two views cannot tell the part of the second run's displacement along its epipolar lines from
depth, and a third view placed on a model at the wrong depth is shifted to agree with it. The most probable breathing
motion consistent with every shift (:func:`breathing_correction`: the heart moves mostly head-foot) gives the second
view's missing shift along its epipolar lines; where it is at least :data:`MIN_BREATHING_CORRECTION_PX`, the first two
views are matched again with it and the further views placed again (data-re with a third run: 3D centreline error
1.86 → 1.64 mm). Where breathing moved the runs so far that every further view's shift onto the first two views'
model lies beyond :data:`MAX_VIEW_SHIFT_PX`, the shifts measure nothing; the second view is then first moved along its
epipolar lines in steps (:data:`ALONG_SEARCH_PX`), to where the further views are placed within reach and agree best
with the model (:func:`_search_along_shift`). Last, the second view's shift *across* its epipolar lines, which its
two-view alignment measures from the two views' crossing profiles and often misses (flat profiles of wide vessels),
is measured again on the model of the first view with the further views (:func:`across_from_further_views`), and
from :data:`MIN_ACROSS_CORRECTION_PX` the first two views are matched again with it and the further views placed
again; then once more on that model (:data:`ACROSS_ROUNDS`; data-re with a third run, 20 cases: accuracy 0.851 →
0.880, EPE 1.80 → 1.60 mm with one round, 0.883 and 1.52 mm with two).

With two views (or when no further view is consistent) the result is exactly
:func:`stages.twoview.method.match_views`'s.
"""

from __future__ import annotations

import itertools

import numpy as np
from scipy import ndimage

from ..core.errors import UserError
from ..core.geometry import outside_away_from_exits
from .centreline2d import extract_centreline
from .method import Polyline3D, match_views, tubes_to_voxels
from .select import SelectionParams

__all__ = ["EVIDENCE_SIGMA_PX", "MAX_OFF_VESSEL_PX", "MIN_CONSISTENCY", "MAX_VIEW_SHIFT_PX", "view_evidence",
           "view_consistency", "fit_view_shift", "drop_contradicted", "breathing_correction", "across_from_further_views",
           "multiview_polylines", "multiview_prediction"]

# how far (px) a 3D point may project from another view's vessel before that view's evidence against it is
# strong: a few pixels of residual geometry error between runs (header offsets after the table placement,
# the heart's motion between two runs of one phase)
EVIDENCE_SIGMA_PX = 2.0
# a pooled point that projects farther than this from the vessel of any view is not kept
MAX_OFF_VESSEL_PX = 3.0
# another pair's point this close (mm) corroborates a pooled point; one that projects within COMPETE_PX of it in a
# view but lies farther than COMPETE_FAR_MM from it in 3D competes for that view's pixels
CORROBORATE_MM = 2.0
COMPETE_PX = 1.5
COMPETE_FAR_MM = 4.0
# a further view is used when at least this share of the first two views' reconstruction lies on its vessels
MIN_CONSISTENCY = 0.45
# how far (px) a further view's image may be shifted to agree with the first two (breathing, table, header error)
MAX_VIEW_SHIFT_PX = 32
# fewer confirmed two-view points than this: the further views are placed and judged on all of them
MIN_ANCHOR_POINTS = 200
# breathing displaces the heart between runs mostly head-foot (left-right, anterior-posterior, head-foot: mm)
RESP_SIGMA_MM = (2.0, 3.0, 6.0)
# the second view is moved along its epipolar lines (and its model rebuilt) only when breathing asks this much (px)
MIN_BREATHING_CORRECTION_PX = 2.0
# the second view is moved across its epipolar lines onto the further views' model from this many pixels, unless the
# share of that model on its vessels then drops by more than this (the share barely moves with a few pixels' shift
# of wide vessels, and that model's own ghosts miss them either way; a wrong shift loses more)
MIN_ACROSS_CORRECTION_PX = 2.0
MAX_ACROSS_CONSISTENCY_LOSS = 0.05
ACROSS_ROUNDS = 2  # measured again after the move, at most this many times in all
# where every further view's shift onto the first two views' model lies beyond MAX_VIEW_SHIFT_PX, the second view is
# tried moved along its epipolar lines by these amounts (px) first: the further views' shifts are then measured
ALONG_SEARCH_PX = tuple(float(v) for v in range(-48, 49, 8) if v)


def _distance_to_vessel(mask) -> np.ndarray:
    return ndimage.distance_transform_edt(~np.asarray(mask, bool))


def _centreline_distance(centreline) -> np.ndarray:
    """Distance (px) from every pixel to the view's 2D centreline."""
    on = np.zeros(centreline.shape, bool)
    rc = np.rint(centreline.points).astype(int)
    ok = (rc[:, 0] >= 0) & (rc[:, 0] < on.shape[0]) & (rc[:, 1] >= 0) & (rc[:, 1] < on.shape[1])
    on[rc[ok, 0], rc[ok, 1]] = True
    return ndimage.distance_transform_edt(~on) if on.any() else np.full(on.shape, np.inf)


def _off_vessel_px(points: np.ndarray, cam, dist_map: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Distance (px) from each point's projection to the view's vessel, and whether it projects into the image."""
    rc = cam.project(points)
    inside = cam.in_image(rc) & np.isfinite(rc).all(1)
    d = ndimage.map_coordinates(dist_map, np.nan_to_num(rc).T, order=1, mode="nearest")
    return d, inside


def view_evidence(cameras, dist_maps, sigma_px: float = EVIDENCE_SIGMA_PX):
    """A function of N×3 points → [0, 1]: how well every one of the given views sees a vessel where the point
    projects (the product of ``exp(−d²/2σ²)`` over the views; a view the point projects outside of counts 1)."""

    def evidence(X):
        X = np.asarray(X, float)
        p = np.ones(len(X))
        for cam, dist in zip(cameras, dist_maps):
            d, inside = _off_vessel_px(X, cam, dist)
            p *= np.where(inside, np.exp(-0.5 * (d / sigma_px) ** 2), 1.0)
        return p

    return evidence


def view_consistency(polylines: list[Polyline3D], cam, dist_map: np.ndarray, max_px: float = MAX_OFF_VESSEL_PX):
    """Share of the polylines' points inside a view's image that project within ``max_px`` of its vessels (NaN
    when none projects into it)."""
    if not polylines:
        return float("nan")
    d, inside = _off_vessel_px(np.concatenate([p.points for p in polylines]), cam, dist_map)
    return float(np.mean(d[inside] <= max_px)) if inside.any() else float("nan")


def fit_view_shift(polylines: list[Polyline3D], cam, centreline_dist: np.ndarray, dist_map: np.ndarray,
                   max_px: float = MAX_OFF_VESSEL_PX, max_shift_px: int = MAX_VIEW_SHIFT_PX) -> tuple[tuple[int, int], float]:
    """The integer image shift (d_row, d_col), |d| ≤ ``max_shift_px``, that brings the polylines' points closest to
    the view's vessel centrelines (``centreline_dist``: distance map of its 2D centreline), and the share of them then
    within ``max_px`` of its vessels (``dist_map``: distance map of its mask). Every shift at once: the correlation
    (FFT) of the points' pixel histogram with a closeness map that falls linearly from 1 on a centreline to 0 at
    2 × ``max_px`` (inside a wide vessel every shift of a few pixels is as good on the mask; the centreline is not)."""
    from scipy.signal import fftconvolve

    if not polylines:
        return (0, 0), float("nan")
    rc = np.rint(cam.project(np.concatenate([p.points for p in polylines])))
    inside = cam.in_image(rc) & np.isfinite(rc).all(1)
    if not inside.any():
        return (0, 0), float("nan")
    rc = rc[inside].astype(int)
    hist = np.zeros(centreline_dist.shape)
    np.add.at(hist, (rc[:, 0], rc[:, 1]), 1.0)
    near = np.clip(1.0 - centreline_dist / (2.0 * max_px), 0.0, 1.0)
    # full[i, j] = Σ_x hist(x) near(x + d) with d = (i, j) − (H − 1, W − 1)
    full = fftconvolve(near, hist[::-1, ::-1], mode="full")
    h, w = centreline_dist.shape
    m = int(max_shift_px)
    window = full[h - 1 - m:h + m, w - 1 - m:w + m]
    i, j = np.unravel_index(int(np.argmax(window)), window.shape)
    shift = (int(i - m), int(j - m)) if window[i, j] > 1e-9 else (0, 0)  # no point near any centreline: no shift
    return shift, view_consistency(polylines, cam.shifted(*shift), dist_map, max_px)


def _confirmed_only(polylines: list[Polyline3D]) -> list[Polyline3D]:
    """The polylines' points that both directions of their pair found (each polyline's confirmed points)."""
    return [Polyline3D(p.points[p.confirmed], p.radius[p.confirmed], p.confirmed[p.confirmed]) for p in polylines
            if np.count_nonzero(p.confirmed) >= 2]


def drop_contradicted(polylines: list[Polyline3D], pair_ids, cameras, *, corroborate_mm: float = CORROBORATE_MM,
                      compete_px: float = COMPETE_PX, far_mm: float = COMPETE_FAR_MM, min_views: int = 2,
                      window: int = 5) -> list[Polyline3D]:
    """The pooled polylines without the points that other pairs of views contradict and none corroborates.

    ``pair_ids``: per polyline, the pair of views that made it. A point is *corroborated* when another pair has a
    point within ``corroborate_mm`` of it, and *contradicted in a view* when another pair has a point that projects
    within ``compete_px`` of it there but lies more than ``far_mm`` from it: that pair explains the same pixels with
    another 3D vessel. Dropped: points contradicted in at least ``min_views`` views and not corroborated (a vessel
    crossing another in one view is contradicted there only, and a vessel one pair alone found is contradicted by
    nobody). The verdicts are smoothed along each polyline (a running median over ``window`` points) so that a
    stretch goes or stays as a whole.

    Measured on the real phantom (held-out check, U-Net masks, fitted poses, 20 sampled subsets each): three runs
    0.923 / 1.29 mm → 0.917 / 1.09 mm, four runs 0.931 / 0.83 → 0.928 / 0.72 mm, the distance lower on all 40
    subsets; what it drops is mostly a vessel that lies along the epipolar lines of one pair (docs/TWOVIEW.md)."""
    from scipy.spatial import cKDTree

    if not polylines:
        return polylines
    pair_ids = np.asarray(pair_ids)
    points = np.concatenate([p.points for p in polylines])
    owner = np.repeat(pair_ids, [len(p.points) for p in polylines])
    pairs = np.unique(owner)
    corroborated = np.zeros(len(points), bool)
    for q in pairs:
        others = owner != q
        if others.any():
            d, _ = cKDTree(points[owner == q]).query(points[others], distance_upper_bound=corroborate_mm)
            corroborated[others] |= np.isfinite(d)
    contradicted_in = np.zeros(len(points), int)
    for cam in cameras:
        rc = cam.project(points)
        seen = cam.in_image(rc) & np.isfinite(rc).all(1)
        contradicted = np.zeros(len(points), bool)
        for q in pairs:
            theirs = np.flatnonzero(seen & (owner == q))
            mine = np.flatnonzero(seen & (owner != q))
            if not len(theirs) or not len(mine):
                continue
            # a few nearest in the image suffice: along one polyline only 2–4 points fall within compete_px
            d, j = cKDTree(rc[theirs]).query(rc[mine], k=4, distance_upper_bound=compete_px)
            near = np.isfinite(d)
            mine_of = np.broadcast_to(mine[:, None], d.shape)  # the point each neighbour was found for
            far = np.zeros(d.shape, bool)
            far[near] = np.linalg.norm(points[theirs[j[near]]] - points[mine_of[near]], axis=1) > far_mm
            contradicted[mine] |= far.any(axis=1)
        contradicted_in += contradicted
    drop = (contradicted_in >= min_views) & ~corroborated
    out, start = [], 0
    for pl in polylines:
        n = len(pl.points)
        d = drop[start:start + n]
        start += n
        if window > 1 and n >= window:
            d = ndimage.median_filter(d.astype(np.uint8), size=window, mode="nearest").astype(bool)
        idx = np.flatnonzero(~d)
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            if len(run) >= 2:
                out.append(Polyline3D(pl.points[run], pl.radius[run], pl.confirmed[run]))
    return out


def _keep_on_vessels(polylines: list[Polyline3D], cameras, masks, dist_maps, max_px: float) -> list[Polyline3D]:
    """Each polyline cut where a point projects farther than ``max_px`` from the vessel of any view, or outside a
    view's image away from where its vessels leave it, or where fewer than three views see it and its pair's two
    directions did not both find it."""
    if not polylines:
        return []
    points = np.vstack([pl.points for pl in polylines])
    ok = np.ones(len(points), bool)
    seen_by = np.zeros(len(points), int)
    for cam, mask, dist in zip(cameras, masks, dist_maps):
        d, inside = _off_vessel_px(points, cam, dist)
        ok &= ((d <= max_px) | ~inside) & ~outside_away_from_exits(cam, mask, cam.project(points))
        seen_by += inside
    ok &= (seen_by >= 3) | np.concatenate([pl.confirmed for pl in polylines])
    out = []
    for pl, ok_pl in zip(polylines, np.split(ok, np.cumsum([len(pl.points) for pl in polylines])[:-1])):
        idx = np.flatnonzero(ok_pl)
        for run in np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1):
            if len(run) >= 2:
                out.append(Polyline3D(pl.points[run], pl.radius[run], pl.confirmed[run]))
    return out


def _check_views(masks, cameras, probs) -> None:
    if len(masks) != len(cameras) or (probs is not None and len(probs) != len(masks)):
        raise ValueError("one camera (and one probability map, when given) per mask")
    if len(masks) < 2:
        raise UserError(f"a reconstruction needs at least two views, got {len(masks)}")
    for n, mask in enumerate(masks):
        if not np.asarray(mask).any():
            raise UserError(f"view {n + 1}'s vessel mask is empty: nothing to reconstruct")


def _place_further_views(two_view: list[Polyline3D], cameras, dist_maps, centreline_dists, max_off_vessel_px,
                         always_shift: bool = False):
    """Every further view placed on (shifted onto) the first two views' model and judged by its consistency with
    it (module docstring); with ``always_shift`` its best shift is applied even where it gains little consistency
    (the model moved: the shift that fitted the old one is stale). Returns the cameras (further ones shifted), the
    views kept, the anchor points and the per-view report entries."""
    cameras = list(cameras)
    gain = -np.inf if always_shift else 0.05
    keep, entries = [0, 1], {}
    # the further views are placed and judged on the points both directions of A + B agree on: fewer ghosts
    anchor = _confirmed_only(two_view)
    anchor = anchor if sum(len(p.points) for p in anchor) >= MIN_ANCHOR_POINTS else two_view
    for k in range(2, len(cameras)):
        c = view_consistency(anchor, cameras[k], dist_maps[k], max_off_vessel_px)
        shift, c_shifted = fit_view_shift(anchor, cameras[k], centreline_dists[k], dist_maps[k], max_off_vessel_px)
        if shift != (0, 0) and c_shifted >= (0.0 if c != c else c) + gain:
            cameras[k] = cameras[k].shifted(*shift)
            c = view_consistency(anchor, cameras[k], dist_maps[k], max_off_vessel_px)
        else:
            shift = (0, 0)
        used = bool(c >= MIN_CONSISTENCY)  # NaN (the view sees none of it): not used
        entries[k] = {"consistency": None if c != c else round(c, 3), "used": used, "shift_px": list(shift)}
        if used:
            keep.append(k)
    return {"cameras": cameras, "keep": keep, "anchor": anchor, "report": entries}


def _projection_jacobian(cam, X: np.ndarray, step_mm: float = 1.0) -> np.ndarray:
    """2×3: how a view's projection (row, col px) moves per mm the object moves at X."""
    J = np.zeros((2, 3))
    for i in range(3):
        e = np.zeros(3)
        e[i] = step_mm
        J[:, i] = (cam.project((X + e)[None])[0] - cam.project((X - e)[None])[0]) / (2 * step_mm)
    return J


def _in_reach(cam) -> bool:
    """Whether a further view's shift onto the first two views' model stayed inside :data:`MAX_VIEW_SHIFT_PX` (at the
    edge the search found no placement: its displacement is not measured)."""
    return max(abs(v) for v in cam.image_shift_px) < MAX_VIEW_SHIFT_PX


def _search_along_shift(rebuild, cameras, anchor):
    """(shift of the second view along its epipolar lines, its two-view model, the further views placed on it) for
    the step of :data:`ALONG_SEARCH_PX` at which the further views placed within reach (and used) agree best with
    the model; None when no step places one. ``rebuild(shift)``: the two-view model with the second view moved by
    ``shift`` and the further views placed on it. Breathing can displace the runs so far that the first two views'
    depth error puts the model beyond every further view's search: their shifts then say nothing
    (:func:`breathing_correction` leaves them out) until the second view is moved nearer its true position."""
    epipolar = _epipolar_direction(cameras, np.concatenate([p.points for p in anchor]).mean(axis=0))
    best, best_score = None, -np.inf
    for step in ALONG_SEARCH_PX:
        shift = step * epipolar
        try:
            two_view, placed = rebuild(shift)
        except UserError:
            continue
        measured = [k for k in placed["keep"][2:] if _in_reach(placed["cameras"][k])]
        if not measured:
            continue
        score = float(np.mean([placed["report"][k]["consistency"] for k in measured]))
        if score > best_score:
            best, best_score = (shift, two_view, placed), score
    return best


def breathing_correction(anchor: list[Polyline3D], cameras, further, sigma_mm=RESP_SIGMA_MM) -> np.ndarray | None:
    """The image shift (px, row and column) along its epipolar lines that the second view's geometry lacks, by
    the further views placed on the first two views' model (their cameras' ``image_shift_px``) and the breathing
    prior; None when no further view is placed (or one's shift hit :data:`MAX_VIEW_SHIFT_PX`: not measured).

    Each run k sees the tree displaced by breathing from its mean position: an offset t_k (mm); the first run's
    t_A too, since the model is built where run A sees it, and run A is no more likely than any other run to have
    been filmed at the mean. Run k's image shows the part of t_k − t_A across its rays, J_k (t_k − t_A) (J_k: the
    projection's derivative at the centre of the first two views' model, ``anchor``). The first two views cannot
    tell the part of the second's offset along its epipolar lines from depth: their model is off by some d along
    the first view's axis a, and a view placed on it is shifted by s_k = J_k (t_k − t_A − d·a) — the second view
    by its alignment across the epipolar lines. Every (d, t) that gives the measured shifts explains the images
    equally well, so the offsets are taken as the most probable breathing motion: the least Σ t_kᵀ Σ⁻¹ t_k over
    every run, Σ = diag(``sigma_mm``²) in (left–right, anterior–posterior, head–foot): the heart moves mostly
    head–foot as one breathes. The second view then lacks d·J_B a."""
    shifts = [cam.image_shift_px for cam in cameras]
    further = [k for k in further if _in_reach(cameras[k])]
    if not further or not anchor:
        return None
    X = np.concatenate([p.points for p in anchor]).mean(axis=0)
    a = cameras[0].view_dir
    views = [1, *further]
    n_unknowns = 3 * (len(views) + 1) + 1  # the first view's offset t_A, each other view's t_k, then d
    weight = 100.0  # the measured shifts hold (nearly) exactly; the prior chooses among the offsets that give them
    prior = np.diag(1.0 / np.asarray(sigma_mm, float))
    rows, rhs = [], []
    jacobians = {k: _projection_jacobian(cameras[k], X) for k in views}
    for slot, k in enumerate(views, start=1):
        J = jacobians[k]
        A = np.zeros((2, n_unknowns))
        A[:, 3 * slot:3 * slot + 3] = J
        A[:, :3] = -J
        A[:, -1] = -(J @ a)
        rows.append(weight * A)
        rhs.append(weight * np.asarray(shifts[k], float))
    for slot in range(len(views) + 1):
        P = np.zeros((3, n_unknowns))
        P[:, 3 * slot:3 * slot + 3] = prior
        rows.append(P)
        rhs.append(np.zeros(3))
    d = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0][-1]
    return d * (jacobians[1] @ a)


def _epipolar_direction(cameras, X: np.ndarray) -> np.ndarray:
    """Unit (row, col) direction of the second view's epipolar lines at the 3D point X: where a point moves in that
    view as it slides along the first view's ray."""
    epipolar = _projection_jacobian(cameras[1], X) @ cameras[0].view_dir
    return epipolar / max(float(np.linalg.norm(epipolar)), 1e-9)


def across_from_further_views(cameras, masks, probs, centrelines, dist_maps, further,
                              params: SelectionParams = SelectionParams()) -> np.ndarray:
    """The image shift (px, row and column) across its epipolar lines that places the second view on the model of
    the first view with the further views ``further`` (their ``cameras`` already placed), or zero where that model is
    too small, the shift is under :data:`MIN_ACROSS_CORRECTION_PX` or the second view, placed on it by the whole
    shift, agrees with it less (by :data:`MAX_ACROSS_CONSISTENCY_LOSS`). The whole shift is judged, not its part
    across: the part along is the two models' difference in depth, which would count against a right across part
    (judging the across part alone: data-re with a third run, EPE 1.52 → 1.56 mm). Further views whose own placement
    lay beyond reach are left out.

    Two views alone measure that shift from the overlap of their epipolar crossing profiles, which a wide vessel or a
    tree drawn along the epipolar lines leaves flat; the model of the other views is a sharper reference (its
    centrelines against the second view's, every shift at once). The part along the epipolar lines is left out: the
    further views were placed on the first two views' model, so their model shares its depth error, which shifts it
    along the second view's epipolar lines (:func:`breathing_correction` weighs that)."""
    anchor = []
    for k in further:
        if not _in_reach(cameras[k]):  # its placement on the first two views' model was not measured
            continue
        try:
            anchor += _confirmed_only(match_views(masks[0], masks[k], cameras[0], cameras[k], probs[0], probs[k],
                                                  params=params, centrelines=(centrelines[0], centrelines[k])).polylines)
        except UserError:  # nearly parallel to the first view
            continue
    if sum(len(p.points) for p in anchor) < MIN_ANCHOR_POINTS:
        return np.zeros(2)
    before = view_consistency(anchor, cameras[1], dist_maps[1])
    shift, after = fit_view_shift(anchor, cameras[1], _centreline_distance(centrelines[1]), dist_maps[1])
    epipolar = _epipolar_direction(cameras, np.concatenate([p.points for p in anchor]).mean(axis=0))
    across_dir = np.array([-epipolar[1], epipolar[0]])
    across = float(np.dot(shift, across_dir)) * across_dir
    if np.hypot(*across) < MIN_ACROSS_CORRECTION_PX or not after >= before - MAX_ACROSS_CONSISTENCY_LOSS:
        return np.zeros(2)
    return across


def multiview_polylines(masks, cameras, probs=None, *, params: SelectionParams = SelectionParams(),
                        sigma_px: float = EVIDENCE_SIGMA_PX, max_off_vessel_px: float = MAX_OFF_VESSEL_PX,
                        centrelines=None, report: dict | None = None) -> list[Polyline3D]:
    """The 3D polylines (points, radii, confirmed flags) of N ≥ 2 views (module docstring). ``centrelines``: the
    views' precomputed 2D centrelines (e.g. when the same masks are matched under several cameras). ``report``: a
    dict that receives, per further view (index from 0), ``consistency``, the image shift applied to it
    (``shift_px``, row and column) and whether it was ``used``; and, under 1, the second view's ``shift_px`` where the
    further views moved it (:func:`breathing_correction` along its epipolar lines, :func:`across_from_further_views`
    across them)."""
    _check_views(masks, cameras, probs)
    n = len(masks)
    probs = probs if probs is not None else [None] * n
    if centrelines is None:
        centrelines = [extract_centreline(m, p, source=f"view {k + 1}") for k, (m, p) in enumerate(zip(masks, probs))]
    two_view = match_views(masks[0], masks[1], cameras[0], cameras[1], probs[0], probs[1], params=params,
                           centrelines=tuple(centrelines[:2])).polylines
    if n == 2:
        return two_view
    dist_maps = [_distance_to_vessel(m) for m in masks]
    centreline_dists = [None, None] + [_centreline_distance(c) for c in centrelines[2:]]

    def rebuild(shift_b, always_shift: bool = False):
        """The first two views' model with the second view moved by ``shift_b`` (px), the further views placed on it."""
        moved = [cameras[0], cameras[1].shifted(*shift_b), *cameras[2:]]
        model = match_views(masks[0], masks[1], moved[0], moved[1], probs[0], probs[1], params=params,
                            centrelines=tuple(centrelines[:2])).polylines
        return model, _place_further_views(model, moved, dist_maps, centreline_dists, max_off_vessel_px,
                                           always_shift=always_shift)

    placed = _place_further_views(two_view, cameras, dist_maps, centreline_dists, max_off_vessel_px)
    searched = np.zeros(2)
    if not any(_in_reach(cam) for cam in placed["cameras"][2:]):
        found = _search_along_shift(rebuild, cameras, placed["anchor"])
        if found is not None:
            searched, two_view, placed = found
    along = breathing_correction(placed["anchor"], placed["cameras"], placed["keep"][2:])
    along = np.zeros(2) if along is None or np.hypot(*along) < MIN_BREATHING_CORRECTION_PX else along
    moved = searched + along  # the second view's image shift beyond its two-view alignment
    if along.any():
        # the first two views' model rebuilt at the depth the further views and breathing place it
        two_view, placed = rebuild(moved, always_shift=True)
    for _ in range(ACROSS_ROUNDS):
        if len(placed["keep"]) <= 2:
            break
        # then the second view's shift across its epipolar lines, measured again on the other views' model (which
        # moves with it: the further views are placed again on the rebuilt model), until it is under the minimum
        across = across_from_further_views([cameras[0], cameras[1].shifted(*moved), *placed["cameras"][2:]],
                                           masks, probs, centrelines, dist_maps, placed["keep"][2:], params)
        if not across.any():
            break
        moved = moved + across
        two_view, placed = rebuild(moved, always_shift=True)
    if report is not None and moved.any():
        report[1] = {"shift_px": [round(float(v), 2) for v in moved]}
    cameras, keep = placed["cameras"], placed["keep"]
    if report is not None:
        report.update(placed["report"])
    if len(keep) == 2:
        return two_view
    if len(keep) < n:
        masks, cameras, probs, centrelines, dist_maps = ([seq[k] for k in keep] for seq in
                                                         (masks, cameras, probs, centrelines, dist_maps))
        n = len(keep)
    polylines, pair_ids = [], []
    for pair, (i, j) in enumerate(itertools.combinations(range(n), 2)):
        others = [k for k in range(n) if k not in (i, j)]
        evidence = view_evidence([cameras[k] for k in others], [dist_maps[k] for k in others], sigma_px)
        try:
            m = match_views(masks[i], masks[j], cameras[i], cameras[j], probs[i], probs[j], params=params,
                            centrelines=(centrelines[i], centrelines[j]), prior=evidence)
        except UserError:  # two nearly parallel views of the set: the other pairs triangulate their vessels
            continue
        polylines += m.polylines
        pair_ids += [pair] * len(m.polylines)
    if not polylines and n > 2:
        raise UserError("no two of the views are far enough apart to triangulate vessels")
    polylines = drop_contradicted(polylines, pair_ids, cameras)
    return _keep_on_vessels(polylines, cameras, masks, dist_maps, max_off_vessel_px)


def multiview_prediction(masks, cameras, probs=None, *, voxel_size: float = 0.5,
                         params: SelectionParams = SelectionParams(), centrelines=None, report: dict | None = None):
    """The sparse prediction (occupancy + centreness tubes on the 0.5 mm grid) of N ≥ 2 views. ``report``: see
    :func:`multiview_polylines`."""
    polylines = multiview_polylines(masks, cameras, probs, params=params, centrelines=centrelines, report=report)
    return tubes_to_voxels(polylines, voxel_size)
