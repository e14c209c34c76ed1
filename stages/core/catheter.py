"""What a catheter looks like, in a 2D vessel centreline and in a 3D tree: the one home of the rule.

Reads and writes nothing. A contrast-filled guiding catheter is dark and tubular, so segmenters keep it
(the shipped U-Net does on data-re's rendered runs), but it is not a coronary. In projection it runs almost
straight across much of the image and enters it from outside, which coronaries, curving over the heart, do
not. A centreline piece at least :data:`STRAIGHT_MIN_PX` long and close to a straight line is taken for one.
Where vessels cross it, the skeleton cuts it into pieces, so the shorter pieces that lie along a detected
catheter line are catheter too (:func:`along_lines`); where a vessel crosses it near the image edge, no one
piece is both long enough and entering the image, so straight pieces that continue each other along one line
are taken together (:func:`catheter_lines`; a guide wire is found the same way).

Two strictnesses (:func:`catheter_line`): the view alignment takes any long piece within
:data:`STRAIGHT_RMS_PX` of a line (dropping a straight vessel there only costs it a little profile mass);
the two-view method, which would lose a vessel it drops, asks for :data:`STRICT_RMS_PX` and an end within
:data:`BORDER_PX` of the image edge. Measured on centreline chains ≥ 60 px: the U-Net's catheters on
data-re's runs are 0.38–0.74 px RMS from their line and the piece entering the image ends 7–26 px from
its edge; data-se's straightest vessel chains ≥ 100 px are 0.75–1.5 px RMS and end ≥ 32 px inside.

In 3D (:func:`straight_end_run`, :func:`catheter_runs`) a catheter that the 2D rule missed is a long
(≥ :data:`CATHETER_MIN_MM`), almost straight (chord / arc ≥ :data:`CATHETER_STRAIGHTNESS`) stretch from a free end
of the tree whose free end projects near the image border (within :data:`CATHETER_BORDER_FRACTION` of the image
size) or outside the image in a view: it enters the field of view, and that climbs from the tree towards its free end
(heading at least :data:`CATHETER_MIN_RISE` towards the head, +z of the patient's LPS frame): a guiding catheter
reaches the ostium from the aorta above the heart, while the coronaries run from the base towards the apex, down.
A catheter entering the tree at the ostium makes one segment with the vessel it joins, so the straight stretch is
measured from the free end only. Straight coronary stretches ending inside the image (a straight mid-LAD, 27 mm in
the bundled example) are not taken, nor those leaving the image downwards: on data-re the straight stretches the
rule took without the climb were true catheters heading 0.45–0.94 up and ghosts, but also 22–40 mm of true vessel
heading 0.20–0.53 down (case_2000017, case_2000011, case_2000000 with three runs), and on the phantom a long
straight vessel leaving IM6's image downwards (0.43–0.74 down).

Before the contrast arrives (:func:`precontrast_frames`, :func:`precontrast_catheter`) a catheter, curved or
straight, is the one tube a run shows: a cine run starts filming before the injection, so its first frames
hold the catheter (and a guide wire) but no coronary. Their masks, shifted onto a key frame's (the catheter
moves with the heart and breathing), say where its catheter lies; the key frame's centreline there that runs
along the shifted catheter is catheter, and so is the mask around it. A vessel crossing the catheter runs
across it and keeps its pixels, the junction included; the left main continuing the catheter's tip lies
beyond the catheter's end and stays. A run that starts after the injection, or a static phantom filled
throughout, has no such frames and keeps its masks as they are.

Used by the inter-run view alignment (a catheter spans every epipolar plane it crosses and drowns the
vessels' crossing profile), by the two-view correspondence method's 2D centrelines and graph-opt's completion
from the views (a catheter in one view finds partners among the other view's vessels and becomes a ghost
tree); the 3D rule by graph-opt, which
drops such stretches, and by the reconstruction's quality check, which flags them; the frames before the contrast by
reconstruct, which labels the key frames' catheter pixels in predictions.zarr (:func:`vessel_labels`), and by
graph-opt, which drops the tracked tree's stretch on them (:func:`stages.graph.stage.drop_catheter_tracked`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage

__all__ = ["STRAIGHT_MIN_PX", "STRAIGHT_RMS_PX", "STRICT_RMS_PX", "BORDER_PX", "ALONG_TOL_PX", "MAX_LINE_GAP_PX",
           "CatheterLine", "line_fit", "catheter_line", "catheter_lines", "along_lines", "CATHETER_MIN_MM", "CATHETER_STRAIGHTNESS", "CATHETER_BORDER_FRACTION", "CATHETER_MIN_RISE", "near_border",
           "straight_end_run", "catheter_runs", "precontrast_frames", "precontrast_catheter",
           "VESSEL", "CATHETER", "vessel_labels"]

STRAIGHT_MIN_PX = 100  # a centreline piece this long (px) ...
STRAIGHT_RMS_PX = 1.5  # ... and this close to a straight line (RMS px) is taken for a catheter (lenient)
STRICT_RMS_PX = 0.8  # the strict rule: this close to a line ...
BORDER_PX = 32  # ... with an end this near the image edge (it enters the field of view)
ALONG_TOL_PX = 2.5  # a shorter piece whose points all lie this close to a catheter line is catheter too
MAX_LINE_GAP_PX = 20  # straight pieces continuing each other across a gap this long (a crossing) make one line
CATHETER_MIN_MM = 20.0  # 3D: a straight stretch from a free end this long ...
CATHETER_STRAIGHTNESS = 0.99  # ... this straight (chord / arc) ...
CATHETER_BORDER_FRACTION = 0.1  # ... whose free end projects this near an image edge (a share of its size) ...
CATHETER_MIN_RISE = 0.25  # ... and which heads at least this much towards the head from the tree to that free end
PRECONTRAST_FILLED_SHARE = 0.4  # a run's leading frames whose mask stays under this share of its filled frames' area
PRECONTRAST_GROWTH = 0.25  # ... and within this growth over its first frames' area hold no contrast yet
PRECONTRAST_REACH_PX = 12  # how far the catheter may move between a frame before the contrast and a key frame
PRECONTRAST_MARGIN_PX = 3  # a key frame's centreline this near the shifted catheter ...
PRECONTRAST_MAX_ANGLE_DEG = 30.0  # ... and this close to its direction ...
PRECONTRAST_MIN_RUN_PX = 8  # ... over this many connected pixels is catheter


@dataclass(frozen=True)
class CatheterLine:
    centre: np.ndarray  # (row, col)
    direction: np.ndarray  # unit (row, col)


def line_fit(points) -> tuple[np.ndarray, np.ndarray, float]:
    """(centre, unit direction, RMS distance of the points from the line) of the least-squares line."""
    pts = np.asarray(points, float).reshape(-1, 2)
    centre = pts.mean(0)
    _, sv, vt = np.linalg.svd(pts - centre, full_matrices=False)
    rms = float(sv[1] / np.sqrt(len(pts))) if len(sv) > 1 else 0.0
    return centre, vt[0], rms


def catheter_line(points, *, max_rms_px: float = STRAIGHT_RMS_PX, shape=None) -> CatheterLine | None:
    """The catheter line through a centreline piece (K×2 pixels, 1 px steps; ordered when ``shape`` is given),
    or None when the piece is too short, further than ``max_rms_px`` RMS from a straight line, or — with the
    image ``shape`` (H, W) — has neither end within :data:`BORDER_PX` of the image edge."""
    pts = np.asarray(points, float).reshape(-1, 2)
    if len(pts) < STRAIGHT_MIN_PX:
        return None
    centre, direction, rms = line_fit(pts)
    if rms >= max_rms_px:
        return None
    if shape is not None:
        ends = pts[[0, -1]]
        edge = np.minimum(ends, np.asarray(shape, float) - 1 - ends).min(1)
        if edge.min() > BORDER_PX:
            return None
    return CatheterLine(centre, direction)


def catheter_lines(chains, shape, *, max_rms_px: float = STRICT_RMS_PX) -> list[CatheterLine]:
    """The catheter lines among one view's centreline chains (ordered K×2 pixels, 1 px steps): each chain that is
    one by itself (:func:`catheter_line` with the image ``shape``), and each line along which straight pieces
    (≥ half :data:`STRAIGHT_MIN_PX`, within ``max_rms_px`` of it) continue each other across gaps of at most
    :data:`MAX_LINE_GAP_PX` and together pass :func:`catheter_line`. A vessel crossing a catheter cuts its
    skeleton; where it crosses near the image edge, no single piece both is long enough and enters the image."""
    lines = [line for line in (catheter_line(c, max_rms_px=max_rms_px, shape=shape) for c in chains)
             if line is not None]
    seeds = sorted((c for c in chains if len(c) >= STRAIGHT_MIN_PX // 2), key=len, reverse=True)
    for seed in seeds:
        centre, direction, rms = line_fit(seed)
        if rms >= max_rms_px or along_lines(seed, lines):
            continue
        pieces = [c for c in chains if along_lines(c, [CatheterLine(centre, direction)])]
        pts = np.vstack(pieces)
        pts = pts[np.argsort((pts - centre) @ direction)]
        if np.max(np.abs(np.diff((pts - centre) @ direction)), initial=0.0) > MAX_LINE_GAP_PX:
            continue
        line = catheter_line(pts, max_rms_px=max_rms_px, shape=shape)
        if line is not None:
            lines.append(line)
    return lines


def along_lines(points, lines: list[CatheterLine], tol_px: float = ALONG_TOL_PX, share: float = 0.9) -> bool:
    """Whether at least ``share`` of the points lie within ``tol_px`` of one catheter line (the whole line:
    a catheter continues straight beyond the piece it was found on)."""
    pts = np.asarray(points, float).reshape(-1, 2)
    if not len(pts):
        return False
    for line in lines:
        rel = pts - line.centre
        across = np.abs(rel[:, 0] * line.direction[1] - rel[:, 1] * line.direction[0])
        if np.mean(across <= tol_px) >= share:
            return True
    return False


def near_border(camera, point) -> bool:
    """Whether a 3D point projects within :data:`CATHETER_BORDER_FRACTION` of the image's edge, or outside it."""
    r, c = np.asarray(camera.project(np.asarray(point, float)[None]), float).reshape(2)
    if not np.isfinite([r, c]).all():
        return True
    margin = CATHETER_BORDER_FRACTION * min(camera.rows, camera.cols)
    return bool(min(r, c, camera.rows - 1 - r, camera.cols - 1 - c) <= margin)


