"""Held-out-view check: scoring a reconstruction of a *static* scene on real X-ray runs without 3D truth.

Reads: a folder of XA DICOM runs of one static object (e.g. ../shared/data/phantom_xa, 8 runs) via
:func:`stages.core.dicom_io.read_xa`. Writes (from :func:`write_heldout_report`): a JSON file with every row
and a Markdown table.

For every pair of runs (i, j) a reconstruction is made from those two views only — the visual hull of
their vessel masks (:func:`stages.visual_hull.visual_hull`, ``method="visual-hull"``) or the SBP
network's occupancy ≥ 0.5 (``method="sbp"``, shipped or given weights; any method of
:mod:`stages.methods3d`) — and for every other run k it
is projected into k and compared with k's own segmentation:

* **coverage** — fraction of k's segmented vessel centreline pixels (2D thinning of the mask) that
  lie within ε (3 mm at the isocentre) of the projected reconstruction (all reconstructed voxels,
  splatted to their nearest pixel and dilated by one pixel so the splats join);
* **distance** — mean distance in mm (isocentre pixel spacing of k) from the projected 3D centreline
  of the reconstruction (3D thinning of its voxels) to the nearest segmented centreline pixel of k.
  Projected points outside k's field of view are left out (the vessel may leave k's image).

Coverage is recall-like (is every vessel of k explained?), distance precision-like (does every
reconstructed vessel lie on a vessel of k?). Ghost branches of the two-view hull inflate coverage and
the distance alike.

Segmentation: a full-contrast frame (median of the later frames, :func:`stages.segment.vesselness.contrast_frame`),
segmented with ``seg_method`` (:func:`stages.segment.segment_frames`: the U-Net, Frangi vesselness with
hysteresis, or thresholding).

Geometry. By default (:func:`run_heldout`) each pair is first self-calibrated from its own
two runs only (:func:`stages.calibration.calibrate_masks`: run B corrected against run A), and every
held-out view is scored twice: with its header pose (``pose: "nominal"``) and after a bounded 6-DoF
fit of its pose to the reconstruction (``pose: "fitted"``, :func:`stages.calibration.views.fit_view_pose`:
symmetric chamfer between the projected 3D centreline and the view's centreline, the reconstruction fixed), so that the check measures the reconstruction rather than the held-out
header. ``own`` rows (in ``result["own_rows"]``) give the reprojection distance of the reconstruction
into its own two views under the calibrated cameras.
"""

from __future__ import annotations

import itertools
import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..core.errors import UserError
from ..core.geometry import Camera, cameras_on_one_table
from ..core.metrics import EPSILON_MM, skeleton
from ..methods3d import DEFAULT_METHOD, METHODS, MULTI_VIEW_METHODS, load_predictor
from ..segment.vesselness import centreline_2d, contrast_frame, fov_mask, segment_vesselness
from ..visual_hull import project_to_mask, visual_hull

log = logging.getLogger(__name__)

__all__ = ["View", "load_views", "heldout_rows", "run_heldout", "write_heldout_report", "METHODS", "resolve_method",
           "calibrate_subset_views", "projected_distances", "score_in_view", "in_views_frame"]


def resolve_method(method: str) -> str:
    """``default`` → what ``autocar reconstruct`` uses by default (:data:`stages.methods3d.DEFAULT_METHOD`)."""
    return DEFAULT_METHOD if method == "default" else method



@dataclass
class View:
    """One run reduced to what the check needs."""

    name: str
    camera: Camera
    mask: np.ndarray  # H×W vessel mask
    fov: np.ndarray  # H×W field of view
    centreline: np.ndarray  # H×W 1-px centreline of the mask
    table_offset_mm: list | None = None  # where its table stood from the first run's, when its camera was moved

    def __post_init__(self):
        # distance (px) from each pixel to the nearest centreline pixel, computed once per view
        self.dist_to_centreline = ndimage.distance_transform_edt(~self.centreline)


