"""Appearance and geometry augmentation of simulated XA frames, batched in torch (cheap on one thread).

Reads/writes nothing. :func:`augment_batch` turns B full simulated frames (grey values, 8-bit scale,
vessels dark) and their masks into B random ``crop``² training crops, so the network sees far more
appearance variety than the renderer draws — what lets it transfer to real images:

* geometry: random rotation (any angle), flip, zoom ×0.6–1.6 (vessel widths of other pixel spacings),
  translation; bilinear resampling, masks thresholded at ½;
* background structures: a smooth random field (±30 grey), straight soft step edges (table, filters,
  phantom holders), blurred elliptic blobs (bone, bowel gas), faint thin straight lines;
* collimator: a random rounded rectangle outside which the image is dark (optionally a bright rim),
  with a soft edge — never labelled as vessel;
* contrast/gamma: global contrast ×0.45–1.8 about the background level, gamma 0.6–1.7;
* blur (σ 0–1.6 px) or unsharp masking, Gaussian noise (σ 0–10 grey), 8-bit quantisation;
* inverted polarity (10 %: vessels bright);
* finally :func:`stages.segment.model.normalise_batch`.
Every draw comes from the ``torch.Generator`` passed in (seeded by the training loop).
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from .model import normalise_batch

__all__ = ["augment_batch"]


def _u(g, n, lo, hi):
    return lo + (hi - lo) * torch.rand(n, generator=g)


def _gauss_blur(x: torch.Tensor, sigma: torch.Tensor) -> torch.Tensor:
    """Per-sample Gaussian blur (σ in px, 0 = none) with a separable 9-tap kernel."""
    B = x.shape[0]
    r = torch.arange(-4, 5, dtype=x.dtype)
    k = torch.exp(-0.5 * (r[None] / sigma.clamp(min=1e-3)[:, None]) ** 2)
    k = torch.where(sigma[:, None] < 0.05, (r[None] == 0).to(x.dtype), k)
    k = k / k.sum(1, keepdim=True)
    y = x.transpose(0, 1)  # 1×B×H×W: grouped conv, one kernel per sample
    y = F.conv2d(F.pad(y, (4, 4, 0, 0), mode="replicate"), k.view(B, 1, 1, 9), groups=B)
    y = F.conv2d(F.pad(y, (0, 0, 4, 4), mode="replicate"), k.view(B, 1, 9, 1), groups=B)
    return y.transpose(0, 1)


def _grid(B, H, W):
    yy = torch.linspace(-1, 1, H).view(1, H, 1).expand(B, H, W)
    xx = torch.linspace(-1, 1, W).view(1, 1, W).expand(B, H, W)
    return yy, xx


def augment_batch(frames: torch.Tensor, masks: torch.Tensor, g: torch.Generator, crop: int = 256,
                  strength: float = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """frames B×1×H×W float (grey), masks B×1×H×W float {0,1} → (normalised crops, mask crops)."""
    B, _, H, W = frames.shape
    # ---- geometry: output pixel (u, v) in [-1,1]² maps to input via rotation/zoom/translation
    ang = _u(g, B, 0, 2 * math.pi)
    zoom = torch.exp(_u(g, B, math.log(0.6), math.log(1.6)))  # >1: vessels appear wider
    flip = torch.where(torch.rand(B, generator=g) < 0.5, -1.0, 1.0)
    half = crop / W / zoom  # half-extent of the crop in normalised input coordinates
    tx = _u(g, B, -1, 1) * (1 - half).clamp(min=0)
    ty = _u(g, B, -1, 1) * (1 - half).clamp(min=0)
    # most crops are centred near a vessel pixel (the trees cover a few % of the frame only)
    for b in range(B):
        pos = torch.nonzero(masks[b, 0] > 0.5)
        if len(pos) and torch.rand(1, generator=g).item() < 0.75:
            r, c = pos[int(torch.randint(len(pos), (1,), generator=g))].tolist()
            lim = float((1 - half[b]).clamp(min=0))
            ty[b] = min(max((2 * r + 1) / H - 1 + float(_u(g, 1, -0.5, 0.5)) * half[b], -lim), lim)
            tx[b] = min(max((2 * c + 1) / W - 1 + float(_u(g, 1, -0.5, 0.5)) * half[b], -lim), lim)
    cos, sin = torch.cos(ang), torch.sin(ang)
    theta = torch.zeros(B, 2, 3)
    theta[:, 0, 0] = half * cos * flip
    theta[:, 0, 1] = -half * sin
    theta[:, 1, 0] = half * sin * flip
    theta[:, 1, 1] = half * cos
    theta[:, 0, 2] = tx
    theta[:, 1, 2] = ty
    grid = F.affine_grid(theta, (B, 1, crop, crop), align_corners=False)
    bg = frames.flatten(1).median(1).values.view(B, 1, 1, 1)
    x = F.grid_sample(frames - bg, grid, mode="bilinear", padding_mode="zeros", align_corners=False) + bg
    y = (F.grid_sample(masks, grid, mode="bilinear", padding_mode="zeros", align_corners=False) > 0.5).float()
    s = strength
    yy, xx = _grid(B, crop, crop)
    yy, xx = yy[:, None], xx[:, None]
    # ---- background structures
    field = F.interpolate(torch.randn(B, 1, 4, 4, generator=g), size=(crop, crop), mode="bicubic", align_corners=False)
    x = x + s * _u(g, B, 0, 30).view(B, 1, 1, 1) * field
    for _ in range(2):  # soft straight step edges
        on = (torch.rand(B, generator=g) < 0.3 * s).float().view(B, 1, 1, 1)
        a = _u(g, B, 0, 2 * math.pi).view(B, 1, 1, 1)
        d = torch.cos(a) * xx + torch.sin(a) * yy - _u(g, B, -0.8, 0.8).view(B, 1, 1, 1)
        x = x + on * _u(g, B, -20, 20).view(B, 1, 1, 1) * torch.sigmoid(d * crop / 3.0)
    for _ in range(3):  # blurred elliptic blobs
        on = (torch.rand(B, generator=g) < 0.3 * s).float().view(B, 1, 1, 1)
        cy, cx = _u(g, B, -1, 1).view(B, 1, 1, 1), _u(g, B, -1, 1).view(B, 1, 1, 1)
        ry, rx = _u(g, B, 0.1, 0.6).view(B, 1, 1, 1), _u(g, B, 0.1, 0.6).view(B, 1, 1, 1)
        r2 = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2
        x = x + on * _u(g, B, -30, 30).view(B, 1, 1, 1) * torch.sigmoid((1 - r2) * 6)
    on = (torch.rand(B, generator=g) < 0.3 * s).float().view(B, 1, 1, 1)  # faint thin straight line (no label)
    a = _u(g, B, 0, 2 * math.pi).view(B, 1, 1, 1)
    d = (torch.cos(a) * xx + torch.sin(a) * yy - _u(g, B, -0.8, 0.8).view(B, 1, 1, 1)) * crop / 2
    x = x - on * _u(g, B, 5, 15).view(B, 1, 1, 1) * torch.exp(-0.5 * (d / _u(g, B, 0.5, 1.5).view(B, 1, 1, 1)) ** 2)
    # ---- collimator: outside a rounded rectangle the image goes dark (bright rim sometimes)
    on = (torch.rand(B, generator=g) < 0.45 * s).float().view(B, 1, 1, 1)
    hy = _u(g, B, 0.7, 1.4).view(B, 1, 1, 1)
    hx = _u(g, B, 0.7, 1.4).view(B, 1, 1, 1)
    oy, ox = _u(g, B, -0.5, 0.5).view(B, 1, 1, 1), _u(g, B, -0.5, 0.5).view(B, 1, 1, 1)
    rc = _u(g, B, 0.05, 0.5).view(B, 1, 1, 1)
    qy = ((yy - oy).abs() - (hy - rc)).clamp(min=0)
    qx = ((xx - ox).abs() - (hx - rc)).clamp(min=0)
    box = torch.maximum((yy - oy).abs() - hy, (xx - ox).abs() - hx).clamp(max=0)
    sd = torch.sqrt(qy ** 2 + qx ** 2) + torch.maximum((yy - oy).abs() - (hy - rc), (xx - ox).abs() - (hx - rc)).clamp(max=0) - rc
    sd = torch.where(sd > 0, sd, torch.maximum(sd, box))
    inside = torch.sigmoid(-sd * crop / _u(g, B, 1.0, 6.0).view(B, 1, 1, 1))
    dark = _u(g, B, 0, 60).view(B, 1, 1, 1)
    rim = (torch.rand(B, generator=g) < 0.3).float().view(B, 1, 1, 1) * _u(g, B, 30, 120).view(B, 1, 1, 1) \
        * torch.exp(-0.5 * (sd * crop / 3.0 - 4.0) ** 2)
    x = on * (x * inside + dark * (1 - inside) + rim) + (1 - on) * x
    y = y * (on * (inside > 0.5).float() + (1 - on))
    # ---- contrast and gamma about the background level
    bg = x.flatten(1).median(1).values.view(B, 1, 1, 1)
    x = bg + _u(g, B, 0.45, 1.8).view(B, 1, 1, 1) * (x - bg)
    gam = torch.exp(_u(g, B, math.log(0.6), math.log(1.7))).view(B, 1, 1, 1)
    x = 255.0 * (x.clamp(0, 255) / 255.0) ** gam
    # ---- blur or sharpen, noise, quantise
    sig = torch.where(torch.rand(B, generator=g) < 0.6, _u(g, B, 0.0, 1.6), torch.zeros(B))
    x = _gauss_blur(x, sig)
    sharp = (torch.rand(B, generator=g) < 0.2).float().view(B, 1, 1, 1)
    x = x + sharp * _u(g, B, 0.3, 1.0).view(B, 1, 1, 1) * (x - _gauss_blur(x, torch.full((B,), 2.0)))
    x = x + _u(g, B, 0, 10).view(B, 1, 1, 1) * torch.randn(x.shape, generator=g)
    x = torch.round(x.clamp(0, 255))
    inv = (torch.rand(B, generator=g) < 0.1).float().view(B, 1, 1, 1)
    x = inv * (255 - x) + (1 - inv) * x
    return normalise_batch(x), y