def straight_end_run(points: np.ndarray, start_free: bool, end_free: bool):
    """The longest straight run (chord / arc ≥ :data:`CATHETER_STRAIGHTNESS`) from a free end of a polyline
    (K×3 mm): (length mm, straightness, free end point, the run's point indices from the free end), or None."""
    pts = np.asarray(points, float)
    best = None
    for free, order in ((start_free, np.arange(len(pts))), (end_free, np.arange(len(pts))[::-1])):
        if not free or len(pts) < 2:
            continue
        path = pts[order]
        arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(path, axis=0), axis=1))]
        chord = np.linalg.norm(path - path[0], axis=1)
        ok = np.flatnonzero((arc > 0) & (chord >= CATHETER_STRAIGHTNESS * arc))
        if len(ok):
            j = ok[np.argmax(arc[ok])]
            if best is None or arc[j] > best[0]:
                best = (float(arc[j]), float(chord[j] / arc[j]), path[0], order[: j + 1])
    return best


def catheter_runs(graph, cameras) -> list[tuple[np.ndarray, float, float]]:
    """The catheter-like stretches of a 3D vascular graph (module docstring): per stretch, its node indices
    from the free end inwards, its length (mm) and straightness. ``cameras``: the views' cameras."""
    deg = graph.degrees()
    runs = []
    for seg in graph.segments():
        run = straight_end_run(graph.nodes[seg], deg[seg[0]] == 1, deg[seg[-1]] == 1)
        if run is None or run[0] < CATHETER_MIN_MM:
            continue
        nodes = np.asarray(seg)[run[3]]
        heading = graph.nodes[nodes[0]] - graph.nodes[nodes[-1]]  # from the tree to the free end
        if heading[2] >= CATHETER_MIN_RISE * np.linalg.norm(heading) and any(near_border(cam, run[2]) for cam in cameras):
            runs.append((nodes, run[0], run[1]))
    return runs


