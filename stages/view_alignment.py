"""Inter-run motion correction: the image shift of view B that makes two vessel masks epipolar-consistent.

Reads: the two views' vessel masks of each key-frame pair and their cameras (in memory; no artefact).
Writes: nothing; :func:`estimate_run_shifts` returns view B's shift per key frame (:class:`ViewShift`),
with which ``autocar reconstruct`` shifts view B's camera (:meth:`Camera.shifted`) and stores it per key
frame in ``predictions.zarr``, the shifts in ``summary.json``.

Why: the two runs are acquired seconds apart, so between run A's frame and run B's frame the heart has
moved with breathing (and any residual cardiac phase difference) by several millimetres. Header
geometry is then no longer consistent with the images: the back-projected rays of a vessel in A and
the same vessel in B miss each other, the sparse voxel set loses the true vessel and keeps ghosts.

Which shift: every plane through the two X-ray sources (an *epipolar plane*) cuts the 3D tree in a
set of points that both views see, so the number of vessel crossings per epipolar plane is the same
in both images when the geometry is right. A rigid motion of the tree shows in view B, to first
order, as an image shift; only its component across the epipolar lines breaks consistency (the
component along them is taken up as depth). So we search that one direction for the shift whose
crossing profile, histogrammed over the epipolar-plane angle, matches view A's best. The crossing
density of a centreline pixel is how fast the angle changes along the vessel there (a vessel running
along an epipolar line crosses few planes, one running across it many), which makes the profile
independent of foreshortening and of the two detectors' magnifications.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage.morphology import skeletonize

from .core.catheter import catheter_line
from .core.geometry import Camera, epipolar_angles, epipolar_frame

__all__ = ["ViewShift", "MismatchCurve", "mismatch_curve", "estimate_view_b_shift", "estimate_run_shifts"]

MAX_SHIFT_MM = 10.0  # search range at the isocentre: breathing moves the heart by up to about 1 cm
STEP_PX = 0.5
MARGIN_PX = 10  # profile bins beyond view A's epipolar range, in view-B pixels
# SLOPE_PX … PRIOR_PER_PX: chosen on the tuning cases (docs/benchmarks/view_alignment.md; the script:
# git show 4cf1374:benchmarks/tune_view_alignment.py)
SLOPE_PX = 0.5  # joint fit: largest change of the shift per frame of either run (px/frame); 0: one shift per run pair
REFINE_PX = 4.0  # joint fit: how far each pair's shift may leave the fitted line (px)
MIN_GAIN = 0.02  # a pair's shift is applied only if it lowers that pair's mismatch by this much
PRIOR_PER_PX = 0.004  # joint fit: mismatch added per px of shift, so flat or ambiguous curves favour small motion
MIN_CENTRELINE_PX = 50  # fewer centreline pixels in either view: too little to align on, keep the header


@dataclass
class ViewShift:
    """View B's image shift (pixels, row/col) and how well the crossing profiles matched."""

    shift_px: tuple[float, float]
    across_px: float  # the same, signed, along the direction across view B's epipolar lines
    mismatch: float  # 1 − correlation of the two crossing profiles at the chosen shift
    mismatch_header: float  # the same with the header geometry

    @classmethod
    def none(cls, mismatch: float = float("nan")) -> "ViewShift":
        """No shift: the header geometry (``mismatch`` at it, when known)."""
        return cls((0.0, 0.0), 0.0, mismatch, mismatch)

    @property
    def applied(self) -> bool:
        return bool(self.shift_px[0] or self.shift_px[1])

    def to_dict(self, spacing_mm: float) -> dict:
        return {"shift_px": [round(float(v), 2) for v in self.shift_px], "across_px": round(self.across_px, 2),
                "across_mm": round(self.across_px * spacing_mm, 3), "mismatch": round(self.mismatch, 4),
                "mismatch_header": round(self.mismatch_header, 4)}


def _without_straight_branches(skel: np.ndarray) -> np.ndarray:
    """The centreline without its long straight branches: a catheter, which the segmenter keeps, runs
    straight across much of the image and spans every epipolar plane there, drowning the vessels' profile."""
    neighbours = ndimage.convolve(skel.astype(np.int32), np.ones((3, 3), np.int32), mode="constant") - 1
    branches, n = ndimage.label(skel & (neighbours < 3), np.ones((3, 3)))
    out = skel.copy()
    for i, sl in enumerate(ndimage.find_objects(branches), start=1):
        pts = np.argwhere(branches[sl] == i).astype(float)
        if catheter_line(pts) is not None:
            out[sl][branches[sl] == i] = False
    return out


