"""C-arm camera geometry: the one place where 3D world points meet 2D X-ray pixels.

Conventions (../shared/DESIGN.md §2–3):

* World frame: DICOM patient LPS (+x Left, +y Posterior, +z Superior), millimetres, origin at the
  C-arm isocentre. Angles at interfaces in degrees: primary α (LAO +, RAO −), secondary β (CRA +, CAU −).
* Isocentre → detector direction ``d = (sin α cos β, −cos α cos β, sin β)``; source ``S = −SOD·d``;
  detector centre ``S + SID·d``; detector column axis (screen right) ``c = (cos α, sin α, 0)``; row axis
  (screen down) ``r = (sin α sin β, −cos α sin β, −cos β)``.
* Images are indexed (row, col), 0-based, a pixel's centre at its integer index, so the detector centre
  sits at ((rows−1)/2, (cols−1)/2).
* ImagerPixelSpacing is given as (row spacing, column spacing) in mm at the detector, as in DICOM.

Every camera, whether built from DICOM angles or from a user's 3×4 matrix, is held as a pinhole
``K·R·(X − S)`` with ``R`` rows = (c, r, d). The 3×4 matrix ``P = K·[R | −R·S]`` maps homogeneous world
points to homogeneous **(col, row, 1)** — the usual pinhole order (u right, v down); the functions
below return (row, col) to match image indexing.

NumPy functions serve the stages; the ``*_torch`` functions are the same maths in torch, differentiable
with respect to points and (for :func:`carm_camera_torch`) the pose parameters.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .errors import UserError

log = logging.getLogger(__name__)

__all__ = [
    "MIN_VIEW_SEPARATION_DEG", "view_separation_deg", "epipolar_frame", "epipolar_angles",
    "EXIT_MARGIN_MM", "EXIT_REACH_MM", "outside_away_from_exits",
    "Camera",
    "carm_axes",
    "camera_from_geometry_dict",
    "cameras_on_one_table",
    "table_position_from_dict",
    "load_geometry_json",
    "read_geometry_json",
    "validate_geometry_dict",
    "check_carm_parameters",
]


def carm_axes(alpha_deg: float, beta_deg: float) -> np.ndarray:
    """Rows (c, r, d): detector column axis, detector row axis, isocentre→detector direction."""
    a, b = math.radians(alpha_deg), math.radians(beta_deg)
    sa, ca, sb, cb = math.sin(a), math.cos(a), math.sin(b), math.cos(b)
    return np.array(
        [
            [ca, sa, 0.0],
            [sa * sb, -ca * sb, -cb],
            [sa * cb, -ca * cb, sb],
        ]
    )


@dataclass
class Camera:
    """A projective X-ray camera.

    ``K`` (3×3 intrinsics mapping camera coords to (col, row, 1)), ``R`` (3×3, rows = detector column
    axis, row axis, viewing direction), ``source`` (3,) in world mm, and the image size. ``carm`` keeps
    the DICOM-style parameters when the camera came from them (alpha, beta, sid, sod, spacing);
    ``image_shift_px`` how far (row, col) :meth:`shifted` has moved its image from that geometry.
    """

    K: np.ndarray
    R: np.ndarray
    source: np.ndarray
    rows: int
    cols: int
    carm: dict[str, Any] | None = field(default=None)
    image_shift_px: tuple[float, float] = (0.0, 0.0)

    # ---------------------------------------------------------------- construction
    @classmethod
    def from_carm(cls, alpha: float, beta: float, sid: float, sod: float, spacing, rows: int, cols: int) -> "Camera":
        """Camera from C-arm angles (deg), SID/SOD (mm) and detector pixel spacing (row, col) in mm."""
        sr, sc = (float(spacing), float(spacing)) if np.isscalar(spacing) else (float(spacing[0]), float(spacing[1]))
        check_carm_parameters(sid, sod, (sr, sc), rows, cols)
        axes = carm_axes(alpha, beta)
        d = axes[2]
        K = np.array(
            [
                [sid / sc, 0.0, (cols - 1) / 2.0],
                [0.0, sid / sr, (rows - 1) / 2.0],
                [0.0, 0.0, 1.0],
            ]
        )
        carm = {"alpha": float(alpha), "beta": float(beta), "sid": float(sid), "sod": float(sod),
                "spacing": [sr, sc]}
        return cls(K=K, R=axes, source=-float(sod) * d, rows=int(rows), cols=int(cols), carm=carm)

    @classmethod
    def from_matrix(cls, P, rows: int, cols: int) -> "Camera":
        """Camera from a 3×4 projection matrix mapping world (x, y, z, 1) to homogeneous (col, row, 1)."""
        from scipy.linalg import rq

        P = np.asarray(P, dtype=float)
        if P.shape != (3, 4) or not np.all(np.isfinite(P)):
            raise UserError(f"projection matrix must be a finite 3×4 array, got shape {P.shape}")
        M = P[:, :3]
        if abs(np.linalg.det(M)) < 1e-12:
            raise UserError("projection matrix is singular (its left 3×3 block has no inverse)")
        # P is defined up to scale. Fix the sign so the isocentre (world origin), which always lies
        # between source and detector, has positive depth. R may then have determinant −1: the C-arm
        # image frame (c, r, d) of DESIGN.md is mirrored with respect to a pinhole camera at the source.
        if abs(P[2, 3]) < 1e-12:
            raise UserError("projection matrix puts the isocentre (world origin) at zero depth")
        P = P * np.sign(P[2, 3])
        K, R = rq(P[:, :3])
        signs = np.sign(np.diag(K))
        signs[signs == 0] = 1
        K = K * signs[None, :]
        R = signs[:, None] * R
        scale = K[2, 2]
        K = K / scale
        source = -np.linalg.solve(P[:, :3], P[:, 3])
        return cls(K=K, R=R, source=source, rows=int(rows), cols=int(cols), carm=None)

    def resampled(self, factor: int) -> "Camera":
        """The camera of the same view sampled ``factor``× finer (rows·factor × cols·factor pixels).

        Pixel centres sit at integer indices, so old pixel x maps to (x + ½)·factor − ½.
        """
        f = int(factor)
        S = np.array([[f, 0.0, (f - 1) / 2.0], [0.0, f, (f - 1) / 2.0], [0.0, 0.0, 1.0]])
        carm = None
        if self.carm is not None:
            carm = dict(self.carm, spacing=[v / f for v in self.carm["spacing"]])
        return Camera(K=S @ self.K, R=self.R.copy(), source=self.source.copy(), rows=self.rows * f,
                      cols=self.cols * f, carm=carm)

    def on_table_moved_by(self, offset_mm) -> "Camera":
        """This C-arm seen from a table (and the patient on it) displaced by ``offset_mm`` (LPS, mm) from
        the reference table position: a patient point X of the reference frame lies at X + offset in the
        room, so in the reference frame source and detector move by −offset. ``carm`` is kept (the angles,
        SID and SOD are unchanged) with ``table_offset_mm`` added."""
        t = np.asarray(offset_mm, float).reshape(3)
        carm = None if self.carm is None else dict(self.carm, table_offset_mm=[float(v) for v in t])
        return Camera(K=self.K.copy(), R=self.R.copy(), source=self.source - t, rows=self.rows, cols=self.cols,
                      carm=carm)

    def shifted(self, d_row: float, d_col: float) -> "Camera":
        """The same C-arm with its image shifted by (d_row, d_col) px (principal point moved): every point
        projects (d_row, d_col) further. A shifted camera no longer matches its C-arm angles, so ``carm``
        is dropped unless the shift is zero."""
        K = self.K.copy()
        K[0, 2] += d_col
        K[1, 2] += d_row
        return Camera(K=K, R=self.R.copy(), source=self.source.copy(), rows=self.rows, cols=self.cols,
                      carm=None if (d_row or d_col) else self.carm,
                      image_shift_px=(self.image_shift_px[0] + float(d_row), self.image_shift_px[1] + float(d_col)))

    # ---------------------------------------------------------------- derived quantities
    @property
    def view_dir(self) -> np.ndarray:
        """Unit vector from the source towards the detector (principal axis)."""
        return self.R[2]

    @property
    def matrix(self) -> np.ndarray:
        """The 3×4 projection matrix P = K·[R | −R·S] (world → homogeneous (col, row, 1))."""
        return self.K @ np.hstack([self.R, -(self.R @ self.source)[:, None]])

    @property
    def isocentre_spacing(self) -> float:
        """Pixel size in mm of an object at the isocentre (world origin): detector spacing × SOD/SID.

        For a matrix camera, the depth of the origin along the principal axis divided by the focal
        length (mean of the two axes) gives the same quantity.
        """
        depth = float(self.R[2] @ (np.zeros(3) - self.source))
        focal = 0.5 * (self.K[0, 0] + self.K[1, 1])
        return depth / focal

    def isocentre_spacing_rc(self) -> tuple[float, float]:
        """(row, col) isocentre pixel spacing in mm."""
        depth = float(self.R[2] @ (-self.source))
        return depth / self.K[1, 1], depth / self.K[0, 0]

    # ---------------------------------------------------------------- projection
    def project(self, points, return_depth: bool = False):
        """Project N×3 world points (mm) to N×2 (row, col) pixel coordinates.

        With ``return_depth`` also returns the depth along the viewing direction (mm from the source);
        points with depth ≤ 0 are behind the source and get NaN coordinates.
        """
        X = np.asarray(points, dtype=float)
        cam = (X - self.source) @ self.R.T
        depth = cam[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            h = cam @ self.K.T
            col = h[..., 0] / h[..., 2]
            row = h[..., 1] / h[..., 2]
        rc = np.stack([row, col], axis=-1)
        rc[depth <= 0] = np.nan
        return (rc, depth) if return_depth else rc

    def rays(self, pixels):
        """Back-project N×2 (row, col) pixels to rays: (origins N×3 = source, unit directions N×3)."""
        rc = np.asarray(pixels, dtype=float)
        h = np.stack([rc[..., 1], rc[..., 0], np.ones(rc.shape[:-1])], axis=-1)
        cam_dirs = h @ np.linalg.inv(self.K).T
        dirs = cam_dirs @ self.R  # R is orthonormal: camera → world is R^T
        dirs /= np.linalg.norm(dirs, axis=-1, keepdims=True)
        origins = np.broadcast_to(self.source, dirs.shape).copy()
        return origins, dirs

    def in_image(self, rc, margin: float = 0.0) -> np.ndarray:
        """Boolean mask of (row, col) coordinates that fall inside the image (pixel centres ± 0.5)."""
        rc = np.asarray(rc)
        return (
            (rc[..., 0] >= -0.5 + margin) & (rc[..., 0] <= self.rows - 0.5 - margin)
            & (rc[..., 1] >= -0.5 + margin) & (rc[..., 1] <= self.cols - 0.5 - margin)
        )

    # ---------------------------------------------------------------- torch
    def project_torch(self, points):
        """Differentiable torch version of :meth:`project` (no depth test): points (...×3) → (...×2) (row, col)."""
        import torch

        K = torch.as_tensor(self.K, dtype=points.dtype, device=points.device)
        R = torch.as_tensor(self.R, dtype=points.dtype, device=points.device)
        S = torch.as_tensor(self.source, dtype=points.dtype, device=points.device)
        return project_points_torch(points, K, R, S)

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        d = {"rows": self.rows, "cols": self.cols, "K": self.K.tolist(), "R": self.R.tolist(),
             "source": self.source.tolist(), "matrix": self.matrix.tolist()}
        if self.carm is not None:
            d.update({
                "PositionerPrimaryAngle": self.carm["alpha"],
                "PositionerSecondaryAngle": self.carm["beta"],
                "DistanceSourceToDetector": self.carm["sid"],
                "DistanceSourceToPatient": self.carm["sod"],
                "ImagerPixelSpacing": list(self.carm["spacing"]),
            })
        return d

    @classmethod
    def from_dict(cls, d: dict) -> "Camera":
        """Inverse of :meth:`to_dict`; also accepts the user geometry JSON forms (see :func:`camera_from_geometry_dict`)."""
        if "K" in d and "R" in d and "source" in d:
            cam = cls(K=np.asarray(d["K"], float), R=np.asarray(d["R"], float),
                      source=np.asarray(d["source"], float), rows=int(d["rows"]), cols=int(d["cols"]))
            if "PositionerPrimaryAngle" in d:
                cam.carm = {"alpha": float(d["PositionerPrimaryAngle"]), "beta": float(d["PositionerSecondaryAngle"]),
                            "sid": float(d["DistanceSourceToDetector"]), "sod": float(d["DistanceSourceToPatient"]),
                            "spacing": [float(x) for x in d["ImagerPixelSpacing"]]}
            return cam
        return camera_from_geometry_dict(d)


def check_carm_parameters(sid, sod, spacing, rows, cols, source: str = "geometry") -> None:
    """Refuse physically impossible C-arm parameters with a message naming the problem."""
    values = {"SID": sid, "SOD": sod}
    for name, v in values.items():
        if v is None or not np.isfinite(v) or v <= 0:
            raise UserError(f"{source}: {name} must be a positive distance in mm, got {v!r}")
    if sod >= sid:
        raise UserError(f"{source}: SOD ({sod} mm) must be smaller than SID ({sid} mm)")
    sr, sc = spacing
    if not (np.isfinite(sr) and np.isfinite(sc)) or sr <= 0 or sc <= 0:
        raise UserError(f"{source}: pixel spacing must be positive, got ({sr}, {sc})")
    if int(rows) < 1 or int(cols) < 1:
        raise UserError(f"{source}: image size must be positive, got {rows}×{cols}")


_CARM_KEYS = {
    "alpha": ("PositionerPrimaryAngle", "alpha", "primary_angle"),
    "beta": ("PositionerSecondaryAngle", "beta", "secondary_angle"),
    "sid": ("DistanceSourceToDetector", "sid", "SID"),
    "sod": ("DistanceSourceToPatient", "sod", "SOD"),
    "spacing": ("ImagerPixelSpacing", "pixel_spacing", "spacing"),
    "rows": ("Rows", "rows"),
    "cols": ("Columns", "cols", "columns"),
}
# plausible ranges (interface units: degrees, mm); a value outside is refused, with a hint at the unit
_RANGES = {"alpha": (-180.0, 180.0), "beta": (-90.0, 90.0), "sid": (300.0, 3000.0), "sod": (100.0, 3000.0),
           "spacing": (0.01, 5.0)}
_UNIT_KEYS = ("units", "angle_unit", "length_unit")


def _lookup(d: dict, key: str):
    for name in _CARM_KEYS[key]:
        if name in d:
            return d[name]
    return None


def _key_name(d: dict, key: str) -> str:
    for name in _CARM_KEYS[key]:
        if name in d:
            return name
    return _CARM_KEYS[key][0]


def _number(value, source: str, name: str) -> float:
    """A finite number, or a UserError naming the key."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"{source}: {name} must be a number (degrees or mm), got {value!r}")
    v = float(value)
    if not math.isfinite(v):
        raise UserError(f"{source}: {name} is {value!r}; it must be a finite number")
    return v