# ------------------------------------------------------------------------------------- before the contrast
VESSEL, CATHETER = 1, 2  # a key frame's mask in a prediction artefact: vessel pixels, and those that are catheter


def vessel_labels(mask, catheter=None) -> np.ndarray:
    """H×W uint8: :data:`VESSEL` on the vessel ``mask``, :data:`CATHETER` where ``catheter`` (H×W bool, or None) marks
    it as the catheter, 0 elsewhere. Readers that take any non-zero pixel for vessel see the segmenter's mask."""
    labels = (np.asarray(mask) > 0).astype(np.uint8) * VESSEL
    if catheter is not None:
        labels[(labels > 0) & np.asarray(catheter, bool)] = CATHETER
    return labels


def precontrast_frames(masks) -> np.ndarray | None:
    """The masks (K×H×W bool) of a run's frames before its contrast arrived, from its per-frame vessel masks
    (T×H×W): the leading frames whose segmented area stays under :data:`PRECONTRAST_FILLED_SHARE` of the filled
    frames' (the 90th percentile) and within :data:`PRECONTRAST_GROWTH` of the first frames', less the last of
    them (the ostium may already fill there). None when fewer than two such frames show anything: the run
    starts after the injection, or never fills (a phantom filled throughout)."""
    masks = np.asarray(masks, bool)
    area = masks.reshape(len(masks), -1).sum(1).astype(float)
    filled = float(np.percentile(area, 90))
    first = float(np.median(area[:3]))
    limit = min(PRECONTRAST_FILLED_SHARE * filled, first + max(PRECONTRAST_GROWTH * first, 0.02 * filled))
    n = int(np.argmax(area > limit)) if np.any(area > limit) else 0
    n -= 1
    if n < 2 or np.count_nonzero(area[:n]) < 2:
        return None
    return masks[:n]


