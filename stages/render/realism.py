"""Image statistics used to compare simulated XA frames with real ones (docs/SIMULATION.md).

Reads frames given as arrays (any bit depth, vessels dark); writes nothing. The same automatic
procedure is applied to real and simulated frames, so the numbers are comparable:

* field of view: pixels whose heavily smoothed value exceeds half the median (drops the dark
  collimator/shutter border), eroded by 12 px;
* local background: a grey closing with a 15 px disc (fills thin dark structures), lightly smoothed;
* vessel response: local background − frame; pixel noise σₙ: robust (MAD) std of the frame minus its
  σ = 2 px Gaussian smoothing, over background pixels;
* vessel pixels: response > 6 σₙ (connected components ≥ 30 px), inside the field of view;
* CNR = mean vessel response / σₙ; background mean and std: raw values over non-vessel field-of-view
  pixels (the std includes anatomy, not only noise).

All intensities are reported on an 8-bit scale (values × 255 / (2^bits − 1)).
"""

from __future__ import annotations

import numpy as np

__all__ = ["frame_statistics"]


def frame_statistics(frame: np.ndarray, bits: int = 8, vessel_mask: np.ndarray | None = None) -> dict:
    """Statistics of one frame (see the module docstring); ``vessel_mask`` overrides the automatic one."""
    from scipy import ndimage

    f = np.asarray(frame, dtype=np.float64) * (255.0 / (2 ** bits - 1))
    smooth = ndimage.gaussian_filter(f, 8)
    fov = smooth > 0.5 * np.median(smooth)
    fov = ndimage.binary_erosion(fov, iterations=12)
    yy, xx = np.mgrid[-7:8, -7:8]
    disc = (yy ** 2 + xx ** 2) <= 49
    bg_local = ndimage.gaussian_filter(ndimage.grey_closing(f, footprint=disc), 1.0)
    response = bg_local - f
    hp = f - ndimage.gaussian_filter(f, 2.0)
    bg_guess = fov & (response < np.percentile(response[fov], 80))
    noise = 1.4826 * np.median(np.abs(hp[bg_guess] - np.median(hp[bg_guess])))
    if vessel_mask is None:
        vessel = fov & (response > 6.0 * noise)
        lab, n = ndimage.label(vessel)
        if n:
            sizes = ndimage.sum(vessel, lab, index=np.arange(1, n + 1))
            vessel = np.isin(lab, 1 + np.flatnonzero(sizes >= 30))
    else:
        vessel = fov & np.asarray(vessel_mask, bool)
    background = fov & ~ndimage.binary_dilation(vessel, iterations=3)
    cnr = float(response[vessel].mean() / noise) if vessel.any() else 0.0
    return {
        "cnr": cnr,
        "vessel_contrast": float(response[vessel].mean()) if vessel.any() else 0.0,
        "noise_std": float(noise),
        "background_mean": float(f[background].mean()),
        "background_std": float(f[background].std()),
        "vessel_fraction": float(vessel.sum() / max(fov.sum(), 1)),
        "fov_fraction": float(fov.mean()),
    }
