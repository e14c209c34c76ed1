"""Artefact store: the one place where stages write and read their on-disk results.

An artefact is either one zarr v3 directory store (``*.zarr``) or one ``.npz`` file, never a loose set
of files. Its root attributes say what it is::

    kind             e.g. "autocar.pose-model"
    schema_version   integer, bumped when the layout changes incompatibly
    writer           {"stage": "fit-poses", "package": "autocar", "version": "0.1.0"}
    inputs           list of input paths / identifiers
    parameters       the parameters the stage ran with (JSON-serialisable)
    created          ISO-8601 UTC timestamp

Writes are atomic: everything goes to a hidden temporary sibling that is renamed onto the final name
only when the writer finished without error, so a crash never leaves half an artefact under the final
name. Reads validate kind and schema version and raise :class:`~stages.core.errors.UserError` with a
message that names the file, what was expected and what was found.

Usage::

    with write_zarr("poses.zarr", kind=POSE_KIND, schema_version=1, stage="fit-poses",
                    inputs=[...], parameters={...}) as group:
        group.create_array("alpha", data=alpha)

    group = read_zarr("poses.zarr", kind=POSE_KIND, schema_version=1)

    save_npz("pairs.npz", {"mask_a": m}, kind=..., schema_version=1, stage="render")
    arrays, attrs = load_npz("pairs.npz", kind=..., schema_version=1)
"""

from __future__ import annotations

import contextlib
import datetime as _dt
import json
import math
import os
import shutil
import uuid
from pathlib import Path
from typing import Any, Iterator, Mapping

import numpy as np

from .. import __version__
from .errors import UserError

_NPZ_META_KEY = "__autocar_meta__"


def _json_ready(value: Any) -> Any:
    """Convert numpy scalars/arrays and paths so attributes survive JSON encoding.

    The plain types are tested first, with exact classes: a graph's JSON holds thousands of small lists, and an
    ``isinstance`` against ``typing.Mapping`` on each of them cost more than the encoding."""
    kind = type(value)
    if kind is dict:
        return {str(k): _json_ready(v) for k, v in value.items()}
    if kind is list or kind is tuple:
        return [_json_ready(v) for v in value]
    if kind is str or kind is int or kind is bool or value is None:
        return value
    if kind is float:
        return value if math.isfinite(value) else None
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, Mapping):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, Path):
        return str(value)
    if isinstance(value, float) and not np.isfinite(value):
        return None
    return value


def root_attributes(kind: str, schema_version: int, stage: str, inputs=(), parameters=None, extra=None) -> dict:
    """The standard root attributes every artefact carries."""
    attrs = {
        "kind": kind,
        "schema_version": int(schema_version),
        "writer": {"stage": stage, "package": "autocar", "version": __version__},
        "inputs": [str(i) for i in inputs],
        "parameters": parameters or {},
        "created": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
    }
    if extra:
        attrs.update(extra)
    return _json_ready(attrs)


