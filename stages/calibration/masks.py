"""Calibrating a pair of runs from their vessel masks: :func:`calibrate_masks`.

Reads/writes nothing. Two routes:

* ``crossing-profile`` (the default) — the shift of run B across its epipolar lines that makes the two
  views' epipolar crossing profiles overlap most (:func:`profile_overlap_curve` over ±``shift_mm``). Two centreline images without independent correspondences carry only this degree of
  freedom: every other one is held at the header;
* ``matches`` — matched centreline points from :func:`stages.twoview.match_views` fed to
  :func:`stages.calibration.pair.calibrate_pair`, then matched again under the corrected geometry. Note
  that those matches are chosen *on* the epipolar lines of the current geometry, so their epipolar
  residual is ~0 by construction (measured on the phantom: median 1e-5 px) and they cannot move the
  calibration; the route is kept for matches made independently of the geometry (landmarks, bifurcations).
"""

from __future__ import annotations

import logging
import time

import numpy as np

from ..core.errors import UserError
from ..core.geometry import Camera, epipolar_angles, epipolar_frame
from .model import DEFAULT_BOUNDS, Correction, apply_correction
from .pair import MIN_POINTS, PairCalibration, calibrate_pair, check_pair_geometry

log = logging.getLogger(__name__)

__all__ = ["calibrate_masks", "profile_overlap_curve", "MIN_PROFILE_GAIN"]

MIN_PROFILE_GAIN = 0.01  # crossing-profile route: the shift must raise the profile overlap by this much
PROFILE_SHIFT_MM = 30.0  # search range (mm at the isocentre): wider ranges meet spurious peaks (phantom IM1+IM3: 29 mm)
STEP_MM = 0.5  # trial shifts of the crossing-profile route (mm at the isocentre)
PROFILE_SMOOTH_BINS = 2.0  # Gaussian smoothing of the crossing profiles (bins of one view-B pixel)


def profile_overlap_curve(mask_a, mask_b, cam_a: Camera, cam_b: Camera, max_shift_mm: float, step_mm: float = STEP_MM):
    """(trial shifts px along ``direction``, overlap score per shift, direction): the overlap of the two
    views' epipolar crossing profiles as run B's image is shifted across its epipolar lines; None when
    either mask has too little centreline.

    The crossing profile of a view is the histogram, over the epipolar-plane angle, of its centreline
    pixels weighted by how many planes each crosses (:mod:`stages.view_alignment`: independent of
    foreshortening and magnification); with the geometry right, each plane cuts the tree in as many
    points in both views. The score is the histogram intersection Σ min(h_A, h_B) / max(Σ h_A, Σ h_B):
    the share of vessel that can find a partner on its epipolar line. (Measured on the phantom's 28 pairs
    against the 8-run joint calibration: median residual 0.86 mm, where the correlation of the profiles
    used for heart motion, :func:`stages.view_alignment.mismatch_curve`, gave 1.2 mm and failed on the
    pairs with IM6.)
    """
    from scipy import ndimage

    from .. import view_alignment as va

    frame = epipolar_frame(cam_a, cam_b)
    u, rate = va._across_direction(cam_b, frame)
    ia = va._crossing_profile_inputs(np.asarray(mask_a, bool), cam_a, frame)
    ib = va._crossing_profile_inputs(np.asarray(mask_b, bool), cam_b, frame)
    if ia is None or ib is None:
        return None
    _, theta_a, dens_a = ia
    px_b, _, dens_b = ib
    edges = np.arange(theta_a.min() - va.MARGIN_PX * rate, theta_a.max() + (va.MARGIN_PX + 1) * rate, rate)
    h_a = ndimage.gaussian_filter1d(np.histogram(theta_a, edges, weights=dens_a)[0], PROFILE_SMOOTH_BINS)
    sp = cam_b.isocentre_spacing
    steps = np.arange(-max_shift_mm, max_shift_mm + 1e-9, step_mm) / sp
    score = np.empty(len(steps))
    for k, t in enumerate(steps):
        th = epipolar_angles(cam_b.shifted(*(t * u)), px_b, frame)
        h_b = ndimage.gaussian_filter1d(np.histogram(th, edges, weights=dens_b)[0], PROFILE_SMOOTH_BINS)
        score[k] = np.minimum(h_a, h_b).sum() / max(h_a.sum(), h_b.sum(), 1e-12)
    return steps, score, u