def _check_units(d: dict, source: str) -> None:
    units = d.get("units")
    if units is not None and not isinstance(units, dict):
        raise UserError(f"{source}: units must be an object such as {{\"angle\": \"deg\", \"length\": \"mm\"}}, "
                        f"got {units!r}")
    pairs = dict(units or {})
    if "angle_unit" in d:
        pairs["angle"] = d["angle_unit"]
    if "length_unit" in d:
        pairs["length"] = d["length_unit"]
    for k, v in pairs.items():
        want = {"angle": ("deg", "degree", "degrees"), "angles": ("deg", "degree", "degrees"),
                "length": ("mm",), "lengths": ("mm",)}.get(k)
        if want is None:
            raise UserError(f"{source}: units.{k}: unknown unit key (angle, length)")
        if str(v).lower() not in want:
            raise UserError(f"{source}: units.{k} is {v!r}; give angles in degrees (deg) and lengths in mm")


def _check_range(v: float, key: str, source: str, name: str) -> None:
    lo, hi = _RANGES[key]
    if lo <= v <= hi:
        return
    hint = ""
    if key in ("sid", "sod") and 0 < v < lo:
        hint = " (it looks like metres or centimetres; lengths are in mm)" if v < 300 else ""
    if key == "spacing" and v > hi:
        hint = " (it looks like micrometres; pixel spacing is in mm)"
    if key in ("alpha", "beta") and abs(v) > hi:
        hint = " (angles are in degrees)"
    raise UserError(f"{source}: {name} = {v:g} is outside the plausible range {lo:g}…{hi:g}"
                    f"{' deg' if key in ('alpha', 'beta') else ' mm'}{hint}")


