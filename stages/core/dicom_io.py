"""X-ray angiography DICOM input/output: frames, C-arm geometry, timing and ECG/phase information.

Reads single- and multi-frame XA (and RF) files, compressed or not (JPEG-lossless via python-gdcm, a
permissively licensed decoder; pydicom picks it automatically), and writes multi-frame XA files with
the same geometry and timing tags so a written run reads back identically.

Geometry tags (DESIGN.md §3): PositionerPrimaryAngle, PositionerSecondaryAngle,
DistanceSourceToDetector, DistanceSourceToPatient and the detector pixel spacing, taken from, in order:
ImagerPixelSpacing → PixelSpacing × SID/SOD → FieldOfViewDimensions / matrix size. Every fallback is
logged and recorded in ``XARun.spacing_source``.

Reads: ``*.dcm`` (or any DICOM file). Writes: multi-frame XA DICOM (``write_xa``).
"""

from __future__ import annotations

import datetime as _dt
import logging
import os
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .errors import UserError
from .geometry import Camera, check_carm_parameters

log = logging.getLogger(__name__)

XA_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.12.1"
RF_SOP_CLASS = "1.2.840.10008.5.1.4.1.1.12.2"
ACCEPTED_MODALITIES = {"XA", "RF"}


@dataclass
class XAGeometry:
    """C-arm pose of one run (degrees, mm) and where the pixel spacing came from."""

    alpha: float
    beta: float
    sid: float
    sod: float
    spacing: tuple[float, float]  # detector (row, col) mm
    rows: int
    cols: int
    spacing_source: str = "ImagerPixelSpacing"
    table_mm: tuple[float, float, float] | None = None  # table position (patient LPS x, y, z mm), when the header has it
    table_source: str = ""

    def camera(self) -> Camera:
        """The header camera, as if the table had not moved; runs whose table moved are placed in one
        patient frame by :func:`stages.core.geometry.cameras_on_one_table`."""
        return Camera.from_carm(self.alpha, self.beta, self.sid, self.sod, self.spacing, self.rows, self.cols)

    def as_dict(self) -> dict:
        d = {"alpha": self.alpha, "beta": self.beta, "sid": self.sid, "sod": self.sod,
             "spacing": list(self.spacing), "rows": self.rows, "cols": self.cols,
             "spacing_source": self.spacing_source}
        if self.table_mm is not None:
            d.update(table_mm=list(self.table_mm), table_source=self.table_source)
        return d


@dataclass
class XARun:
    """One cine run: frames (T×H×W float32, raw stored values, vessels dark), geometry and timing."""

    path: Path
    frames: np.ndarray | None
    geometry: XAGeometry
    frame_times_ms: np.ndarray  # (T,) acquisition time of each frame relative to the first, ms
    n_frames: int
    bits_stored: int
    ecg: dict | None = None  # e.g. {"r_peak_times_ms": [...]} or {"phase": [...]} when present
    metadata: dict = field(default_factory=dict)

    @property
    def camera(self) -> Camera:
        return self.geometry.camera()


# ------------------------------------------------------------------------------------------- reading
# Sanity bounds on what a header may claim before anything is allocated for it
MAX_SIDE = 16384  # rows/columns of an XA detector are ≤ 2048; anything above 16 k is a lying header
MAX_DECODED_BYTES = 32 * 2 ** 30
_ENCAPSULATED_MIN_FRAME_BYTES = 8  # every compressed frame needs at least an item header (tag + length)


