"""Held-out-view check: scoring a reconstruction of a *static* scene on real X-ray runs without 3D truth.

Reads: a folder of XA DICOM runs of one static object (e.g. ../shared/data/phantom_xa, 8 runs) via
:func:`stages.dicom_io.read_xa`. Writes (from :func:`write_heldout_report`): a JSON file with every row
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

Segmentation: a full-contrast frame (median of the later frames, :func:`stages.vesselness.contrast_frame`),
segmented with ``seg_method`` (:func:`stages.segment.segment_frames`: the U-Net, Frangi vesselness with
hysteresis, or thresholding).

No pose refinement is applied: the header geometry is used as it is. (A refinement of the second
view's image shift that maximises two-view consistency was tried and dropped: with nominal headers
the hull's reprojection already covers 99.7 % of the input views' centrelines, so the two input
views alone give no signal to fit an offset; see docs/HELDOUT.md.)
"""

from __future__ import annotations

import itertools
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy import ndimage

from .errors import UserError
from .geometry import Camera
from .methods3d import METHODS, load_predictor
from .metrics import EPSILON_MM, skeleton
from .vesselness import centreline_2d, contrast_frame, fov_mask, segment_vesselness
from .visual_hull import project_to_mask, visual_hull

log = logging.getLogger(__name__)

__all__ = ["View", "load_views", "heldout_rows", "run_heldout", "write_heldout_report", "METHODS"]



@dataclass
class View:
    """One run reduced to what the check needs."""

    name: str
    camera: Camera
    mask: np.ndarray  # H×W vessel mask
    fov: np.ndarray  # H×W field of view
    centreline: np.ndarray  # H×W 1-px centreline of the mask

    def __post_init__(self):
        # distance (px) from each pixel to the nearest centreline pixel, computed once per view
        self.dist_to_centreline = ndimage.distance_transform_edt(~self.centreline)


def load_views(folder, seg_method: str = "vesselness") -> list[View]:
    """Read every ``*.dcm`` in ``folder``, segment a full-contrast frame, return the views by name."""
    from .dicom_io import read_xa
    from .segment import segment_frames

    folder = Path(folder)
    files = sorted(folder.glob("*.dcm"))
    if len(files) < 3:
        raise UserError(f"{folder}: the held-out check needs at least 3 DICOM runs (*.dcm), found {len(files)}")
    views = []
    for f in files:
        run = read_xa(f)
        img = contrast_frame(run.frames)
        fov = fov_mask(img)
        if seg_method == "vesselness":
            mask = segment_vesselness(img, fov=fov)
        else:
            mask = segment_frames(img, method=seg_method)[1].astype(bool)
        views.append(View(f.stem, run.camera, mask, fov, centreline_2d(mask)))
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


def two_view_voxels(mask_a, mask_b, cam_a: Camera, cam_b: Camera, method: str = "visual-hull", predictor=None,
                    side: str = "left"):
    """The reconstruction (SparseVoxels, occupied voxels only) of one two-view pair by ``method``
    (:mod:`stages.methods3d`; ``predictor``: that method's loaded predictor, to load weights only once)."""
    if method == "visual-hull" and predictor is None:
        return visual_hull([mask_a, mask_b], [cam_a, cam_b])  # occupancy is 1 everywhere: no features needed
    pred = (predictor or load_predictor(method))(mask_a, mask_b, cam_a, cam_b, side)
    return pred.subset(np.asarray(pred.features["occupancy"]) >= 0.5)


