"""The per-run geometry correction of the calibration stage, and gauge-free measures of two-view geometry.

A correction of one run's camera has six parameters (:data:`DOF`), in interface units:

* ``shift_row_px``, ``shift_col_px`` — detector shift: the principal point moves by this many pixels,
  so every point projects that much further (an isocentre/table offset across the view, to first order);
* ``inplane_deg`` — in-plane rotation: the detector axes (c, r) turn by this angle about the viewing
  direction d (positive from c towards r); the image content turns by the opposite angle about the
  principal point;
* ``dalpha_deg``, ``dbeta_deg`` — primary/secondary angle corrections: the C-arm (source and detector
  together) rotates about the isocentre from the run's (α, β) to (α + dα, β + dβ), DESIGN.md §3;
* ``dsid_mm`` — magnification: the focal length (SID / detector spacing) scales by (SID + dSID) / SID,
  the source staying where it is (SOD unchanged).

The corrected camera is ``K'·R'·(X − S')`` with ``R' = Rz(θ)·R·Qᵀ``, ``S' = Q·S`` (Q the rotation of the
C-arm about the isocentre), ``K'`` the focal scaled and the principal point shifted. It works for any
:class:`~stages.core.geometry.Camera`; for a matrix camera the run's (α, β) are read off its viewing
direction and dSID is relative to :data:`DEFAULT_SID_MM`.

Reads/writes nothing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..core.geometry import Camera, carm_axes

__all__ = ["DOF", "DOF_UNITS", "DEFAULT_BOUNDS", "DEFAULT_SID_MM", "Correction", "apply_correction",
           "carm_angles", "effective_rotation", "relative_rotation_error_deg", "triangulate",
           "similarity_align", "relative_geometry_error", "isocentre_shift_camera"]

DOF = ("shift_row_px", "shift_col_px", "inplane_deg", "dalpha_deg", "dbeta_deg", "dsid_mm")
DOF_UNITS = {"shift_row_px": "px", "shift_col_px": "px", "inplane_deg": "deg", "dalpha_deg": "deg",
             "dbeta_deg": "deg", "dsid_mm": "mm"}
# Default bounds of a correction: shifts in mm at the isocentre (converted per camera), the rest as named.
# A correction of run B is relative to run A's header, so it must hold the errors of both runs: the
# benchmark injects up to ±10 mm (per axis), ±3° per angle, ±2° in-plane, ±20 mm SID in *each* run, i.e.
# up to 6° of relative angle, 4° in-plane and 40 mm of SID; the phantom's worst header (IM6) is 26 mm off.
DEFAULT_BOUNDS = {"shift_mm": 40.0, "inplane_deg": 5.0, "angle_deg": 8.0, "dsid_mm": 60.0}
DEFAULT_SID_MM = 1000.0  # reference SID of a matrix camera (no C-arm parameters) for dsid_mm


def carm_angles(cam: Camera) -> tuple[float, float]:
    """(α, β) in degrees of the camera's viewing direction d = (sin α cos β, −cos α cos β, sin β)."""
    d = cam.R[2] / np.linalg.norm(cam.R[2])
    beta = math.degrees(math.asin(float(np.clip(d[2], -1.0, 1.0))))
    alpha = math.degrees(math.atan2(float(d[0]), float(-d[1])))
    return alpha, beta


def _sid(cam: Camera) -> float:
    return float(cam.carm["sid"]) if cam.carm else DEFAULT_SID_MM


@dataclass
class Correction:
    """One run's correction (see the module doc); zeros = the header geometry."""

    shift_row_px: float = 0.0
    shift_col_px: float = 0.0
    inplane_deg: float = 0.0
    dalpha_deg: float = 0.0
    dbeta_deg: float = 0.0
    dsid_mm: float = 0.0

    @classmethod
    def from_vector(cls, v) -> "Correction":
        return cls(*[float(x) for x in v])

    def vector(self) -> np.ndarray:
        return np.array([getattr(self, k) for k in DOF], float)

    def is_zero(self) -> bool:
        return not np.any(self.vector())

    def to_dict(self, cam: Camera | None = None) -> dict:
        """The parameters, plus the shift in mm at the isocentre when the camera is given."""
        d = {k: round(float(getattr(self, k)), 4) for k in DOF}
        if cam is not None:
            sr, sc = cam.isocentre_spacing_rc()
            d["shift_mm"] = [round(self.shift_row_px * sr, 3), round(self.shift_col_px * sc, 3)]
            d["shift_mm_norm"] = round(float(math.hypot(self.shift_row_px * sr, self.shift_col_px * sc)), 3)
        return d


