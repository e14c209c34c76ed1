"""Calibrating two or more runs from their vessel masks: :func:`calibrate_runs` (what ``autocar calibrate``
and ``autocar reconstruct`` call).

Reads/writes nothing.

* Two runs: :func:`stages.calibration.masks.calibrate_masks` (run A fixed, run B corrected).
* More than two runs of a **static** scene (``static=True``, e.g. the phantom): a joint calibration.
  The reference run is fixed; every other run starts from its pairwise shift against the reference.
  A 3D centreline model is built from the two-view hull of the reference and its partner (the run at the
  largest angle from it); ``iterations`` times each non-reference run's correction (detector shift, in-plane rotation, dα, dβ,
  dSID) is fitted to it by chamfer onto its own centreline (:func:`stages.calibration.views.fit_view_correction`),
  and the model is rebuilt under the new cameras keeping only the points that most other runs confirm
  (:data:`VOTE_PX`, :data:`VOTE_SHARE`), which removes the two-view hull's ghosts.
  Held fixed: the reference run entirely (a common motion of all runs is a gauge freedom).
* More than two runs, not static (moving heart): each run is calibrated against the reference pairwise.

The report: per run the correction (px, mm at the isocentre, degrees), the residual before/after
(mean chamfer distance of the model's projection to the run's centreline, px and mm), warnings.
A run's correction is refused (header kept, with a warning) if it does not lower its residual or ends
at a bound.
"""

from __future__ import annotations

import logging
import time

import numpy as np
from scipy import ndimage

from ..core.errors import UserError
from ..core.geometry import Camera
from .masks import calibrate_masks
from .model import DEFAULT_BOUNDS, Correction, apply_correction

log = logging.getLogger(__name__)

__all__ = ["calibrate_runs", "HULL_DILATE_PX"]

HULL_DILATE_PX = 2
# joint calibration: the shift bound is wider, since the model's gauge (reference run + partner) can put a
# run's apparent offset beyond its physical one (phantom IM6: 26 mm in the gauge of IM1+IM2)
JOINT_SHIFT_MM = 30.0
SHIFT_ONLY = ("shift_row_px", "shift_col_px")
VOTE_PX = 3.0  # a model point is confirmed by a run when it projects this close to its centreline
VOTE_SHARE = 0.6  # ... and kept when this share of the other runs confirm it


def _model_points(masks, cameras, dilate_px: int) -> np.ndarray:
    """3D centreline points of the visual hull of all views (masks dilated by ``dilate_px``)."""
    from ..core.metrics import skeleton
    from ..visual_hull import visual_hull

    st = ndimage.generate_binary_structure(2, 1)
    dil = [ndimage.binary_dilation(m, st, iterations=dilate_px) if dilate_px else m for m in masks]
    hull = visual_hull(dil, cameras)
    if len(hull) == 0:
        return np.zeros((0, 3))
    dense, lo = hull.to_dense(pad=1)
    sk = skeleton(dense)
    return hull.origin + (np.argwhere(sk) + lo) * hull.voxel_size


def _voted(points: np.ndarray, cams, dmaps, exclude, tol_px: float = VOTE_PX, share: float = VOTE_SHARE):
    """The points that project within ``tol_px`` of the centreline in at least ``share`` of the runs not in
    ``exclude`` (ghosts of a two-view hull are confirmed by few other views)."""
    from .views import chamfer_residuals

    others = [k for k in range(len(cams)) if k not in exclude]
    if not others or not len(points):
        return points
    votes = sum((chamfer_residuals(points, cams[k], dmaps[k]) <= tol_px).astype(int) for k in others)
    return points[votes >= share * len(others)]


def _centreline_maps(masks):
    from skimage.morphology import skeletonize

    from .views import centreline_distance_map

    return [centreline_distance_map(skeletonize(np.asarray(m, bool))) for m in masks]