def _crossing_profile_inputs(mask: np.ndarray, cam: Camera, frame):
    """Centreline pixels of a mask, their epipolar angle and crossing density (|dθ| per pixel step)."""
    px = np.argwhere(_without_straight_branches(skeletonize(mask))).astype(float)
    if len(px) < MIN_CENTRELINE_PX:
        return None
    srr, src, scc = _structure_tensor(mask.astype(float), sigma=2.0)
    r, c = px[:, 0].astype(int), px[:, 1].astype(int)
    across = 0.5 * np.arctan2(2 * src[r, c], srr[r, c] - scc[r, c])  # dominant gradient: across the vessel
    normal = np.stack([np.cos(across), np.sin(across)], 1)
    theta = epipolar_angles(cam, px, frame)
    grad = np.stack([epipolar_angles(cam, px + [1.0, 0.0], frame) - theta,
                     epipolar_angles(cam, px + [0.0, 1.0], frame) - theta], 1)
    # the vessel's tangent is perpendicular to ``normal``: its component along grad θ is normal × grad
    density = np.abs(normal[:, 0] * grad[:, 1] - normal[:, 1] * grad[:, 0])
    return px, theta, density


def _structure_tensor(image: np.ndarray, sigma: float):
    """The smoothed gradient products (rr, rc, cc) of an image: Sobel derivatives, Gaussian window. Written
    here with scipy.ndimage because importing skimage.feature for it also imports scipy.stats (0.3 s)."""
    gr = ndimage.sobel(image, axis=0, mode="constant")
    gc = ndimage.sobel(image, axis=1, mode="constant")
    return tuple(ndimage.gaussian_filter(a, sigma, mode="constant") for a in (gr * gr, gr * gc, gc * gc))


def _across_direction(cam_b: Camera, frame) -> tuple[np.ndarray, float]:
    """Unit (row, col) direction across view B's epipolar lines at the image centre, and |dθ/dpx| there."""
    c = np.array([[cam_b.rows / 2, cam_b.cols / 2]], float)
    t = epipolar_angles(cam_b, np.vstack([c, c + [1.0, 0.0], c + [0.0, 1.0]]), frame)
    g = np.array([t[1] - t[0], t[2] - t[0]])
    return g / np.linalg.norm(g), float(np.linalg.norm(g))


@dataclass
class MismatchCurve:
    """How badly the two crossing profiles match, for each trial shift of view B across its epipolar lines."""

    direction: np.ndarray  # unit (row, col) across view B's epipolar lines
    steps_px: np.ndarray  # trial shifts along ``direction``
    mismatch: np.ndarray  # 1 − correlation of the profiles at each trial shift (NaN: nothing to align on)
    at_header: float  # the same at zero shift

    def at(self, shift_px) -> np.ndarray:
        return np.interp(shift_px, self.steps_px, self.mismatch)


def mismatch_curve(mask_a, mask_b, cam_a: Camera, cam_b: Camera, max_shift_mm: float = MAX_SHIFT_MM,
                   step_px: float = STEP_PX) -> MismatchCurve:
    """:class:`MismatchCurve` of one key-frame pair (all NaN when either mask has too little centreline)."""
    frame = epipolar_frame(cam_a, cam_b)
    u, rate = _across_direction(cam_b, frame)
    reach = max_shift_mm / cam_b.isocentre_spacing
    steps = np.arange(-reach, reach + 1e-9, step_px)
    ia = _crossing_profile_inputs(np.asarray(mask_a, bool), cam_a, frame)
    ib = _crossing_profile_inputs(np.asarray(mask_b, bool), cam_b, frame)
    if ia is None or ib is None:
        return MismatchCurve(u, steps, np.full(len(steps), np.nan), float("nan"))
    _, theta_a, dens_a = ia
    px_b, _, dens_b = ib
    # bins one view-B pixel wide in θ over view A's range and a margin: view B's vessels outside view A's
    # planes say nothing about the shift (one view may be collimated tighter than the other)
    edges = np.arange(theta_a.min() - MARGIN_PX * rate, theta_a.max() + (MARGIN_PX + 1) * rate, rate)

    def profile(theta, dens):
        return ndimage.gaussian_filter1d(np.histogram(theta, edges, weights=dens)[0], 1.0)

    prof_a = profile(theta_a, dens_a)

    def mismatch_at(shift_rc):
        prof_b = profile(epipolar_angles(cam_b.shifted(*shift_rc), px_b, frame), dens_b)
        return 1.0 - float(np.corrcoef(prof_a, prof_b)[0, 1]) if prof_b.any() else 1.0

    return MismatchCurve(u, steps, np.array([mismatch_at(t * u) for t in steps]), mismatch_at((0.0, 0.0)))