def apply_correction(cam: Camera, corr) -> Camera:
    """The camera after a :class:`Correction` (or its 6-vector in :data:`DOF` order)."""
    p = corr.vector() if isinstance(corr, Correction) else np.asarray(corr, float)
    dr, dc, th, da, db, dsid = (float(x) for x in p)
    a0, b0 = carm_angles(cam)
    A0, A1 = carm_axes(a0, b0), carm_axes(a0 + da, b0 + db)
    Q = A1.T @ A0  # rotation of the C-arm about the isocentre: A1 = A0·Qᵀ
    t = math.radians(th)
    Rz = np.array([[math.cos(t), math.sin(t), 0.0], [-math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
    R = Rz @ cam.R @ Q.T
    S = Q @ cam.source
    K = cam.K.copy()
    m = (_sid(cam) + dsid) / _sid(cam)
    K[0, 0] *= m
    K[1, 1] *= m
    K[0, 1] *= m
    K[0, 2] += dc
    K[1, 2] += dr
    carm = None
    if cam.carm is not None and dr == 0 and dc == 0 and th == 0:
        carm = dict(cam.carm, alpha=cam.carm["alpha"] + da, beta=cam.carm["beta"] + db, sid=cam.carm["sid"] + dsid)
    return Camera(K=K, R=R, source=S, rows=cam.rows, cols=cam.cols, carm=carm)


def isocentre_shift_camera(cam: Camera, shift_mm) -> Camera:
    """The camera whose whole C-arm (source and detector) is translated by ``shift_mm`` (world, mm):
    what an isocentre or table offset of that size does. Used to inject errors in the benchmark."""
    t = np.asarray(shift_mm, float)
    return Camera(K=cam.K.copy(), R=cam.R.copy(), source=cam.source + t, rows=cam.rows, cols=cam.cols, carm=None)


# ------------------------------------------------------------------------------------ gauge-free measures
def effective_rotation(cam: Camera) -> np.ndarray:
    """The camera's orientation with its principal-point offset folded in: the orthonormal part (polar
    decomposition) of K₀⁻¹·K·R, K₀ the same focal lengths with the principal point at the image centre.
    A detector shift and a small turn of the camera about its source then count alike."""
    K0 = np.array([[cam.K[0, 0], 0.0, (cam.cols - 1) / 2.0], [0.0, cam.K[1, 1], (cam.rows - 1) / 2.0], [0, 0, 1.0]])
    M = np.linalg.solve(K0, cam.K) @ cam.R
    U, _, Vt = np.linalg.svd(M)
    return U @ Vt


def relative_rotation_error_deg(cam_a: Camera, cam_b: Camera, true_a: Camera, true_b: Camera) -> float:
    """Angle (deg) between the relative orientation of B with respect to A and the true one
    (effective rotations, so a common rotation of both cameras — the gauge — does not count)."""
    rel = effective_rotation(cam_b) @ effective_rotation(cam_a).T
    rel_t = effective_rotation(true_b) @ effective_rotation(true_a).T
    D = rel @ rel_t.T
    return math.degrees(math.acos(float(np.clip((np.trace(D) - 1.0) / 2.0, -1.0, 1.0))))


def triangulate(cam_a: Camera, cam_b: Camera, rc_a, rc_b) -> np.ndarray:
    """Linear (DLT) triangulation of matched (row, col) points; N×3 world mm."""
    rc_a, rc_b = np.atleast_2d(np.asarray(rc_a, float)), np.atleast_2d(np.asarray(rc_b, float))
    Pa, Pb = cam_a.matrix, cam_b.matrix
    # rows u·P3 − P1, v·P3 − P2 with (u, v) = (col, row)
    A = np.stack([rc_a[:, 1, None] * Pa[2] - Pa[0], rc_a[:, 0, None] * Pa[2] - Pa[1],
                  rc_b[:, 1, None] * Pb[2] - Pb[0], rc_b[:, 0, None] * Pb[2] - Pb[1]], axis=1)
    # scale rows for conditioning
    A = A / np.linalg.norm(A, axis=2, keepdims=True)
    _, _, Vt = np.linalg.svd(A)
    X = Vt[:, -1, :]
    return X[:, :3] / X[:, 3:4]


def similarity_align(X, Y, scale: bool = True):
    """Least-squares s, R, t with s·R·X + t ≈ Y (Umeyama). Returns (aligned X, s, R, t)."""
    X, Y = np.asarray(X, float), np.asarray(Y, float)
    mx, my = X.mean(0), Y.mean(0)
    Xc, Yc = X - mx, Y - my
    U, S, Vt = np.linalg.svd(Yc.T @ Xc / len(X))
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    s = float(np.trace(np.diag(S) @ D) / Xc.var(0).sum()) if scale else 1.0
    t = my - s * R @ mx
    return s * X @ R.T + t, s, R, t


def relative_geometry_error(cam_a: Camera, cam_b: Camera, true_a: Camera, true_b: Camera, points=None) -> dict:
    """How well the pair (cam_a, cam_b) reproduces the true pair's relative geometry, free of the gauge.

    ``points`` (default: a 5 mm grid in a 100 mm cube at the isocentre) are projected by the true
    cameras, triangulated with (cam_a, cam_b), aligned to the true points by a similarity transform
    (the gauge two views cannot fix), and compared: ``rms_mm``. ``rotation_deg``: error of B's
    orientation relative to A (:func:`relative_rotation_error_deg`). ``rigid_rms_mm``: the same after
    a rigid alignment only.
    """
    if points is None:
        g = np.arange(-50.0, 50.01, 10.0)
        points = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    X = np.asarray(points, float)
    Y = triangulate(cam_a, cam_b, true_a.project(X), true_b.project(X))
    ok = np.all(np.isfinite(Y), axis=1)
    al, *_ = similarity_align(Y[ok], X[ok])
    rig, *_ = similarity_align(Y[ok], X[ok], scale=False)
    return {"rms_mm": float(np.sqrt(np.mean(np.sum((al - X[ok]) ** 2, 1)))),
            "rigid_rms_mm": float(np.sqrt(np.mean(np.sum((rig - X[ok]) ** 2, 1)))),
            "rotation_deg": relative_rotation_error_deg(cam_a, cam_b, true_a, true_b)}
