"""Writing figures: every PNG the stages make (overlays, key-frame curves, QCA plots, previews) goes through here.

Reads nothing; writes one PNG per call, atomically (:func:`stages.core.artefacts.atomic_path`).
"""

from __future__ import annotations

from pathlib import Path

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