def _shifted(img: np.ndarray, dr: int, dc: int) -> np.ndarray:
    """``img`` moved by (dr, dc) pixels, zeros shifted in."""
    out = np.zeros_like(img)
    h, w = img.shape
    out[max(dr, 0):h + min(dr, 0), max(dc, 0):w + min(dc, 0)] = img[max(-dr, 0):h - max(dr, 0), max(-dc, 0):w - max(dc, 0)]
    return out


def _registered(precontrast: np.ndarray, mask: np.ndarray) -> np.ndarray | None:
    """The frame before the contrast that best overlaps ``mask`` once shifted (up to :data:`PRECONTRAST_REACH_PX`),
    shifted there; None when none overlaps it. Searched on masks at half resolution (FFT correlation), then
    refined by a pixel."""
    reach = PRECONTRAST_REACH_PX // 2
    half = mask[::2, ::2].astype(np.float32)
    size = (half.shape[0] + 2 * reach, half.shape[1] + 2 * reach)
    spectrum = np.fft.rfft2(half, size)
    best, best_score = None, 0.0
    for frame in precontrast:
        small = frame[::2, ::2].astype(np.float32)
        total = small.sum()
        if not total:
            continue
        corr = np.fft.irfft2(spectrum * np.conj(np.fft.rfft2(small, size)), size)
        window = np.roll(corr, (reach, reach), (0, 1))[:2 * reach + 1, :2 * reach + 1]  # shifts -reach … reach
        r, c = np.unravel_index(np.argmax(window), window.shape)
        if window[r, c] / total > best_score:
            best_score, best = window[r, c] / total, (frame, 2 * (r - reach), 2 * (c - reach))
    if best is None:
        return None
    frame, dr, dc = best
    shifts = [(dr + i, dc + j) for i in (-1, 0, 1) for j in (-1, 0, 1)]
    overlap = [np.count_nonzero(_shifted(frame, *s) & mask) for s in shifts]
    return _shifted(frame, *shifts[int(np.argmax(overlap))])


