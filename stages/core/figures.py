"""Writing figures: every PNG the stages make (overlays, key-frame curves, QCA plots, previews) goes through here.

Reads nothing; writes one PNG per call, atomically (:func:`stages.core.artefacts.atomic_path`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .artefacts import atomic_path

# zlib level 3: as small as the default level 6 on our overlays and plots (within 0.1 %), and 3× faster to
# encode (a 900×470 overlay: 26 ms against 76 ms), which a reconstruction pays once per key frame
PNG_COMPRESS_LEVEL = 3


def save_png(fig, path, dpi: float, close: bool = True) -> Path:
    """Write a matplotlib figure as a PNG at ``dpi``, atomically; close the figure unless told not to."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL})
    if close:
        import matplotlib.pyplot as plt

        plt.close(fig)
    return path


def save_image_png(image, path) -> Path:
    """Write a PIL image as a PNG, atomically (same compression as :func:`save_png`)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG", compress_level=PNG_COMPRESS_LEVEL)
    return path


def draw_overlay_panels(path, frames, titles, segments, values, *, cmap: str = "turbo", line_px: float = 1.6,
                        supersample: int = 3, title_px: int = 22, gap_px: int = 8, min_panel_px: int = 400) -> Path:
    """Write a PNG of grey frames side by side, each under its title, with line segments drawn over it:
    ``segments[i]`` (K×4: row₀, col₀, row₁, col₁ in frame i's pixels, centres at integer indices) coloured by
    ``values`` (K, 0…1) through the colormap ``cmap``. A panel shows its frame at its own resolution, enlarged by
    a whole factor while smaller than ``min_panel_px`` (a 256² run: 2×). The lines are drawn ``supersample`` times
    larger still and the panel shrunk back (antialiased lines), by Pillow: a matplotlib figure of the same took
    ~0.1 s."""
    from matplotlib import colormaps
    from PIL import Image, ImageDraw

    colours = (np.asarray(colormaps[cmap](np.clip(np.asarray(values, float), 0.0, 1.0)))[:, :3] * 255).round()
    colours = [tuple(c) for c in colours.astype(int).tolist()]
    supersample = int(supersample)
    panels = []
    for frame, seg in zip(frames, segments):
        f = np.asarray(frame, np.float32)
        lo, hi = float(np.nanmin(f)), float(np.nanmax(f))
        grey = np.clip((f - lo) / max(hi - lo, 1e-12) * 255.0, 0, 255).astype(np.uint8)
        zoom = max(1, -(-int(min_panel_px) // max(grey.shape)))
        h, w = grey.shape[0] * zoom, grey.shape[1] * zoom
        panel = Image.fromarray(grey).convert("RGB").resize((w, h), Image.BICUBIC)  # no-op at zoom 1
        big = panel.resize((w * supersample, h * supersample), Image.NEAREST)
        draw = ImageDraw.Draw(big)
        line_width = max(int(round(line_px * supersample)), 1)
        scale = zoom * supersample  # frame pixel → enlarged panel pixel (centres at integer indices)
        xy = (np.asarray(seg, float).reshape(-1, 4) + 0.5) * scale - 0.5
        finite = np.isfinite(xy).all(1).tolist()
        for (r0, c0, r1, c1), colour, ok in zip(xy.tolist(), colours, finite):
            if ok:
                draw.line([(c0, r0), (c1, r1)], fill=colour, width=line_width)
        panels.append(big.resize((w, h), Image.BOX))
    width = sum(p.width for p in panels) + gap_px * (len(panels) + 1)
    canvas = Image.new("RGB", (width, max(p.height for p in panels) + title_px + gap_px), "white")
    draw = ImageDraw.Draw(canvas)
    font = _title_font(13)
    x = gap_px
    for panel, title in zip(panels, titles):
        canvas.paste(panel, (x, title_px))
        draw.text((x + panel.width / 2, title_px / 2), title, fill="black", font=font, anchor="mm")
        x += panel.width + gap_px
    return save_image_png(canvas, path)


def _title_font(size: int):
    """DejaVu Sans (the font of the matplotlib figures, shipped with matplotlib) at ``size`` px, or Pillow's own."""
    import os

    import matplotlib
    from PIL import ImageFont

    try:
        return ImageFont.truetype(os.path.join(matplotlib.get_data_path(), "fonts", "ttf", "DejaVuSans.ttf"), size)
    except OSError:
        return ImageFont.load_default(size=size)
