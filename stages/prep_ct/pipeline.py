"""prep-ct pipeline: input file / procedural seed → prepared cases on disk (see the package docstring)."""

from __future__ import annotations

import logging
import os
import traceback
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from ..core.errors import UserError
from ..core.prepared_case import PreparedCase
from .centreline import SurfaceDistance, extract_centreline
from .io import input_kind, read_label_volume, read_mesh, validate_labels
from .labels import sparse_labels
from .mesh import lumen_surface

log = logging.getLogger(__name__)
STAGE = "prep-ct"


@dataclass
class PrepParams:
    fine_mm: float = 0.1  # upsampled grid for the lumen mesh
    sigma_mm: float = 0.2  # Gaussian filter on the upsampled mask
    block: int = 72  # fine points per block edge (a multiple of coarse)
    coarse: int = 3  # occupancy grid for the skeleton = coarse × fine_mm
    label_voxel_mm: float = 0.5  # sparse labels
    band_mm: float = 1.0  # outside band kept as negatives
    centreline_step_mm: float = 0.5
    spur_factor: float = 1.0
    spur_mm: float = 0.5
    mesh_pitch_mm: float = 0.25  # voxelisation of mesh inputs
    preview: bool = True
    min_fraction: float = 0.005  # smaller components (of the foreground) are dropped

    def to_dict(self) -> dict:
        return asdict(self)


# ---------------------------------------------------------------------------------------------- splitting
def split_trees(labels: np.ndarray, affine: np.ndarray, path="label", side: Optional[str] = None,
                min_fraction: float = 0.005) -> list[tuple[str, np.ndarray]]:
    """[(side, boolean mask)] of the coronary trees in a label volume (rule in the package docstring)."""
    from scipy import ndimage as ndi

    values = [int(v) for v in np.unique(labels) if v != 0]
    if set(values) == {1, 2}:
        return [("left", labels == 1), ("right", labels == 2)]
    if len(values) > 1:
        log.warning("%s: label values %s; not the (1 = left, 2 = right) convention, using all as foreground",
                    path, values)
    fg = labels > 0
    comp, n = ndi.label(fg, structure=np.ones((3, 3, 3), bool))
    sizes = np.bincount(comp.ravel())[1:]
    order = np.argsort(sizes)[::-1]
    total = sizes.sum()
    keep = [i + 1 for i in order if sizes[i] >= min_fraction * total]
    dropped = [i + 1 for i in order if sizes[i] < min_fraction * total]
    if dropped:
        log.warning("%s: dropped %d small component(s) (%d voxels, < %.1f %% of the foreground each)",
                    path, len(dropped), int(sizes[np.asarray(dropped) - 1].sum()), 100 * min_fraction)
    objects = ndi.find_objects(comp)

    def voxels(label_id):
        sl = objects[label_id - 1]
        idx = np.argwhere(comp[sl] == label_id) + [s.start for s in sl]
        return idx

    def world(idx):
        return idx @ affine[:3, :3].T + affine[:3, 3]

    if len(keep) == 1:
        s = side or "left"
        if side is None:
            log.warning("%s: one connected tree only; taken as the %s tree (pass --side to choose)", path, s)
        return [(s, comp == keep[0])]
    main = keep[:2]
    cx = [world(voxels(m)).mean(axis=0)[0] for m in main]
    left_id, right_id = (main[0], main[1]) if cx[0] >= cx[1] else (main[1], main[0])
    groups = {left_id: [left_id], right_id: [right_id]}
    if len(keep) > 2:
        from scipy.spatial import cKDTree

        trees = {m: cKDTree(world(voxels(m))[::7]) for m in (left_id, right_id)}
        for extra in keep[2:]:
            pts = world(voxels(extra))[::7]
            d = {m: trees[m].query(pts)[0].min() for m in trees}
            target = min(d, key=d.get)
            groups[target].append(extra)
        log.warning("%s: %d extra component(s) attached to the nearer tree (broken vessels?)", path, len(keep) - 2)
    def mask_of(ids):
        m = comp == ids[0]
        for extra in ids[1:]:
            m |= comp == extra
        return m

    return [("left", mask_of(groups[left_id])), ("right", mask_of(groups[right_id]))]


def _border_faces(mask: np.ndarray) -> list[str]:
    names = []
    for ax in range(3):
        if np.take(mask, 0, axis=ax).any():
            names.append(f"axis {ax} start")
        if np.take(mask, mask.shape[ax] - 1, axis=ax).any():
            names.append(f"axis {ax} end")
    return names


