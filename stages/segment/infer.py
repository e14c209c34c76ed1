"""Inference of the vessel segmenter and the two classical baselines; the masks artefact; overlays.

Reads: frames in memory or a run (:mod:`stages.core.runs`), the shipped weights
``stages/weights/seg.pt`` (loaded by :mod:`stages.segment.weights`). Writes: the ``autocar.vessel-masks``
zarr artefact (:func:`write_masks`, layout in :mod:`stages.segment`) and overlay PNGs / GIF
(:func:`save_overlays`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy import ndimage

from ..core.errors import UserError
from .vesselness import _remove_small, temporal_median  # one small-component filter for every method
from .weights import load_model  # re-exported: stages.segment.load_model

log = logging.getLogger(__name__)

METHODS = ("unet", "vesselness", "threshold")
TEXT_MARGIN_PX = 3  # vessel is not looked for this close to burned-in text (its inpainted strokes leave edges)
__all__ = ["segment_frames", "segment_run", "write_masks", "read_masks", "save_overlays", "load_model",
           "field_of_view", "METHODS"]


def field_of_view(frames: np.ndarray, margin: int = 4) -> np.ndarray:
    """H×W field of view of a run: the convex hull of :func:`stages.segment.vesselness.fov_mask` of its temporal
    median frame, eroded by ``margin`` px.

    The hull because collimator shutters and iris leave a convex open field, while a thick, strongly
    opacified vessel reaching the image edge is as dark as the blades: without the hull it was cut out
    of the field of view (and out of every mask) as if it were collimator.
    """
    return _field_of_view_of(temporal_median(frames) if frames.shape[0] > 1 else frames[0], margin)


def _field_of_view_of(ref: np.ndarray, margin: int) -> np.ndarray:
    """:func:`field_of_view` of a run's temporal median frame ``ref``."""
    from skimage.morphology import convex_hull_image

    from .vesselness import fov_mask

    fov = fov_mask(ref, margin=0)
    if fov.mean() < 0.2:  # no recognisable collimator (or an odd image): use everything but the rim
        fov = np.zeros(ref.shape, bool)
        fov[2:-2, 2:-2] = True
        return fov
    fov = convex_hull_image(fov)
    if margin > 0:
        fov = ndimage.binary_erosion(fov, iterations=int(margin), border_value=0)
    return fov


def _unet_prob(frames: np.ndarray, weights=None, batch: int = 4, threads: int | None = 1) -> tuple[np.ndarray, float]:
    """Network probabilities of T×H×W frames, ``batch`` frames per call, on ``threads`` torch threads.

    One thread by default: measured on the shared 2-core machine, 2 OpenMP threads ran this small
    network 5–15× *slower* than one (thread synchronisation under oversubscription), while one thread
    gives ~20–25 frames/s at 512². The caller's torch thread setting is restored afterwards.
    Channels-last memory layout: ~1.4× faster than NCHW for these few-channel convolutions; batch norms folded
    into the convolutions (:func:`~stages.segment.model.fold_batchnorm`): another ~1.2×.
    """
    import torch

    from .model import fold_batchnorm, normalise_frame

    model, thr, _ = load_model(weights)
    model = fold_batchnorm(model).to(memory_format=torch.channels_last)
    old = torch.get_num_threads()
    if threads:
        torch.set_num_threads(int(threads))
    out = np.empty(frames.shape, np.float32)
    try:
        with torch.inference_mode():
            for s in range(0, len(frames), batch):
                x = torch.from_numpy(np.stack([normalise_frame(f) for f in frames[s:s + batch]]))[:, None]
                out[s:s + batch] = torch.sigmoid(model(x.contiguous(memory_format=torch.channels_last)))[:, 0].numpy()
    finally:
        torch.set_num_threads(old)
    return out, thr