def validate_geometry_dict(d: dict, source: str = "geometry JSON", rows: int | None = None,
                           cols: int | None = None) -> dict:
    """Check a DICOM-style geometry description and return it normalised:
    ``{"alpha", "beta", "sid", "sod", "spacing": (row, col), "rows", "cols"}`` (degrees, mm).

    Every problem is one :class:`UserError` naming the key: a missing key, a value that is not a finite
    number (NaN, ∞, a string), a unit other than degrees/mm (``units``), a value outside its plausible
    range (e.g. SID 0.9 — metres), SOD ≥ SID, or an image size that differs from the frames'.
    ``rows``/``cols``: the frames' size, used when the JSON gives none.
    """
    if not isinstance(d, dict):
        raise UserError(f"{source}: geometry must be a JSON object")
    _check_units(d, source)
    need = ["alpha", "beta", "sid", "sod", "spacing"] + ([] if rows is not None else ["rows"]) + \
        ([] if cols is not None else ["cols"])
    missing = [_CARM_KEYS[k][0] for k in need if _lookup(d, k) is None]
    if missing:
        raise UserError(f"{source}: missing geometry field(s) {', '.join(missing)} (or give a 3×4 'matrix' with rows/cols)")
    out = {}
    for k in ("alpha", "beta", "sid", "sod"):
        name = _key_name(d, k)
        out[k] = _number(_lookup(d, k), source, name)
        _check_range(out[k], k, source, name)
    sp_name = _key_name(d, "spacing")
    sp = _lookup(d, "spacing")
    sp = [sp] if not isinstance(sp, (list, tuple)) else list(sp)
    if len(sp) not in (1, 2):
        raise UserError(f"{source}: {sp_name} must be one value or [row, col] in mm, got {len(sp)} values")
    sp = [_number(v, source, sp_name) for v in sp]
    for v in sp:
        _check_range(v, "spacing", source, sp_name)
    out["spacing"] = (sp[0], sp[-1])
    if out["sod"] >= out["sid"]:
        raise UserError(f"{source}: SOD ({_key_name(d, 'sod')} = {out['sod']:g} mm) must be smaller than "
                        f"SID ({_key_name(d, 'sid')} = {out['sid']:g} mm)")
    for k, given in (("rows", rows), ("cols", cols)):
        v = _lookup(d, k)
        if v is None:
            out[k] = int(given)
            continue
        name = _key_name(d, k)
        f = _number(v, source, name)
        if f != int(f) or f < 1:
            raise UserError(f"{source}: {name} must be a positive whole number of pixels, got {v!r}")
        if given is not None and int(f) != int(given):
            raise UserError(f"{source}: {name} = {int(f)} but the frames have {int(given)}")
        out[k] = int(f)
    return out