def _read_dataset(path: Path, stop_before_pixels: bool):
    """The dataset, or a UserError naming the file. pydicom's warnings are caught: a truncation warning
    becomes the error, any other is logged once (not printed as a raw ``UserWarning``).

    Pixel data is always located (a deferred read: large values stay on disk, except encapsulated pixel
    data, which pydicom reads to find its end — at most the file's size), so its size can be checked
    against the header before anything is decoded (:func:`check_pixel_claims`)."""
    import pydicom
    from pydicom.errors import InvalidDicomError

    if not path.exists():
        raise UserError(f"{path}: no such file")
    if path.is_dir():
        raise UserError(f"{path}: is a folder, expected a DICOM file")
    with _PydicomMessages() as said:
        try:
            ds = pydicom.dcmread(path, defer_size=4096)
        except InvalidDicomError:
            raise UserError(f"{path}: not a DICOM file (no DICM preamble)") from None
        except MemoryError:
            raise UserError(f"{path}: unreadable DICOM (an element claims more memory than there is)") from None
        except Exception as exc:  # truncated or corrupt files raise a variety of errors
            raise UserError(f"{path}: unreadable DICOM ({type(exc).__name__}: {_short(exc)})") from None
    messages = [m.replace(f" found in file {path}", "").replace(f" in file {path}", "") for m in said.messages]
    for msg in messages:
        if "end of file" in msg.lower() or "truncat" in msg.lower():
            raise UserError(f"{path}: truncated DICOM file ({path.stat().st_size} bytes; {_short(msg)})")
    for msg in messages:
        log.warning("%s: %s", path.name, _short(msg))
    if len(ds) == 0:
        raise UserError(f"{path}: truncated or empty DICOM file (no data elements after the file meta header)")
    return ds


class _PydicomMessages:
    """Collects what pydicom says while reading (its warnings and its log records, which repeat each
    other) so the caller decides: an error, or one log line per distinct message."""

    def __enter__(self):
        import warnings

        self._warn = warnings.catch_warnings(record=True)
        self._caught = self._warn.__enter__()
        warnings.simplefilter("always")
        self._logger = logging.getLogger("pydicom")
        self._level, self._propagate = self._logger.level, self._logger.propagate
        self._logger.setLevel(logging.CRITICAL)
        return self

    def __exit__(self, *exc):
        self._logger.setLevel(self._level)
        self._warn.__exit__(*exc)
        return False

    @property
    def messages(self) -> list[str]:
        return list(dict.fromkeys(str(w.message) for w in self._caught))


