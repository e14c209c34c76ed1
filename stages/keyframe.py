"""``autocar keyframe``: phase-matched, contrast-filled frame pairs of two XA runs.

Reads: two runs (:func:`stages.core.runs.load_run`: DICOM, image folder or stack + geometry JSON)
and optionally their ``autocar.vessel-masks`` artefacts (``autocar segment``; segmented here with
the default method when not given). Writes (:func:`write_keyframes`) a zarr artefact, kind
``"autocar.keyframes"`` (schema 1)::

    attrs: standard header + runs {"a"|"b": {source, masks, n_frames, phase_source, period_frames,
           max_filling, fill_fraction (the one used, see Selection)}}, k, warnings (list of str)
    pairs        K×2 int32    (frame of run a, frame of run b)
    phase        K float64    phase of each pair (circular mean of the two, in [0, 1))
    phase_error  K float64    estimated circular phase difference between the two frames (cycles)
    a/phase, b/phase      T float64  estimated cardiac phase of every frame, in [0, 1), 0 = end-diastole
    a/filling, b/filling  T float64  contrast filling of every frame (:func:`contrast_filling`)
    a/area, b/area        T float64  vessel mask area (px) of every frame
    a/washout, b/washout  T float64  filling over the same phase's in earlier beats (:func:`washout_ratio`)
    a/filled, b/filled    T uint8    frame counts as contrast-filled (:func:`filled_frames`)

and a PNG plot of the phase curves, filling and chosen pairs (:func:`plot_keyframes`).

Cardiac phase of each frame (:func:`estimate_phase`):

* **ECG** — with R-wave times (DICOM RWaveTimeVector, ms from the first frame, as our simulator and
  many vendors write it), phase = fractional position of the frame time between the R waves around it
  (before the first / after the last R wave: extrapolated with the mean RR interval). R wave = phase 0
  (end-diastole).
* **Images** — otherwise, from the periodic motion of the vessel masks: (1) the period from the
  frame-to-frame dissimilarity of a translation-invariant shape descriptor, the Fourier magnitudes of
  each blurred, ¼-size probability map in the band |f| ≤ 0.375 Nyquist, scaled to mean 1 (so respiratory
  shift and the amount of contrast in view matter less than the tree's shape and size):
  D(i, j) = mean |A_i − A_j|. The lag curve m(L) = mean of D(i, i+L) over pairs of filled frames
  (fractional L interpolated, ≥ 3 pairs) rises with L as the bolus and respiration change the tree, so
  each lag is scored against the curve's mean from L/2 to 1.5 L, where that trend is the same:
  score(L) = m(L) / mean m([L/2, 1.5 L]). The period P (0.4–1.5 s, or 60/HeartRate when the header has
  it) is the shortest local minimum within 0.2·(1 − best) of the best score (so 2P is not taken). It is
  only measured over ≥ 1.1 periods of filled frames (filling ≥ 0.6 of the maximum) and accepted when
  score ≤ 0.75; otherwise the header heart rate or 70 bpm is used, with a warning. These were
  calibrated on 924 windows of the 42 data-re runs (30–42 frames, every third start, ECG removed): 93 %
  accepted, 2.7 % of those off by > 8 % (mostly 30-frame windows of 55–60 bpm hearts with a late
  bolus). On the benchmark's 37/40-frame windows (docs/benchmarks/segment.md, short runs) the old
  criterion (mean dissimilarity of the probability maps, ≥ 1.3 periods, score ≤ 0.8) fell back on 30 %
  of them. A run shorter than a beat falls back (9 frames of a 12.3-frame beat, every
  start), except that one of 0.8–0.9 beat which begins and ends in the resting phase (diastasis) looks
  like one faster beat and can be taken for it. (2) the phase origin from the tree's spread (RMS
  distance of vessel pixels from their centroid, which shrinks as the heart contracts in every view,
  and is insensitive to respiratory translation): a least-squares fit s(t) ≈ a + b·t − c·C((t − t₀)/P),
  c ≥ 0, over the filled frames, with C the typical contraction curve (systole 0.34, relaxation 0.2 of a
  cycle, :func:`stages.render.motion.contraction`), grid over t₀ (and over P ± 8 % when the filled
  frames span ≥ 1.5 image-measured periods); phase = (t − t₀)/P mod 1.

Contrast filling (:func:`contrast_filling`): the summed darkening (black top-hat, of the frame smoothed by
1 px so that noise does not add to it) over each frame's dilated vessel mask — the iodine in view, which
does not change as the heart contracts (the mask *area* does, by ~20 %); a frame is *filled* when it
reaches ``fill_fraction`` (0.95) of the run's maximum as a *bolus state* (the smaller of the filling's
maxima over the cardiac period before and the one after the frame, because the instantaneous measure
dips by 10–25 % in systole where vessels crowd and the clinical image processing flattens them) and at
least 1 − 2.5·(1 − fill_fraction) (0.875) of it instantaneously, and is not *washing out*: its filling is
≥ 0.975 of the largest at the same phase in earlier beats (:func:`washout_ratio`). The image measure lags the wash-out — thick, saturated
vessels hardly darken less while the true lumen filling already falls — so without that comparison
frames at 0.88 of the true filling still measured 0.96 of the maximum (data-re, 3 of 294 chosen frames).

Selection (:func:`select_keyframes`): K phase bins
centred on k/K; per bin the pair (i, j) of filled frames minimising
|φ_a(i) − φ_b(j)| + ½(|φ_a(i) − c_k| + |φ_b(j) − c_k|) (circular), without reusing a pair; when that
pair is mismatched by more than half a frame interval (the filled frames of one run do not reach that
phase), the run whose filled frames leave the widest phase gap has its ``fill_fraction`` lowered by
0.05 (down to 0.85, with a warning) and the selection is repeated: one isolated filling peak (a frame
measuring 1.0 where the plateau measures 0.88) must not leave a single filled frame to pair with
every phase of the other run (data-re case 2000012 had all seven key frames on one frame of run a,
mismatched by up to 0.39 cycles). Only when the floor is reached is the best-matched unused pair taken
instead, and a warning names the uncovered bins.

Bad input: a single-frame run → every pair uses that frame, with a warning; a run with no contrast
(maximal vessel area < ``min_vessel_px``) → UserError naming the run; frames of different sizes
between the runs are fine (each run is handled in its own image space); masks whose shape differs
from their run's frames → UserError.

Python API: ``select_keyframes(run_a, run_b, masks_a, masks_b, k=7) -> [(frame_a, frame_b, phase)]``
where runs are paths or :class:`stages.core.runs.Run` and masks are T×H×W arrays, artefact paths,
or None (segmented here). :func:`keyframe_pairs` returns the full result dict.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
from scipy import ndimage

from .core.errors import UserError

log = logging.getLogger(__name__)

KIND = "autocar.keyframes"
SCHEMA = 1
DEFAULT_BPM = 70.0
# a frame whose filling is below this share of the same phase's in an earlier beat is washing out
MIN_WASHOUT_RATIO = 0.975
# when the filled frames of a run leave phase bins uncovered, its fill fraction is lowered by this step,
# down to this floor (at 0.85 a frame still needs 0.625 of the peak filling instantaneously)
FILL_RELAX_STEP = 0.05
MIN_FILL_FRACTION = 0.85

__all__ = ["estimate_phase", "phase_from_ecg", "phase_from_images", "select_keyframes", "keyframe_pairs",
           "write_keyframes", "plot_keyframes", "circ_diff", "filled_frames", "washout_ratio", "KIND"]


def circ_diff(a, b) -> np.ndarray:
    """Circular phase difference |a − b| in cycles, in [0, ½]."""
    d = np.mod(np.asarray(a, float) - np.asarray(b, float), 1.0)
    return np.minimum(d, 1.0 - d)


def phase_from_ecg(times_ms: np.ndarray, r_waves_ms, heart_rate_bpm: float | None = None) -> np.ndarray | None:
    """Phase in [0, 1) of each frame time from R-wave times (ms, same clock); None if unusable."""
    r = np.sort(np.asarray([float(v) for v in (r_waves_ms or [])], float))
    t = np.asarray(times_ms, float)
    if len(r) == 0:
        return None
    rr = float(np.median(np.diff(r))) if len(r) > 1 else (60000.0 / heart_rate_bpm if heart_rate_bpm else None)
    if rr is None or rr <= 0:
        return None
    # extend the beat list on both sides so every frame lies between two R waves
    n_before = int(np.ceil(max(r[0] - t.min(), 0) / rr)) + 1
    n_after = int(np.ceil(max(t.max() - r[-1], 0) / rr)) + 1
    r = np.concatenate([r[0] - rr * np.arange(n_before, 0, -1), r, r[-1] + rr * np.arange(1, n_after + 1)])
    k = np.clip(np.searchsorted(r, t, side="right") - 1, 0, len(r) - 2)
    return np.mod((t - r[k]) / (r[k + 1] - r[k]), 1.0)


def _template(phi):
    from .render.motion import contraction

    return contraction(phi, 0.34, 0.2)


def _spread(prob: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """RMS distance (px) of each frame's vessel pixels from their centroid (probability-weighted)."""
    T, H, W = prob.shape
    rr, cc = np.mgrid[0:H, 0:W]
    out = np.full(T, np.nan)
    for t in range(T):
        w = prob[t] * (mask[t] > 0)
        s = w.sum()
        if s > 0:
            r0, c0 = (w * rr).sum() / s, (w * cc).sum() / s
            out[t] = np.sqrt((w * ((rr - r0) ** 2 + (cc - c0) ** 2)).sum() / s)
    return out


