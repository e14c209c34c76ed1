"""Calibrating a pair of runs from their vessel masks: :func:`calibrate_masks`.

Reads/writes nothing. Two routes:

* ``crossing-profile`` (the default) — the shift of run B across its epipolar lines that makes the two
  views' epipolar crossing profiles agree (:func:`stages.view_alignment.mismatch_curve` over
  ±``shift_mm``). Two centreline images without independent correspondences carry only this degree of
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

from ..errors import UserError
from ..geometry import Camera
from .model import DEFAULT_BOUNDS, Correction, apply_correction
from .pair import MIN_POINTS, PairCalibration, calibrate_pair, check_pair_geometry

log = logging.getLogger(__name__)

__all__ = ["calibrate_masks", "twoview_available", "MIN_PROFILE_GAIN"]

MIN_PROFILE_GAIN = 0.02  # crossing-profile route: the shift must lower the mismatch by this much


def twoview_available() -> bool:
    try:
        from ..twoview import match_views  # noqa: F401
    except ImportError:
        return False
    return True


def _profile_route(mask_a, mask_b, cam_a: Camera, cam_b: Camera, names, bounds: dict, t0: float,
                   note: str = "") -> PairCalibration:
    from ..view_alignment import _refine, mismatch_curve

    curve = mismatch_curve(mask_a, mask_b, cam_a, cam_b, max_shift_mm=bounds["shift_mm"])
    base = {"method": "crossing-profile", "runs": list(names), "reference_run": names[0],
            "free_dofs": [f"{names[1]}: shift across its epipolar lines"],
            "fixed_dofs": [f"{names[0]}: all six (reference run)",
                           f"{names[1]}: shift along its epipolar lines (↔ depth), in-plane rotation, angles, SID "
                           "(two centreline images without correspondences carry only the across-epipolar shift)"],
            "bounds": bounds}
    if note:
        base["note"] = note
    if not np.isfinite(curve.mismatch).any():
        raise UserError(f"calibration: runs {names[0]} and {names[1]} have too little vessel centreline to "
                        "calibrate on (use --no-calibrate)")
    s = _refine(curve, 0.0, np.inf)
    d = s * curve.direction
    corr = Correction(float(d[0]), float(d[1]))
    before, after = float(curve.at_header), float(curve.at(s))
    reach = curve.steps_px[-1]
    warnings = []
    if abs(s) >= reach - 0.5 * (curve.steps_px[1] - curve.steps_px[0]):
        warnings.append(f"calibration of {names[1]} refused: its shift ({s * cam_b.isocentre_spacing:.1f} mm) "
                        f"reached the bound ±{bounds['shift_mm']:g} mm; header geometry kept")
    if not after < before - MIN_PROFILE_GAIN:
        warnings.append(f"calibration of {names[1]} refused: crossing-profile mismatch {after:.3f} after vs "
                        f"{before:.3f} before (needs a gain of {MIN_PROFILE_GAIN}); header geometry kept")
    for w in warnings:
        log.warning(w)
    applied = not warnings
    corr_out = corr if applied else Correction()
    report = dict(base, applied=applied, n_points=None,
                  corrections={names[0]: Correction().to_dict(cam_a), names[1]: corr_out.to_dict(cam_b)},
                  proposed_correction=corr.to_dict(cam_b),
                  residual_before={"crossing_mismatch": round(before, 4)},
                  residual_after={"crossing_mismatch": round(after if applied else before, 4)},
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