class _DecoderStderr:
    """Catches what C decoders (gdcm, libjpeg) write straight to file descriptor 2 ("Corrupt JPEG data: ...")
    and logs it once, with the file's name, instead of letting raw lines interleave with the CLI's output."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        import tempfile

        self._saved = None
        try:
            sys.stderr.flush()
            self._tmp = tempfile.TemporaryFile()
            self._saved = os.dup(2)
            os.dup2(self._tmp.fileno(), 2)
        except (OSError, ValueError, AttributeError):
            self._saved = None
        return self

    def __exit__(self, *exc):
        if self._saved is None:
            return False
        os.dup2(self._saved, 2)
        os.close(self._saved)
        self._tmp.seek(0)
        text = self._tmp.read().decode("utf-8", "replace")
        self._tmp.close()
        lines = list(dict.fromkeys(line.strip() for line in text.splitlines() if line.strip()))
        if lines:
            more = f" (and {len(lines) - 2} other message(s))" if len(lines) > 2 else ""
            log.warning("%s: the pixel decoder reported: %s%s", self.path.name, "; ".join(lines[:2]), more)
        return False


def _short(text, limit: int = 200) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _int_tag(ds, name, path: Path, default=None):
    value = ds.get(name, default)
    if value is None or value == "":
        return default
    try:
        return int(value)
    except (TypeError, ValueError):
        raise UserError(f"{path}: {name} {_short(value, 40)!r} is not an integer") from None


def check_pixel_claims(ds, path: Path) -> dict:
    """Check what the header claims (NumberOfFrames, Rows, Columns, BitsAllocated, SamplesPerPixel) against
    the pixel data actually in the file, before decoding anything. Returns the checked numbers."""
    from pydicom.uid import UID

    rows, cols = _int_tag(ds, "Rows", path, 0), _int_tag(ds, "Columns", path, 0)
    n_frames = _int_tag(ds, "NumberOfFrames", path, 1)
    bits = _int_tag(ds, "BitsAllocated", path, None)
    spp = _int_tag(ds, "SamplesPerPixel", path, 1)
    if not (0 < rows <= MAX_SIDE and 0 < cols <= MAX_SIDE):
        raise UserError(f"{path}: image size Rows × Columns = {rows} × {cols} is missing or absurd (1…{MAX_SIDE} each)")
    if n_frames < 1:
        raise UserError(f"{path}: NumberOfFrames {n_frames} (need ≥ 1)")
    if bits not in (8, 16, 32):
        raise UserError(f"{path}: BitsAllocated {bits} is not 8, 16 or 32")
    if spp != 1:
        raise UserError(f"{path}: SamplesPerPixel {spp}: X-ray angiography frames are grey (1 sample per pixel)")
    if "PixelData" not in ds:
        return {"rows": rows, "cols": cols, "frames": n_frames, "bits": bits, "samples": spp, "pixel_bytes": 0}
    frame_bytes = rows * cols * spp * bits // 8
    decoded = n_frames * frame_bytes
    file_size = path.stat().st_size
    elem = ds.get_item("PixelData")
    length = getattr(elem, "length", None)
    value = getattr(elem, "value", None)
    tsyntax = UID(str(getattr(getattr(ds, "file_meta", None), "TransferSyntaxUID", "") or "1.2.840.10008.1.2"))
    encapsulated = bool(tsyntax.is_encapsulated) if tsyntax.is_transfer_syntax else False
    if encapsulated:
        data = value if isinstance(value, (bytes, bytearray)) else None
        present = len(data) if data is not None else max(file_size - int(getattr(elem, "value_tell", 0) or 0), 0)
        fragments = _count_fragments(data) if data is not None else None
        if fragments is None and n_frames * _ENCAPSULATED_MIN_FRAME_BYTES > present:
            fragments = 0
        if fragments is not None and fragments < n_frames:
            raise UserError(f"{path}: header claims {n_frames} frame(s) but the compressed pixel data holds "
                            f"{fragments} fragment(s) ({present} bytes): a truncated file or a lying NumberOfFrames")
        if decoded > MAX_DECODED_BYTES:
            raise UserError(f"{path}: {n_frames} frame(s) of {rows} × {cols} × {bits} bit would need "
                            f"{decoded / 2 ** 30:.1f} GiB decoded (limit {MAX_DECODED_BYTES / 2 ** 30:.0f} GiB)")
    else:
        if isinstance(value, (bytes, bytearray)):
            present = len(value)
        elif length is not None and length != 0xFFFFFFFF:
            tell = int(getattr(elem, "value_tell", 0) or 0)
            present = min(int(length), max(file_size - tell, 0))
            if tell + int(length) > file_size:
                raise UserError(f"{path}: truncated DICOM file: PixelData claims {int(length)} bytes, the file "
                                f"holds {max(file_size - tell, 0)} of them")
        else:
            present = 0
        if present < decoded:
            raise UserError(f"{path}: header claims {n_frames} frame(s) of {rows} × {cols} × {bits} bit "
                            f"({decoded} bytes) but the pixel data holds {present} bytes: a truncated file or a "
                            "lying header (NumberOfFrames, Rows, Columns, BitsAllocated)")
    return {"rows": rows, "cols": cols, "frames": n_frames, "bits": bits, "samples": spp, "pixel_bytes": present}


def _count_fragments(data: bytes) -> int | None:
    """Fragments (excluding the basic offset table) in encapsulated pixel data; None if the items do not parse."""
    import struct

    pos, n, first = 0, 0, True
    end = len(data)
    while pos + 8 <= end:
        group, elem, size = struct.unpack_from("<HHI", data, pos)
        if (group, elem) == (0xFFFE, 0xE0DD):  # sequence delimiter
            return n
        if (group, elem) != (0xFFFE, 0xE000) or size == 0xFFFFFFFF:
            return None
        pos += 8 + size
        if pos > end:
            return n  # the last item runs past the data: truncated
        if not first:
            n += 1
        first = False
    return n


def _float_tag(ds, name):
    """A numeric tag as a finite float; None when absent, empty, not a number or not finite."""
    try:
        value = ds.get(name)
    except Exception:  # a value pydicom cannot convert
        return None
    if value is None or value == "":
        return None
    try:
        v = float(value)
    except (TypeError, ValueError, OverflowError):
        return None
    return v if np.isfinite(v) else None


def _present_but_invalid(ds, name) -> bool:
    try:
        value = ds.get(name)
    except Exception:
        return True
    return value is not None and value != "" and _float_tag(ds, name) is None


def _pair(value) -> tuple[float, float] | None:
    if value is None or value == "":
        return None
    try:
        vals = [float(v) for v in (value if hasattr(value, "__len__") and not isinstance(value, str) else [value])]
    except (TypeError, ValueError):
        return None
    if len(vals) == 1:
        vals = vals * 2
    return (vals[0], vals[1])


def geometry_from_dataset(ds, path: Path) -> XAGeometry:
    """C-arm geometry of a dataset, with DESIGN.md's spacing fallbacks (logged)."""
    modality = str(ds.get("Modality", "")).upper()
    if modality not in ACCEPTED_MODALITIES:
        raise UserError(f"{path}: modality {modality or 'missing'!s} is not X-ray angiography (expected XA or RF)")
    alpha, beta = _float_tag(ds, "PositionerPrimaryAngle"), _float_tag(ds, "PositionerSecondaryAngle")
    sid, sod = _float_tag(ds, "DistanceSourceToDetector"), _float_tag(ds, "DistanceSourceToPatient")
    tags = [("PositionerPrimaryAngle", "(0018,1510)", alpha), ("PositionerSecondaryAngle", "(0018,1511)", beta),
            ("DistanceSourceToDetector", "(0018,1110)", sid), ("DistanceSourceToPatient", "(0018,1111)", sod)]
    invalid = [f"{n} {t}" for n, t, v in tags if v is None and _present_but_invalid(ds, n)]
    if invalid:
        raise UserError(f"{path}: C-arm geometry tag(s) {', '.join(invalid)} hold no finite number; pass a geometry JSON instead")
    if alpha is not None and beta is not None and (abs(alpha) > 360 or abs(beta) > 360):
        raise UserError(f"{path}: positioner angles α = {alpha:g}°, β = {beta:g}° are outside ±360°")
    missing = [f"{n} {t}" for n, t, v in tags if v is None]
    if missing:
        raise UserError(f"{path}: missing C-arm geometry tag(s) {', '.join(missing)}; pass a geometry JSON instead")
    rows, cols = _int_tag(ds, "Rows", path, 0) or 0, _int_tag(ds, "Columns", path, 0) or 0
    if rows <= 0 or cols <= 0:
        raise UserError(f"{path}: missing image size (Rows/Columns)")

    spacing = _pair(ds.get("ImagerPixelSpacing"))
    source = "ImagerPixelSpacing"
    if spacing is None:
        ps = _pair(ds.get("PixelSpacing"))
        if ps is not None and sod > 0:
            spacing = (ps[0] * sid / sod, ps[1] * sid / sod)
            source = "PixelSpacing×SID/SOD"
    if spacing is None:
        fov = _pair(ds.get("FieldOfViewDimensions"))
        if fov is not None:
            spacing = (fov[0] / rows, fov[1] / cols)
            source = "FieldOfViewDimensions/matrix"
    if spacing is None:
        raise UserError(f"{path}: no pixel spacing (ImagerPixelSpacing (0018,1164), PixelSpacing or FieldOfViewDimensions); pass a geometry JSON instead")
    if source != "ImagerPixelSpacing":
        log.warning("%s: ImagerPixelSpacing absent, detector spacing %.4f×%.4f mm from %s", path.name, spacing[0], spacing[1], source)
    try:
        check_carm_parameters(sid, sod, spacing, rows, cols, source=str(path))
    except UserError:
        raise
    table, table_source = table_position(ds)
    return XAGeometry(alpha, beta, sid, sod, spacing, rows, cols, source, table, table_source)