def camera_from_geometry_dict(d: dict, source: str = "geometry JSON", rows: int | None = None,
                              cols: int | None = None) -> Camera:
    """Camera from a user geometry description (the schema: docs/CALIBRATION.md, "Geometry JSON").

    Two forms are accepted:

    * DICOM-style: ``PositionerPrimaryAngle``, ``PositionerSecondaryAngle`` (deg), ``DistanceSourceToDetector``,
      ``DistanceSourceToPatient`` (mm), ``ImagerPixelSpacing`` (mm, one value or [row, col]), ``Rows``,
      ``Columns`` (lower-case aliases alpha/beta/sid/sod/spacing/rows/cols also work; rows/cols may be left
      out when the frames give them); checked by :func:`validate_geometry_dict`;
    * matrix: ``"matrix"`` (3×4, world mm → homogeneous (col, row, 1)) with ``rows`` and ``cols``.
    """
    if not isinstance(d, dict):
        raise UserError(f"{source}: geometry must be a JSON object")
    if "matrix" in d or "projection_matrix" in d:
        r, c = _lookup(d, "rows"), _lookup(d, "cols")
        r, c = (rows if r is None else r), (cols if c is None else c)
        if r is None or c is None:
            raise UserError(f"{source}: a 3×4 'matrix' needs 'rows' and 'cols'")
        try:
            return Camera.from_matrix(d.get("matrix", d.get("projection_matrix")), int(r), int(c))
        except (TypeError, ValueError) as exc:
            raise UserError(f"{source}: matrix: not a 3×4 array of numbers ({exc})") from None
        except UserError as exc:
            raise UserError(f"{source}: matrix: {exc}") from None
    g = validate_geometry_dict(d, source, rows, cols)
    try:
        return Camera.from_carm(g["alpha"], g["beta"], g["sid"], g["sod"], g["spacing"], g["rows"], g["cols"])
    except UserError as exc:
        raise UserError(f"{source}: {exc}") from None


