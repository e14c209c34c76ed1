"""Reading an XA run for ``segment``/``keyframe``/``calibrate``/``reconstruct``: DICOM, a folder of frame
images, or a NumPy stack.

Reads: ``*.dcm`` (any DICOM via :func:`stages.core.dicom_io.read_xa`), a folder of ``.png/.tif/.tiff/.jpg/.bmp``
frames (sorted by name, 8 or 16 bit, RGB converted to grey), or ``.npy``/``.npz`` (array ``frames``)
T×H×W; for the last two an optional geometry JSON (``geometry.json`` in the folder or beside the stack,
or given). Its schema (docs/CALIBRATION.md, "Geometry JSON"): C-arm keys ``PositionerPrimaryAngle``/``alpha``,
``PositionerSecondaryAngle``/``beta`` (deg), ``DistanceSourceToDetector``/``sid``,
``DistanceSourceToPatient``/``sod`` (mm), ``ImagerPixelSpacing``/``spacing`` (mm, scalar or [row, col]),
optional ``Rows``/``Columns`` (must match the frames); timing ``frame_time_ms`` or ``frame_rate_fps``;
optional ECG ``r_wave_times_ms`` (increasing, ms from the first frame) and ``heart_rate_bpm``; optional
``TablePosition`` ([x, y, z] patient LPS mm, for runs between which the table moved); optional
``units`` ({"angle": "deg", "length": "mm"}). Without any C-arm key the run has no camera; with some but
not all, or with a bad value, a :class:`UserError` names the key. Writes nothing.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import UserError

log = logging.getLogger(__name__)

__all__ = ["Run", "load_run", "run_from_frames", "export_frames", "place_on_one_table"]

IMAGE_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp"}


@dataclass
class Run:
    """Frames (T×H×W float32, vessels dark) with what we know about the acquisition."""

    path: str
    frames: np.ndarray
    frame_times_ms: np.ndarray
    camera: object = None  # stages.core.geometry.Camera or None
    ecg: dict | None = None  # {"r_wave_time_vector_ms": [...], "heart_rate_bpm": ...}
    metadata: dict = field(default_factory=dict)
    table_mm: np.ndarray | None = None  # table position (patient LPS mm) when the header or JSON gives it

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


def _geometry_json(path: Path, geometry) -> tuple[dict, str]:
    from .geometry import read_geometry_json

    g = Path(geometry) if geometry else None
    if g is None:
        for cand in ([path / "geometry.json"] if path.is_dir() else [path.with_suffix(".json"), path.parent / "geometry.json"]):
            if cand.exists():
                g = cand
                break
    if g is None:
        return {}, ""
    return read_geometry_json(g), str(g)


_CARM_ANY = ("PositionerPrimaryAngle", "alpha", "primary_angle", "PositionerSecondaryAngle", "beta",
             "secondary_angle", "DistanceSourceToDetector", "sid", "SID", "DistanceSourceToPatient", "sod", "SOD",
             "ImagerPixelSpacing", "pixel_spacing", "spacing", "matrix", "projection_matrix")


def _camera_from(geo: dict, rows: int, cols: int, name: str):
    from .geometry import camera_from_geometry_dict

    if not any(k in geo for k in _CARM_ANY):
        return None
    try:
        return camera_from_geometry_dict(geo, source=name, rows=rows, cols=cols)
    except UserError as exc:
        msg = str(exc)
        if "missing geometry field" in msg:  # keep the short form for a partial C-arm description
            msg = msg.replace("missing geometry field(s)", "geometry JSON lacks")
        raise UserError(msg) from None


def _positive(geo: dict, key: str, name: str, lo: float, hi: float) -> float | None:
    if key not in geo:
        return None
    v = geo[key]
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
        raise UserError(f"{name}: {key} must be a finite number, got {v!r}")
    if not lo <= float(v) <= hi:
        raise UserError(f"{name}: {key} = {v:g} is outside the plausible range {lo:g}…{hi:g}")
    return float(v)


def _timing(geo: dict, name: str) -> tuple[float, dict | None]:
    """(frame time ms, ECG dict or None) from a geometry JSON, each value checked."""
    ft = _positive(geo, "frame_time_ms", name, 1.0, 1000.0)
    fps = _positive(geo, "frame_rate_fps", name, 1.0, 1000.0)
    if ft is not None and fps is not None and abs(ft - 1000.0 / fps) > 0.01 * ft:
        raise UserError(f"{name}: frame_time_ms ({ft:g}) and frame_rate_fps ({fps:g}) disagree")
    if ft is None and fps is not None:
        ft = 1000.0 / fps
    if ft is None:
        log.warning("%s: no frame_time_ms / frame_rate_fps in the geometry JSON; assuming 15 frames/s", name)
        ft = 1000.0 / 15
    ecg = {}
    hr = _positive(geo, "heart_rate_bpm", name, 20.0, 300.0)
    if hr is not None:
        ecg["heart_rate_bpm"] = hr
    if "r_wave_times_ms" in geo:
        rw = geo["r_wave_times_ms"]
        if not isinstance(rw, list) or not all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in rw):
            raise UserError(f"{name}: r_wave_times_ms must be a list of numbers (ms), got {rw!r}")
        arr = np.asarray(rw, float)
        if not np.all(np.isfinite(arr)) or np.any(np.diff(arr) <= 0):
            raise UserError(f"{name}: r_wave_times_ms must be finite and increasing")
        ecg["r_wave_time_vector_ms"] = [float(v) for v in arr]
    return ft, ecg or None


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
            if im.ndim == 3:  # grey+alpha, RGB or RGBA: drop alpha, average the colours
                im = im[..., :1].mean(-1) if im.shape[-1] in (1, 2) else im[..., :3].mean(-1)
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
        from .dicom_io import read_xa

        xa = read_xa(path)
        table = None if xa.geometry.table_mm is None else np.asarray(xa.geometry.table_mm, float)
        return Run(str(path), xa.frames, np.asarray(xa.frame_times_ms, float), xa.camera, xa.ecg,
                   {"bits_stored": xa.bits_stored, **xa.metadata}, table)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.ndim != 3:
        raise UserError(f"{path}: expected T×H×W grey frames, got shape {frames.shape}")
    geo, geo_path = _geometry_json(path, geometry)
    name = geo_path or str(path)
    cam = _camera_from(geo, frames.shape[1], frames.shape[2], name)
    ft, ecg = _timing(geo, name) if geo else (1000.0 / 15, None)
    from .geometry import table_position_from_dict

    table = table_position_from_dict(geo, name) if geo else None
    return Run(str(path), frames, np.arange(len(frames)) * ft, cam, ecg,
               {"geometry_json": geo_path} if geo_path else {}, table)


def place_on_one_table(runs, names=None) -> dict:
    """Move the cameras of runs whose table moved into the first run's patient frame, in place
    (:func:`stages.core.geometry.cameras_on_one_table`); returns ``{name: offset mm}`` of the runs moved."""
    from .geometry import cameras_on_one_table

    names = names or [Path(r.path).stem for r in runs]
    cams, offsets = cameras_on_one_table([r.camera for r in runs], [r.table_mm for r in runs], names)
    for r, c in zip(runs, cams):
        r.camera = c
    for name, d in offsets.items():
        log.info("%s: the table stood (%+.1f, %+.1f, %+.1f) mm (x, y, z) from %s's; its camera is placed "
                 "accordingly", name, *d, names[0])
    return offsets


def export_frames(run_path, folder, fmt: str = "png") -> Path:
    """Write a DICOM run as a frame folder (16-bit PNG or TIFF per frame, ``frame_000.png`` …) plus the
    ``geometry.json`` of its header (DICOM key names, frame time, ECG when present): the form of a
    clinical export, readable by :func:`load_run`. Returns the folder."""
    from skimage import io

    from .artefacts import write_json
    from .dicom_io import read_xa

    if fmt not in ("png", "tif"):
        raise UserError(f"export format {fmt!r}: choose png or tif")
    xa = read_xa(run_path)
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    frames = np.asarray(xa.frames)
    if frames.min() < 0 or frames.max() > 65535 or not np.all(frames == np.round(frames)):
        raise UserError(f"{run_path}: frames are not 16-bit integers; cannot export them losslessly to {fmt}")
    for t, f in enumerate(frames.astype(np.uint16)):
        io.imsave(folder / f"frame_{t:03d}.{fmt}", f, check_contrast=False)
    g = xa.geometry
    times = np.asarray(xa.frame_times_ms, float)
    geo = {"PositionerPrimaryAngle": g.alpha, "PositionerSecondaryAngle": g.beta,
           "DistanceSourceToDetector": g.sid, "DistanceSourceToPatient": g.sod,
           "ImagerPixelSpacing": list(g.spacing), "Rows": g.rows, "Columns": g.cols,
           "frame_time_ms": float(np.median(np.diff(times))) if len(times) > 1 else 1000.0 / 15,
           "units": {"angle": "deg", "length": "mm"}}
    if g.table_mm is not None:
        geo["TablePosition"] = [float(v) for v in g.table_mm]
    ecg = xa.ecg or {}
    for k in ("r_wave_time_vector_ms", "r_peak_times_ms"):
        if k in ecg:
            geo["r_wave_times_ms"] = [float(v) for v in ecg[k]]
    if "heart_rate_bpm" in ecg:
        geo["heart_rate_bpm"] = float(ecg["heart_rate_bpm"])
    write_json(folder / "geometry.json", geo)
    return folder
