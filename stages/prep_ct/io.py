"""Readers for prep-ct inputs: label volumes (NIfTI, NRRD, NumPy) and surface meshes (STL, PLY, OBJ).

Every reader returns data in the project's world frame, DICOM LPS in mm:

* NIfTI affines (``sform``/``qform``) map voxel indices to RAS+; LPS = diag(−1, −1, 1) · RAS, so the
  first two rows of the affine are negated.
* NRRD: ``space directions`` / ``space origin`` are honoured with the ``space`` field:
  "left-posterior-superior" (LPS) is used as is, "right-anterior-superior" (RAS) is flipped in x and y,
  "left-anterior-superior" (LAS) in y. A file without a space field is taken as LPS (logged).
* ``.npy``: the array plus ``spacing`` (required) and optional ``origin`` (mm, LPS), or a full 4×4
  index→LPS affine passed by the caller.
* Meshes: vertex coordinates are taken as world mm in LPS.

Validation (:func:`validate_labels`) turns the array into integer labels or refuses it with a
:class:`~stages.core.errors.UserError` naming the file: empty label, non-finite values, a float intensity
image. A float mask with values in [0, 1] is thresholded at 0.5 (logged repair).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from ..core.errors import UserError

log = logging.getLogger(__name__)

LABEL_EXTS = (".nii", ".nii.gz", ".nrrd", ".nhdr", ".npy")
MESH_EXTS = (".stl", ".ply", ".obj")
RAS_TO_LPS = np.diag([-1.0, -1.0, 1.0, 1.0])


def input_kind(path) -> str:
    """"label" or "mesh" from the file name; anything else is a UserError."""
    name = str(path).lower()
    if any(name.endswith(e) for e in LABEL_EXTS):
        return "label"
    if any(name.endswith(e) for e in MESH_EXTS):
        return "mesh"
    raise UserError(f"{path}: unknown input type; prep-ct reads label volumes ({', '.join(LABEL_EXTS)}) "
                    f"or surface meshes ({', '.join(MESH_EXTS)})")


def read_label_volume(path, spacing=None, origin=None, affine=None) -> tuple[np.ndarray, np.ndarray, dict]:
    """(array, 4×4 index→LPS affine, source metadata) of a label file."""
    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    name = path.name.lower()
    try:
        if name.endswith((".nii", ".nii.gz")):
            import nibabel as nib

            img = nib.load(str(path))
            data = np.asanyarray(img.dataobj)
            aff = RAS_TO_LPS @ np.asarray(img.affine, float)
            meta = {"format": "nifti", "affine_ras": np.asarray(img.affine, float).tolist()}
        elif name.endswith((".nrrd", ".nhdr")):
            import nrrd

            data, header = nrrd.read(str(path))
            aff, meta = _nrrd_affine(path, header)
        elif name.endswith(".npy"):
            data = np.load(path, allow_pickle=False)
            meta = {"format": "npy"}
            if affine is not None:
                aff = np.asarray(affine, float)
            else:
                if spacing is None:
                    raise UserError(f"{path}: a .npy label needs its voxel spacing (--spacing sx,sy,sz in mm)")
                aff = np.eye(4)
                aff[:3, :3] = np.diag(np.broadcast_to(np.asarray(spacing, float), (3,)))
                aff[:3, 3] = np.zeros(3) if origin is None else np.asarray(origin, float)
        else:
            input_kind(path)
            raise UserError(f"{path}: not a label volume")
    except UserError:
        raise
    except Exception as exc:  # corrupt files: one clear line, not a traceback
        raise UserError(f"{path}: cannot read label volume ({type(exc).__name__}: {exc})") from None
    if data.ndim == 4 and data.shape[3] == 1:
        data = data[..., 0]
    if data.ndim != 3:
        raise UserError(f"{path}: expected a 3D label volume, got shape {data.shape}")
    if aff.shape != (4, 4) or not np.all(np.isfinite(aff)) or abs(np.linalg.det(aff[:3, :3])) < 1e-9:
        raise UserError(f"{path}: invalid (singular or non-finite) voxel-to-world affine")
    meta["affine_lps"] = aff.tolist()
    meta["shape"] = list(data.shape)
    meta["file"] = str(path)
    return np.asarray(data), aff, meta


def _nrrd_affine(path, header) -> tuple[np.ndarray, dict]:
    space = str(header.get("space", "")).lower()
    dirs = header.get("space directions")
    if dirs is None:
        spacings = header.get("spacings")
        if spacings is None:
            raise UserError(f"{path}: NRRD header has neither 'space directions' nor 'spacings'")
        dirs = np.diag(np.asarray(spacings, float)[:3])
    dirs = np.asarray([d for d in dirs if d is not None and not (isinstance(d, float) and np.isnan(d))], float)
    dirs = dirs[~np.all(np.isnan(dirs), axis=1)] if dirs.ndim == 2 else dirs
    if dirs.shape != (3, 3):
        raise UserError(f"{path}: NRRD 'space directions' must describe 3 spatial axes, got {dirs.tolist()}")
    org = np.asarray(header.get("space origin", np.zeros(3)), float)
    aff = np.eye(4)
    aff[:3, :3] = dirs.T  # each space direction is the world step of one index axis (a column)
    aff[:3, 3] = org
    flips = {"left-posterior-superior": (1, 1, 1), "lps": (1, 1, 1),
             "right-anterior-superior": (-1, -1, 1), "ras": (-1, -1, 1),
             "left-anterior-superior": (1, -1, 1), "las": (1, -1, 1)}
    if space in flips:
        f = np.diag(list(flips[space]) + [1.0])
    elif space == "":
        log.warning("%s: NRRD without a 'space' field: taking its directions as LPS", path)
        f = np.eye(4)
    else:
        raise UserError(f"{path}: NRRD space {space!r} is not supported (use LPS, RAS or LAS)")
    return f @ aff, {"format": "nrrd", "space": space or "unspecified"}


def validate_labels(data: np.ndarray, path) -> np.ndarray:
    """Integer label array (uint8/uint16) from a mask; refuses what is not a segmentation."""
    data = np.asarray(data)
    if data.dtype == bool:
        data = data.astype(np.uint8)
    if np.issubdtype(data.dtype, np.floating):
        if not np.all(np.isfinite(data)):
            raise UserError(f"{path}: label volume contains NaN or infinite values")
        rounded = np.rint(data)
        if np.array_equal(rounded, data):
            data = rounded
        elif data.min() >= 0.0 and data.max() <= 1.0:
            log.warning("%s: non-binary float mask (values in [0, 1]); thresholded at 0.5", path)
            data = (data >= 0.5).astype(np.uint8)
        else:
            raise UserError(f"{path}: float volume with values in [{data.min():g}, {data.max():g}] is not a label "
                            "mask (expected integer labels or a [0, 1] mask; is this an intensity image?)")
    if data.min() < 0:
        raise UserError(f"{path}: negative label values ({int(data.min())}) in a segmentation")
    if data.max() > 65535:
        raise UserError(f"{path}: label values up to {int(data.max())}; expected a small number of labels")
    data = data.astype(np.uint8 if data.max() < 256 else np.uint16)
    if not data.any():
        raise UserError(f"{path}: empty label volume (no foreground voxel)")
    return data


def read_mesh(path):
    """A watertight, consistently oriented trimesh.Trimesh in world mm (LPS); repairs are logged."""
    import trimesh

    path = Path(path)
    if not path.exists():
        raise UserError(f"{path}: no such file")
    try:
        mesh = trimesh.load(str(path), force="mesh")
    except Exception as exc:
        raise UserError(f"{path}: cannot read mesh ({type(exc).__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
        raise UserError(f"{path}: no triangles in the mesh")
    if not mesh.is_watertight:
        before = _open_edges(mesh)
        mesh.merge_vertices()
        trimesh.repair.fill_holes(mesh)
        if not mesh.is_watertight:
            raise UserError(f"{path}: mesh is not watertight ({before} open edges) and simple hole filling "
                            "could not close it; a lumen must be a closed surface")
        log.warning("%s: mesh was not watertight (%d open edges); holes filled", path, before)
    if not mesh.is_winding_consistent:
        trimesh.repair.fix_winding(mesh)
        log.warning("%s: inconsistent triangle winding repaired", path)
    if mesh.volume < 0:
        mesh.invert()
        log.warning("%s: inward-facing normals; mesh inverted", path)
    return mesh


def _open_edges(mesh) -> int:
    from collections import Counter

    counts = Counter(map(tuple, mesh.edges_sorted.tolist()))
    return sum(1 for c in counts.values() if c != 2)