def load_geometry_json(path, rows: int | None = None, cols: int | None = None) -> Camera:
    """Read a geometry JSON file (see :func:`camera_from_geometry_dict`)."""
    return camera_from_geometry_dict(read_geometry_json(path), source=str(path), rows=rows, cols=cols)


def read_geometry_json(path) -> dict:
    """The object of a geometry JSON file, or a UserError naming the file."""
    from .artefacts import read_json

    path = Path(path)
    d = read_json(path, "geometry file")  # NaN / Infinity parse as floats; the validation names them
    if not isinstance(d, dict):
        raise UserError(f"{path}: geometry JSON must be an object")
    return d


TABLE_KEYS = ("TablePosition", "table_position_mm")  # geometry JSON: [x, y, z] table position, patient LPS mm
MAX_TABLE_MM = 2000.0


def table_position_from_dict(d: dict, source: str = "geometry JSON"):
    """The optional table position of a geometry JSON (``TablePosition``: [x, y, z], patient LPS mm — where
    the table, with the patient on it, stood during the run, in any fixed room frame shared by the runs):
    a length-3 array, or None when the key is absent; a UserError naming the key otherwise."""
    name = next((k for k in TABLE_KEYS if k in d), None)
    if name is None:
        return None
    v = d[name]
    if not isinstance(v, (list, tuple)) or len(v) != 3:
        raise UserError(f"{source}: {name} must be [x, y, z] in mm (patient left, posterior, superior), got {v!r}")
    t = np.array([_number(x, source, name) for x in v])
    if np.any(np.abs(t) > MAX_TABLE_MM):
        raise UserError(f"{source}: {name} = {t.tolist()} is beyond ±{MAX_TABLE_MM:g} mm (lengths are in mm)")
    return t