# GE Innova/DL headers keep the table position in a private block. The axes and signs are not documented;
# measured on ../shared/data/phantom_xa (docs/CALIBRATION.md, "The table moved"): with x = lateral,
# y = vertical, z = longitudinal, all +, the displacements of runs IM5–IM8 from IM1–IM4 explain the 4.7–26.6 mm
# offsets that an 8-run joint calibration finds, to 1.0–3.2 mm; the next-best of the 8 sign choices leaves 17.8 mm.
_GE_TABLE = ("DLX_SERIE_01", 0x0019, {"lateral": 0x23, "vertical": 0x21, "longitudinal": 0x22})


def table_position(ds) -> tuple[tuple[float, float, float] | None, str]:
    """(table position as patient LPS (x, y, z) mm, where it came from), or (None, "") when the header
    does not say. Read: GE's private table block (lateral → x, vertical → y, longitudinal → z). Other
    vendors' table tags are not read (their conventions are unverified here): such runs keep the
    DESIGN.md assumption of a fixed table, and a geometry JSON can give ``TablePosition``."""
    creator, group, elements = _GE_TABLE
    try:
        block = ds.private_block(group, creator)
        vals = []
        for key in ("lateral", "vertical", "longitudinal"):
            elem = block[elements[key]]
            v = float(elem.value)
            if not np.isfinite(v):
                return None, ""
            vals.append(v)
    except (KeyError, ValueError, TypeError):
        return None, ""
    return (vals[0], vals[1], vals[2]), f"{creator} (0019,xx21–23)"