def heldout_rows(views: list[View], pair: tuple[int, int], epsilon_mm: float = EPSILON_MM,
                 shift_b=(0.0, 0.0), label: str = "nominal", method: str = "visual-hull", predictor=None,
                 side: str = "left") -> list[dict]:
    """Reconstruct from ``views[pair]`` (by ``method``) and score it in every other view."""
    i, j = pair
    cam_j = views[j].camera.shifted(*shift_b) if np.any(shift_b) else views[j].camera
    hull = two_view_voxels(views[i].mask, views[j].mask, views[i].camera, cam_j, method, predictor, side)
    pts = hull.world_points()
    cl = _hull_centreline(hull)
    rows = []
    for k, v in enumerate(views):
        if k in pair:
            continue
        spacing = v.camera.isocentre_spacing
        cov = _coverage(pts, v, v.camera, epsilon_mm / spacing)
        rc = v.camera.project(cl)
        r = np.rint(rc[:, 0])
        c = np.rint(rc[:, 1])
        ok = np.isfinite(r) & np.isfinite(c) & (r >= 0) & (r < v.camera.rows) & (c >= 0) & (c < v.camera.cols)
        ok[ok] = v.fov[r[ok].astype(int), c[ok].astype(int)]
        if ok.any():
            # sub-pixel: interpolate the distance map bilinearly at the projected points
            d_px = ndimage.map_coordinates(v.dist_to_centreline, rc[ok].T, order=1, mode="nearest")
            dist = float(d_px.mean() * spacing)
        else:
            dist = float("nan")
        rows.append({
            "pair": f"{views[i].name}+{views[j].name}", "heldout": v.name, "pose": label, "method": method,
            "shift_px": [float(shift_b[0]), float(shift_b[1])],
            "hull_voxels": len(hull), "centreline_points": int(ok.sum()),
            "coverage": cov, "distance_mm": dist,
            "status": "ok" if ok.any() else "no-projected-centreline-in-fov",
        })
    return rows


def run_heldout(folder, epsilon_mm: float = EPSILON_MM, pairs=None, progress=None, method: str = "visual-hull",
                weights=None, seg_method: str = "vesselness", side: str = "left") -> dict:
    """All run pairs (or the given index pairs) of a static scene; returns {views, epsilon_mm, rows, summary}."""
    if method not in METHODS:
        raise UserError(f"unknown reconstruction method {method!r} (choose from {', '.join(METHODS)})")
    predictor = None if method == "visual-hull" else load_predictor(method, weights)
    views = load_views(folder, seg_method)
    pairs = list(itertools.combinations(range(len(views)), 2)) if pairs is None else [tuple(p) for p in pairs]
    rows = []
    for n, (i, j) in enumerate(pairs):
        rows += heldout_rows(views, (i, j), epsilon_mm, method=method, predictor=predictor, side=side)
        if progress:
            progress(n + 1, len(pairs))
    return {"views": [v.name for v in views], "epsilon_mm": epsilon_mm, "method": method, "seg_method": seg_method,
            "rows": rows, "summary": summarise(rows)}


def summarise(rows: list[dict]) -> dict:
    """Mean ± sd and median of coverage and distance per pose label, over all (pair, held-out) rows."""
    out = {}
    for label in sorted({r["pose"] for r in rows}):
        sel = [r for r in rows if r["pose"] == label]
        stats = {"n": len(sel)}
        for key in ("coverage", "distance_mm"):
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
    lines.append("| held-out view | rows | coverage mean | distance mm mean |")
    lines.append("|---|---|---|---|")
    for name in result["views"]:
        sel = [r for r in rows if r["heldout"] == name and r["pose"] == labels[0]]
        if sel:
            lines.append(f"| {name} | {len(sel)} | {np.nanmean([r['coverage'] for r in sel]):.3f} | "
                         f"{np.nanmean([r['distance_mm'] for r in sel]):.2f} |")
    lines.append("")
    lines.append("| pose | rows | coverage mean ± sd (median) | distance mm mean ± sd (median) |")
    lines.append("|---|---|---|---|")
    for lab in labels:
        s = result["summary"][lab]
        c, d = s["coverage"], s["distance_mm"]
        lines.append(f"| {lab} | {s['n']} | {c['mean']:.3f} ± {c['sd']:.3f} ({c['median']:.3f}) | "
                     f"{d['mean']:.2f} ± {d['sd']:.2f} ({d['median']:.2f}) |")
    return "\n".join(lines) + "\n"


def write_heldout_report(result: dict, json_path, md_path=None) -> None:
    from .artefacts import atomic_path, write_json

    write_json(json_path, result)
    if md_path is not None:
        with atomic_path(md_path) as tmp:
            Path(tmp).write_text(markdown_table(result))
