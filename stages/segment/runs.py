"""Reading an XA run for ``segment``/``keyframe``: DICOM, a folder of frame images, or a NumPy stack.

Reads: ``*.dcm`` (any DICOM via :func:`stages.dicom_io.read_xa`), a folder of ``.png/.tif/.tiff/.jpg``
frames (sorted by name, converted to grey), or ``.npy``/``.npz`` (array ``frames``) T×H×W; for the
last two an optional geometry JSON (``geometry.json`` in the folder or beside the stack, or given):
``{"alpha", "beta", "sid", "sod", "spacing": [row, col] or scalar, "rows", "cols",
"frame_time_ms", "r_wave_times_ms", "heart_rate_bpm"}`` — every key optional; without C-arm keys the
run has no camera. Writes nothing.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserError

log = logging.getLogger(__name__)

__all__ = ["Run", "load_run", "run_from_frames"]

IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp"}


@dataclass
class Run:
    """Frames (T×H×W float32, vessels dark) with what we know about the acquisition."""

    path: str
    frames: np.ndarray
    frame_times_ms: np.ndarray
    camera: object = None  # stages.geometry.Camera or None
    ecg: dict | None = None  # {"r_wave_time_vector_ms": [...], "heart_rate_bpm": ...}
    metadata: dict = field(default_factory=dict)

    @property
    def n_frames(self) -> int:
        return int(self.frames.shape[0])


def run_from_frames(frames, frame_time_ms: float = 1000.0 / 15, camera=None, ecg=None, name: str = "<array>") -> Run:
    f = np.asarray(frames, np.float32)
    if f.ndim == 2:
        f = f[None]
    if f.ndim != 3 or min(f.shape) < 1:
        raise UserError(f"{name}: expected frames T×H×W, got shape {f.shape}")
    return Run(name, f, np.arange(len(f)) * float(frame_time_ms), camera, ecg)


def _geometry_json(path: Path, geometry) -> dict:
    g = Path(geometry) if geometry else None
    if g is None:
        for cand in ([path / "geometry.json"] if path.is_dir() else [path.with_suffix(".json"), path.parent / "geometry.json"]):
            if cand.exists():
                g = cand
                break
    if g is None:
        return {}
    try:
        return json.loads(Path(g).read_text())
    except (OSError, ValueError) as exc:
        raise UserError(f"{g}: cannot read geometry JSON ({exc})") from None


def _camera_from(geo: dict, rows: int, cols: int, name: str):
    from ..geometry import Camera

    keys = ("alpha", "beta", "sid", "sod", "spacing")
    if not all(k in geo for k in keys):
        missing = [k for k in keys if k not in geo]
        if len(missing) < len(keys):
            raise UserError(f"{name}: geometry JSON lacks {', '.join(missing)}")
        return None
    sp = geo["spacing"]
    sp = (float(sp), float(sp)) if np.isscalar(sp) else (float(sp[0]), float(sp[1]))
    return Camera.from_carm(float(geo["alpha"]), float(geo["beta"]), float(geo["sid"]), float(geo["sod"]), sp, rows, cols)


def load_run(path, geometry=None) -> Run:
    """Load a run from a DICOM file, an image folder or a ``.npy``/``.npz`` stack (see module doc)."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file or folder")
    if path.is_dir():
        files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise UserError(f"{path}: no frame images ({', '.join(sorted(IMAGE_SUFFIXES))}) in the folder")
        from skimage import io

        imgs = []
        for p in files:
            im = np.asarray(io.imread(p), np.float32)
            if im.ndim == 3:
                im = im[..., :3].mean(-1)
            imgs.append(im)
        if len({im.shape for im in imgs}) > 1:
            raise UserError(f"{path}: frame images differ in size ({sorted({im.shape for im in imgs})})")
        frames = np.stack(imgs)
    elif path.suffix.lower() in (".npy", ".npz"):
        try:
            arr = np.load(path)
            frames = arr["frames"] if path.suffix.lower() == ".npz" else arr
        except (OSError, ValueError, KeyError) as exc:
            raise UserError(f"{path}: cannot read a frame stack ({exc}); .npz needs an array named 'frames'") from None
        frames = np.asarray(frames, np.float32)
    else:
        from ..dicom_io import read_xa

        xa = read_xa(path)
        return Run(str(path), xa.frames, np.asarray(xa.frame_times_ms, float), xa.camera, xa.ecg,
                   {"bits_stored": xa.bits_stored, **xa.metadata})
    if frames.ndim == 2:
        frames = frames[None]
    if frames.ndim != 3:
        raise UserError(f"{path}: expected T×H×W grey frames, got shape {frames.shape}")
    geo = _geometry_json(path, geometry)
    cam = _camera_from(geo, frames.shape[1], frames.shape[2], str(path))
    ft = float(geo.get("frame_time_ms", 1000.0 / 15))
    ecg = {k: geo[k] for k in ("heart_rate_bpm",) if k in geo}
    if "r_wave_times_ms" in geo:
        ecg["r_wave_time_vector_ms"] = [float(v) for v in geo["r_wave_times_ms"]]
    return Run(str(path), frames, np.arange(len(frames)) * ft, cam, ecg or None)
