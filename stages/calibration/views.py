"""Fitting one view's pose to a fixed 3D model by chamfer, without matches.

Reads/writes nothing. The residual of a view is the distance (px), looked up bilinearly in the distance
transform of the view's 2D centreline, at the projection of each 3D model point: no correspondences
are needed. Used by the held-out check (a held-out view's bounded 6-DoF pose fitted to a
reconstruction, the reconstruction fixed) and by the joint calibration of static multi-run scenes.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from ..core.geometry import Camera
from .model import Correction, apply_correction

__all__ = ["Pose6", "apply_pose", "centreline_distance_map", "chamfer_residuals", "fit_view_pose", "fit_view_correction",
           "POSE_BOUNDS"]

POSE_BOUNDS = {"rotation_deg": 5.0, "translation_mm": 20.0, "depth_mm": 10.0}
# weak prior towards the header pose (one model point's worth): a rotation about the isocentre and a
# translation across the view move a compact object's image almost alike, and a translation along the
# view only magnifies it slightly; the prior keeps these near-degenerate combinations near zero
POSE_PRIOR_SIGMA = np.array([3.0, 3.0, 3.0, 10.0, 10.0, 5.0])
CAP_PX = 25.0  # distance-map values are capped here (a point far from any vessel counts as this far)
F_SCALE_PX = 2.0


@dataclass
class Pose6:
    """A rigid motion of one C-arm: rotation about the isocentre (dα, dβ, in-plane, deg) then a translation
    of source and detector together along the camera's own (column, row, viewing) axes (mm)."""

    dalpha_deg: float = 0.0
    dbeta_deg: float = 0.0
    inplane_deg: float = 0.0
    t_col_mm: float = 0.0
    t_row_mm: float = 0.0
    t_view_mm: float = 0.0

    def vector(self) -> np.ndarray:
        return np.array([self.dalpha_deg, self.dbeta_deg, self.inplane_deg, self.t_col_mm, self.t_row_mm,
                         self.t_view_mm], float)

    def to_dict(self) -> dict:
        return {k: round(float(v), 4) for k, v in zip(
            ("dalpha_deg", "dbeta_deg", "inplane_deg", "t_col_mm", "t_row_mm", "t_view_mm"), self.vector())}


def apply_pose(cam: Camera, pose) -> Camera:
    """The camera moved rigidly by a :class:`Pose6` (or its 6-vector)."""
    p = pose.vector() if isinstance(pose, Pose6) else np.asarray(pose, float)
    rot = apply_correction(cam, Correction(0.0, 0.0, p[2], p[0], p[1], 0.0))
    t = p[3] * rot.R[0] + p[4] * rot.R[1] + p[5] * rot.R[2]
    return Camera(K=rot.K, R=rot.R, source=rot.source + t, rows=cam.rows, cols=cam.cols, carm=None)


def centreline_distance_map(centreline: np.ndarray, cap_px: float = CAP_PX) -> np.ndarray:
    """Distance (px) from every pixel to the nearest centreline pixel, capped at ``cap_px``."""
    cl = np.asarray(centreline, bool)
    if not cl.any():
        return np.full(cl.shape, float(cap_px))
    return np.minimum(ndimage.distance_transform_edt(~cl), cap_px)


def chamfer_residuals(points3d: np.ndarray, cam: Camera, dist_map: np.ndarray, fov=None,
                      cap_px: float = CAP_PX) -> np.ndarray:
    """Per model point: the distance-map value (px) at its projection; ``cap_px`` outside the image or the
    field of view ``fov`` (H×W bool)."""
    rc = cam.project(points3d)
    ok = np.all(np.isfinite(rc), 1) & cam.in_image(rc)
    out = np.full(len(rc), float(cap_px))
    if ok.any():
        out[ok] = ndimage.map_coordinates(dist_map, rc[ok].T, order=1, mode="nearest")
        if fov is not None:
            r = np.clip(np.rint(rc[ok, 0]).astype(int), 0, cam.rows - 1)
            c = np.clip(np.rint(rc[ok, 1]).astype(int), 0, cam.cols - 1)
            inside = np.asarray(fov, bool)[r, c]
            vals = out[ok]
            vals[~inside] = cap_px
            out[ok] = vals
    return out