def segment_frames(frames, method: str = "unet", threshold: float | None = None, fov=True, min_size: int = 30,
                   fov_margin: int = 4, weights=None, return_fov: bool = False):
    """Vessel probability and mask of every frame: frames T×H×W (or H×W), vessels dark → (prob, mask).

    ``prob`` float32 in [0, 1] and ``mask`` uint8 of the input's shape. ``fov``: True = estimate the
    field of view (:func:`field_of_view`), False = none, or an H×W boolean array. ``threshold``
    overrides the method's default (unet: 0.5 from the weights; vesselness: hysteresis high level 0.3).
    Burned-in text (:func:`stages.segment.cleanup.text_overlay` of the run's temporal median) is painted over
    first and, with ``TEXT_MARGIN_PX`` around it, left out of the field of view (``return_fov`` returns it so).
    """
    from .cleanup import darken_bright_outside, inpaint, text_overlay
    from .vesselness import segment_intensity, segment_vesselness, vesselness

    arr = np.asarray(frames, np.float32)
    single = arr.ndim == 2
    if single:
        arr = arr[None]
    if arr.ndim != 3 or arr.shape[1] < 16 or arr.shape[2] < 16:
        raise UserError(f"segment: expected frames T×H×W of at least 16×16 pixels, got shape {np.shape(frames)}")
    if method not in METHODS:
        raise UserError(f"segment: unknown method {method!r} (choose {', '.join(METHODS)})")
    ref = temporal_median(arr) if arr.shape[0] > 1 else arr[0]
    # burned-in text: painted over with its surroundings before any method sees the frames, and a margin
    # around it left out of the field of view (stages.segment.cleanup); no text found: frames unchanged
    text = text_overlay(ref)
    arr, ref = inpaint(arr, text), inpaint(ref[None], text)[0]
    # a white collimator or detector rim: painted dark, as the training frames' blades (unet normalisation)
    arr = darken_bright_outside(arr, ref)
    if fov is True:
        fov_arr = _field_of_view_of(ref, fov_margin)
    elif fov is False or fov is None:
        fov_arr = np.ones(arr.shape[1:], bool)
    else:
        fov_arr = np.asarray(fov, bool)
    if text.any():
        fov_arr = fov_arr & ~ndimage.binary_dilation(text, iterations=TEXT_MARGIN_PX)
    mask = np.zeros(arr.shape, np.uint8)
    if method == "unet":
        prob, thr = _unet_prob(arr, weights)
        thr = thr if threshold is None else float(threshold)
        prob *= fov_arr
        for t in range(len(arr)):
            mask[t] = _remove_small(prob[t] >= thr, min_size)
    elif method == "vesselness":
        thr = 0.3 if threshold is None else float(threshold)
        prob = np.empty(arr.shape, np.float32)
        for t in range(len(arr)):
            prob[t] = np.clip(vesselness(arr[t], fov=fov_arr), 0, 1)
            mask[t] = segment_vesselness(arr[t], fov=fov_arr, high=thr, min_size=min_size)
    else:
        prob = np.empty(arr.shape, np.float32)
        thr = float("nan") if threshold is None else float(threshold)
        for t in range(len(arr)):
            img = arr[t]
            r = 15
            yy, xx = np.mgrid[-r:r + 1, -r:r + 1]
            tophat = ndimage.grey_closing(img, footprint=(yy ** 2 + xx ** 2) <= r * r) - img
            ref = np.percentile(tophat[fov_arr], 99.5) if fov_arr.any() else 1.0
            prob[t] = np.clip(tophat / max(ref, 1e-6), 0, 1) * fov_arr
            mask[t] = segment_intensity(img, fov=fov_arr, min_size=min_size,
                                        threshold=None if threshold is None else threshold * ref)
    if single:
        prob, mask = prob[0], mask[0]
    if return_fov:
        return prob, mask, fov_arr
    return prob, mask


def segment_run(run, method: str = "unet", geometry=None, threshold: float | None = None, weights=None,
                fov: bool = True, min_size: int = 30) -> dict:
    """Segment every frame of a run (path or :class:`stages.core.runs.Run`) → dict for :func:`write_masks`."""
    from ..core.runs import Run, load_run

    r = run if isinstance(run, Run) else load_run(run, geometry)
    prob, mask, fov_arr = segment_frames(r.frames, method, threshold, fov, min_size, weights=weights, return_fov=True)
    if method == "unet":
        thr = load_model(weights)[1] if threshold is None else threshold
        winfo = {"file": str(Path(weights) if weights else "stages/weights/seg.pt"), "train": load_model(weights)[2]}
    else:
        thr, winfo = (0.3 if threshold is None else threshold) if method == "vesselness" else threshold, None
    return {"run": r, "prob": prob, "mask": mask, "fov": fov_arr, "method": method, "threshold": thr,
            "fov_mode": "estimated" if fov else "none", "weights": winfo}