def _frame_times(ds, n_frames: int, path: Path) -> np.ndarray:
    """Frame acquisition times (ms from the first frame) from FrameTimeVector, FrameTime or CineRate."""
    ftv = ds.get("FrameTimeVector")
    try:
        vector = [float(v) for v in ftv] if ftv is not None and not isinstance(ftv, (str, bytes)) else None
    except (TypeError, ValueError):
        vector = None
    if vector is not None and len(vector) == n_frames and np.isfinite(vector).all():
        # FrameTimeVector holds the increment from the previous frame; the first entry is 0
        return np.cumsum(np.asarray(vector)) - vector[0]
    ft = _float_tag(ds, "FrameTime")
    if ft is None or ft <= 0:
        rate = _float_tag(ds, "CineRate") or _float_tag(ds, "RecommendedDisplayFrameRate")
        if rate:
            ft = 1000.0 / rate
    if ft is None or ft <= 0:
        if n_frames > 1:
            log.warning("%s: no frame timing (FrameTime/FrameTimeVector/CineRate); assuming 15 frames/s", path.name)
        ft = 1000.0 / 15.0
    return np.arange(n_frames, dtype=float) * ft


def _ecg(ds) -> dict | None:
    """ECG/phase information when present: R-peak times (our writer's private-free convention) or curve data."""
    out = {}
    # Cardiac synchronisation: R-wave time vector per frame (0018,1086 is skipped beats); we use
    # RWaveTimeVector (0018,6060) when present, and the trigger time of each frame.
    rwave = ds.get("RWaveTimeVector")
    if rwave is not None and rwave != "":
        values = rwave if isinstance(rwave, (list, tuple)) or hasattr(rwave, "__iter__") and not isinstance(rwave, (str, bytes)) else [rwave]
        out["r_wave_time_vector_ms"] = [float(v) for v in values]
    hr = _float_tag(ds, "HeartRate")
    if hr:
        out["heart_rate_bpm"] = hr
    return out or None


def read_xa(path, load_pixels: bool = True) -> XARun:
    """Read one XA/RF DICOM run. Raises UserError with the file name on any problem."""
    path = Path(path)
    ds = _read_dataset(path, stop_before_pixels=not load_pixels)
    with _PydicomMessages() as said:  # pydicom converts values lazily, and warns about bad ones as it does
        try:
            run = _run_from_dataset(ds, path, load_pixels)
        except UserError:
            raise
        except MemoryError:
            raise UserError(f"{path}: the file claims more memory than this machine has") from None
        except Exception as exc:
            # everything in there interprets the file's own values, which pydicom parses lazily: an unknown
            # VR, a value of the wrong type or multiplicity (a corrupt header) is the file's problem, not a
            # bug to show as a traceback
            raise UserError(f"{path}: malformed DICOM header ({type(exc).__name__}: {_short(exc)})") from None
    for msg in said.messages:
        log.warning("%s: %s", path.name, _short(msg))
    return run