# period from images: the low-frequency band of the frames' Fourier magnitudes compared (as a share of the
# ¼-size map's Nyquist frequency), the shortest measurable span of filled frames (periods) and the fewest
# frame pairs a lag is measured on, the tolerance
# for a shorter local minimum (share of 1 − best score), and the acceptance threshold on the score
SPECTRUM_BAND = 0.375
MIN_PERIODS = 1.1
MIN_PAIRS = 3
HARMONIC_TOL = 0.2
MAX_PERIOD_SCORE = 0.75


def _spectra(prob: np.ndarray) -> np.ndarray:
    """Translation-invariant shape descriptor of each frame: the Fourier magnitudes of its blurred, ¼-size
    probability map in the band |f| ≤ SPECTRUM_BAND·Nyquist (both row-frequency signs), scaled to mean 1 (so
    the amount of contrast in view matters less than the tree's shape and size)."""
    small = np.stack([ndimage.zoom(ndimage.gaussian_filter(p, 3.0), 0.25, order=1) for p in prob])
    A = np.abs(np.fft.rfft2(small - small.mean((1, 2), keepdims=True)))
    br = max(3, int(np.ceil(SPECTRUM_BAND * small.shape[1] / 2)))
    bc = max(3, int(np.ceil(SPECTRUM_BAND * small.shape[2] / 2)))
    A = np.concatenate([A[:, :br, :bc], A[:, -br:, :bc]], 1).reshape(len(prob), -1)
    return A / (A.mean(1, keepdims=True) + 1e-12)