def _float16(a: np.ndarray) -> np.ndarray:
    """``a`` cast to float16 by torch: the same bits as NumPy's cast, but NumPy takes a slow path for values below
    float16's normal range (most of a probability map: 0.5 s for one 42-frame run, against 0.01 s)."""
    import torch

    return torch.from_numpy(np.ascontiguousarray(a, np.float32)).half().numpy()


def write_masks(path, res: dict) -> Path:
    """Write a :func:`segment_run` result as an ``autocar.vessel-masks`` zarr artefact."""
    from ..core.artefacts import write_zarr
    from . import MASKS_KIND, MASKS_SCHEMA

    r = res["run"]
    T, H, W = res["mask"].shape
    thr = res["threshold"]
    extra = {"source": str(r.path), "method": res["method"],
             "threshold": None if thr is None or (isinstance(thr, float) and np.isnan(thr)) else float(thr),
             "camera": r.camera.to_dict() if r.camera is not None else None,
             "frame_times_ms": [float(v) for v in r.frame_times_ms], "n_frames": T, "shape": [H, W],
             "ecg": r.ecg, "fov": res.get("fov_mode", "estimated"), "weights": res.get("weights")}
    with write_zarr(path, kind=MASKS_KIND, schema_version=MASKS_SCHEMA, stage="segment", inputs=[str(r.path)],
                    parameters={"method": res["method"], "threshold": extra["threshold"]}, extra_attrs=extra) as g:
        g.create_array("prob", data=_float16(res["prob"]), chunks=(1, H, W))
        g.create_array("mask", data=res["mask"].astype(np.uint8), chunks=(1, H, W))
        g.create_array("fov", data=res["fov"].astype(np.uint8))
    return Path(path)


def read_masks(path) -> dict:
    """Read an ``autocar.vessel-masks`` artefact → {prob (float32), mask (uint8), fov, attrs}."""
    from ..core.artefacts import read_zarr
    from . import MASKS_KIND, MASKS_SCHEMA

    g = read_zarr(path, kind=MASKS_KIND, schema_version=MASKS_SCHEMA)
    return {"prob": g["prob"][...].astype(np.float32), "mask": g["mask"][...], "fov": g["fov"][...].astype(bool),
            "attrs": dict(g.attrs)}


def overlay_rgb(frame: np.ndarray, mask: np.ndarray, fov: np.ndarray | None = None) -> np.ndarray:
    """8-bit RGB: the frame in grey, the mask in translucent red, the field-of-view border in yellow."""
    f = np.asarray(frame, np.float32)
    lo, hi = np.percentile(f, [0.5, 99.5])
    g = np.clip((f - lo) / max(hi - lo, 1e-6) * 255, 0, 255)
    rgb = np.repeat(g[..., None], 3, -1)
    m = np.asarray(mask, bool)
    rgb[m] = 0.45 * rgb[m] + 0.55 * np.array([255.0, 30.0, 30.0])
    if fov is not None:
        edge = fov & ~ndimage.binary_erosion(fov)
        rgb[ndimage.binary_dilation(edge)] = [255.0, 220.0, 0.0]
    return rgb.astype(np.uint8)


def save_overlays(frames, mask, out_prefix, fov=None, every: int = 1, max_png: int = 4) -> list[Path]:
    """``<prefix>_fNNN.png`` overlays of up to ``max_png`` frames and ``<prefix>.gif`` of all frames."""
    from PIL import Image

    from ..core.artefacts import atomic_path
    from ..core.figures import save_image_png

    frames = np.asarray(frames)
    mask = np.asarray(mask)
    if frames.ndim == 2:
        frames, mask = frames[None], mask[None]
    out_prefix = Path(out_prefix)
    out_prefix.parent.mkdir(parents=True, exist_ok=True)
    written = []
    T = len(frames)
    pick = np.unique(np.linspace(0, T - 1, min(max_png, T)).round().astype(int))
    for t in pick:
        p = out_prefix.parent / f"{out_prefix.name}_f{t:03d}.png"
        written.append(save_image_png(Image.fromarray(overlay_rgb(frames[t], mask[t], fov)), p))
    imgs = [Image.fromarray(overlay_rgb(frames[t], mask[t], fov)).resize((256, 256 * frames.shape[1] // frames.shape[2]))
            for t in range(0, T, max(every, 1))]
    p = out_prefix.parent / f"{out_prefix.name}.gif"
    with atomic_path(p) as tmp:
        imgs[0].save(tmp, format="GIF", save_all=True, append_images=imgs[1:], duration=80, loop=0)
    written.append(p)
    return written