def _orientation(skeleton: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel, the local direction of a skeleton's lines as a doubled-angle unit vector (cos 2θ, sin 2θ) of
    its smoothed structure tensor (doubled, so a line's two directions agree)."""
    s = ndimage.gaussian_filter(skeleton.astype(float), 1.0)
    gr, gc = ndimage.sobel(s, 0), ndimage.sobel(s, 1)
    jrr, jcc, jrc = (ndimage.gaussian_filter(g, 2.0) for g in (gr * gr, gc * gc, gr * gc))
    cos2, sin2 = jcc - jrr, 2.0 * jrc
    norm = np.hypot(cos2, sin2) + 1e-12
    return cos2 / norm, sin2 / norm


def precontrast_catheter(mask, precontrast) -> np.ndarray:
    """H×W bool: the pixels of a frame's vessel ``mask`` that are catheter by the frames before the contrast
    (``precontrast``, from :func:`precontrast_frames`; module docstring). Empty when nothing matches."""
    mask = np.asarray(mask, bool)
    gone = np.zeros(mask.shape, bool)
    catheter = None if precontrast is None or not mask.any() else _registered(precontrast, mask)
    if catheter is None or not catheter.any():
        return gone
    # only the catheter's surroundings are looked at (and a margin, so the centreline there is the whole mask's)
    rows, cols = np.flatnonzero(catheter.any(1)), np.flatnonzero(catheter.any(0))
    pad = 4 * PRECONTRAST_MARGIN_PX + PRECONTRAST_REACH_PX
    box = (slice(max(rows[0] - pad, 0), rows[-1] + pad + 1), slice(max(cols[0] - pad, 0), cols[-1] + pad + 1))
    gone[box] = _catheter_in(mask[box], catheter[box])
    return gone


def _catheter_in(mask: np.ndarray, catheter: np.ndarray) -> np.ndarray:
    """:func:`precontrast_catheter` on one image box: ``catheter`` is the registered frame before the contrast."""
    from skimage.morphology import skeletonize

    skel = skeletonize(mask)
    cath_skel = skeletonize(catheter)
    dist, (ir, ic) = ndimage.distance_transform_edt(~cath_skel, return_indices=True)
    near = dist <= PRECONTRAST_MARGIN_PX + np.median(ndimage.distance_transform_edt(catheter)[cath_skel])
    # junctions keep the pixels around them: a vessel crossing the catheter stays whole
    neighbours = ndimage.convolve(skel.astype(np.uint8), np.ones((3, 3), np.uint8), mode="constant")
    junction = ndimage.binary_dilation(skel & (neighbours >= 4), structure=np.ones((3, 3), bool))
    cos_k, sin_k = _orientation(skel)
    cos_c, sin_c = _orientation(cath_skel)
    along = cos_k * cos_c[ir, ic] + sin_k * sin_c[ir, ic] >= np.cos(np.deg2rad(2 * PRECONTRAST_MAX_ANGLE_DEG))
    candidate = skel & near & along & ~junction
    lab, n = ndimage.label(candidate, structure=np.ones((3, 3), bool))
    if not n:
        return np.zeros(mask.shape, bool)
    size = np.bincount(lab.ravel(), minlength=n + 1)
    size[0] = 0
    catheter_skel = size[lab] >= PRECONTRAST_MIN_RUN_PX
    # every mask pixel goes with its nearest centreline pixel
    _, (sr, sc) = ndimage.distance_transform_edt(~skel, return_indices=True)
    return mask & catheter_skel[sr, sc]
