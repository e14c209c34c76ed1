"""The segmenter's accuracy, measured: simulated frames against their truth, the real phantom's
held-out-view check with each method's masks, and key-frame choice on simulated runs against their truth.

Reads: simulated frames + truth masks (arrays; data/seg/test through :func:`stages.segment.data.load_split`),
XA runs (the phantom's ``*.dcm``), data-re case folders (``run_a.dcm``, ``run_b.dcm``, ``truth.zarr``).
Writes nothing but, when asked, the key-frame plots of the first case; every function returns its
figures (``benchmarks/bench_segment.py`` turns them into docs/benchmarks/segment.md).
:func:`short_run_check` scores phase from images on 2–3-beat windows of the data-re runs without ECG.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import numpy as np

from .infer import METHODS, segment_frames
from .scores import cldice_2d, dice_2d

__all__ = ["filled_frames", "score_frames", "collimator_pixels", "phantom_check", "keyframe_check", "short_run_check"]


def filled_frames(masks: np.ndarray, group: int = 3) -> np.ndarray:
    """A frame is *filled* when its visible vessel area is ≥ 80 % of the best-filled frame of its
    ``group`` consecutive frames (one view); the others catch the bolus arriving or washing out."""
    area = masks.reshape(len(masks), -1).sum(1).astype(float)
    ids = np.arange(len(masks)) // group
    best = np.array([area[ids == g].max() for g in ids])
    return area >= 0.8 * np.maximum(best, 1)


def score_frames(frames, masks, filled, method: str = "unet", step: int = 1) -> dict:
    """Dice / clDice of ``method`` on every ``step``-th frame with vessel, pooled Dice, the filled flag of
    each scored frame, and the false-positive pixel count on each frame without vessel."""
    d, c, fp, fl, pool = [], [], [], [], np.zeros(3)
    for f, m, isf in zip(frames[::step], masks[::step], filled[::step]):
        p = segment_frames(f, method=method)[1].astype(bool)
        m = m.astype(bool)
        if m.sum() == 0:
            fp.append(int(p.sum()))
            continue
        d.append(dice_2d(p, m))
        c.append(cldice_2d(p, m))
        fl.append(isf)
        pool += [(p & m).sum(), p.sum(), m.sum()]
    return {"n": len(d), "dice": np.array(d), "cldice": np.array(c), "empty_fp": fp,
            "filled": np.array(fl, bool), "pooled": 2 * pool[0] / max(pool[1] + pool[2], 1)}


def collimator_pixels(img: np.ndarray, mask: np.ndarray) -> int:
    """Mask pixels in the dark region touching the image border (smoothed image < ½ its median) or within 3 px of it."""
    from scipy import ndimage

    sm = ndimage.gaussian_filter(img, 6)
    lab, _ = ndimage.label(sm < 0.5 * np.median(sm))
    edge = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
    dark = ndimage.binary_dilation(np.isin(lab, edge[edge > 0]), iterations=3)
    return int((mask & dark).sum())


def phantom_check(paths, methods=METHODS, pair_step: int = 1) -> dict:
    """Held-out-view check (:mod:`stages.evaluate.heldout`, nominal headers) with each method's masks of the same
    full-contrast frame per run, over every ``pair_step``-th run pair: summary per method, collimator pixels
    per method, and the runs, frames and masks (for figures)."""
    from ..core.dicom_io import read_xa
    from ..evaluate.heldout import View, heldout_rows, summarise
    from .vesselness import centreline_2d, contrast_frame, fov_mask

    runs = [read_xa(p) for p in paths]
    imgs = [contrast_frame(r.frames) for r in runs]
    fovs = [fov_mask(img) for img in imgs]
    masks = {m: [segment_frames(img, method=m)[1].astype(bool) for img in imgs] for m in methods}
    pairs = list(itertools.combinations(range(len(runs)), 2))[::pair_step]
    summary, collimator = {}, {}
    for m, ms in masks.items():
        views = [View(r.path.stem, r.camera, mk, fov, centreline_2d(mk)) for r, mk, fov in zip(runs, ms, fovs)]
        summary[m] = summarise([row for pr in pairs for row in heldout_rows(views, pr)])["nominal"]
        collimator[m] = sum(collimator_pixels(img, mk) for img, mk in zip(imgs, ms))
    return {"runs": runs, "imgs": imgs, "masks": masks, "pairs": pairs, "summary": summary, "collimator": collimator}


def keyframe_check(case_dirs, k: int = 7, plot_prefix: Path | None = None) -> dict:
    """Key frames of each case (network masks) with the DICOM ECG and with it removed (phase from images):
    per case and source the pair phase errors against the truth and the true filling of the chosen frames
    (relative to the run's maximum); per frame the image phase error. ``plot_prefix``: the first case's
    plots go to ``<plot_prefix>_ecg.png`` and ``<plot_prefix>_images.png``."""
    from ..core.runs import load_run
    from ..keyframe import circ_diff, keyframe_pairs, plot_keyframes, truth_filling
    from ..render.acquire import load_truth

    rows, image_phase = [], []
    for n, d in enumerate(case_dirs):
        tr = load_truth(Path(d) / "truth.zarr")
        ra, rb = load_run(Path(d) / "run_a.dcm"), load_run(Path(d) / "run_b.dcm")
        ma, mb = (segment_frames(r.frames, method="unet") for r in (ra, rb))
        tf = {key: truth_filling(tr, key) for key in "ab"}
        for src in ("ecg", "images"):
            if src == "images":
                ra.ecg = rb.ecg = None
            res = keyframe_pairs(ra, rb, {"prob": ma[0], "mask": ma[1]}, {"prob": mb[0], "mask": mb[1]}, k=k)
            err = np.array([circ_diff(tr["a"]["phase"][i], tr["b"]["phase"][j]) for i, j in res["pairs"]])
            fill = np.array([tf["a"][i] / tf["a"].max() for i, _ in res["pairs"]] +
                            [tf["b"][j] / tf["b"].max() for _, j in res["pairs"]])
            rows.append({"case": Path(d).name, "source": src, "errors": err, "filling": fill})
            if src == "images":
                for key in "ab":
                    image_phase += circ_diff(res["estimates"][key]["phase"], tr[key]["phase"]).tolist()
            if n == 0 and plot_prefix is not None:
                plot_keyframes(f"{plot_prefix}_{src}.png", res, {"a": tr["a"]["phase"], "b": tr["b"]["phase"]})
    return {"rows": rows, "image_phase_errors": np.array(image_phase)}


def _truth_period(phase: np.ndarray) -> float:
    """Mean period (frames) of a true phase curve: the slope of its unwrapped phase."""
    up = np.concatenate([[0.0], np.cumsum(np.mod(np.diff(phase), 1.0))])
    return float(1.0 / np.polyfit(np.arange(len(up)), up, 1)[0])


def short_run_check(case_dirs, lengths=(37, 40), masks: dict | None = None) -> list[dict]:
    """Phase from images on short runs: every run of each data-re case cut to ``lengths`` consecutive
    frames (2–3 beats), ECG and heart rate removed, in two windows: from the first frame, and the one with
    the largest summed contrast filling (:func:`stages.keyframe.contrast_filling` of the network masks;
    earliest on ties). Each run is segmented once (or taken from ``masks[(case, key)]`` = (prob, mask))
    and its masks sliced. Per window: the estimated period's relative error against the truth's (slope of
    the unwrapped true phase), the per-frame |phase error| (cycles, all frames), whether the 'no measurable
    period' fallback fired, and the period score."""
    from dataclasses import replace

    from ..core.runs import load_run
    from ..keyframe import circ_diff, contrast_filling, estimate_phase
    from ..render.acquire import load_truth

    rows = []
    for d in case_dirs:
        tr = load_truth(Path(d) / "truth.zarr")
        for key in "ab":
            run = load_run(Path(d) / f"run_{key}.dcm")
            prob, mask = (masks or {}).get((Path(d).name, key)) or segment_frames(run.frames, method="unet")
            fill = contrast_filling(run.frames, mask)
            for n in lengths:
                n = min(n, run.n_frames)
                sums = np.convolve(fill, np.ones(n), "valid")
                for window, s in (("first", 0), ("filled", int(np.argmax(sums)))):
                    sl = slice(s, s + n)
                    w = replace(run, frames=run.frames[sl], frame_times_ms=run.frame_times_ms[sl], ecg=None)
                    est = estimate_phase(w, prob[sl], mask[sl], name=f"{Path(d).name} {key}")
                    true_ph = np.asarray(tr[key]["phase"], float)[sl]
                    p_true = _truth_period(true_ph)
                    rows.append({"case": Path(d).name, "run": key, "frames": n, "window": window, "start": s,
                                 "period_true": p_true, "period": est["info"]["period_frames"],
                                 "period_error": abs(est["info"]["period_frames"] - p_true) / p_true,
                                 "phase_errors": circ_diff(est["phase"], true_ph),
                                 "fallback": est["info"]["period_source"].startswith("default"),
                                 "score": est["info"].get("period_score", float("nan"))})
    return rows