def in_views_frame(points: np.ndarray, views: list[View], reference_run: str) -> np.ndarray:
    """3D points of a reconstruction whose first run is ``reference_run`` (``autocar reconstruct`` places every later
    run on that run's table, so its output lies in that run's patient frame) moved into the patient frame of
    ``views`` (:func:`load_views`: the first file's table). Runs of one study on different table positions otherwise
    score a reconstruction tens of millimetres away from where the views have it."""
    offset = next(v.table_offset_mm for v in views if v.name == reference_run)
    return np.asarray(points, float) - np.asarray(offset if offset is not None else (0.0, 0.0, 0.0), float)


def contrast_mask(frames, seg_method: str = "vesselness"):
    """(vessel mask, field of view) of a run's full-contrast frame (:func:`stages.segment.vesselness.contrast_frame`)
    segmented with ``seg_method`` (vesselness within the field of view, or the segmenter's methods)."""
    from ..segment import segment_frames

    img = contrast_frame(frames)
    fov = fov_mask(img)
    if seg_method == "vesselness":
        return segment_vesselness(img, fov=fov), fov
    return segment_frames(img, method=seg_method)[1].astype(bool), fov


def load_views(folder, seg_method: str = "vesselness") -> list[View]:
    """Read every ``*.dcm`` in ``folder``, segment a full-contrast frame, return the views by name."""
    from ..core.dicom_io import read_xa

    folder = Path(folder)
    files = sorted(folder.glob("*.dcm"))
    if len(files) < 3:
        raise UserError(f"{folder}: the held-out check needs at least 3 DICOM runs (*.dcm), found {len(files)}")
    views, tables = [], []
    for f in files:
        run = read_xa(f)
        mask, fov = contrast_mask(run.frames, seg_method)
        views.append(View(f.stem, run.camera, mask, fov, centreline_2d(mask)))
        tables.append(run.geometry.table_mm)
    # runs whose table moved (header table position) are placed in the first run's patient frame
    cams, offsets = cameras_on_one_table([v.camera for v in views], tables, [v.name for v in views])
    for v, cam in zip(views, cams):
        v.camera = cam
        v.table_offset_mm = offsets.get(v.name)
    return views


def _coverage(points: np.ndarray, view: View, camera: Camera, tol_px: float) -> float:
    """Fraction of the view's centreline pixels within ``tol_px`` of the splatted projection of points."""
    n = int(view.centreline.sum())
    if n == 0:
        return float("nan")
    if len(points) == 0:
        return 0.0
    proj = project_to_mask(points, camera, dilate_px=1)
    d = ndimage.distance_transform_edt(~proj)
    return float(np.count_nonzero(d[view.centreline] <= tol_px) / n)


def _hull_centreline(hull) -> np.ndarray:
    """World points of the 3D thinning skeleton of a voxel set (SparseVoxels)."""
    if len(hull) == 0:
        return np.zeros((0, 3))
    dense, lo = hull.to_dense(pad=1)
    sk = skeleton(dense)
    return hull.origin + (np.argwhere(sk) + lo) * hull.voxel_size


def subset_voxels(mask_a, mask_b, cam_a: Camera, cam_b: Camera, method: str = "visual-hull", predictor=None,
                    side: str = "left", extra=()):
    """The reconstruction (SparseVoxels, occupied voxels only) of one pair of views (and ``extra``) by ``method``
    (:mod:`stages.methods3d`; ``predictor``: that method's loaded predictor, to load weights only once).
    ``extra``: (mask, camera) of further views of the same scene, for the methods that use every view
    (:data:`stages.methods3d.MULTI_VIEW_METHODS`)."""
    if method == "visual-hull" and predictor is None:
        return visual_hull([mask_a, mask_b, *(m for m, _ in extra)], [cam_a, cam_b, *(c for _, c in extra)])
    predict = predictor or load_predictor(method)
    pred = predict(mask_a, mask_b, cam_a, cam_b, side, extra=extra) if extra else predict(mask_a, mask_b, cam_a,
                                                                                         cam_b, side)
    return pred.subset(np.asarray(pred.features["occupancy"]) >= 0.5)


