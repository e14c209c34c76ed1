"""The segmenters on real X-ray frames, measured without ground truth.

Reads: XA runs (DICOM through :func:`stages.core.dicom_io.read_xa`, e.g. the static phantom in
``../shared/data/phantom_xa``) or frames in memory. Writes nothing: every function returns arrays or
dicts; ``benchmarks/bench_segment_real.py`` turns them into docs/benchmarks/segment_real.md.

Per run, on the full-contrast frame the project already uses (:func:`stages.evaluate.heldout.contrast_mask`:
the median of the later half of the frames), for each segmenter:

* vessel area (px, and % of the field of view), connected pieces (8-connected) and the share of the area
  in the largest;
* centreline length (px of the 2D thinning, :func:`stages.segment.vesselness.centreline_2d`);
* pieces touching the border zone (within ``BORDER_PX`` of the open field's edge — the collimator blades
  or the detector edge) and mask pixels in the collimator corners (the border zone near the open
  field's bounding-box corners);
* catheter-like pieces: long, straight centreline branches (:func:`straight_branches`) found in the union
  of the segmenters' masks, and how much of each lies in each segmenter's mask;
* agreement between two segmenters: Dice, and the share of each one's centreline within ``TOL_PX`` of
  the other's.

:func:`heldout_explained` adds, for a few run pairs, what fraction of each held-out view's centreline
(each segmenter's own masks) the pair's reconstruction explains (:func:`stages.evaluate.heldout.heldout_rows`).

:func:`stress_frames` / :func:`stress_scores` put what clinical frames carry and the phantom does not into its
real frames — burned-in white text inside the field, a white collimator, a white detector border (and dark
text, which is not handled) — and count the vessel pixels each segmenter then finds in them.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from .vesselness import centreline_2d, fov_mask

__all__ = ["BORDER_PX", "CORNER_PX", "TOL_PX", "open_field", "border_zones", "piece_stats", "straight_branches",
           "catheter_pieces", "agreement", "measure_run", "heldout_explained",
           "burn_text", "stress_frames", "stress_scores"]

BORDER_PX = 8  # a piece within this many px of the open field's edge "touches the border"
CORNER_PX = 80  # corner zone: border zone within this many px (Chebyshev) of a corner of the field's bounding box
TOL_PX = 3  # agreement tolerance between two centrelines
EIGHT = np.ones((3, 3), bool)


def open_field(img: np.ndarray) -> np.ndarray:
    """The exposed area without margin (:func:`stages.segment.vesselness.fov_mask` with ``margin=0``)."""
    return fov_mask(img, margin=0)


def border_zones(img: np.ndarray, border_px: int = BORDER_PX, corner_px: int = CORNER_PX):
    """(border, corner) zones of a frame: open-field pixels within ``border_px`` of its edge (or outside it),
    and those of them near the four corners of the open field's bounding box."""
    field = open_field(img)
    inner = ndimage.binary_erosion(field, iterations=int(border_px), border_value=0)
    border = ~inner
    corner = np.zeros_like(border)
    if field.any():
        rows, cols = np.nonzero(field)
        r0, r1, c0, c1 = rows.min(), rows.max(), cols.min(), cols.max()
        rr, cc = np.mgrid[0:img.shape[0], 0:img.shape[1]]
        for r, c in ((r0, c0), (r0, c1), (r1, c0), (r1, c1)):
            corner |= (np.abs(rr - r) < corner_px) & (np.abs(cc - c) < corner_px)
    return border, border & corner


def piece_stats(mask: np.ndarray, fov: np.ndarray, border: np.ndarray, corner: np.ndarray) -> dict:
    """Area, pieces, largest share, centreline length, border-touching pieces and corner pixels of one mask."""
    m = np.asarray(mask, bool)
    lab, n = ndimage.label(m, structure=EIGHT)
    sizes = np.bincount(lab.ravel())[1:]
    touching = np.unique(lab[border & m])
    touching = touching[touching > 0]
    area = int(m.sum())
    return {"area_px": area, "area_pct_fov": 100.0 * area / max(int(fov.sum()), 1), "pieces": int(n),
            "largest_share": float(sizes.max() / area) if n else 0.0,
            "centreline_px": int(centreline_2d(m).sum()),
            "border_pieces": int(len(touching)), "border_px": int(sizes[touching - 1].sum()) if len(touching) else 0,
            "corner_px": int((m & corner).sum())}


