"""Images as ``data:`` URIs, so that an HTML page (the reconstruction's report, the QCA section, the cohort
index) carries its figures in itself and opens anywhere, offline. Reads the image files; writes nothing."""

from __future__ import annotations

import base64
import io
from pathlib import Path

# overlays are photographs with thin lines: as JPEG at this quality they take ~4x less room than as PNG
JPEG_QUALITY = 85


def data_uri(png_path) -> str:
    """A PNG file as a ``data:image/png;base64,...`` URI."""
    return "data:image/png;base64," + base64.b64encode(Path(png_path).read_bytes()).decode("ascii")


def compact_data_uri(png_path) -> str:
    """An image file as a ``data:`` URI in the smaller of PNG (as it is) and JPEG (:data:`JPEG_QUALITY`)."""
    from PIL import Image

    raw = Path(png_path).read_bytes()
    with Image.open(io.BytesIO(raw)) as im:
        buf = io.BytesIO()
        im.convert("RGB").save(buf, format="JPEG", quality=JPEG_QUALITY, optimize=True)
    jpeg = buf.getvalue()
    if len(jpeg) < len(raw):
        return "data:image/jpeg;base64," + base64.b64encode(jpeg).decode("ascii")
    return "data:image/png;base64," + base64.b64encode(raw).decode("ascii")
