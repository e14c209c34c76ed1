"""Synthetic scenes for testing and benchmarking the calibration: a 3D vessel-like tree, header cameras,
and "true" cameras with injected C-arm errors.

Reads/writes nothing. Deterministic for a given seed.
"""

from __future__ import annotations

import numpy as np

from ..core.geometry import Camera
from .model import Correction, apply_correction, isocentre_shift_camera

__all__ = ["synthetic_tree", "InjectedError", "random_error", "true_camera", "header_camera", "synthetic_matches"]


def synthetic_tree(seed: int = 0, n_branches: int = 9, step_mm: float = 0.5, extent_mm: float = 45.0) -> np.ndarray:
    """Points (N×3 mm, spaced ``step_mm``) along a branching tree of smooth 3D curves within ±extent of
    the isocentre: a main vessel and side branches leaving it, like a coronary tree seen at the isocentre."""
    rng = np.random.default_rng(seed)
    curves = []

    def grow(start, direction, length):
        pts = [np.asarray(start, float)]
        d = np.asarray(direction, float)
        d /= np.linalg.norm(d)
        for _ in range(int(length / step_mm)):
            d = d + rng.normal(0.0, 0.06, 3)
            d /= np.linalg.norm(d)
            nxt = pts[-1] + step_mm * d
            if np.any(np.abs(nxt) > extent_mm):
                break
            pts.append(nxt)
        return np.array(pts)

    main = grow(rng.uniform(-20, 20, 3) * [1, 1, 0.2] + [0, 0, 30], [0.2, 0.1, -1.0], 110.0)
    curves.append(main)
    for _ in range(n_branches - 1):
        base = curves[int(rng.integers(len(curves)))]
        start = base[int(rng.integers(len(base) // 5, max(len(base) // 5 + 1, len(base) - 5)))]
        curves.append(grow(start, rng.normal(0, 1, 3), rng.uniform(25, 70)))
    return np.concatenate(curves)


class InjectedError(dict):
    """Per-run injected error: isocentre shift (3 mm), dalpha/dbeta/inplane (deg), dsid (mm)."""


def random_error(rng, shift_mm: float = 10.0, angle_deg: float = 3.0, inplane_deg: float = 2.0,
                 sid_mm: float = 20.0) -> InjectedError:
    """Uniform errors up to the given sizes (each component independently, either sign)."""
    return InjectedError(
        iso_shift_mm=rng.uniform(-shift_mm, shift_mm, 3).tolist(),
        dalpha_deg=float(rng.uniform(-angle_deg, angle_deg)), dbeta_deg=float(rng.uniform(-angle_deg, angle_deg)),
        inplane_deg=float(rng.uniform(-inplane_deg, inplane_deg)), dsid_mm=float(rng.uniform(-sid_mm, sid_mm)))


def true_camera(header: Camera, err: dict) -> Camera:
    """The camera the run really had, given its header camera and an injected error."""
    cam = apply_correction(header, Correction(0.0, 0.0, err.get("inplane_deg", 0.0), err.get("dalpha_deg", 0.0),
                                              err.get("dbeta_deg", 0.0), err.get("dsid_mm", 0.0)))
    return isocentre_shift_camera(cam, err.get("iso_shift_mm", (0.0, 0.0, 0.0)))


def header_camera(true, err: dict):
    """The header camera of a run whose real camera is ``true`` and whose header is off by ``err``: the exact
    inverse of :func:`true_camera`, so ``true_camera(header_camera(T, e), e)`` projects as ``T``. (``true_camera`` turns the C-arm by (dα, dβ) about the isocentre from the header's
    angles, turns the detector in-plane, scales the focal length by (SID + dSID) / SID, then translates the
    whole C-arm by the isocentre shift; here each step is undone in the opposite order.)"""
    import math

    from ..core.geometry import carm_axes
    from .model import DEFAULT_SID_MM, carm_angles

    t = np.asarray(err.get("iso_shift_mm", (0.0, 0.0, 0.0)), float)
    da, db = float(err.get("dalpha_deg", 0.0)), float(err.get("dbeta_deg", 0.0))
    th, dsid = math.radians(float(err.get("inplane_deg", 0.0))), float(err.get("dsid_mm", 0.0))
    a1, b1 = carm_angles(true)  # the viewing direction is untouched by the shift and the in-plane turn
    Q = carm_axes(a1, b1).T @ carm_axes(a1 - da, b1 - db)  # header angles → true angles
    Rz = np.array([[math.cos(th), math.sin(th), 0.0], [-math.sin(th), math.cos(th), 0.0], [0.0, 0.0, 1.0]])
    sid_true = float(true.carm["sid"]) if true.carm else DEFAULT_SID_MM + dsid
    sid_header = sid_true - dsid
    K = true.K.copy()
    for ij in ((0, 0), (1, 1), (0, 1)):
        K[ij] *= sid_header / sid_true
    carm = None
    if true.carm:  # the header's nominal C-arm parameters
        carm = dict(true.carm, alpha=float(true.carm["alpha"]) - da, beta=float(true.carm["beta"]) - db,
                    sid=sid_header)
    return Camera(K=K, R=Rz.T @ true.R @ Q, source=Q.T @ (true.source - t), rows=true.rows, cols=true.cols,
                  carm=carm)


def synthetic_matches(points3d, true_a: Camera, true_b: Camera, noise_px: float = 0.0, outliers: float = 0.0,
                      seed: int = 0):
    """(row, col) projections of the points in both true views, inside both images, with Gaussian noise
    and a fraction of outlier matches (B point replaced by another random point's projection)."""
    rng = np.random.default_rng(seed)
    a, b = true_a.project(points3d), true_b.project(points3d)
    ok = true_a.in_image(a) & true_b.in_image(b)
    a, b = a[ok], b[ok]
    if noise_px:
        a = a + rng.normal(0.0, noise_px, a.shape)
        b = b + rng.normal(0.0, noise_px, b.shape)
    if outliers:
        k = rng.random(len(b)) < outliers
        b[k] = b[rng.integers(0, len(b), int(k.sum()))]
    return a, b