def _run_from_dataset(ds, path: Path, load_pixels: bool) -> XARun:
    geometry = geometry_from_dataset(ds, path)
    claims = check_pixel_claims(ds, path)
    n_frames = claims["frames"]
    if "PixelData" not in ds:
        raise UserError(f"{path}: no pixel data")
    frames = None
    if load_pixels:
        with _DecoderStderr(path):
            try:
                arr = ds.pixel_array
            except MemoryError:
                raise UserError(f"{path}: pixel data too large to decode on this machine") from None
            except Exception as exc:
                raise UserError(f"{path}: cannot decode pixel data ({type(exc).__name__}: {_short(exc)})") from None
        arr = np.asarray(arr)
        if arr.ndim == 3 and arr.shape[0] != n_frames:
            raise UserError(f"{path}: header claims {n_frames} frame(s), the pixel data decoded to {arr.shape[0]}")
        if arr.ndim == 2:
            arr = arr[None]
        if arr.ndim != 3:
            raise UserError(f"{path}: expected grey-scale frames, got pixel array of shape {arr.shape}")
        frames = arr.astype(np.float32)
        if str(ds.get("PhotometricInterpretation", "MONOCHROME2")) == "MONOCHROME1":
            # MONOCHROME1 stores vessels bright; flip so vessels are dark as everywhere else in autocar
            frames = float(2 ** min(_int_tag(ds, "BitsStored", path, 8) or 8, 32) - 1) - frames
        n_frames = frames.shape[0]
    bits_stored = _int_tag(ds, "BitsStored", path, 8) or 8
    meta = {k: str(ds.get(k, "")) for k in ("PatientID", "StudyInstanceUID", "SeriesInstanceUID",
                                            "SOPInstanceUID", "Manufacturer", "Modality", "AcquisitionDate")}
    return XARun(
        path=path, frames=frames, geometry=geometry, frame_times_ms=_frame_times(ds, n_frames, path),
        n_frames=n_frames, bits_stored=bits_stored, ecg=_ecg(ds), metadata=meta,
    )


def iter_dicom_files(folder) -> list[Path]:
    """All files under ``folder`` (recursively) that are not obviously something else; sorted."""
    folder = Path(folder)
    if not folder.exists():
        raise UserError(f"{folder}: no such folder")
    if not folder.is_dir():
        raise UserError(f"{folder}: not a folder")
    skip = {".txt", ".md", ".json", ".png", ".jpg", ".csv", ".zarr", ".npz", ".html", ".py"}
    return sorted(p for p in folder.rglob("*") if p.is_file() and p.suffix.lower() not in skip and not p.name.startswith("."))


# ------------------------------------------------------------------------------------------- writing
def compress_lossless(path) -> Path:
    """Re-encode a DICOM file's pixel data as JPEG Lossless (process 14, first-order prediction), in
    place and atomically. Pixels are unchanged (:func:`read_xa` decodes it with python-gdcm); noisy
    8-bit cine runs shrink by ~1.4×, which keeps the bundled example small."""
    import gdcm

    from .artefacts import atomic_path

    path = Path(path)
    reader = gdcm.ImageReader()
    reader.SetFileName(str(path))
    if not reader.Read():
        raise UserError(f"{path}: not a DICOM image gdcm can read")
    change = gdcm.ImageChangeTransferSyntax()
    change.SetTransferSyntax(gdcm.TransferSyntax(gdcm.TransferSyntax.JPEGLosslessProcess14_1))
    change.SetInput(reader.GetImage())
    if not change.Change():
        raise UserError(f"{path}: could not re-encode the pixel data as JPEG Lossless")
    with atomic_path(path) as tmp:
        writer = gdcm.ImageWriter()
        writer.SetFileName(str(tmp))
        writer.SetFile(reader.GetFile())
        writer.SetImage(change.GetOutput())
        if not writer.Write():
            raise UserError(f"{path}: could not write the re-encoded file")
    return path