def projected_distances(cl: np.ndarray, v: View, camera: Camera) -> np.ndarray:
    """Distance (mm at the isocentre) from each projected 3D point to ``v``'s centreline, bilinear on the distance
    map (sub-pixel); NaN where the point projects outside the image or the field of view."""
    rc = camera.project(cl)
    r = np.rint(rc[:, 0])
    c = np.rint(rc[:, 1])
    ok = np.isfinite(r) & np.isfinite(c) & (r >= 0) & (r < camera.rows) & (c >= 0) & (c < camera.cols)
    ok[ok] = v.fov[r[ok].astype(int), c[ok].astype(int)]
    out = np.full(len(rc), np.nan)
    out[ok] = ndimage.map_coordinates(v.dist_to_centreline, rc[ok].T, order=1, mode="nearest") * camera.isocentre_spacing
    return out


def _project_distance(cl: np.ndarray, v: View, camera: Camera, median: bool = False):
    """Mean distance (mm at the isocentre) from the projected 3D centreline to ``v``'s centreline, over the
    projected points inside its field of view; and how many there were (and the median, if asked)."""
    d = projected_distances(cl, v, camera)
    d = d[np.isfinite(d)]
    if not len(d):
        return (float("nan"), 0, float("nan")) if median else (float("nan"), 0)
    if median:
        return float(d.mean()), len(d), float(np.median(d))
    return float(d.mean()), len(d)


def score_in_view(points: np.ndarray, centreline: np.ndarray, view: View, camera: Camera,
                  epsilon_mm: float = EPSILON_MM) -> dict:
    """How a reconstruction explains a view it was not built from: ``coverage`` (share of the view's centreline
    within ``epsilon_mm`` of the projected ``points``), ``distance_mm`` / ``distance_median_mm`` (from the
    projected ``centreline`` to the view's centreline, isocentre mm) and ``centreline_points`` (projected
    centreline points inside the field of view)."""
    dist, n, dist_med = _project_distance(centreline, view, camera, median=True)
    return {"centreline_points": n, "coverage": _coverage(points, view, camera, epsilon_mm / camera.isocentre_spacing),
            "distance_mm": dist, "distance_median_mm": dist_med}


def calibrate_subset_views(views: list[View], subset) -> tuple[list[Camera], dict]:
    """Self-calibrate the runs of ``subset`` from their own vessels only, each against the first run
    (:func:`stages.calibration.calibrate_runs`: the shift across the epipolar lines, run by run; the joint
    static-scene calibration of three runs made the held-out figures worse: docs/HELDOUT.md). The header
    cameras and a report saying why when they cannot be calibrated."""
    from ..calibration import calibrate_runs

    names = [views[k].name for k in subset]
    headers = [views[k].camera for k in subset]
    try:
        return calibrate_runs([views[k].mask for k in subset], headers, names)
    except UserError as exc:
        log.warning("%s", exc)
        return headers, {"runs": names, "applied": False, "error": str(exc)}


def heldout_rows(views: list[View], pair: tuple[int, int], epsilon_mm: float = EPSILON_MM,
                 shift_b=(0.0, 0.0), label: str = "nominal", method: str = "visual-hull", predictor=None,
                 side: str = "left", calibrate: bool = False, fit_pose: bool = False, own: list | None = None,
                 calibration: dict | None = None) -> list[dict]:
    """Reconstruct from ``views[pair]`` (two or more view indices; by ``method``) and score it in every other view.

    ``calibrate``: self-calibrate the pair first (its two runs only); ``fit_pose``: add a ``pose:
    "fitted"`` row per held-out view (its 6-DoF pose fitted to the reconstruction). ``own``: a list that
    receives the pair's own-view rows (reprojection distance into its two views); ``calibration``: a
    dict that receives the pair's calibration report under its pair name.
    """
    from ..calibration.views import CAP_PX, fit_view_pose

    method = resolve_method(method)
    pair = tuple(pair)
    pair_name = "+".join(views[k].name for k in pair)
    cams = [views[k].camera for k in pair]
    report = None
    if calibrate:
        cams, report = calibrate_subset_views(views, pair)
        if calibration is not None:
            calibration[pair_name] = report
    if np.any(shift_b):
        cams[1] = cams[1].shifted(*shift_b)
    hull = subset_voxels(views[pair[0]].mask, views[pair[1]].mask, cams[0], cams[1], method, predictor, side,
                           extra=[(views[k].mask, cam) for k, cam in zip(pair[2:], cams[2:])])
    pts = hull.world_points()
    cl = _hull_centreline(hull)
    calibrated = bool(report and report.get("applied"))
    if own is not None:
        for k, cam in zip(pair, cams):
            dist, n = _project_distance(cl, views[k], cam)
            own.append({"pair": pair_name, "view": views[k].name, "method": method, "calibrated": calibrated,
                        "centreline_points": n, "distance_mm": dist})
    rows = []
    for k, v in enumerate(views):
        if k in pair:
            continue
        poses = [(label, v.camera, None)]
        if fit_pose and len(cl):
            cam_f, _, fit = fit_view_pose(cl, v.camera, np.minimum(v.dist_to_centreline, CAP_PX), v.fov,
                                          centreline=v.centreline)
            poses.append(("fitted", cam_f, fit))
        for lab, cam, fit in poses:
            score = score_in_view(pts, cl, v, cam, epsilon_mm)
            row = {
                "pair": pair_name, "heldout": v.name, "pose": lab, "method": method,
                "calibrated": calibrated, "shift_px": [float(shift_b[0]), float(shift_b[1])],
                "hull_voxels": len(hull), **score,
                "status": "ok" if score["centreline_points"] else "no-projected-centreline-in-fov",
            }
            if fit is not None:
                row["pose_fit"] = fit
            rows.append(row)
    return rows