def _robust_cost(res: np.ndarray, f: float = F_SCALE_PX) -> float:
    z = (res / f) ** 2
    return float(np.sum(2.0 * f * f * (np.sqrt(1.0 + z) - 1.0)))


def _reverse_residuals(X, cam: Camera, target_px: np.ndarray, cap_px: float = CAP_PX) -> np.ndarray:
    """Distance (px) from each target pixel (the view's centreline) to the nearest projected model point."""
    from scipy.spatial import cKDTree

    rc = cam.project(X)
    rc = rc[np.all(np.isfinite(rc), 1)]
    if len(rc) == 0:
        return np.full(len(target_px), float(cap_px))
    d, _ = cKDTree(rc).query(target_px, distance_upper_bound=cap_px)
    return np.minimum(d, cap_px)


def _fit(X, cam: Camera, dist_map, fov, apply, hi, sigma, x_scale, starts, target_px=None):
    """Bounded robust chamfer fit of ``apply(cam, p)``; returns (p, residuals before, residuals after).
    ``target_px``: the view's centreline pixels, for the reverse term (symmetric chamfer)."""
    from scipy.optimize import least_squares

    n = len(hi)

    def data(p):
        return chamfer_residuals(X, apply(cam, p), dist_map, fov)

    w = 0.0 if target_px is None else np.sqrt(len(X) / max(len(target_px), 1))

    def res(p):
        c = apply(cam, p)
        parts = [chamfer_residuals(X, c, dist_map, fov)]
        if target_px is not None:
            parts.append(w * _reverse_residuals(X, c, target_px))
        return np.concatenate(parts + [p / sigma])

    r0 = data(np.zeros(n))
    ranked = sorted(((_robust_cost(data(p)), tuple(p)) for p in starts), key=lambda s: s[0])
    best = None
    for p0 in [np.zeros(n)] + [np.array(p) for _, p in ranked[:3]]:
        fit = least_squares(res, p0, bounds=(-hi, hi), loss="soft_l1", f_scale=F_SCALE_PX, x_scale=x_scale,
                            diff_step=1e-3, max_nfev=100)
        if best is None or fit.cost < best.cost:
            best = fit
    return best.x, r0, data(best.x)


def _subsample(points3d, max_points: int, seed: int) -> np.ndarray:
    X = np.asarray(points3d, float)
    if len(X) > max_points:
        X = X[np.random.default_rng(seed).choice(len(X), max_points, replace=False)]
    return X


def fit_view_pose(points3d, cam: Camera, dist_map: np.ndarray, fov=None, bounds: dict | None = None,
                  grid_mm: float = 4.0, max_points: int = 4000, seed: int = 0,
                  centreline=None) -> tuple[Camera, Pose6, dict]:
    """Bounded 6-DoF pose of one view fitted to fixed 3D model points (chamfer onto ``dist_map``).

    Multi-start: the robust cost is evaluated on a grid of translations across the view (``grid_mm`` steps
    within ¾ of the translation bound), and the three best starts (and the header) are refined with a
    bounded soft-L1 least squares and a weak prior (:data:`POSE_PRIOR_SIGMA`). Bounds
    (:data:`POSE_BOUNDS`): rotation ±5°, translation across the view ±20 mm, along it ±10 mm. Returns
    (fitted camera, pose, report with ``cost_before_px``/``cost_after_px`` — mean capped chamfer, px);
    ``centreline`` (H×W bool, the view's centreline): add the reverse term (each centreline pixel's distance
    to the nearest projected model point, weighted to the same total), a symmetric chamfer that keeps the
    fit from shrinking the projection onto part of the view;
    the header camera and a zero pose when the fit does not lower the cost.
    """
    b = dict(POSE_BOUNDS, **(bounds or {}))
    X = _subsample(points3d, max_points, seed)
    hi = np.array([b["rotation_deg"]] * 3 + [b["translation_mm"]] * 2 + [b["depth_mm"]])
    g = np.arange(-0.75 * b["translation_mm"], 0.75 * b["translation_mm"] + 1e-9, grid_mm)
    starts = [np.array([0.0, 0.0, 0.0, tc, tr, 0.0]) for tc in g for tr in g]
    target = None
    if centreline is not None:
        target = np.argwhere(np.asarray(centreline, bool)).astype(float)
        if len(target) > max_points:
            target = target[np.random.default_rng(seed).choice(len(target), max_points, replace=False)]
    x, r0, r1 = _fit(X, cam, dist_map, fov, apply_pose, hi, POSE_PRIOR_SIGMA,
                     np.array([0.2, 0.2, 0.2, 1.0, 1.0, 5.0]), starts, target)
    report = {"cost_before_px": float(r0.mean()), "cost_after_px": float(r1.mean()), "n_points": int(len(X))}
    if not _robust_cost(r1) < _robust_cost(r0):
        report.update(applied=False, pose=Pose6().to_dict())
        return cam, Pose6(), report
    pose = Pose6(*x)
    at_bound = [k for k, v, h in zip(pose.to_dict(), x, hi) if abs(abs(v) - h) <= 1e-3 * h]
    report.update(applied=True, pose=pose.to_dict(), at_bound=at_bound,
                  translation_mm=float(math.hypot(x[3], x[4])))
    return apply_pose(cam, x), pose, report


