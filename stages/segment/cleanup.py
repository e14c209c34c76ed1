"""What real frames carry besides the patient: burned-in text and graphics, bright collimator fields and rims.

Reads: one 2D frame (H×W float, vessels dark) — a run's temporal median for :func:`text_overlay` and
:func:`darken_bright_outside`, any frame for :func:`bright_outside` — or a T×H×W stack for :func:`inpaint`.
Writes nothing (arrays in memory).

Measured on the real phantom and on synthetic stress frames (docs/benchmarks/segment_real.md):

* **Burned-in text** (patient name, angles, frame counter; white on most systems) is a set of thin,
  saturated-bright strokes. Both segmenters fired on it: the dark gaps between strokes look like
  thin vessels (three lines burned into each of the 8 phantom frames: 28 169 false vessel px for the U-Net,
  65 197 for Frangi; after this module 463 and 0).
  :func:`text_overlay` finds it — thin bright structures (white top-hat, ``TOPHAT_PX``) within 10 % of the
  frame's top value and ≥ 30 % of its intensity span above their surroundings, grouped in glyph-sized
  pieces (``MIN_GLYPH_PX``–``GLYPH_PX`` across, ≥ ``MIN_STROKE_PX`` stroke pixels, half as many within
  2 % of the span of the top value: text is drawn saturated, a bright noise speck has one such pixel) —
  and :func:`inpaint` replaces it by the surrounding background before segmentation; the segmenter then leaves a margin around it (:mod:`stages.segment.infer`).
  Text that is not near the frame's top value (dark text, grey text) is not found.
* **Bright collimator fields and detector borders** (some systems show the blades white, or a white rim
  around the detector): :func:`stages.segment.vesselness.fov_mask` used to remove only *dark* outside
  regions, so the step from the bright outside to the field was a "vessel" for Frangi (5 400 px along a
  white collimator on a synthetic frame, 738 px over the 8 phantom frames with white blades). :func:`bright_outside` marks regions brighter than ``BRIGHT_FACTOR`` × the smoothed
  median that touch the image border, grown by ``BRIGHT_GROW_PX``; ``fov_mask`` removes them as it removes the
  dark ones. A bright *rim* inside dark blades is not removed (it does not touch the image border); the U-Net
  ignores it, the Frangi baseline of ``segment_frames`` (field-of-view margin 4 px) answers along it.
"""

from __future__ import annotations

import numpy as np
from scipy import ndimage

__all__ = ["TOPHAT_PX", "GLYPH_PX", "MIN_GLYPH_PX", "MIN_STROKE_PX", "BRIGHT_FACTOR", "BRIGHT_GROW_PX", "text_overlay",
           "inpaint", "bright_outside", "darken_bright_outside"]

TOPHAT_PX = 7  # strokes narrower than this are "thin bright structures"
GLYPH_PX = 48  # a glyph (or a clump of touching glyphs) is at most this many px across
MIN_GLYPH_PX = 5  # ... and at least this many (noise specks and halo speckle on the phantom: 1-4 px)
MIN_STROKE_PX = 12  # ... with at least this many stroke pixels (phantom specks: 3-5 px)
BRIGHT_FACTOR = 1.6  # smoothed outside regions this much brighter than the median are not field of view
BRIGHT_GROW_PX = 12  # ... nor is this band inside them (2 × the largest Frangi scale of the vesselness baseline)