def run_heldout(folder, epsilon_mm: float = EPSILON_MM, pairs=None, progress=None, method: str = "visual-hull",
                weights=None, seg_method: str = "vesselness", side: str = "left", calibrate: bool = True,
                fit_pose: bool = True, views: list | None = None, views_per_subset: int = 2,
                max_subsets: int | None = None, seed: int = 0) -> dict:
    """Every subset of ``views_per_subset`` runs (all pairs by default; or the given index tuples in ``pairs``) of
    a static scene reconstructed and scored on the runs left out; returns {views, epsilon_mm, table_offsets_mm,
    rows, summary, own_rows, own_summary, calibration, s_per_pair, views_per_subset, subsets}. ``method``
    ``default``: :data:`stages.methods3d.DEFAULT_METHOD`. ``views``: the folder's :func:`load_views` already
    loaded (several methods on the same masks). ``max_subsets``: at most this many subsets, drawn with ``seed``."""
    method = resolve_method(method)
    if method not in METHODS:
        raise UserError(f"unknown reconstruction method {method!r} (choose from default, {', '.join(METHODS)})")
    views_per_subset = int(views_per_subset)
    if views_per_subset > 2 and method not in (*MULTI_VIEW_METHODS, "visual-hull"):
        raise UserError(f"--views {views_per_subset}: the {method} method reconstructs from two runs (methods that "
                        f"take every run: {', '.join(MULTI_VIEW_METHODS)}, visual-hull)")
    predictor = None if method == "visual-hull" else load_predictor(method, weights)
    views = load_views(folder, seg_method) if views is None else views
    pairs = (held_out_subsets(len(views), views_per_subset, max_subsets, seed) if pairs is None
             else [tuple(p) for p in pairs])
    rows, own, calibration, t0 = [], [], {}, time.perf_counter()
    for n, subset in enumerate(pairs):
        rows += heldout_rows(views, subset, epsilon_mm, method=method, predictor=predictor, side=side,
                             calibrate=calibrate, fit_pose=fit_pose, own=own, calibration=calibration)
        if progress:
            progress(n + 1, len(pairs))
    own_d = np.array([r["distance_mm"] for r in own], float)
    own_d = own_d[np.isfinite(own_d)]
    return {"views": [v.name for v in views], "epsilon_mm": epsilon_mm, "method": method, "seg_method": seg_method,
            "calibrate": calibrate,
            "table_offsets_mm": {v.name: v.table_offset_mm for v in views if v.table_offset_mm is not None},
            "rows": rows, "summary": summarise(rows), "own_rows": own,
            "own_summary": {"n": int(len(own_d)), "distance_mm_mean": float(own_d.mean()) if len(own_d) else None,
                            "distance_mm_median": float(np.median(own_d)) if len(own_d) else None},
            "calibration": calibration, "s_per_pair": (time.perf_counter() - t0) / max(len(pairs), 1),
            "views_per_subset": views_per_subset, "subsets": [[views[k].name for k in p] for p in pairs]}