def cameras_on_one_table(cameras, tables, names) -> tuple[list, dict]:
    """The runs' cameras in one patient frame when the table moved between runs (DESIGN.md §2: the table
    is assumed fixed unless a run's geometry says otherwise).

    ``tables``: per run its table position (LPS mm, :func:`table_position_from_dict`, or from the DICOM
    header, :mod:`stages.core.dicom_io`) or None. The first run's table is the reference; every other run's
    camera is moved by its table's displacement from it (:meth:`Camera.on_table_moved_by`). Returns the
    cameras and ``{name: [x, y, z] offset}`` for the runs that moved (empty when none did, or when any run
    lacks a table position — then nothing is moved and the header cameras stand)."""
    cams = list(cameras)
    if len(cams) < 2 or any(t is None for t in tables) or any(c is None for c in cams):
        known = [str(n) for n, t in zip(names, tables) if t is not None]
        if known and len(known) < len(cams):
            log.warning("the table position is known for %s only: the table is assumed fixed between the runs "
                        "(give TablePosition in a geometry JSON for the others)", ", ".join(known))
        return cams, {}
    ref = np.asarray(tables[0], float)
    offsets = {}
    for k in range(1, len(cams)):
        d = np.asarray(tables[k], float) - ref
        if np.linalg.norm(d) > 0.05:
            cams[k] = cams[k].on_table_moved_by(d)
            offsets[str(names[k])] = [round(float(v), 2) for v in d]
    return cams, offsets


# ---------------------------------------------------------------------------- torch maths
# ---------------------------------------------------------------------------------------------- two views
MIN_VIEW_SEPARATION_DEG = 10.0  # two views closer than this cannot triangulate vessels


def view_separation_deg(cam_a: Camera, cam_b: Camera) -> float:
    """Angle between two viewing directions, folded to 0–90° (opposite views see the same projection)."""
    cosang = float(np.clip(cam_a.view_dir @ cam_b.view_dir, -1.0, 1.0))
    return float(np.degrees(np.arccos(abs(cosang))))


# A 3D point projecting outside a view's image is judged only beyond this margin (mm at the isocentre): a vessel
# can leave the segmented field without its mask reaching the pixel array's border (the collimator's dark rim and
# the segmentation's field of view end 6–11 px inside it on the real phantom's runs, where a true vessel's end
# projected 2–3 mm outside one run's image) ...
EXIT_MARGIN_MM = 3.0
# ... and only where no vessel of the view meets the border within this distance of where the point would enter
EXIT_REACH_MM = 10.0