def _branches(skel: np.ndarray):
    """Labelled branches of a 1-px skeleton: the skeleton without its junction pixels (≥ 3 neighbours)."""
    nb = ndimage.convolve(skel.astype(np.uint8), EIGHT.astype(np.uint8), mode="constant") - skel
    return ndimage.label(skel & (nb < 3), structure=EIGHT)


def straight_branches(mask: np.ndarray, min_len: int = 60, max_rms: float = 1.2) -> list[dict]:
    """Long straight pieces of a mask's centreline: branches between junctions/ends with ≥ ``min_len`` px
    whose RMS distance from their principal axis is ≤ ``max_rms`` px. Each: length (px, extent along the
    axis), rms, and its pixels (N×2 row, col). Catheters and straight tubes look like this; coronaries
    rarely stay that straight over 60 px (~20 mm at the phantom's ~0.32 mm isocentre pixel)."""
    lab, n = _branches(centreline_2d(np.asarray(mask, bool)))
    out = []
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        pts = np.argwhere(lab[sl] == k) + [sl[0].start, sl[1].start]
        if len(pts) < min_len:
            continue
        c = pts - pts.mean(0)
        _, s, vt = np.linalg.svd(c, full_matrices=False)
        along = c @ vt[0]
        rms = float(np.sqrt(np.mean((c @ vt[1]) ** 2)))
        if rms <= max_rms and np.ptp(along) >= min_len:
            out.append({"length_px": float(np.ptp(along)), "rms_px": rms, "pixels": pts})
    return sorted(out, key=lambda b: -b["length_px"])


def catheter_pieces(masks: dict) -> list[dict]:
    """Catheter-like straight pieces in the union of the segmenters' masks, each with the share of its
    centreline inside each segmenter's mask (dilated by 1 px)."""
    union = np.logical_or.reduce([np.asarray(m, bool) for m in masks.values()])
    grown = {k: ndimage.binary_dilation(np.asarray(m, bool), structure=EIGHT) for k, m in masks.items()}
    out = []
    for b in straight_branches(union):
        r, c = b["pixels"].T
        out.append({"length_px": b["length_px"], "rms_px": b["rms_px"],
                    "in_mask": {k: float(g[r, c].mean()) for k, g in grown.items()}})
    return out