def held_out_subsets(n_views: int, size: int, max_subsets: int | None = None, seed: int = 0) -> list[tuple]:
    """Every ``size``-subset of ``n_views`` runs (index tuples, in order), or ``max_subsets`` of them drawn with
    ``seed``; at least one run must be left out to score on."""
    if not 2 <= size < n_views:
        raise UserError(f"--views {size}: choose 2 to {n_views - 1} views for {n_views} runs (at least one run is "
                        "left out to score on)")
    subsets = list(itertools.combinations(range(n_views), size))
    if max_subsets is not None and 0 < max_subsets < len(subsets):
        pick = np.random.default_rng(seed).choice(len(subsets), size=max_subsets, replace=False)
        subsets = [subsets[k] for k in sorted(pick)]
    return subsets


def summarise(rows: list[dict]) -> dict:
    """Mean ± sd and median of coverage and distance per pose label, over all (pair, held-out) rows."""
    out = {}
    for label in sorted({r["pose"] for r in rows}):
        sel = [r for r in rows if r["pose"] == label]
        stats = {"n": len(sel)}
        for key in ("coverage", "distance_mm", "distance_median_mm"):
            if not all(key in r for r in sel):
                continue
            vals = np.array([r[key] for r in sel], float)
            vals = vals[np.isfinite(vals)]
            stats[key] = {"mean": float(vals.mean()) if len(vals) else None,
                          "sd": float(vals.std(ddof=1)) if len(vals) > 1 else None,
                          "median": float(np.median(vals)) if len(vals) else None, "n": int(len(vals))}
        out[label] = stats
    return out


def markdown_table(result: dict) -> str:
    """Per-pair table (mean over that pair's held-out views) and the overall summary."""
    rows = result["rows"]
    labels = sorted({r["pose"] for r in rows}, key=lambda s: (s != "nominal", s))
    eps = result["epsilon_mm"]
    head = "| pair | hull voxels | " + " | ".join(
        f"coverage@{eps:g}mm ({lab}) | distance mm ({lab})" for lab in labels) + " |"
    lines = [head, "|" + "---|" * (2 + 2 * len(labels))]
    pairs = list(dict.fromkeys(r["pair"] for r in rows))
    for p in pairs:
        cells = []
        nvox = next(r["hull_voxels"] for r in rows if r["pair"] == p and r["pose"] == "nominal")
        for lab in labels:
            sel = [r for r in rows if r["pair"] == p and r["pose"] == lab]
            cov = np.nanmean([r["coverage"] for r in sel])
            dist = np.array([r["distance_mm"] for r in sel], float)
            dist_s = f"{np.nanmean(dist):.2f}" if np.isfinite(dist).any() else "n/a (no centreline in FOV)"
            cells += [f"{cov:.3f}", dist_s]
        lines.append(f"| {p} | {nvox} | " + " | ".join(cells) + " |")
    lines.append("")
    lines.append("| held-out view | pose | rows | coverage mean | distance mm mean |")
    lines.append("|---|---|---|---|---|")
    for name in result["views"]:
        for lab in labels:
            sel = [r for r in rows if r["heldout"] == name and r["pose"] == lab]
            if sel:
                lines.append(f"| {name} | {lab} | {len(sel)} | {np.nanmean([r['coverage'] for r in sel]):.3f} | "
                             f"{np.nanmean([r['distance_mm'] for r in sel]):.2f} |")
    lines.append("")
    lines.append("| pose | rows | coverage mean ± sd (median) | distance mm mean ± sd (median) |")
    lines.append("|---|---|---|---|")
    for lab in labels:
        s = result["summary"][lab]
        c, d = s["coverage"], s["distance_mm"]
        lines.append(f"| {lab} | {s['n']} | {c['mean']:.3f} ± {c['sd'] or 0:.3f} ({c['median']:.3f}) | "
                     f"{d['mean']:.2f} ± {d['sd'] or 0:.2f} ({d['median']:.2f}) |")
    if all("distance_median_mm" in result["summary"][lab] for lab in labels):
        lines.append("")
        lines.append("Per-row median distance (half of each reconstruction's projected centreline lies closer), "
                     "mean over rows: " + ", ".join(
                         f"{lab} {result['summary'][lab]['distance_median_mm']['mean']:.2f} mm" for lab in labels) + ".")
    own = result.get("own_summary")
    if own and own.get("n"):
        lines.append("")
        n_views = result.get("views_per_subset", 2)
        lines.append(f"Own {'two' if n_views == 2 else n_views} views (reprojection of each reconstruction's 3D "
                     f"centreline into the views it was made from, calibrated cameras): mean {own['distance_mm_mean']:.2f} mm, median "
                     f"{own['distance_mm_median']:.2f} mm over {own['n']} views.")
    cal = result.get("calibration") or {}
    if cal:
        applied = [k for k, v in cal.items() if v.get("applied")]
        lines.append("")
        what = "pairs" if result.get("views_per_subset", 2) == 2 else "subsets"
        lines.append(f"Self-calibration applied in {len(applied)} of {len(cal)} {what}.")
    return "\n".join(lines) + "\n"