def _profile_route(mask_a, mask_b, cam_a: Camera, cam_b: Camera, names, bounds: dict, t0: float,
                   note: str = "") -> PairCalibration:
    bounds = dict(bounds, shift_mm=min(bounds["shift_mm"], PROFILE_SHIFT_MM))
    curve = profile_overlap_curve(mask_a, mask_b, cam_a, cam_b, bounds["shift_mm"])
    base = {"method": "crossing-profile", "runs": list(names), "reference_run": names[0],
            "free_dofs": [f"{names[1]}: shift across its epipolar lines"],
            "fixed_dofs": [f"{names[0]}: all six (reference run)",
                           f"{names[1]}: shift along its epipolar lines (↔ depth), in-plane rotation, angles, SID "
                           "(two centreline images without correspondences carry only the across-epipolar shift)"],
            "bounds": bounds}
    if note:
        base["note"] = note
    if curve is None:
        raise UserError(f"calibration: runs {names[0]} and {names[1]} have too little vessel centreline to "
                        "calibrate on (use --no-calibrate)")
    steps, score, u = curve
    k = int(np.argmax(score))
    s = float(steps[k])
    if 0 < k < len(steps) - 1:  # parabola through the peak
        y0, y1, y2 = score[k - 1:k + 2]
        curv = y0 - 2 * y1 + y2
        if curv < 0:
            s += 0.5 * (steps[1] - steps[0]) * (y0 - y2) / curv
    d = s * u
    corr = Correction(float(d[0]), float(d[1]))
    before = float(np.interp(0.0, steps, score))
    after = float(np.interp(s, steps, score))
    warnings = []
    if k in (0, len(steps) - 1) or abs(s) >= steps[-1] - (steps[1] - steps[0]):
        warnings.append(f"calibration of {names[1]} refused: its shift ({s * cam_b.isocentre_spacing:.1f} mm) "
                        f"reached the bound ±{bounds['shift_mm']:g} mm; header geometry kept")
    if not after >= before + MIN_PROFILE_GAIN:
        warnings.append(f"calibration of {names[1]} refused: crossing-profile overlap {after:.3f} after vs "
                        f"{before:.3f} before (needs a gain of {MIN_PROFILE_GAIN}); header geometry kept")
    for w in warnings:
        log.warning(w)
    applied = not warnings
    corr_out = corr if applied else Correction()
    report = dict(base, applied=applied, n_points=None,
                  corrections={names[0]: Correction().to_dict(cam_a), names[1]: corr_out.to_dict(cam_b)},
                  proposed_correction=corr.to_dict(cam_b),
                  residual_before={"profile_overlap": round(before, 4)},
                  residual_after={"profile_overlap": round(after if applied else before, 4)},
                  warnings=warnings, seconds=round(time.perf_counter() - t0, 3))
    return PairCalibration(cam_a, apply_correction(cam_b, corr_out), corr_out, applied, report)


def calibrate_masks(mask_a, mask_b, cam_a: Camera, cam_b: Camera, *, names=("A", "B"), prob_a=None, prob_b=None,
                    bounds: dict | None = None, rounds: int = 2, route: str = "auto") -> PairCalibration:
    """Calibrate run B against run A (fixed) from their vessel masks (H×W bool); see the module doc.

    ``route``: ``crossing-profile`` (``auto`` is the same) or ``matches``. Raises :class:`UserError` for a degenerate pair (views < 10° apart, too little
    vessel). Returns :class:`~stages.calibration.pair.PairCalibration` (``report["method"]`` names the route).
    """
    t0 = time.perf_counter()
    bounds = dict(DEFAULT_BOUNDS, **(bounds or {}))
    check_pair_geometry(cam_a, cam_b, MIN_POINTS, names)
    if route not in ("auto", "crossing-profile", "matches"):
        raise UserError(f"calibration: unknown route {route!r} (crossing-profile | matches)")
    use_matches = route == "matches"
    if not use_matches:
        return _profile_route(mask_a, mask_b, cam_a, cam_b, names, bounds, t0)
    from ..twoview import match_views

    cb = cam_b
    result = None
    for _ in range(max(1, rounds)):
        m = match_views(mask_a, mask_b, cam_a, cb, prob_a=prob_a, prob_b=prob_b)
        pa, pb = np.asarray(m.points_a, float), np.asarray(m.points_b, float)
        if len(pa) < MIN_POINTS:
            if result is not None:
                break
            return _profile_route(mask_a, mask_b, cam_a, cam_b, names, bounds, t0,
                                  note=f"two-view matching found {len(pa)} points (< {MIN_POINTS})")
        # the matches were made under camera cb; calibrate the header camera of B on them
        r = calibrate_pair(pa, pb, cam_a, cam_b, bounds=bounds, names=names)
        if result is not None and not r.applied:
            break
        result = r
        if not r.applied:
            break
        cb = r.cam_b
    result.report["method"] = "pair-epipolar (twoview matches)"
    result.report["seconds"] = round(time.perf_counter() - t0, 3)
    return result