# ---------------------------------------------------------------------------------------------- one tree
def prepare_mask(mask: np.ndarray, affine: np.ndarray, *, side: str, case_id: str, source: dict,
                 params: Optional[PrepParams] = None, heart=None, stenoses=None, truth=None,
                 name: str = "label") -> PreparedCase:
    """Prepare one tree given as a boolean mask in a volume with index→LPS ``affine``."""
    p = params or PrepParams()
    source = dict(source)
    border = _border_faces(mask)
    if border:
        log.warning("%s (%s tree): label touches the volume border (%s); the lumen is capped (closed) there",
                    name, side, ", ".join(border))
        source["touches_border"] = border
    try:
        surf = lumen_surface(mask, affine, fine_mm=p.fine_mm, sigma_mm=p.sigma_mm, block=p.block, coarse=p.coarse)
    except ValueError as exc:
        raise UserError(f"{name} ({side} tree): {exc}") from None
    phi = SurfaceDistance(surf.vertices, surf.faces)
    try:
        cl = extract_centreline(surf.occupancy, surf.occupancy_affine, phi, step_mm=p.centreline_step_mm,
                                spur_factor=p.spur_factor, spur_mm=p.spur_mm)
    except ValueError as exc:
        raise UserError(f"{name} ({side} tree): {exc}") from None
    labels = sparse_labels(phi, cl.nodes, cl.radius, cl.edges, voxel_mm=p.label_voxel_mm, band_mm=p.band_mm)
    return PreparedCase(case_id=case_id, side=side, vertices=surf.vertices, faces=surf.faces, nodes=cl.nodes,
                        radius=cl.radius, edges=cl.edges, labels=labels, source=source, heart=heart,
                        stenoses=stenoses, truth=truth)


def save_case(case: PreparedCase, path: Path, params: PrepParams, inputs: Sequence[str]) -> Path:
    case.save(path, stage=STAGE, inputs=list(inputs), parameters=params.to_dict())
    if params.preview:
        from .preview import save_preview

        save_preview(case, Path(path).with_suffix(".png"))
    return Path(path)


# ---------------------------------------------------------------------------------------------- inputs
def _output_paths(output: Path, case_id: str, sides: list[str]) -> list[Path]:
    output = Path(output)
    if output.suffix == ".zarr":
        if len(sides) == 1:
            return [output]
        log.info("%d trees for one artefact name: writing %s", len(sides),
                 ", ".join(f"{output.stem}_{s}.zarr" for s in sides))
        return [output.with_name(f"{output.stem}_{s}.zarr") for s in sides]
    return [output / f"{case_id}_{s}.zarr" for s in sides]


def _case_id_from(path: Path) -> str:
    name = path.name
    for ext in (".nii.gz", ".nii", ".nrrd", ".nhdr", ".npy", ".stl", ".ply", ".obj"):
        if name.lower().endswith(ext):
            return name[: -len(ext)]
    return path.stem


def prepare_file(path, output, params: Optional[PrepParams] = None, *, spacing=None, origin=None, affine=None,
                 side: Optional[str] = None, case_id: Optional[str] = None) -> list[Path]:
    """Prepare every tree of a label volume or surface mesh; returns the artefacts written."""
    p = params or PrepParams()
    path = Path(path)
    kind = input_kind(path)
    case_id = case_id or _case_id_from(path)
    if kind == "label":
        data, aff, meta = read_label_volume(path, spacing=spacing, origin=origin, affine=affine)
        labels = validate_labels(data, path)
        trees = split_trees(labels, aff, path, side=side, min_fraction=p.min_fraction)
    else:
        mesh = read_mesh(path)
        meta = {"format": "mesh", "file": str(path), "faces": int(len(mesh.faces))}
        trees, aff = _mesh_trees(mesh, p.mesh_pitch_mm, path, side)
        meta["voxelised_at_mm"] = p.mesh_pitch_mm
    outs = _output_paths(Path(output), case_id, [s for s, _ in trees])
    written = []
    for (s, mask), out in zip(trees, outs):
        m_aff = aff[s] if isinstance(aff, dict) else aff
        case = prepare_mask(mask, m_aff, side=s, case_id=case_id, source=dict(meta), params=p, name=str(path))
        written.append(save_case(case, out, p, [str(path)]))
    return written


def _mesh_trees(mesh, pitch: float, path, side):
    """Split a mesh into trees (components, same left/right rule) and voxelise each at ``pitch``."""
    parts = mesh.split(only_watertight=False)
    parts = sorted(parts, key=lambda m: -abs(m.volume))
    total = sum(abs(m.volume) for m in parts)
    parts = [m for m in parts if abs(m.volume) >= 0.005 * total]
    if len(parts) == 1:
        s = side or "left"
        groups = {s: parts}
    else:
        a, b = parts[0], parts[1]
        left, right = (a, b) if a.centroid[0] >= b.centroid[0] else (b, a)
        groups = {"left": [left], "right": [right]}
        for extra in parts[2:]:
            d = {k: np.linalg.norm(v[0].vertices - extra.centroid, axis=1).min() for k, v in groups.items()}
            groups[min(d, key=d.get)].append(extra)
    import trimesh

    trees, affs = [], {}
    for s, meshes in groups.items():
        m = trimesh.util.concatenate(meshes)
        shell = m.voxelized(pitch)
        vg = shell.copy().fill()
        mat = np.asarray(vg.matrix, bool).copy()
        aff = np.asarray(vg.transform, float).copy()
        # surface voxels count as inside only when their centre is (trimesh marks every voxel the
        # surface touches, which would widen the lumen by about half a voxel)
        surf_idx = np.argwhere(np.asarray(shell.matrix, bool))
        centres = surf_idx @ aff[:3, :3].T + aff[:3, 3]
        sd = trimesh.proximity.signed_distance(m, centres)  # positive inside
        mat[tuple(surf_idx[sd < 0].T)] = False
        mat = np.pad(mat, 2)
        aff[:3, 3] -= 2 * aff[:3, :3].sum(axis=1)  # account for the 2-voxel padding
        trees.append((s, mat))
        affs[s] = aff
    log.info("%s: voxelised %d tree(s) at %.2f mm", path, len(trees), pitch)
    return trees, affs