def calibrate_runs(masks, cameras, names=None, *, static: bool = False, reference: int = 0,
                   bounds: dict | None = None, iterations: int = 3, fovs=None,
                   full_model: bool = True) -> tuple[list[Camera], dict]:
    """Corrected cameras of every run and a report dict (see the module doc).

    ``masks``: one H×W vessel mask per run (e.g. of a contrast-filled frame); ``cameras``: their header
    cameras; ``names``: run names for the report; ``static``: the scene does not move between runs (joint
    calibration of > 2 runs); ``reference``: index of the run held fixed; ``fovs``: optional fields of view;
    ``full_model``: joint calibration fits the full correction after the shift (False: shift only).
    Raises :class:`UserError` for fewer than two runs or a degenerate pair.
    """
    t0 = time.perf_counter()
    n = len(masks)
    if n < 2 or len(cameras) != n:
        raise UserError(f"calibration needs two or more runs with one camera each, got {n} mask(s), "
                        f"{len(cameras)} camera(s)")
    names = list(names) if names is not None else [f"run{k + 1}" for k in range(n)]
    bounds = dict(DEFAULT_BOUNDS, **(bounds or {}))
    ref = int(reference)
    if n == 2:
        other = 1 - ref
        cal = calibrate_masks(masks[ref], masks[other], cameras[ref], cameras[other],
                              names=(names[ref], names[other]), bounds=bounds)
        cams = list(cameras)
        cams[other] = cal.cam_b
        rep = dict(cal.report, seconds=round(time.perf_counter() - t0, 3))
        return cams, rep

    # pairwise start against the reference
    cams = list(cameras)
    pairwise, warnings = {}, []
    for k in range(n):
        if k == ref:
            continue
        try:
            cal = calibrate_masks(masks[ref], masks[k], cameras[ref], cameras[k], names=(names[ref], names[k]),
                                  bounds=bounds)
            pairwise[names[k]] = cal.report
            cams[k] = cal.cam_b
        except UserError as exc:
            pairwise[names[k]] = {"applied": False, "error": str(exc)}
            warnings.append(str(exc))
    if not static:
        return cams, {"method": "pairwise against the reference", "runs": names, "reference_run": names[ref],
                      "applied": any(r.get("applied") for r in pairwise.values()), "pairs": pairwise,
                      "corrections": {names[ref]: Correction().to_dict(cameras[ref]),
                                      **{k: r.get("corrections", {}).get(k, Correction().to_dict())
                                         for k, r in pairwise.items()}},
                      "warnings": warnings, "seconds": round(time.perf_counter() - t0, 3)}

    from .views import chamfer_residuals, fit_view_correction

    bounds = dict(bounds, shift_mm=max(bounds["shift_mm"], JOINT_SHIFT_MM))
    dmaps = _centreline_maps(masks)
    sp = [c.isocentre_spacing for c in cameras]
    corrections = {k: Correction() for k in range(n)}
    # the pairwise shifts as the start of the joint fit
    for k in range(n):
        if k != ref and names[k] in pairwise and pairwise[names[k]].get("applied"):
            c = pairwise[names[k]]["corrections"][names[k]]
            corrections[k] = Correction(c["shift_row_px"], c["shift_col_px"])
    # the model: the 3D centreline of the two-view hull of the reference and its partner (the run seen
    # from the most different angle), kept where the other runs agree (votes), refitted each iteration
    angles = [float(np.degrees(np.arccos(np.clip(cameras[ref].view_dir @ c.view_dir, -1, 1)))) for c in cameras]
    partner = int(np.argmax([a if k != ref else -1 for k, a in enumerate(angles)]))
    cams = [apply_correction(cameras[k], corrections[k]) for k in range(n)]
    base = _model_points([masks[ref], masks[partner]], [cams[ref], cams[partner]], 0)
    model = base
    before = {names[k]: float(chamfer_residuals(base, cameras[k], dmaps[k]).mean()) if len(base) else None
              for k in range(n)}
    fits = {}
    for it in range(max(1, iterations)):
        if len(model) < 50:
            warnings.append(f"joint calibration: the model has only {len(model)} centreline points; stopped")
            break
        for k in range(n):
            if k == ref or (it == 0 and k == partner):
                continue
            fov = fovs[k] if fovs is not None else None
            # the shift first (on the phantom one shift per run explains nearly all of the header error),
            # then the full model from there; the full fit is kept only if it stays inside its bounds
            _, corr, fit = fit_view_correction(model, cameras[k], dmaps[k], fov, bounds=bounds, free=SHIFT_ONLY,
                                               start=corrections[k])
            if fit["applied"] and not fit["at_bound"]:
                corrections[k] = corr
            if full_model and it > 0:
                _, corr2, fit2 = fit_view_correction(model, cameras[k], dmaps[k], fov, bounds=bounds,
                                                     start=corrections[k], grid_mm=None)
                if fit2["applied"] and not fit2["at_bound"] and fit2["cost_after_px"] < fit["cost_after_px"]:
                    corr, fit = corr2, fit2
                    corrections[k] = corr
            fits[names[k]] = fit
        cams = [apply_correction(cameras[k], corrections[k]) for k in range(n)]
        base = _model_points([masks[ref], masks[partner]], [cams[ref], cams[partner]], 0)
        model = _voted(base, cams, dmaps, exclude=(ref, partner))
    model_final = model if len(model) >= 50 else base
    after = {names[k]: float(chamfer_residuals(model_final, cams[k], dmaps[k]).mean()) if len(model_final) else None
             for k in range(n)}
    # the residual before, on the same final model (header cameras)
    before = {names[k]: float(chamfer_residuals(model_final, cameras[k], dmaps[k]).mean()) if len(model_final)
              else None for k in range(n)}
    # refuse what does not help, per run
    for k in range(n):
        if k == ref or corrections[k].is_zero():
            continue
        nm = names[k]
        at = fits.get(nm, {}).get("at_bound") or []
        if at:
            warnings.append(f"calibration of {nm} refused: {', '.join(at)} at the bound; header geometry kept")
        elif before[nm] is not None and after[nm] is not None and not after[nm] < before[nm]:
            warnings.append(f"calibration of {nm} refused: residual {after[nm]:.2f} px after ≥ {before[nm]:.2f} px "
                            "before; header geometry kept")
        else:
            continue
        corrections[k] = Correction()
        cams[k] = cameras[k]
    for w in warnings:
        log.warning(w)
    report = {
        "method": "joint chamfer (static scene)", "runs": names, "reference_run": names[ref],
        "applied": any(not c.is_zero() for c in corrections.values()),
        "corrections": {names[k]: corrections[k].to_dict(cameras[k]) for k in range(n)},
        "residual_before": {nm: {"chamfer_px": v, "chamfer_mm": None if v is None else v * sp[k]}
                            for k, (nm, v) in enumerate(before.items())},
        "residual_after": {nm: {"chamfer_px": v, "chamfer_mm": None if v is None else v * sp[k]}
                           for k, (nm, v) in enumerate(after.items())},
        "model_points": int(len(model_final)), "partner_run": names[partner], "pairs": pairwise,
        "free_dofs": ["every run but the reference: detector shift (2), in-plane rotation, dalpha, dbeta, dSID"],
        "fixed_dofs": [f"{names[ref]}: all six (reference run; a common motion of all runs is a gauge freedom)"],
        "bounds": bounds, "warnings": warnings, "seconds": round(time.perf_counter() - t0, 3),
    }
    return cams, report