def _temporary_sibling(path: Path) -> Path:
    return path.with_name(f".{path.name}.tmp-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _replace(tmp: Path, final: Path) -> None:
    """Move ``tmp`` onto ``final``; an existing artefact is swapped out only after the new one is complete."""
    if final.exists() or final.is_symlink():
        old = _temporary_sibling(final)
        os.replace(final, old)
        os.replace(tmp, final)
        if old.is_dir():
            shutil.rmtree(old, ignore_errors=True)
        else:
            old.unlink(missing_ok=True)
    else:
        os.replace(tmp, final)


def _remove(path: Path) -> None:
    if path.is_dir():
        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink(missing_ok=True)


@contextlib.contextmanager
def atomic_path(final: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary sibling path; rename it onto ``final`` if the block succeeds, delete it otherwise.

    Used for artefacts and for the exports beside them (PNG, VTP, STL, JSON, HTML).
    """
    final = Path(final)
    try:
        final.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise output_error(final.parent, exc) from None
    tmp = _temporary_sibling(final)
    try:
        yield tmp
        if not tmp.exists():
            raise RuntimeError(f"{final}: nothing was written")
        _replace(tmp, final)
    except OSError as exc:  # read-only, full disk, permission: one line naming the file, nothing left behind
        _remove(tmp)
        raise output_error(final, exc) from None
    except BaseException:
        _remove(tmp)
        raise


def output_error(path, exc: BaseException) -> UserError:
    """A write that failed (OSError, or a library's error wrapping one) as a one-line UserError naming ``path``."""
    err = exc
    while err is not None and not isinstance(err, OSError):  # zarr/matplotlib may wrap the OSError
        err = err.__cause__ or err.__context__
    reason = (err.strerror or str(err)) if isinstance(err, OSError) else f"{type(exc).__name__}: {exc}"
    return UserError(f"{path}: cannot write ({reason})")


@contextlib.contextmanager
def write_zarr(path, *, kind: str, schema_version: int, stage: str, inputs=(), parameters=None, extra_attrs=None):
    """Create a zarr v3 group atomically; yields the open group to fill."""
    import zarr

    with atomic_path(path) as tmp:
        group = zarr.open_group(store=str(tmp), mode="w", zarr_format=3)
        group.attrs.update(root_attributes(kind, schema_version, stage, inputs, parameters, extra_attrs))
        yield group


def _check_header(path: Path, attrs: Mapping, kind: str | tuple[str, ...] | None, schema_version: int | None):
    kinds = (kind,) if isinstance(kind, str) else kind
    found_kind = attrs.get("kind")
    if kinds is not None and found_kind not in kinds:
        expected = " or ".join(repr(k) for k in kinds)
        raise UserError(f"{path}: expected an artefact of kind {expected}, found {found_kind!r}")
    if schema_version is not None:
        found_version = attrs.get("schema_version")
        if found_version != schema_version:
            raise UserError(
                f"{path}: {found_kind} artefact has schema version {found_version!r}, "
                f"this autocar reads version {schema_version}"
            )


def read_zarr(path, *, kind: str | tuple[str, ...] | None, schema_version: int | None):
    """Open a zarr artefact read-only after checking its kind and schema version."""
    import zarr

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such artefact")
    try:
        group = zarr.open_group(store=str(path), mode="r")
        attrs = dict(group.attrs)
    except Exception as exc:  # zarr raises a zoo of types for "not a group"
        raise UserError(f"{path}: not a readable zarr v3 artefact ({type(exc).__name__}: {exc})") from None
    _check_header(path, attrs, kind, schema_version)
    return group


def save_npz(path, arrays: Mapping[str, np.ndarray], *, kind: str, schema_version: int, stage: str,
             inputs=(), parameters=None, extra_attrs=None, compress: bool = True) -> Path:
    """Write an NPZ artefact atomically; the root attributes ride along as a JSON string."""
    path = Path(path)
    if _NPZ_META_KEY in arrays:
        raise ValueError(f"array name {_NPZ_META_KEY} is reserved")
    meta = root_attributes(kind, schema_version, stage, inputs, parameters, extra_attrs)
    payload = {k: np.asarray(v) for k, v in arrays.items()}
    payload[_NPZ_META_KEY] = np.array(json.dumps(meta))
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:  # a file handle stops numpy from appending ".npz" to the temp name
            (np.savez_compressed if compress else np.savez)(fh, **payload)
    return path


def load_npz(path, *, kind: str | tuple[str, ...] | None, schema_version: int | None):
    """Read an NPZ artefact: returns (arrays, attributes) after checking kind and schema version."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such artefact")
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {k: data[k] for k in data.files}
    except Exception as exc:
        raise UserError(f"{path}: not a readable NPZ artefact ({type(exc).__name__})") from None
    if _NPZ_META_KEY not in arrays:
        raise UserError(f"{path}: NPZ file has no autocar header (not an autocar artefact)")
    attrs = json.loads(str(arrays.pop(_NPZ_META_KEY)))
    _check_header(path, attrs, kind, schema_version)
    return arrays, attrs


def artefact_attributes(path) -> dict:
    """Root attributes of any artefact (zarr or NPZ) without kind checks, e.g. to dispatch on kind."""
    path = Path(path)
    if path.suffix == ".npz":
        return load_npz(path, kind=None, schema_version=None)[1]
    return dict(read_zarr(path, kind=None, schema_version=None).attrs)


def read_json(path, what: str = "JSON file") -> Any:
    """The content of a JSON file, or a one-line UserError naming the file (missing, unreadable, not JSON);
    ``what`` names the kind of file in the messages."""
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise UserError(f"{path}: no such {what}") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: not valid JSON ({exc})") from None
    except OSError as exc:
        raise UserError(f"{path}: cannot read the {what} ({exc.strerror or exc})") from None


def write_json(path, obj: Any) -> Path:
    """Atomic JSON export (graphs, correspondences, metric tables)."""
    with atomic_path(path) as tmp:
        tmp.write_text(json.dumps(_json_ready(obj), indent=2))
    return Path(path)


def load_torch_file(path, missing_hint: str = "") -> dict:
    """A torch weights/checkpoint file as a dict, or a one-line UserError naming the file and the problem."""
    import torch

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such weights file{missing_hint}")
    try:
        return torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:
        raise UserError(f"{path}: not a readable weights file ({type(exc).__name__})") from None


def hash_file(h, path: Path) -> None:
    """Feed a file's bytes to the hash ``h`` (content fingerprints of artefacts and weights, e.g. cache keys)."""
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