def _refine(curve: MismatchCurve, centre: float, window_px: float, prior_per_px: float = 0.0) -> float:
    """The minimum of the curve plus ``prior_per_px``·|shift| within ``window_px`` of ``centre``, to a
    fraction of a step (parabola fit)."""
    near = np.flatnonzero(np.abs(curve.steps_px - centre) <= window_px)
    if len(near) == 0 or not np.isfinite(curve.mismatch[near]).any():
        return float(centre)
    cost = curve.mismatch + prior_per_px * np.abs(curve.steps_px)
    best = int(near[np.nanargmin(cost[near])])
    s = float(curve.steps_px[best])
    if 0 < best < len(curve.steps_px) - 1:
        y0, y1, y2 = cost[best - 1:best + 2]
        curv = y0 - 2 * y1 + y2
        if np.isfinite(curv) and curv > 0:
            s += 0.5 * (curve.steps_px[1] - curve.steps_px[0]) * (y0 - y2) / curv
    return s


def _shift(curve: MismatchCurve, across_px: float) -> ViewShift:
    d = across_px * curve.direction
    return ViewShift((float(d[0]), float(d[1])), float(across_px), float(curve.at(across_px)), curve.at_header)


def estimate_view_b_shift(mask_a, mask_b, cam_a: Camera, cam_b: Camera, **kwargs) -> ViewShift:
    """The image shift of view B (across its epipolar lines) that best matches one pair's crossing profiles.

    Returns a zero shift when either mask has too little centreline to align on.
    """
    curve = mismatch_curve(mask_a, mask_b, cam_a, cam_b, **kwargs)
    if not np.isfinite(curve.mismatch).any():
        return ViewShift.none()
    return _shift(curve, _refine(curve, 0.0, np.inf))


def estimate_run_shifts(curves: list[MismatchCurve], frames_a, frames_b, slope_px: float = SLOPE_PX,
                        window_px: float = REFINE_PX, min_gain: float = MIN_GAIN,
                        prior_per_px: float = PRIOR_PER_PX) -> list[ViewShift]:
    """View B's shift for every key-frame pair of one run pair, fitted jointly.

    The motion between the runs is slow (breathing, table drift) next to the cardiac cycle the key
    frames sample, so the shift is modelled as c + a·(frame in B) − b·(frame in A), linear in both frame
    indices, and (c, a, b) minimise the summed mismatch of all pairs. One pair whose profiles happen to
    match best at a wrong shift (a vessel missing from one mask, a catheter) then cannot pull its own
    shift away: each pair's shift is only refined within ``window_px`` of the fitted line. A pair keeps
    the header geometry unless its shift lowers its mismatch by at least ``min_gain``: a flat curve
    (little vessel running along the epipolar lines) locates nothing; nor does a fit that ends at the
    edge of the search range (± ``MAX_SHIFT_MM``), which says the profiles match nowhere inside it.
    ``prior_per_px`` adds that much mismatch per pixel of shift, to the joint fit and to each pair's
    refinement: where curves are flat or have several minima (a catheter, one view's vessel overlapping
    another) the smaller motion wins, since the heart moves little between two runs most of the time.
    """
    ok = [i for i, c in enumerate(curves) if np.isfinite(c.mismatch).any()]
    if not ok:
        return [ViewShift.none() for _ in curves]
    fa = np.asarray(frames_a, float) - np.mean(frames_a)
    fb = np.asarray(frames_b, float) - np.mean(frames_b)
    steps = curves[ok[0]].steps_px
    slopes = np.linspace(-slope_px, slope_px, 2 * int(round(slope_px / 0.05)) + 1)
    best, best_cost = (0.0, 0.0, 0.0), np.inf
    for a in slopes:
        for b in slopes:
            # cost of every intercept at once: each pair's curve read at intercept + its offset
            cost = np.zeros(len(steps))
            for i in ok:
                m = curves[i]
                cost += np.interp(steps + a * fb[i] - b * fa[i], m.steps_px, np.nan_to_num(m.mismatch, nan=1.0),
                                  left=1.0, right=1.0)
            cost += len(ok) * prior_per_px * np.abs(steps)
            j = int(np.argmin(cost))
            if cost[j] < best_cost - 1e-12:
                best, best_cost = (float(steps[j]), float(a), float(b)), float(cost[j])
    c, a, b = best
    limit = steps[-1] - window_px  # a best fit at the edge of the search range has not found a minimum
    out = []
    for i, m in enumerate(curves):
        if i not in ok:
            out.append(ViewShift.none())
            continue
        est = _shift(m, _refine(m, c + a * fb[i] - b * fa[i], window_px, prior_per_px))
        if est.mismatch_header - est.mismatch < min_gain or abs(c) >= limit or abs(est.across_px) >= limit:
            est = ViewShift.none(est.mismatch_header)
        out.append(est)
    return out