def outside_away_from_exits(cam: Camera, mask, rc, reach_mm: float = EXIT_REACH_MM, margin_mm: float = EXIT_MARGIN_MM,
                            edge_px: int = 2) -> np.ndarray:
    """Which (row, col) projections lie outside ``cam``'s image away from every place where the view's vessel
    ``mask`` leaves it: more than ``margin_mm`` beyond the border, and farther than ``reach_mm`` from the nearest
    mask pixel within ``edge_px`` of the border, measured from the border point nearest the projection (mm at the
    isocentre). A tree's vessels leave an image only through its border, so a 3D point projecting out there is not
    on the tree; a projection inside the image, just outside it, or out beside a vessel that leaves it, is not
    judged (False)."""
    from scipy.spatial import cKDTree

    rc = np.asarray(rc, float).reshape(-1, 2)
    out = np.zeros(len(rc), bool)
    border = np.clip(rc, 0, [cam.rows - 1, cam.cols - 1])
    beyond_mm = np.linalg.norm(np.nan_to_num(rc - border), axis=1) * cam.isocentre_spacing
    off = np.flatnonzero(~cam.in_image(rc) & np.isfinite(rc).all(axis=1) & (beyond_mm > margin_mm))
    if not len(off):
        return out
    mask = np.asarray(mask) > 0
    edge = np.ones(mask.shape, bool)
    edge[edge_px:-edge_px, edge_px:-edge_px] = False
    exits = np.argwhere(mask & edge)
    if not len(exits):
        out[off] = True
        return out
    out[off] = cKDTree(exits).query(border[off])[0] * cam.isocentre_spacing > reach_mm
    return out


def epipolar_frame(cam_a: Camera, cam_b: Camera):
    """Baseline direction and two axes across it: the epipolar plane of a ray has normal baseline × ray."""
    b = cam_b.source - cam_a.source
    b = b / np.linalg.norm(b)
    e1 = np.cross(b, cam_a.view_dir)
    e1 /= np.linalg.norm(e1)
    return b, e1, np.cross(b, e1)


def epipolar_angles(cam: Camera, pixels, frame) -> np.ndarray:
    """Angle (rad) about the baseline of the epipolar plane through each (row, col) pixel of ``cam``.

    Both views of the same 3D point give the same angle when the geometry is consistent. The angle of
    the plane through the isocentre is near 0, so the range used never wraps round ±π.
    """
    b, e1, e2 = frame
    _, d = cam.rays(pixels)
    n = np.cross(b, d)
    return np.arctan2(n @ e2, n @ e1)


def project_points_torch(points, K, R, source):
    """(…×3) world points → (…×2) (row, col), differentiable in every argument."""
    cam = (points - source) @ R.transpose(-1, -2)
    h = cam @ K.transpose(-1, -2)
    col = h[..., 0] / h[..., 2]
    row = h[..., 1] / h[..., 2]
    import torch

    return torch.stack([row, col], dim=-1)


def carm_camera_torch(alpha, beta, sid, sod, spacing_row, spacing_col, rows: int, cols: int):
    """(K, R, source) as torch tensors from C-arm parameters given as 0-d tensors (degrees, mm).

    Differentiable with respect to every parameter, e.g. to refine a nominal pose against images.
    """
    import torch

    a = torch.deg2rad(alpha)
    b = torch.deg2rad(beta)
    sa, ca, sb, cb = torch.sin(a), torch.cos(a), torch.sin(b), torch.cos(b)
    zero = torch.zeros_like(a)
    R = torch.stack([
        torch.stack([ca, sa, zero]),
        torch.stack([sa * sb, -ca * sb, -cb]),
        torch.stack([sa * cb, -ca * cb, sb]),
    ])
    one = torch.ones_like(a)
    K = torch.stack([
        torch.stack([sid / spacing_col, zero, zero + (cols - 1) / 2.0]),
        torch.stack([zero, sid / spacing_row, zero + (rows - 1) / 2.0]),
        torch.stack([zero, zero, one]),
    ])
    source = -sod * R[2]
    return K, R, source
