"""``autocar segment``: per-frame 2D vessel probability and mask of an XA run.

Reads: an XA run — a DICOM file (:func:`stages.core.dicom_io.read_xa`), a folder of frame images
(PNG/TIFF/JPEG, sorted by name) or a ``.npy``/``.npz`` T×H×W stack, the last two with an optional
geometry JSON (``{"alpha", "beta", "sid", "sod", "spacing": [r, c], "frame_time_ms", "r_wave_times_ms"}``).
Writes: a masks artefact, zarr kind ``"autocar.vessel-masks"`` (schema 1)::

    attrs: standard header + source (run path), method ("unet" | "vesselness" | "threshold"),
           threshold, camera (Camera.to_dict() or null), frame_times_ms (list), n_frames, shape,
           ecg (dict or null), fov ("estimated" | "none"), weights (file + training info, unet only)
    prob   T×H×W float16   vessel probability (vesselness: normalised response; threshold: scaled top-hat)
    mask   T×H×W uint8     binary vessel mask
    fov    H×W uint8       field of view used (collimator and dark corners excluded)

and, beside it, overlay PNGs and an animated GIF preview (:func:`save_overlays`).

Python API (what ``reconstruct`` calls)::

    from stages.segment import segment_frames, segment_run, write_masks, read_masks
    prob, mask = segment_frames(frames, method="unet")      # frames T×H×W (or H×W), vessels dark
    res = segment_run("run_a.dcm", method="unet")           # dict: prob, mask, fov, run, method, threshold
    write_masks("masks_a.zarr", res); m = read_masks("masks_a.zarr")   # dict with prob, mask, attrs

Methods:

* ``unet`` (default) — the shipped network ``stages/weights/seg.pt`` (:mod:`stages.segment.model`,
  trained by ``make train-seg`` on simulated frames, :mod:`stages.segment.train`), sigmoid
  probability, threshold 0.5 (stored in the weights);
* ``vesselness`` — multiscale Frangi vesselness + hysteresis (:func:`stages.segment.vesselness.segment_vesselness`);
* ``threshold`` — black top-hat + Otsu (:func:`stages.segment.vesselness.segment_intensity`).

Post-processing, all methods: the field of view (:func:`stages.segment.vesselness.fov_mask` of the run's
temporal median frame: heavy smoothing, the dark collimator region and corners removed, a margin of
``fov_margin`` px) is applied to the probability, and connected components smaller than
``min_size`` px are dropped from the mask. Before any method runs, burned-in white text is painted over and
left out of the field of view, and a white collimator or detector border is painted dark and left out
(:mod:`stages.segment.cleanup`; measured on the real phantom: :mod:`stages.segment.real_frames`,
``benchmarks/bench_segment_real.py``).

Key-frame selection (``autocar keyframe``) lives in :mod:`stages.keyframe`. The measured accuracy of both
(``benchmarks/bench_segment.py``): :mod:`stages.segment.validate`.
"""

from __future__ import annotations

from .infer import load_model, read_masks, save_overlays, segment_frames, segment_run, write_masks

MASKS_KIND = "autocar.vessel-masks"
MASKS_SCHEMA = 1

__all__ = ["segment_frames", "segment_run", "write_masks", "read_masks", "save_overlays", "load_model",
           "MASKS_KIND", "MASKS_SCHEMA"]