def synthetic_spacing(seed: int) -> tuple[float, float, float]:
    """CTA-like voxel size of a synthetic case: in-plane 0.35–0.45 mm, slices 0.35–0.5 mm."""
    rng = np.random.default_rng([int(seed), 7919])
    xy = float(rng.uniform(0.35, 0.45))
    return (xy, xy, float(rng.uniform(0.35, 0.5)))


def prepare_synthetic(seed: int, output_dir, params: Optional[PrepParams] = None, case_id: Optional[str] = None,
                      spacing=None, sides=("left", "right"), shape_shift=None) -> list[Path]:
    """Generate procedural anatomy ``seed``, voxelise it and prepare its trees (both by default, or the
    given ``sides``) like a real mask. ``shape_shift``: a :class:`stages.anatomy.ShapeShift` applied first
    (anatomy outside the generator's range)."""
    from ..anatomy import generate, shape_shifted

    p = params or PrepParams()
    case_id = case_id or f"case_{int(seed):04d}"
    anatomy = generate(int(seed))
    if shape_shift is not None:
        anatomy = shape_shifted(anatomy, shape_shift, seed=int(seed))
    sp = spacing or synthetic_spacing(seed)
    vol = anatomy.label_volume(spacing=sp)
    source = {"synthetic": True, "seed": int(seed), "dominance": anatomy.dominance, "spacing_mm": list(sp),
              **({"shape_shift": asdict(shape_shift)} if shape_shift is not None else {}),
              "shape": list(vol.data.shape), "affine_lps": vol.affine.tolist()}
    written = []
    for side, value in (("left", 1), ("right", 2)):
        if side not in sides:
            continue
        tree = anatomy.tree(side)
        case = prepare_mask(vol.data == value, vol.affine, side=side, case_id=case_id, source=source, params=p,
                            heart=anatomy.heart.to_dict(), stenoses=tree.stenoses, truth=tree.truth(),
                            name=f"synthetic seed {seed}")
        written.append(save_case(case, Path(output_dir) / f"{case_id}_{side}.zarr", p, [f"synthetic:{seed}"]))
    return written


# ---------------------------------------------------------------------------------------------- batches
def _run_task(task: dict) -> tuple[dict, list[str], Optional[str]]:
    """Worker: one case; an error becomes a message (one bad case never stops a batch)."""
    try:
        params = PrepParams(**task["params"])
        if task["kind"] == "synthetic":
            out = prepare_synthetic(task["seed"], task["output"], params)
        else:
            out = prepare_file(task["path"], task["output"], params, spacing=task.get("spacing"),
                               origin=task.get("origin"), side=task.get("side"))
        return task, [str(o) for o in out], None
    except UserError as exc:
        return task, [], str(exc)
    except Exception as exc:  # a bug or an unexpected input: report it with its origin, keep going
        tb = traceback.extract_tb(exc.__traceback__)[-1]
        return task, [], f"{type(exc).__name__}: {exc} (at {Path(tb.filename).name}:{tb.lineno})"


def run_batch(tasks: list[dict], jobs: int = 1, on_done: Optional[Callable] = None) -> list[tuple]:
    """Run tasks (dicts for :func:`_run_task`) with ``jobs`` processes; ``on_done(result)`` after each."""
    results = []
    if jobs <= 1 or len(tasks) <= 1:
        for t in tasks:
            r = _run_task(t)
            results.append(r)
            if on_done:
                on_done(r)
        return results
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    env_threads = os.environ.get("OMP_NUM_THREADS")
    os.environ["OMP_NUM_THREADS"] = "1"  # one core per case
    try:
        with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as ex:
            futs = [ex.submit(_run_task, t) for t in tasks]
            for f in as_completed(futs):
                r = f.result()
                results.append(r)
                if on_done:
                    on_done(r)
    finally:
        if env_threads is None:
            os.environ.pop("OMP_NUM_THREADS", None)
        else:
            os.environ["OMP_NUM_THREADS"] = env_threads
    return results