def write_xa(path, frames, geometry: XAGeometry, frame_time_ms: float, *, bits_stored: int | None = None,
             patient_id: str = "AUTOCAR-SIM", study_uid: str | None = None, series_description: str = "",
             heart_rate_bpm: float | None = None, r_wave_times_ms=None, extra: dict | None = None,
             uid_seed: str | None = None) -> Path:
    """Write frames (T×H×W unsigned ints, vessels dark) as an uncompressed multi-frame XA DICOM (atomic).

    With ``uid_seed`` the UIDs are derived from it (and the dates fixed), so the same seed writes the
    same file byte for byte; ``study_uid`` groups runs of one (simulated) study.
    """
    import pydicom
    from pydicom.dataset import FileDataset, FileMetaDataset
    from pydicom.uid import ExplicitVRLittleEndian, generate_uid

    from .artefacts import atomic_path

    frames = np.asarray(frames)
    if frames.ndim == 2:
        frames = frames[None]
    if frames.ndim != 3 or frames.dtype.kind != "u":
        raise ValueError("write_xa needs T×H×W unsigned integer frames")
    T, H, W = frames.shape
    if (H, W) != (geometry.rows, geometry.cols):
        raise ValueError(f"frames are {H}×{W} but geometry says {geometry.rows}×{geometry.cols}")
    bits_allocated = 8 if frames.dtype.itemsize == 1 else 16
    bits_stored = bits_stored or bits_allocated
    if int(frames.max(initial=0)) >= 2 ** bits_stored:
        raise ValueError(f"pixel values exceed {bits_stored} bits")

    def uid(part: str) -> str:
        return generate_uid(entropy_srcs=[uid_seed, part]) if uid_seed is not None else generate_uid()

    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = XA_SOP_CLASS
    meta.MediaStorageSOPInstanceUID = uid("sop")
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = FileDataset(str(path), {}, file_meta=meta, preamble=b"\0" * 128)
    now = _dt.datetime(2026, 1, 1, tzinfo=_dt.timezone.utc) if uid_seed is not None else _dt.datetime.now(_dt.timezone.utc)
    ds.SOPClassUID = XA_SOP_CLASS
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.StudyInstanceUID = study_uid or uid("study")
    ds.SeriesInstanceUID = uid("series")
    ds.Modality = "XA"
    ds.PatientID = patient_id
    ds.PatientName = patient_id
    ds.Manufacturer = "AutoCAR simulator"
    ds.SeriesDescription = series_description
    ds.StudyDate = ds.AcquisitionDate = now.strftime("%Y%m%d")
    ds.StudyTime = now.strftime("%H%M%S")
    ds.SeriesNumber = 1
    ds.InstanceNumber = 1
    ds.Rows, ds.Columns = H, W
    ds.NumberOfFrames = T
    ds.SamplesPerPixel = 1
    ds.PhotometricInterpretation = "MONOCHROME2"
    ds.BitsAllocated = bits_allocated
    ds.BitsStored = bits_stored
    ds.HighBit = bits_stored - 1
    ds.PixelRepresentation = 0
    ds.PositionerPrimaryAngle = f"{geometry.alpha:.4f}"
    ds.PositionerSecondaryAngle = f"{geometry.beta:.4f}"
    ds.DistanceSourceToDetector = f"{geometry.sid:.4f}"
    ds.DistanceSourceToPatient = f"{geometry.sod:.4f}"
    ds.ImagerPixelSpacing = [f"{geometry.spacing[0]:.8g}", f"{geometry.spacing[1]:.8g}"]
    ds.FrameTime = f"{frame_time_ms:.6g}"
    ds.CineRate = int(round(1000.0 / frame_time_ms))
    ds.FrameIncrementPointer = pydicom.tag.Tag("FrameTime")
    if heart_rate_bpm is not None:
        ds.HeartRate = int(round(heart_rate_bpm))
    if r_wave_times_ms is not None:
        ds.RWaveTimeVector = [float(t) for t in r_wave_times_ms]
    for key, value in (extra or {}).items():
        setattr(ds, key, value)
    ds.PixelData = np.ascontiguousarray(frames.astype(np.uint8 if bits_allocated == 8 else np.uint16)).tobytes()
    with atomic_path(path) as tmp:
        ds.save_as(tmp, enforce_file_format=True)
    return Path(path)