def agreement(a: np.ndarray, b: np.ndarray, tol: float = TOL_PX) -> dict:
    """Dice of two masks and the share of each one's centreline within ``tol`` px of the other's."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    ca, cb = centreline_2d(a), centreline_2d(b)
    da, db = ndimage.distance_transform_edt(~ca), ndimage.distance_transform_edt(~cb)
    return {"dice": float(2 * (a & b).sum() / max(a.sum() + b.sum(), 1)),
            "a_in_b": float((db[ca] <= tol).mean()) if ca.any() else float("nan"),
            "b_in_a": float((da[cb] <= tol).mean()) if cb.any() else float("nan")}


def measure_run(frames: np.ndarray, methods=("unet", "vesselness"), stress: bool = True) -> dict:
    """Every figure of the module docstring for one run: {img, fov, masks, stats, catheter, agreement (between
    the first two methods), single_frame (per method: the last raw frame's mask against the full-contrast
    frame's, :func:`agreement` — what per-frame noise changes), stress (:func:`stress_scores`, if asked)}."""
    from ..evaluate.heldout import contrast_mask
    from .vesselness import contrast_frame

    img = contrast_frame(frames)
    masks, fov = {}, None
    for m in methods:
        masks[m], fov = contrast_mask(frames, m)
    border, corner = border_zones(img)
    stats = {m: piece_stats(mk, fov, border, corner) for m, mk in masks.items()}
    agree = agreement(masks[methods[0]], masks[methods[1]]) if len(methods) > 1 else None
    single = {m: agreement(contrast_mask(frames[-1:], m)[0], masks[m]) for m in methods}
    return {"img": img, "fov": fov, "masks": masks, "stats": stats, "catheter": catheter_pieces(masks),
            "agreement": agree, "single_frame": single, "stress": stress_scores(img, masks, methods) if stress else None}


def heldout_explained(folder, pairs, seg_methods=("unet", "vesselness"), method: str = "correspondence") -> dict:
    """Per segmenter: held-out rows (:func:`stages.evaluate.heldout.heldout_rows`, pair calibration on, fitted
    held-out poses) of the given index pairs, every view segmented by that segmenter (reconstruction and
    held-out centrelines alike). Coverage = fraction of the held-out view's centreline within 3 mm
    (isocentre) of the projected reconstruction."""
    from ..evaluate.heldout import heldout_rows, load_views
    from ..methods3d import load_predictor

    predictor = load_predictor(method)
    out = {}
    for seg in seg_methods:
        views = load_views(folder, seg_method=seg)
        out[seg] = [row for pr in pairs for row in heldout_rows(views, tuple(pr), method=method, predictor=predictor,
                                                              calibrate=True, fit_pose=True)]
    return out


# ---------------------------------------------------------------- what the phantom lacks, put into its frames
TEXT_LINES = ("LAO 31.3 CRA 0.1", "FR 15/s 12/14", "PHANTOM ID 000123")


def burn_text(img: np.ndarray, row: int, col: int, value: float, scale: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``img`` with a three-line annotation (PIL's default font, ``scale``× magnified) drawn at (row, col)
    in ``value``; and the stroke pixels."""
    from PIL import Image, ImageDraw

    h, w = img.shape
    canvas = Image.new("L", (w // scale + 1, h // scale + 1), 0)
    ImageDraw.Draw(canvas).multiline_text((col // scale, row // scale), "\n".join(TEXT_LINES), fill=255)
    strokes = np.kron(np.asarray(canvas) > 0, np.ones((scale, scale), bool))[:h, :w]
    return np.where(strokes, np.float32(value), img).astype(np.float32), strokes


def stress_frames(img: np.ndarray) -> dict:
    """name → (frame, artefact pixels) of one real frame with an artefact put in: white / black burned-in text
    in the field's upper left, the dark collimator turned white, a 6-px white detector border."""
    field = open_field(img)
    rows, cols = np.nonzero(field)
    r0, c0 = int(rows.min()) + 24, int(cols.min()) + 24
    top = max(255.0, float(img.max()))
    out = {"white text": burn_text(img, r0, c0, top), "black text": burn_text(img, r0, c0, 0.0)}
    outside = ~ndimage.binary_dilation(field, iterations=2)
    out["white collimator"] = (np.where(outside, np.float32(top), img).astype(np.float32), outside)
    rim = np.zeros(img.shape, bool)
    rim[:6], rim[-6:], rim[:, :6], rim[:, -6:] = True, True, True, True
    out["white border"] = (np.where(rim, np.float32(top), img).astype(np.float32), rim)
    return out


def _mask_of(img: np.ndarray, method: str) -> np.ndarray:
    """The held-out check's mask of one full-contrast frame (:func:`stages.evaluate.heldout.contrast_mask`)."""
    from ..evaluate.heldout import contrast_mask

    return contrast_mask(img[None], method)[0]


def stress_scores(img: np.ndarray, clean: dict, methods=("unet", "vesselness"), near_px: int = 12) -> dict:
    """Per artefact and segmenter: vessel pixels within ``near_px`` of the artefact that the clean frame's mask
    (``clean[method]``) does not have, and the Dice of the mask against the clean one."""
    out = {}
    for name, (frame, art) in stress_frames(img).items():
        zone = ndimage.binary_dilation(art, iterations=int(near_px))
        out[name] = {}
        for m in methods:
            mk, cm = _mask_of(frame, m), np.asarray(clean[m], bool)
            out[name][m] = {"false_px": int((mk & zone & ~cm).sum()),
                            "dice_vs_clean": float(2 * (mk & cm).sum() / max(mk.sum() + cm.sum(), 1))}
    return out