def write_heldout_report(result: dict, json_path, md_path=None) -> None:
    from ..core.artefacts import atomic_path, write_json

    write_json(json_path, result)
    if md_path is not None:
        with atomic_path(md_path) as tmp:
            Path(tmp).write_text(markdown_table(result))


# ----------------------------------------------------- several methods side by side (Table 2, bench_heldout)
def method_on_views(views, pairs, method: str, weights=None, side: str = "left") -> tuple[list, float]:
    """Held-out rows (nominal poses, no calibration) of every pair reconstructed by ``method``, and s per pair."""
    res = run_heldout(None, pairs=pairs, method=method, weights=weights, side=side, calibrate=False,
                      fit_pose=False, views=views)
    return res["rows"], res["s_per_pair"]


def method_job(job: tuple) -> dict:
    """One method on the phantom in a worker process: (name, method, weights, folder, side) → rows + timing."""
    import torch

    name, method, weights, folder, side = job
    torch.set_num_threads(1)
    views = load_views(folder, seg_method="unet")
    pairs = list(itertools.combinations(range(len(views)), 2))
    rows, seconds = method_on_views(views, pairs, method, weights, side)
    return {"name": name, "rows": rows, "s_per_pair": seconds, "views": [v.name for v in views],
            "pairs": [list(p) for p in pairs]}


def summary_line(rows) -> str:
    s = summarise(rows)["nominal"]
    return f"coverage {s['coverage']['mean']:.3f} distance {s['distance_mm']['mean']:.2f} mm"


def compare_tables(results: dict, seconds: dict, names: list, pairs: list) -> tuple[list, list]:
    """Markdown: one summary row per method, and per pair (mean over its held-out views) per method."""
    lines = ["| reconstruction (U-Net masks) | rows | coverage@3 mm mean ± sd (median) ↑ | distance mm mean ± sd (median) ↓ | s per pair |",
             "|---|---|---|---|---|"]
    for method, rows in results.items():
        s = summarise(rows)["nominal"]
        c, d = s["coverage"], s["distance_mm"]
        lines.append(f"| {method} | {s['n']} | {c['mean']:.3f} ± {c['sd']:.3f} ({c['median']:.3f}) | "
                     f"{d['mean']:.2f} ± {d['sd']:.2f} ({d['median']:.2f}) | {seconds[method]:.1f} |")
    per_pair = ["| pair | " + " | ".join(f"{m}: coverage / distance mm" for m in results) + " |",
                "|---|" + "---|" * len(results)]
    for i, j in pairs:
        key = f"{names[i]}+{names[j]}"
        cells = []
        for rows in results.values():
            sel = [r for r in rows if r["pair"] == key]
            cov = sum(r["coverage"] for r in sel) / len(sel)
            dist = [r["distance_mm"] for r in sel if r["distance_mm"] == r["distance_mm"]]
            cells.append(f"{cov:.3f} / {sum(dist) / len(dist):.2f}" if dist else f"{cov:.3f} / n/a")
        per_pair.append(f"| {key} | " + " | ".join(cells) + " |")
    return lines, per_pair