def _lag_curve(D: np.ndarray, valid: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Mean of D(i, i + L) over valid frame pairs for each (fractional, linearly interpolated) lag L; nan
    where fewer than MIN_PAIRS pairs."""
    T = len(D)
    out = np.full(len(lags), np.nan)
    for q, L in enumerate(lags):
        lo, w = int(np.floor(L)), L - np.floor(L)
        i = np.arange(max(T - lo - 1, 0))
        ok = valid[i] & valid[i + lo] & valid[i + lo + 1]
        if ok.sum() >= MIN_PAIRS:
            i = i[ok]
            out[q] = np.mean((1 - w) * D[i, i + lo] + w * D[i, i + lo + 1])
    return out


def _period(prob: np.ndarray, valid: np.ndarray, p_lo: float, p_hi: float) -> tuple[float | None, float]:
    """Period (frames) where frames one period apart are most alike relative to nearby lags (module doc) and
    its score; (None, nan) when the filled frames span less than MIN_PERIODS of every candidate."""
    T = len(prob)
    A = _spectra(prob)
    D = np.abs(A[:, None, :] - A[None, :, :]).mean(-1)
    idx = np.flatnonzero(valid)
    span = float(idx.max() - idx.min()) if len(idx) else 0.0
    lags = np.round(np.arange(1.0, T - 1.0 + 1e-9, 0.1), 6)
    m = _lag_curve(D, valid, lags)
    cand = np.flatnonzero((lags >= max(p_lo, 2.0)) & (lags <= min(p_hi, span / MIN_PERIODS) + 1e-9) & np.isfinite(m))
    if len(cand) == 0:
        return None, float("nan")
    # the lag curve rises with the lag as the bolus and respiration change the tree: judge each lag
    # against the mean of the curve from half to one and a half of it, where the trend is the same
    scores = np.array([m[q] / np.nanmean(np.where((lags >= lags[q] / 2) & (lags <= 1.5 * lags[q]), m, np.nan))
                       for q in cand])
    best = float(np.min(scores))
    ok = np.flatnonzero(scores <= best + HARMONIC_TOL * max(1.0 - best, 0.0))
    i = ok[0]  # the shortest acceptable lag, moved to its local minimum (so 2P is not taken)
    while i + 1 < len(scores) and scores[i + 1] < scores[i]:
        i += 1
    return float(lags[cand[i]]), float(scores[i])


def phase_from_images(prob: np.ndarray, mask: np.ndarray, frame_time_ms: float, valid: np.ndarray | None = None,
                      heart_rate_bpm: float | None = None) -> tuple[np.ndarray, dict]:
    """Phase of each frame from the vessel masks' periodic motion (see module doc) → (phase, info)."""
    T = len(prob)
    fps = 1000.0 / frame_time_ms
    valid = np.ones(T, bool) if valid is None else np.asarray(valid, bool)
    info = {}
    if heart_rate_bpm:
        P = 60.0 / heart_rate_bpm * fps
        info["period_source"] = "HeartRate"
    else:
        P, score = _period(prob, valid, 0.4 * fps, 1.5 * fps)
        info["period_score"] = score
        info["period_source"] = "images"
        if P is not None and score > MAX_PERIOD_SCORE:  # frames one period apart hardly more alike than others
            P = None
        if P is None:
            P = 60.0 / DEFAULT_BPM * fps
            info["period_source"] = f"default {DEFAULT_BPM:g} bpm (no measurable period)"
    s = _spread(prob, mask)
    use = valid & np.isfinite(s)
    t = np.arange(T, dtype=float)
    t0 = 0.0
    if use.sum() >= 3:
        # refine the period (±8 %, only when the image-based one spans ≥ 1.5 cycles) jointly with t0
        span = t[use].max() - t[use].min()
        Ps = P * np.arange(0.92, 1.0801, 0.01) if info["period_source"] == "images" and span >= 1.5 * P else [P]
        tu, su = t[use], s[use]
        base = np.stack([np.ones(len(tu)), tu - tu.mean()], 1)
        r_base = su - base @ np.linalg.lstsq(base, su, rcond=None)[0]
        best = None
        for Pc in Ps:
            for t0c in np.arange(0.0, Pc, 0.05):
                C = _template((tu - t0c) / Pc)
                C = C - base @ np.linalg.lstsq(base, C, rcond=None)[0]  # C orthogonal to the trend
                cc = float(C @ C)
                c = -float(C @ r_base) / cc if cc > 1e-12 else 0.0
                res = float(np.sum((r_base + max(c, 0.0) * C) ** 2))
                if best is None or res < best[0] - 1e-12:
                    best = (res, t0c, Pc)
        _, t0, P = best
    info["period_frames"] = float(P)
    info["t0_frames"] = float(t0)
    return np.mod((t - t0) / P, 1.0), info


def _masks_for(run, masks, method: str = "unet"):
    """(prob, mask, source) for a run: given arrays, an artefact path, or segment here."""
    if masks is None:
        from .segment import segment_frames

        prob, mask = segment_frames(run.frames, method=method)
        return prob, mask, f"segmented here ({method})"
    if isinstance(masks, (str, Path)):
        from .segment import read_masks

        m = read_masks(masks)
        return m["prob"], m["mask"], str(masks)
    if isinstance(masks, dict):
        return np.asarray(masks["prob"], np.float32), np.asarray(masks["mask"]), "given"
    m = np.asarray(masks)
    return m.astype(np.float32), (m > 0.5).astype(np.uint8), "given"


def estimate_phase(run, prob: np.ndarray, mask: np.ndarray, fill_fraction: float = 0.95,
                   min_vessel_px: int = 50, name: str = "run", min_washout_ratio: float = MIN_WASHOUT_RATIO) -> dict:
    """Per-frame phase, filling and the 'filled' flags of one run (see module doc)."""
    T = run.n_frames
    if prob.shape != run.frames.shape or mask.shape != run.frames.shape:
        raise UserError(f"{name} ({run.path}): masks of shape {mask.shape} do not match the frames {run.frames.shape}")
    warnings = []
    area = mask.reshape(T, -1).sum(1).astype(float)
    if area.max() < min_vessel_px:
        raise UserError(f"{name} ({run.path}): no contrast-filled vessels found (largest vessel area "
                        f"{int(area.max())} px < {min_vessel_px} px); is contrast injected in this run?")
    filling = contrast_filling(run.frames, mask)
    filled = None  # decided once the period is known (below)
    ft = float(np.median(np.diff(run.frame_times_ms))) if T > 1 else 1000.0 / 15
    ecg = run.ecg or {}
    hr = ecg.get("heart_rate_bpm")
    phase = None
    if T == 1:
        phase, source, info = np.zeros(1), "single frame", {}
        warnings.append(f"{name}: a single frame; its phase is unknown, it is used for every key frame")
    else:
        phase = phase_from_ecg(run.frame_times_ms, ecg.get("r_wave_time_vector_ms"), hr)
        source, info = "ecg", {}
        if phase is not None:
            rw = np.asarray(ecg.get("r_wave_time_vector_ms"), float)
            info["period_frames"] = float(np.median(np.diff(rw)) / ft) if len(rw) > 1 else 60000.0 / hr / ft
        else:
            # motion is measured on frames with enough contrast to see the whole tree
            valid = filling >= 0.6 * filling.max()
            phase, info = phase_from_images(prob, mask, ft, valid, hr)
            source = "images"
            if info["period_source"].startswith("default"):
                warnings.append(f"{name}: no ECG and no measurable heart period in the images (fewer than "
                                f"~{MIN_PERIODS:g} beats of contrast-filled frames, or no clear periodic motion); assumed "
                                f"{DEFAULT_BPM:g} bpm, so the phases are approximate")
        if T * ft < info.get("period_frames", 0) * ft:
            warnings.append(f"{name}: the run ({T} frames) is shorter than one heartbeat "
                            f"({info['period_frames']:.1f} frames); some phases have no frame")
    period = info.get("period_frames", 0.0) if T > 1 else 0.0
    filled, bolus, washout = filled_frames(filling, period, fill_fraction, min_washout_ratio)
    return {"phase": np.asarray(phase, float), "source": source, "filling": filling, "filled": filled, "area": area,
            "bolus": bolus, "washout": washout,
            "info": info, "warnings": warnings}


def filled_frames(filling: np.ndarray, period_frames: float, fill_fraction: float = 0.95,
                  min_washout_ratio: float = MIN_WASHOUT_RATIO) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(filled flags, bolus state, wash-out ratio) of every frame from its contrast filling (module doc)."""
    filling = np.asarray(filling, float)
    T = len(filling)
    # the bolus state: an upper envelope over one cardiac period (the instantaneous value dips by
    # 10–25 % in systole, where vessels crowd and the image processing flattens them) that does not leak
    # into the rising/falling edges: the smaller of the maxima over the period before and the one after
    P = max(int(round(period_frames)), 1)
    back = np.array([filling[max(0, t - P):t + 1].max() for t in range(T)])
    fwd = np.array([filling[t:t + P + 1].max() for t in range(T)])
    bolus = np.minimum(back, fwd)
    top = max(filling.max(), 1e-12)
    washout = washout_ratio(filling, period_frames)
    filled = ((bolus >= fill_fraction * top) & (filling >= (1 - 2.5 * (1 - fill_fraction)) * top)
              & (washout >= min_washout_ratio))
    return filled, bolus, washout


def washout_ratio(filling: np.ndarray, period_frames: float) -> np.ndarray:
    """Each frame's filling over the largest filling at the same cardiac phase in earlier beats (frames
    t − P, t − 2P, …, linearly interpolated); 1 where no earlier beat was recorded.

    Comparing like with like removes the systolic dip, so a ratio below 1 means contrast is leaving. It
    catches the start of the wash-out, which the image measure reports late: the top-hat of thick,
    saturated vessels hardly changes while the true lumen filling already falls (on simulated runs a
    frame at 0.88 true filling still measures 0.96 of the maximum, but 0.96 of the same phase one beat
    earlier)."""
    T = len(filling)
    ratio = np.ones(T)
    if period_frames <= 1.0 or T < 2:
        return ratio
    t = np.arange(T, dtype=float)
    ref = np.zeros(T)
    n = 1
    while n * period_frames <= T - 1:
        back = t - n * period_frames
        ok = back >= 0
        ref[ok] = np.maximum(ref[ok], np.interp(back[ok], t, filling))
        n += 1
    has = ref > 0
    ratio[has] = filling[has] / ref[has]
    return ratio


def contrast_filling(frames: np.ndarray, mask: np.ndarray, width: int = 21, denoise_sigma: float = 1.0) -> np.ndarray:
    """Iodine in view per frame: Σ over the (dilated) vessel mask of the black top-hat (local background
    − intensity, a square grey closing of ``width`` px). With log-windowed XA this is ∝ ∫∫ μ·L dA, the
    contrast volume in the field — unlike the vessel *area*, it does not shrink when the heart contracts
    (area drops by ~20 % in systole, which would make every systolic frame look 'unfilled').

    The closing takes local maxima, so pixel noise alone adds to the top-hat: each frame is smoothed first
    (Gaussian, ``denoise_sigma`` px). Unsmoothed, the real phantom's first frame of a run (3–4× the noise of the
    later ones: the system's temporal filter has not settled; fainter vessels too) measured 1.3–1.5× their
    filling and was the only frame counted as filled, so the noisiest frame became the key frame; smoothed it
    measures 0.97 of the fullest frame and most later frames count as filled."""
    out = np.zeros(len(frames))
    for t in range(len(frames)):
        m = ndimage.binary_dilation(mask[t] > 0, iterations=2)
        if m.any():
            # the closing (a dilation, then an erosion) reads the frame within width − 1 px: cropped to the mask's
            # box with a margin of ``width``, it gives the same values inside the mask, for less work (the
            # smoothing reads 4σ further: within the margin too)
            rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
            box = (slice(max(rows[0] - width, 0), rows[-1] + width + 1),
                   slice(max(cols[0] - width, 0), cols[-1] + width + 1))
            f = np.asarray(frames[t][box], np.float32)
            if denoise_sigma > 0:
                f = ndimage.gaussian_filter(f, denoise_sigma)
            out[t] = float((ndimage.grey_closing(f, size=(width, width)) - f)[m[box]].sum())
    return out


def _widest_phase_gap(phases: np.ndarray) -> float:
    """The largest circular gap (cycles) between the given phases; 1 with fewer than two."""
    if len(phases) < 2:
        return 1.0
    p = np.sort(np.mod(phases, 1.0))
    return float(max(np.diff(p).max(initial=0.0), p[0] + 1.0 - p[-1]))


def _choose(pa: np.ndarray, pb: np.ndarray, cand_a: np.ndarray, cand_b: np.ndarray, k: int, tol: float = 1.0):
    """K pairs, one per phase bin; a bin whose best pair is mismatched by more than ``tol`` cycles (no
    filled frames near that phase in one of the runs) takes the best-matched unused pair instead.
    Returns (pairs, uncovered bin centres)."""
    pairs, used, uncovered = [], set(), []
    allp = sorted((float(circ_diff(pa[i], pb[j])), int(i), int(j)) for i in cand_a for j in cand_b)
    for b in range(k):
        c = b / k
        best = None
        for i in cand_a:
            for j in cand_b:
                if (i, j) in used:
                    continue
                cost = circ_diff(pa[i], pb[j]) + 0.5 * (circ_diff(pa[i], c) + circ_diff(pb[j], c))
                if best is None or cost < best[0]:
                    best = (cost, int(i), int(j))
        if best is None:  # fewer candidate pairs than bins: reuse
            best = allp[0]
        elif circ_diff(pa[best[1]], pb[best[2]]) > tol:
            uncovered.append(c)
            free = [q for q in allp if (q[1], q[2]) not in used]
            best = free[0] if free else allp[0]
        used.add((best[1], best[2]))
        pairs.append((best[1], best[2]))
    return pairs, uncovered


def keyframe_pairs(run_a, run_b, masks_a=None, masks_b=None, k: int = 7, fill_fraction: float = 0.95,
                   geometry_a=None, geometry_b=None, method: str = "unet",
                   min_washout_ratio: float = MIN_WASHOUT_RATIO) -> dict:
    """Full key-frame result: pairs, phases, per-run phase curves and filling, warnings."""
    from .core.runs import Run, load_run

    if k < 1:
        raise UserError(f"keyframe: k must be ≥ 1, got {k}")
    runs = {"a": run_a if isinstance(run_a, Run) else load_run(run_a, geometry_a),
            "b": run_b if isinstance(run_b, Run) else load_run(run_b, geometry_b)}
    est, srcs, warnings = {}, {}, []
    for key, m in (("a", masks_a), ("b", masks_b)):
        prob, mask, srcs[key] = _masks_for(runs[key], m, method)
        est[key] = estimate_phase(runs[key], prob, mask, fill_fraction, name=f"run {key}",
                                  min_washout_ratio=min_washout_ratio)
        warnings += est[key]["warnings"]
    if runs["a"].frames.shape[1:] != runs["b"].frames.shape[1:]:
        warnings.append(f"the runs have different frame sizes ({runs['a'].frames.shape[1:]} vs "
                        f"{runs['b'].frames.shape[1:]}); each is handled in its own image space")
    pa, pb = est["a"]["phase"], est["b"]["phase"]
    ca, cb = np.flatnonzero(est["a"]["filled"]), np.flatnonzero(est["b"]["filled"])
    # a pair may be mismatched by at most about half a frame interval of the slower-sampled run
    per = [est[key]["info"].get("period_frames") or 0.0 for key in "ab"]
    tol = 0.5 / min(p for p in per if p > 0) + 0.01 if any(p > 0 for p in per) else 1.0
    if runs["a"].n_frames == 1 or runs["b"].n_frames == 1:
        tol = 1.0
    pairs, uncovered = _choose(pa, pb, ca, cb, k, tol)
    fractions = {"a": fill_fraction, "b": fill_fraction}
    while uncovered:
        # relax the run whose filled frames leave the widest gap in phase, if it may still be relaxed
        relaxable = [key for key in "ab" if fractions[key] - FILL_RELAX_STEP >= MIN_FILL_FRACTION - 1e-9
                     and runs[key].n_frames > 1]
        if not relaxable:
            break
        key = max(relaxable, key=lambda r: _widest_phase_gap(est[r]["phase"][est[r]["filled"]]))
        fractions[key] -= FILL_RELAX_STEP
        e = est[key]
        e["filled"], e["bolus"], e["washout"] = filled_frames(
            e["filling"], e["info"].get("period_frames", 0.0), fractions[key], min_washout_ratio)
        ca, cb = np.flatnonzero(est["a"]["filled"]), np.flatnonzero(est["b"]["filled"])
        pairs, uncovered = _choose(pa, pb, ca, cb, k, tol)
    for key in "ab":
        est[key]["fill_fraction"] = fractions[key]
        if fractions[key] < fill_fraction:
            warnings.append(f"run {key}: too few frames reach {fill_fraction:.0%} of its peak contrast filling to "
                            f"cover the cardiac cycle; frames from {fractions[key]:.0%} of it were used")
    if uncovered:
        warnings.append(f"phase bins {', '.join(f'{c:.2f}' for c in uncovered)} have no filled frames at a matching "
                        f"phase in both runs; the best-matched remaining pairs were used instead")
    if len(set(pairs)) < len(pairs):
        warnings.append(f"only {len(set(pairs))} distinct filled frame pairs for {k} key frames; some repeat")
    for w in warnings:
        log.warning(w)
    ph = []
    for i, j in pairs:  # circular mean of the two phases
        z = np.exp(2j * np.pi * pa[i]) + np.exp(2j * np.pi * pb[j])
        ph.append(float(np.mod(np.angle(z) / (2 * np.pi), 1.0)))
    return {"pairs": pairs, "phase": ph, "phase_error": [float(circ_diff(pa[i], pb[j])) for i, j in pairs],
            "runs": runs, "estimates": est, "masks": srcs, "k": k, "warnings": warnings}


def match_further_run(phase_ref, frames_ref, run, masks=None, name: str = "run", fill_fraction: float = 0.95,
                       method: str = "unet") -> dict:
    """The frame of a further run (a third, fourth … run of the same study) at each key frame's phase.

    ``phase_ref``: the reference run's per-frame phase (run A of :func:`keyframe_pairs`); ``frames_ref``: its key
    frames. For each, the run's contrast-filled frame closest in phase (every frame when too few are filled),
    accepted when it is within half a frame interval of the run (+ 0.05 cycle for the phase estimates' own error);
    where no filled frame is, one filled to a lower fraction (by ``FILL_RELAX_STEP`` down to ``MIN_FILL_FRACTION``,
    as for runs A and B), with a warning; otherwise ``None`` for that key frame, with a warning saying why. A run
    whose phase is unknown (a single frame; no ECG and no heart period in its images, e.g. a static phantom) gives
    its most contrast-filled frame to every key frame: the 3D step checks it against runs A and B. Returns
    {frames: [index or None per key frame], phase_error: [cycles or None], warnings}."""
    prob, mask, _ = _masks_for(run, masks, method)
    est = estimate_phase(run, prob, mask, fill_fraction, name=name)
    warnings = list(est["warnings"])
    cand = np.flatnonzero(est["filled"])
    if len(cand) == 0:
        cand = np.arange(run.n_frames)
    if run.n_frames == 1 or str(est["info"].get("period_source", "")).startswith("default"):
        best = int(cand[np.argmax(est["filling"][cand])])
        warnings.append(f"{name}: its cardiac phase is unknown; its most contrast-filled frame ({best}) is used for "
                        "every key frame")
        return {"frames": [best] * len(frames_ref), "phase_error": [None] * len(frames_ref), "warnings": warnings}
    period = est["info"].get("period_frames") or 0.0
    tol = 0.5 / period + 0.01 + 0.05
    # as for runs A and B: where the filled frames do not reach a key frame's phase, frames filled to a lower
    # fraction (down to MIN_FILL_FRACTION) are taken
    fractions = np.arange(fill_fraction, MIN_FILL_FRACTION - 1e-9, -FILL_RELAX_STEP)
    pools = [cand] + [np.flatnonzero(filled_frames(est["filling"], period, ff)[0]) for ff in fractions[1:]]
    frames, errors = [], []
    for i in frames_ref:
        for ff, pool in zip(fractions, pools):
            err = np.abs(circ_diff(est["phase"][pool], float(phase_ref[i]))) if len(pool) else np.array([np.inf])
            j = int(np.argmin(err))
            if err[j] <= tol:
                break
        if err[j] <= tol:
            frames.append(int(pool[j]))
            errors.append(float(err[j]))
            if ff < fill_fraction:
                warnings.append(f"{name}: no frame filled to {100 * fill_fraction:.0f}% of its peak at the phase of run "
                                f"A's frame {i}; frame {int(pool[j])}, filled to {100 * ff:.0f}%, is used")
        else:
            frames.append(None)
            errors.append(None)
            warnings.append(f"{name}: no frame within {tol:.2f} cycle of run A's frame {i} (phase {phase_ref[i]:.2f}; "
                            f"closest {est['phase'][pool[j]]:.2f}): not used for that key frame")
    return {"frames": frames, "phase_error": errors, "warnings": warnings}


def select_keyframes(run_a, run_b, masks_a=None, masks_b=None, k: int = 7, **kw) -> list[tuple[int, int, float]]:
    """K (frame_a, frame_b, phase) triples, phase-matched and contrast-filled (see module doc)."""
    res = keyframe_pairs(run_a, run_b, masks_a, masks_b, k=k, **kw)
    return [(i, j, p) for (i, j), p in zip(res["pairs"], res["phase"])]


def write_keyframes(path, res: dict) -> Path:
    from .core.artefacts import write_zarr

    runs_attr = {}
    for key in "ab":
        e = res["estimates"][key]
        runs_attr[key] = {"source": str(res["runs"][key].path), "masks": res["masks"][key],
                          "n_frames": res["runs"][key].n_frames, "phase_source": e["source"],
                          "period_frames": e["info"].get("period_frames"), "max_filling": float(e["filling"].max()),
                          "fill_fraction": float(e.get("fill_fraction", float("nan")))}
    extra = {"runs": runs_attr, "k": res["k"], "warnings": res["warnings"]}
    with write_zarr(path, kind=KIND, schema_version=SCHEMA, stage="keyframe",
                    inputs=[runs_attr["a"]["source"], runs_attr["b"]["source"]], parameters={"k": res["k"]},
                    extra_attrs=extra) as g:
        g.create_array("pairs", data=np.asarray(res["pairs"], np.int32).reshape(-1, 2))
        g.create_array("phase", data=np.asarray(res["phase"], float))
        g.create_array("phase_error", data=np.asarray(res["phase_error"], float))
        for key in "ab":
            e = res["estimates"][key]
            sub = g.require_group(key)
            sub.create_array("phase", data=e["phase"])
            sub.create_array("filling", data=e["filling"])
            sub.create_array("washout", data=e["washout"])
            sub.create_array("filled", data=e["filled"].astype(np.uint8))
            sub.create_array("area", data=e["area"])
    return Path(path)


def plot_keyframes(path, res: dict, truth: dict | None = None) -> Path:
    """PNG: per run the estimated phase (and true phase if given), filling, and the chosen frames."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .core.figures import save_png

    fig, axes = plt.subplots(2, 1, figsize=(9, 5.5), sharex=False)
    for ax, key, col in zip(axes, "ab", (0, 1)):
        e = res["estimates"][key]
        t = np.arange(len(e["phase"]))
        ax.plot(t, e["phase"], "o-", ms=3, label=f"phase ({e['source']})")
        if truth is not None and key in truth:
            ax.plot(t, truth[key], "k--", lw=1, label="true phase")
        f = e["filling"] / max(e["filling"].max(), 1)
        ax.plot(t, f, color="tab:green", label="filling / max")
        ax.axhline(0.9, color="tab:green", lw=0.5, ls=":")
        chosen = [p[col] for p in res["pairs"]]
        ax.plot(chosen, e["phase"][chosen], "r*", ms=11, label="key frames")
        ax.set_ylabel(f"run {key}")
        ax.set_ylim(-0.05, 1.1)
        ax.legend(fontsize=7, loc="lower right")
    axes[-1].set_xlabel("frame")
    fig.suptitle("cardiac phase (0 = end-diastole), contrast filling and chosen key frames", fontsize=10)
    fig.subplots_adjust(left=0.08, right=0.98, top=0.92, bottom=0.09, hspace=0.25)  # tight_layout's result, fixed
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return save_png(fig, path, dpi=90)


def truth_filling(truth: dict, key: str) -> np.ndarray:
    """True vessel filling of each frame of a simulated run (for scoring): the fraction of the lumen
    volume holding contrast, Σ c(node, t)·r²·ℓ / Σ r²·ℓ, from an ``autocar.xa-truth`` sidecar
    (:func:`stages.render.acquire.load_truth`) — the bolus reaches each node after its path distance
    from the ostium divided by the flow speed."""
    from .render.xa import BolusModel, node_path_distance

    nodes, radius, edges = truth["reference_nodes"], truth["radius"], truth["edges"]
    run = truth["attrs"]["runs"][key]
    bolus = BolusModel(**run["bolus"])
    dist, _ = node_path_distance(nodes, edges)
    seg = np.zeros(len(nodes))
    ln = np.linalg.norm(nodes[edges[:, 0]] - nodes[edges[:, 1]], axis=1)
    np.add.at(seg, edges[:, 0], ln / 2)
    np.add.at(seg, edges[:, 1], ln / 2)
    w = radius.astype(float) ** 2 * seg
    t = np.asarray(truth[key]["time_s"], float) - float(run["start_time_s"])
    conc = np.stack([bolus.at(ti - dist / bolus.speed) for ti in t])
    return conc @ w / w.sum()
