"""The calibration's accuracy, measured: recovered against injected C-arm errors on simulated pairs, and
on the real phantom each pair's own calibration against the joint calibration of all its runs.

Reads: nothing for :func:`injected_errors` (synthetic trees at the phantom's C-arm angles); the phantom's
``*.dcm`` runs for :func:`pair_vs_joint`. Writes nothing: both return rows (``benchmarks/bench_calibration.py``
turns them into docs/benchmarks/calibration.md and calibration_phantom.md).
"""

from __future__ import annotations

import itertools
import logging
import time

import numpy as np

__all__ = ["PHANTOM_CARM", "injected_errors", "pair_vs_joint"]

PHANTOM_CARM = [  # (alpha, beta, sid) of phantom runs IM1..IM8 (README of ../shared/data/phantom_xa)
    (31.3, 0.1, 860), (-27.3, -0.1, 865), (-0.8, -23.2, 891), (0.1, 28.7, 907),
    (-26.5, -32.7, 931), (24.0, -18.8, 939), (-29.3, 25.5, 976), (30.7, 23.6, 976),
]


def injected_errors(trials: int, sizes, noises, shift: bool = True, seed: int = 0) -> list[dict]:
    """Per error size, ``trials`` random phantom run pairs whose true cameras are the header cameras with
    uniform errors in both runs up to ``size`` × (±10 mm isocentre shift unless not ``shift``, ±3° dα and dβ,
    ±2° in-plane, ±20 mm SID); per noise level (px) the pair is calibrated from the headers on the true
    projections of a synthetic tree plus noise. A row per calibration: gauge-free 3D RMS error (mm) and
    relative-rotation error (deg) before and after, applied, residual after (px), seconds."""
    from ..core.geometry import Camera
    from . import calibrate_pair, relative_geometry_error
    from .synthetic import random_error, synthetic_matches, synthetic_tree, true_camera

    logging.disable(logging.WARNING)
    pairs = list(itertools.combinations(range(len(PHANTOM_CARM)), 2))
    rows = []
    rng = np.random.default_rng(seed)
    for size in sizes:
        for t in range(trials):
            i, j = pairs[int(rng.integers(len(pairs)))]
            ha, hb = (Camera.from_carm(a, b, s, 720.0, 0.390625, 512, 512) for a, b, s in (PHANTOM_CARM[i], PHANTOM_CARM[j]))
            tree = synthetic_tree(seed=1000 * t + int(size * 100), step_mm=0.3)
            kw = dict(shift_mm=10.0 * size if shift else 0.0, angle_deg=3.0 * size, inplane_deg=2.0 * size,
                      sid_mm=20.0 * size)
            ta, tb = true_camera(ha, random_error(rng, **kw)), true_camera(hb, random_error(rng, **kw))
            for noise in noises:
                pa, pb = synthetic_matches(tree, ta, tb, noise_px=noise, seed=t)
                t0 = time.perf_counter()
                res = calibrate_pair(pa, pb, ha, hb, names=(f"IM{i + 1}", f"IM{j + 1}"))
                dt = time.perf_counter() - t0
                e0 = relative_geometry_error(ha, hb, ta, tb)
                e1 = relative_geometry_error(res.cam_a, res.cam_b, ta, tb)
                rows.append(dict(size=size, noise=noise, n=len(pa), applied=res.applied, seconds=dt,
                                 before_mm=e0["rms_mm"], after_mm=e1["rms_mm"], before_deg=e0["rotation_deg"],
                                 after_deg=e1["rotation_deg"],
                                 resid_after_px=res.report["residual_after"]["epipolar_px"]))
    return rows


def pair_vs_joint(folder) -> dict:
    """The joint calibration of all runs in ``folder`` (static) gives a 3D model whose projections by the
    jointly calibrated cameras are reference matches for every run pair; per pair, their symmetric epipolar
    distance (mm at the isocentre) under the header cameras and under the pair's own calibration from its
    masks. Returns the joint report, its time and model size, and a row per pair."""
    from ..evaluate.heldout import load_views
    from . import calibrate_masks, calibrate_runs, pair_residual
    from .runs import _centreline_maps, _model_points, _voted

    logging.disable(logging.WARNING)
    views = load_views(folder)
    names = [v.name for v in views]
    t0 = time.perf_counter()
    cams, rep = calibrate_runs([v.mask for v in views], [v.camera for v in views], names, static=True,
                               fovs=[v.fov for v in views])
    t_joint = time.perf_counter() - t0
    part = names.index(rep["partner_run"])
    model = _voted(_model_points([views[0].mask, views[part].mask], [cams[0], cams[part]], 0), cams,
                   _centreline_maps([v.mask for v in views]), exclude=(0, part))
    pairs = []
    for i, j in itertools.combinations(range(len(views)), 2):
        xa, xb = cams[i].project(model), cams[j].project(model)
        ok = views[i].camera.in_image(xa) & views[j].camera.in_image(xb)
        t0 = time.perf_counter()
        cal = calibrate_masks(views[i].mask, views[j].mask, views[i].camera, views[j].camera, names=(names[i], names[j]))
        dt = time.perf_counter() - t0
        pairs.append(dict(a=names[i], b=names[j], applied=cal.applied, seconds=dt,
                          shift_mm=cal.report["corrections"][names[j]]["shift_mm_norm"],
                          header_mm=pair_residual(views[i].camera, views[j].camera, xa[ok], xb[ok])["epipolar_mm"],
                          pair_mm=pair_residual(views[i].camera, cal.cam_b, xa[ok], xb[ok])["epipolar_mm"]))
    return {"names": names, "joint": rep, "joint_seconds": t_joint, "model_points": len(model), "pairs": pairs}