def fit_view_correction(points3d, cam: Camera, dist_map: np.ndarray, fov=None, bounds: dict | None = None,
                        grid_mm: float | None = 3.0, max_points: int = 4000, seed: int = 0, free=None, start=None):
    """The run-correction model (:class:`~stages.calibration.model.Correction`: detector shift, in-plane
    rotation, dα, dβ, dSID) of one view fitted to fixed 3D model points by chamfer, as
    :func:`fit_view_pose` does for a rigid pose. Bounds: :data:`~stages.calibration.model.DEFAULT_BOUNDS`.
    ``free``: names of the parameters to fit (default: all six; e.g. ``("shift_row_px", "shift_col_px")`` for
    the shift-only model); the others stay at ``start`` (a :class:`Correction`, default zero).
    Returns (camera, correction, report with ``cost_before_px``, ``cost_after_px``, ``at_bound``)."""
    from .model import DOF
    from .model import DEFAULT_BOUNDS

    b = dict(DEFAULT_BOUNDS, **(bounds or {}))
    X = _subsample(points3d, max_points, seed)
    sp = cam.isocentre_spacing
    hi = np.array([b["shift_mm"] / sp] * 2 + [b["inplane_deg"], b["angle_deg"], b["angle_deg"], b["dsid_mm"]])
    sigma = np.array([10.0 / sp, 10.0 / sp, 2.0, 3.0, 3.0, 20.0])
    g = np.arange(-b["shift_mm"], b["shift_mm"] + 1e-9, grid_mm) / sp if grid_mm else np.zeros(0)
    starts = [np.array([r, c, 0.0, 0.0, 0.0, 0.0]) for r in g for c in g]
    idx = np.array([DOF.index(k) for k in (free or DOF)])
    base = (start or Correction()).vector()
    # the fit works on the offset from ``start`` in the free parameters; bounds apply to the total
    lo_t, hi_t = -hi[idx] - base[idx], hi[idx] - base[idx]

    def full(p):
        v = base.copy()
        v[idx] += p
        return v

    cam0 = cam
    x, r0, r1 = _fit(X, cam0, dist_map, fov, lambda c, p: apply_correction(c, full(p)),
                     np.maximum(np.abs(lo_t), np.abs(hi_t)), sigma[idx],
                     np.array([1.0, 1.0, 0.2, 0.2, 0.2, 5.0])[idx], [st[idx] - base[idx] for st in starts])
    v = np.clip(full(x), -hi, hi)
    r0 = chamfer_residuals(X, cam, dist_map, fov)  # the header's
    r1 = chamfer_residuals(X, apply_correction(cam, v), dist_map, fov)
    corr = Correction.from_vector(v)
    report = {"cost_before_px": float(r0.mean()), "cost_after_px": float(r1.mean()), "n_points": int(len(X)),
              "free": [DOF[i] for i in idx],
              "at_bound": [DOF[i] for i in idx if abs(abs(v[i]) - hi[i]) <= 1e-3 * hi[i]]}
    if not _robust_cost(r1) < _robust_cost(r0):
        return cam, Correction(), dict(report, applied=False)
    return apply_correction(cam, corr), corr, dict(report, applied=True)
