"""Segmenter-style corruption of rendered vessel masks (a training augmentation of the SBP network).

Reads/writes nothing on disk. At inference the SBP network sees masks from the segmentation network,
not exact silhouettes. On the real phantom runs those masks differ from a silhouette in a few recurring
ways, each drawn here by :func:`corrupt_mask` (counts are Poisson, lengths in pixels of a 512² image
and scaled with the image size):

* **breaks**: a disc on the centreline wiped across the vessel where contrast is faint or vessels cross
  (radius more than the local vessel radius, so the vessel is really cut);
* **spurious segments**: short straight bars 2–5 px wide — the edges of holders, wires and catheters —
  half of them starting on a vessel (as the false extensions at vessel ends do), half anywhere;
* **blobs**: small ellipses near or away from vessels (noise, bone edges);
* **widened stretches**: the mask dilated by 1–3 px inside a round patch (blotchy borders where
  vessels overlap or the background is busy);
* **boundary bias**: with probability ``boundary_p`` the whole mask dilated or eroded by one pixel
  (a segmenter whose threshold sits slightly off the true border).

Every draw comes from the ``numpy.random.Generator`` passed in, so a training pair stays a pure
function of its seed. Only the network's input masks are corrupted; the 3D ground truth is not.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import ndimage
from skimage import draw
from skimage.morphology import skeletonize

__all__ = ["MaskNoise", "corrupt_mask"]


@dataclass(frozen=True)
class MaskNoise:
    """Mean counts per view and size ranges (px at 512²) of each kind of segmentation error."""

    breaks: float = 1.5
    break_radius_px: tuple[float, float] = (2.0, 5.0)
    spurs: float = 1.5
    spur_length_px: tuple[float, float] = (15.0, 80.0)
    spur_width_px: tuple[float, float] = (2.0, 5.0)
    blobs: float = 1.0
    blob_radius_px: tuple[float, float] = (2.0, 7.0)
    widened: float = 1.0
    widen_patch_px: tuple[float, float] = (15.0, 40.0)
    widen_by_px: tuple[int, int] = (1, 3)
    boundary_p: float = 0.3


def _disc(radius: int) -> np.ndarray:
    r = np.arange(-radius, radius + 1)
    return r[:, None] ** 2 + r[None, :] ** 2 <= radius * radius


def _random_vessel_pixel(vessel_rc: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    return vessel_rc[int(rng.integers(len(vessel_rc)))].astype(float)


def corrupt_mask(mask: np.ndarray, rng: np.random.Generator, noise: MaskNoise = MaskNoise()) -> np.ndarray:
    """A copy of the boolean ``mask`` (H×W) with segmentation-like errors drawn from ``rng``.

    An empty mask is returned unchanged (nothing to imitate errors of).
    """
    mask = np.asarray(mask, dtype=bool)
    out = mask.copy()
    vessel_rc = np.argwhere(mask)
    if len(vessel_rc) == 0:
        return out
    H, W = mask.shape
    scale = max(H, W) / 512.0

    # widened stretches and the boundary bias act on the vessel itself, so they come first
    for _ in range(rng.poisson(noise.widened)):
        c = _random_vessel_pixel(vessel_rc, rng)
        patch = max(2, int(round(rng.uniform(*noise.widen_patch_px) * scale)))
        by = max(1, int(round(rng.integers(noise.widen_by_px[0], noise.widen_by_px[1] + 1) * scale)))
        r0, r1 = int(max(0, c[0] - patch - by)), int(min(H, c[0] + patch + by + 1))
        c0, c1 = int(max(0, c[1] - patch - by)), int(min(W, c[1] + patch + by + 1))
        grown = ndimage.binary_dilation(mask[r0:r1, c0:c1], structure=_disc(by))
        rr, cc = np.ogrid[r0:r1, c0:c1]
        inside = (rr - c[0]) ** 2 + (cc - c[1]) ** 2 <= patch * patch
        out[r0:r1, c0:c1] |= grown & inside
    if rng.random() < noise.boundary_p:
        cross = ndimage.generate_binary_structure(2, 1)
        out = ndimage.binary_dilation(out, cross) if rng.random() < 0.5 else ndimage.binary_erosion(out, cross)

    n_breaks = rng.poisson(noise.breaks)
    if n_breaks:  # the vessel's centreline and radius only matter to breaks
        centreline_rc = np.argwhere(skeletonize(mask))
        radius = ndimage.distance_transform_edt(mask)
    for _ in range(n_breaks):  # centred on the centreline and wider than the vessel: a real cut
        c = _random_vessel_pixel(centreline_rc, rng)
        r = max(rng.uniform(*noise.break_radius_px) * scale, radius[int(c[0]), int(c[1])] + 1.0)
        rr, cc = draw.disk((c[0], c[1]), r, shape=(H, W))
        out[rr, cc] = False

    for _ in range(rng.poisson(noise.spurs)):
        start = _random_vessel_pixel(vessel_rc, rng) if rng.random() < 0.5 else rng.uniform((0, 0), (H, W))
        angle = rng.uniform(0, np.pi)
        length = rng.uniform(*noise.spur_length_px) * scale
        half_width = 0.5 * rng.uniform(*noise.spur_width_px) * scale
        along = np.array([np.sin(angle), np.cos(angle)])
        across = np.array([along[1], -along[0]]) * half_width
        end = start + along * length
        corners = np.array([start + across, end + across, end - across, start - across])
        rr, cc = draw.polygon(corners[:, 0], corners[:, 1], shape=(H, W))
        out[rr, cc] = True

    for _ in range(rng.poisson(noise.blobs)):
        near = rng.random() < 0.5
        centre = _random_vessel_pixel(vessel_rc, rng) + rng.normal(0, 10 * scale, 2) if near else rng.uniform((0, 0), (H, W))
        radii = rng.uniform(*noise.blob_radius_px, size=2) * scale
        rr, cc = draw.ellipse(centre[0], centre[1], radii[0], radii[1], shape=(H, W), rotation=rng.uniform(0, np.pi))
        out[rr, cc] = True
    return out
