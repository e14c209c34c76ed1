"""Two-view self-calibration from matched centreline points.

Reads/writes nothing: :func:`calibrate_pair` takes matched (row, col) points of the same 3D vessel
points in views A and B (from :func:`stages.twoview.match_views`, or any matcher) and the two header
cameras, and returns corrected cameras plus a report dict.

What two views can observe. The residual is the symmetric epipolar distance of every match (the
distance of each point from the epipolar line of its partner, in both images, in pixels); it depends
on the two cameras only through their fundamental matrix, so:

* a common rigid motion (and scale) of both cameras is a gauge freedom: run A is held fixed entirely
  (its shift, in-plane rotation, angles and SID), and only run B is corrected;
* a shift of B along its epipolar lines moves every triangulated point in depth and leaves every
  residual unchanged (the Jacobian column is exactly zero): **held fixed** (B's shift is fitted across
  its epipolar lines only; :data:`ALONG_EPIPOLAR` is reported as unobservable);
* one combination of B's in-plane rotation and angle corrections (a turn of B that mostly changes the
  angle between the views, i.e. the depth scale) is only weakly observable; a weak prior towards the
  header (:data:`PRIOR_SIGMA`) keeps it from wandering under noise;
* the rest — B's shift across the epipolar lines, its in-plane rotation, dα, dβ and dSID — is fitted
  with a robust loss (soft-L1, :data:`F_SCALE_PX`), several starts, and bounds (:data:`DEFAULT_BOUNDS`).

A correction is refused (the header cameras are returned, with a warning) when it does not lower the
residual or when a parameter ends at its bound.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from ..core.errors import UserError
from ..core.geometry import Camera
from .model import DEFAULT_BOUNDS, Correction, apply_correction, triangulate

log = logging.getLogger(__name__)

__all__ = ["PairCalibration", "calibrate_pair", "epipolar_residuals", "fundamental_matrix", "pair_residual",
           "MIN_POINTS", "MIN_ANGLE_DEG", "check_pair_geometry"]

MIN_POINTS = 20  # fewer matched points: refuse (5 parameters, and a robust loss needs redundancy)
MIN_ANGLE_DEG = 10.0  # views closer than this: the epipolar geometry is too flat to calibrate on
F_SCALE_PX = 1.0  # soft-L1 scale: residuals beyond ~1 px count linearly (outlier matches)
PRIOR_SIGMA = {"across_px": None, "inplane_deg": 2.0, "dalpha_deg": 3.0, "dbeta_deg": 3.0, "dsid_mm": 20.0}
ALONG_EPIPOLAR = "shift of run B along its epipolar lines (equivalent to depth)"
BOUND_TOL = 1e-3  # a parameter within this fraction of its range from a bound counts as "at the bound"
INLIER_PX = 3.0  # second pass: matches with an epipolar distance beyond this (or 3 robust sd) are dropped
FREE = ("across_px", "inplane_deg", "dalpha_deg", "dbeta_deg", "dsid_mm")


def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """F with x_bᵀ·F·x_a = 0 for homogeneous (col, row, 1) pixels of the same 3D point."""
    Pa, Pb = cam_a.matrix, cam_b.matrix
    e = Pb @ np.append(cam_a.source, 1.0)
    ex = np.array([[0.0, -e[2], e[1]], [e[2], 0.0, -e[0]], [-e[1], e[0], 0.0]])
    return ex @ Pb @ np.linalg.pinv(Pa)


def _homogeneous(rc: np.ndarray) -> np.ndarray:
    return np.stack([rc[:, 1], rc[:, 0], np.ones(len(rc))], 1)


def epipolar_residuals(cam_a: Camera, cam_b: Camera, rc_a, rc_b) -> np.ndarray:
    """Signed distances (px) of each B point from the epipolar line of its A partner, then of each A
    point from the line of its B partner: a 2N vector."""
    F = fundamental_matrix(cam_a, cam_b)
    ha, hb = _homogeneous(np.asarray(rc_a, float)), _homogeneous(np.asarray(rc_b, float))
    lb = ha @ F.T
    la = hb @ F
    db = np.sum(hb * lb, 1) / np.maximum(np.linalg.norm(lb[:, :2], axis=1), 1e-12)
    da = np.sum(ha * la, 1) / np.maximum(np.linalg.norm(la[:, :2], axis=1), 1e-12)
    return np.concatenate([db, da])


def pair_residual(cam_a: Camera, cam_b: Camera, rc_a, rc_b) -> dict:
    """Residual summary of a pair: mean |epipolar distance| and mean reprojection distance of the
    triangulated matches, in px and in mm at the isocentre (mean of the two views' isocentre spacings)."""
    rc_a, rc_b = np.asarray(rc_a, float), np.asarray(rc_b, float)
    mm = 0.5 * (cam_a.isocentre_spacing + cam_b.isocentre_spacing)
    e = np.abs(epipolar_residuals(cam_a, cam_b, rc_a, rc_b))
    X = triangulate(cam_a, cam_b, rc_a, rc_b)
    ra = np.linalg.norm(cam_a.project(X) - rc_a, axis=1)
    rb = np.linalg.norm(cam_b.project(X) - rc_b, axis=1)
    rep = np.concatenate([ra, rb])
    rep = rep[np.isfinite(rep)]
    return {"epipolar_px": float(e.mean()), "epipolar_mm": float(e.mean() * mm),
            "epipolar_median_px": float(np.median(e)),
            "reprojection_px": float(rep.mean()) if len(rep) else float("nan"),
            "reprojection_mm": float(rep.mean() * mm) if len(rep) else float("nan"),
            "inlier_fraction": float(np.mean(e < 3.0))}


def _across_direction(cam_a: Camera, cam_b: Camera) -> np.ndarray:
    """Unit (row, col) direction in B across its epipolar line through the image centre."""
    F = fundamental_matrix(cam_a, cam_b)
    centre = np.array([(cam_b.rows - 1) / 2.0, (cam_b.cols - 1) / 2.0])
    # the epipolar line in B through the centre: the image of the ray of A that lands there
    la = F.T @ np.array([centre[1], centre[0], 1.0])  # line in A
    # a point of A on that line near A's centre, mapped back to its line in B
    ca = np.array([(cam_a.cols - 1) / 2.0, (cam_a.rows - 1) / 2.0, 1.0])
    n = la[:2] / np.linalg.norm(la[:2])
    xa = ca - (la @ ca) / np.linalg.norm(la[:2]) * np.append(n, 0.0)
    lb = F @ xa
    normal_colrow = lb[:2] / np.linalg.norm(lb[:2])  # normal of the line in (col, row)
    return np.array([normal_colrow[1], normal_colrow[0]])


def check_pair_geometry(cam_a: Camera, cam_b: Camera, n_points: int, names=("A", "B")) -> float:
    """Refuse a pair that cannot be calibrated (views too close, too few points); returns their angle (deg)."""
    cosang = float(np.clip(np.dot(cam_a.view_dir, cam_b.view_dir) /
                           (np.linalg.norm(cam_a.view_dir) * np.linalg.norm(cam_b.view_dir)), -1, 1))
    angle = math.degrees(math.acos(cosang))
    if angle < MIN_ANGLE_DEG:
        raise UserError(f"calibration: runs {names[0]} and {names[1]} are only {angle:.1f}° apart "
                        f"(< {MIN_ANGLE_DEG:g}°): their epipolar geometry is too flat to calibrate on "
                        "(use --no-calibrate)")
    if n_points < MIN_POINTS:
        raise UserError(f"calibration: runs {names[0]} and {names[1]} share only {n_points} matched vessel "
                        f"points (< {MIN_POINTS}): too few to calibrate on (use --no-calibrate)")
    return angle


@dataclass
class PairCalibration:
    """Corrected cameras of a pair, the correction of run B, and the report."""

    cam_a: Camera
    cam_b: Camera
    correction_b: Correction
    applied: bool
    report: dict = field(default_factory=dict)


def _bounds(cam_b: Camera, bounds: dict) -> tuple[np.ndarray, np.ndarray]:
    shift_px = bounds["shift_mm"] / cam_b.isocentre_spacing
    hi = np.array([shift_px, bounds["inplane_deg"], bounds["angle_deg"], bounds["angle_deg"], bounds["dsid_mm"]])
    return -hi, hi


def _correction(x: np.ndarray, u: np.ndarray) -> Correction:
    """Free parameters (across, θ, dα, dβ, dSID) → full correction (shift = across·u)."""
    return Correction(float(x[0] * u[0]), float(x[0] * u[1]), float(x[1]), float(x[2]), float(x[3]), float(x[4]))


def calibrate_pair(points_a, points_b, cam_a: Camera, cam_b: Camera, *, bounds: dict | None = None,
                   starts: int = 5, names=("A", "B"), f_scale_px: float = F_SCALE_PX,
                   prior_weight: float = 1.0) -> PairCalibration:
    """Correct run B's camera (run A fixed) so that matched centreline points agree epipolarly.

    ``points_a``, ``points_b``: N×2 (row, col) sub-pixel positions of the same 3D points in views A and B
    (outliers allowed: robust loss). ``bounds``: see :data:`~stages.calibration.model.DEFAULT_BOUNDS`
    (shift in mm at the isocentre, angles in degrees, dSID in mm). ``starts``: number of starting points
    (the header, then deterministic spreads of the angle corrections). ``prior_weight``: weight of the
    prior towards the header (0: none — exact recovery on noise-free matches). Raises :class:`UserError` for a
    degenerate pair (views < 10° apart, fewer than 20 points).

    Returns :class:`PairCalibration`; ``report`` holds ``corrections`` (per run, :meth:`Correction.to_dict`),
    ``residual_before``/``residual_after`` (:func:`pair_residual`), ``applied``, ``warnings``,
    ``free_dofs``/``fixed_dofs`` and ``seconds``.
    """
    from scipy.optimize import least_squares

    t0 = time.perf_counter()
    pa, pb = np.asarray(points_a, float), np.asarray(points_b, float)
    if pa.ndim != 2 or pa.shape[1] != 2 or pa.shape != pb.shape:
        raise UserError(f"calibration: matched points must be two N×2 arrays of equal size, got {pa.shape} and {pb.shape}")
    ok = np.all(np.isfinite(pa), 1) & np.all(np.isfinite(pb), 1)
    pa, pb = pa[ok], pb[ok]
    angle = check_pair_geometry(cam_a, cam_b, len(pa), names)
    bounds = dict(DEFAULT_BOUNDS, **(bounds or {}))
    lo, hi = _bounds(cam_b, bounds)
    u = _across_direction(cam_a, cam_b)
    sig = np.array([hi[0] * 10.0, PRIOR_SIGMA["inplane_deg"], PRIOR_SIGMA["dalpha_deg"], PRIOR_SIGMA["dbeta_deg"],
                    PRIOR_SIGMA["dsid_mm"]])
    scale = np.array([1.0, 0.1, 0.1, 0.1, 5.0])  # typical step per parameter for the optimiser

    def fun(x):
        cb = apply_correction(cam_b, _correction(x, u))
        return np.concatenate([epipolar_residuals(cam_a, cb, pa, pb), prior_weight * x / sig])

    rng = np.random.default_rng(0)
    x0s = [np.zeros(5)]
    for _ in range(max(0, starts - 1)):
        x = np.zeros(5)
        x[1:4] = rng.uniform(-0.5, 0.5, 3) * hi[1:4]
        x[4] = rng.uniform(-0.5, 0.5) * hi[4]
        x0s.append(x)
    best = None
    for x0 in x0s:
        r = least_squares(fun, x0, bounds=(lo, hi), loss="soft_l1", f_scale=f_scale_px, x_scale=scale,
                          method="trf", max_nfev=200)
        if best is None or r.cost < best.cost:
            best = r
    # second pass on the inliers: soft-L1 still pulls linearly on gross outliers (wrong matches), and the
    # weakly observable rotation follows that pull; refit from the best start without them
    e = np.abs(epipolar_residuals(cam_a, apply_correction(cam_b, _correction(best.x, u)), pa, pb)).reshape(2, -1)
    keep = np.max(e, 0) <= max(INLIER_PX, 3.0 * 1.4826 * float(np.median(e)))
    n_inliers = int(keep.sum())
    if MIN_POINTS <= n_inliers < len(pa):
        pa_all, pb_all = pa, pb
        pa, pb = pa[keep], pb[keep]
        best = least_squares(fun, best.x, bounds=(lo, hi), loss="soft_l1", f_scale=f_scale_px, x_scale=scale,
                             method="trf", max_nfev=200)
        pa, pb = pa_all, pb_all
    x = best.x
    corr = _correction(x, u)
    cb_new = apply_correction(cam_b, corr)
    before = pair_residual(cam_a, cam_b, pa, pb)
    after = pair_residual(cam_a, cb_new, pa, pb)
    warnings = []
    rng_width = hi - lo
    at_bound = [name for name, v, l, h, w in zip(FREE, x, lo, hi, rng_width)
                if min(v - l, h - v) <= BOUND_TOL * w]
    if at_bound:
        warnings.append(f"calibration of {names[1]} refused: {', '.join(at_bound)} "
                        f"{'reached its bound' if len(at_bound) == 1 else 'reached their bounds'} "
                        f"(bounds: shift ±{bounds['shift_mm']:g} mm, in-plane ±{bounds['inplane_deg']:g}°, "
                        f"angles ±{bounds['angle_deg']:g}°, SID ±{bounds['dsid_mm']:g} mm); header geometry kept")
    if not after["epipolar_px"] < before["epipolar_px"]:
        warnings.append(f"calibration of {names[1]} refused: residual {after['epipolar_px']:.3f} px after "
                        f"≥ {before['epipolar_px']:.3f} px before; header geometry kept")
    applied = not warnings
    for w in warnings:
        log.warning(w)
    if not applied:
        corr_out, cb_out = Correction(), cam_b
    else:
        corr_out, cb_out = corr, cb_new
    report = {
        "method": "pair-epipolar",
        "runs": list(names),
        "reference_run": names[0],
        "views_angle_deg": round(angle, 2),
        "n_points": int(len(pa)),
        "n_inliers": n_inliers,
        "applied": applied,
        "corrections": {names[0]: Correction().to_dict(cam_a), names[1]: corr_out.to_dict(cam_b)},
        "proposed_correction": corr.to_dict(cam_b),
        "residual_before": before,
        "residual_after": after if applied else before,
        "residual_proposed": after,
        "free_dofs": [f"{names[1]}: shift across its epipolar lines", f"{names[1]}: in-plane rotation",
                      f"{names[1]}: dalpha", f"{names[1]}: dbeta", f"{names[1]}: dSID"],
        "fixed_dofs": [f"{names[0]}: all six (reference run; a common motion of both runs is a gauge freedom)",
                       f"{names[1]}: {ALONG_EPIPOLAR}"],
        "weakly_observable": "one combination of the rotation corrections of run B (the angle between the "
                             "views ↔ depth scale), held near the header by a weak prior",
        "bounds": bounds,
        "warnings": warnings,
        "seconds": round(time.perf_counter() - t0, 3),
    }
    return PairCalibration(cam_a, cb_out, corr_out, applied, report)