def text_overlay(image: np.ndarray, grow: int = 2) -> np.ndarray:
    """H×W boolean: burned-in bright text/graphics of a frame (or a run's temporal median), grown by ``grow`` px.

    Empty when the frame carries none (nothing near its top value is thin and glyph-sized), so frames
    without text are segmented exactly as before.
    """
    img = np.asarray(image, np.float32)
    lo, hi = np.percentile(img, [0.5, 99.5])
    span = max(float(hi - lo), 1e-6)
    top = float(img.max())
    tophat = img - ndimage.grey_opening(img, size=(TOPHAT_PX, TOPHAT_PX))
    cand = (img >= top - 0.1 * span) & (tophat > 0.3 * span)
    if not cand.any():
        return np.zeros(img.shape, bool)
    lab, n = ndimage.label(cand, structure=np.ones((3, 3)))
    core = img >= top - 0.02 * span  # burned-in text is drawn at (or next to) the top value, not noise around it
    keep = np.zeros(n + 1, bool)
    for k, sl in enumerate(ndimage.find_objects(lab), start=1):
        h, w = sl[0].stop - sl[0].start, sl[1].stop - sl[1].start
        piece = lab[sl] == k
        keep[k] = (MIN_GLYPH_PX <= max(h, w) <= GLYPH_PX and piece.sum() >= MIN_STROKE_PX
                   and 2 * (piece & core[sl]).sum() >= MIN_STROKE_PX)
    text = keep[lab]
    if grow > 0 and text.any():
        text = ndimage.binary_dilation(text, iterations=int(grow))
    return text


def inpaint(frames: np.ndarray, region: np.ndarray, sigma: float = 4.0) -> np.ndarray:
    """Frames (T×H×W) with ``region`` replaced by the Gaussian-weighted mean of the pixels around it
    (normalised convolution; where none lies within reach, the frame's median). A copy; no-op if empty."""
    region = np.asarray(region, bool)
    if not region.any():
        return frames
    out = np.array(frames, np.float32, copy=True)
    valid = (~region).astype(np.float32)
    weight = ndimage.gaussian_filter(valid, sigma)
    for t in range(len(out)):
        fill = ndimage.gaussian_filter(out[t] * valid, sigma) / np.maximum(weight, 1e-6)
        fill = np.where(weight > 1e-3, fill, np.median(out[t][~region]))
        out[t][region] = fill[region]
    return out


def bright_outside(image: np.ndarray, ref: float, factor: float = BRIGHT_FACTOR, grow: int = BRIGHT_GROW_PX) -> np.ndarray:
    """Regions of a frame brighter than ``factor`` × ``ref`` (its smoothed median) that touch the image border —
    a white collimator field or detector rim, never part of the field of view — grown by ``grow`` px.

    Found after smoothing with σ = 6 px (wide fields) and with σ = 1 px (thin rims, and the last px before
    the field's edge that the heavy smoothing blurs below the level). Grown because the step from a bright
    outside down to the field puts the dark side of the edge, where a dark-ridge filter answers (up to
    about twice its largest scale), inside the field; a dark outside keeps that side outside by itself."""
    img = np.asarray(image, np.float32)
    out = np.zeros(img.shape, bool)
    for sigma in (6.0, 1.0):
        bright = ndimage.gaussian_filter(img, sigma) > factor * ref
        if bright.any():
            lab, _ = ndimage.label(bright)
            edge = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
            out |= np.isin(lab, edge[edge > 0])
    return ndimage.binary_dilation(out, iterations=int(grow)) if grow > 0 and out.any() else out


def darken_bright_outside(frames: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """Frames (T×H×W) with the bright outside of their temporal median ``ref`` (:func:`bright_outside`, not grown)
    painted at ``ref``'s 0.5th percentile, as dark as the collimator blades the U-Net was trained with.

    Why: the network normalises each frame by its 0.5–99.5th percentiles; a white collimator moves the upper
    one from the field's brightest pixels to the blades and shrinks every vessel's contrast (on the phantom's
    frames with their collimator turned white: Dice 0.91 against the masks of the original frames, 0.999 with
    the blades painted dark). A copy; no-op when there is no bright outside."""
    ref = np.asarray(ref, np.float32)
    bright = bright_outside(ref, float(np.median(ndimage.gaussian_filter(ref, 6.0))), grow=0)
    if not bright.any():
        return frames
    out = np.array(frames, np.float32, copy=True)
    out[:, bright] = np.percentile(ref[~bright], 0.5)
    return out
