"""Training pairs: two-view lumen silhouettes of a prepared case under poses from a pose model.

Reads: a prepared case (``autocar.prepared-case``, through :class:`stages.core.prepared_case.PreparedCase`)
and a pose model (``autocar.pose-model``, :class:`stages.poses.PoseModel`).
Writes (``autocar render --pairs``): pair shards, one zarr artefact of kind ``"autocar.render-pairs"``
(schema 1) per shard::

    attrs: standard header + size, cases (list of case paths), case_ids, seed, n_pairs,
           misalign_px, misalign_3d, translation_mm, jitter_px, warp_scale
    mask_a, mask_b        N×H×W uint8 (0/1)   silhouettes; view b carries the 2D (and 3D) misalignment
    camera_a/K, /R, /source, /matrix    N×3×3, N×3×3, N×3, N×3×4   (same for camera_b); the matrix
                                        maps world (mm, LPS) to homogeneous (col, row, 1)
    pose_a, pose_b        N×8 float64 (alpha, beta, sid, sod, spacing_row, spacing_col, rows, cols)
                          of the pose drawn from the model (spacing before resizing to ``size``)
    cluster               N×2 int32 pose-model clusters of the two views
    warp_b                N×K×4 float64  TPS control points (row, col) and displacements (px) of view b
    warp_n                N int32      number of valid rows of warp_b (0: no 2D warp)
    translation           N×3 float64  placement translation (mm) applied to the whole case
    phase_b               N float64    cardiac phase of view b (0 = no 3D misalignment)
    case_index            N int32      index into ``cases``
    visible               N×2 float32  fraction of centreline nodes inside each image

Conventions: pixel (row, col) centres at integer indices; the 3D ground truth of pair i is the case's
``labels/`` voxel set shifted by ``translation[i]`` (it matches view a exactly; view b sees the tree
warped as recorded). Seeds: pair i of a shard uses ``numpy.random.default_rng([seed, i])``.

:func:`render_pair` is the online entry point used by the training loop.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import numpy as np

from ..core.errors import UserError
from ..core.geometry import Camera
from .augment import Warp2D, identity_warp, random_warp
from .motion import HeartMotion, sample_motion
from .raster import rasterise_mask

log = logging.getLogger(__name__)

PAIRS_KIND = "autocar.render-pairs"
PAIRS_SCHEMA = 1
POSE_FIELDS = ("alpha", "beta", "sid", "sod", "spacing_row", "spacing_col", "rows", "cols")

__all__ = ["render_pair", "simplified_for_rendering", "RENDER_MESH_CACHE", "visible_fraction", "write_pair_shard", "load_pair_shard", "PAIRS_KIND",
           "case_from", "pose_model_from"]


# ------------------------------------------------------------------------------------------ inputs
def case_from(case):
    """A PreparedCase from a case object or a path (wrong kinds raise UserError naming the file)."""
    from ..core.prepared_case import PreparedCase

    if isinstance(case, PreparedCase):
        return case
    return PreparedCase.load(case)


def pose_model_from(model):
    from ..poses import PoseModel

    if isinstance(model, PoseModel):
        return model
    if model is None or str(model) == "default":
        return PoseModel.default(seed=0)
    return PoseModel.load(model)


RENDER_MESH_CACHE = ".render_meshes"  # folder beside the prepared cases holding their decimated meshes


def _mesh_key(case, max_faces: int) -> str:
    """Content key of a case's full mesh and the decimation target (the cache stays right when a case
    is re-prepared under the same name)."""
    import hashlib

    h = hashlib.blake2b(digest_size=16)
    h.update(np.ascontiguousarray(case.vertices, np.float32).tobytes())
    h.update(np.ascontiguousarray(case.faces, np.int32).tobytes())
    h.update(str(int(max_faces)).encode())
    return h.hexdigest()


def simplified_for_rendering(case, max_faces: int = 60_000, cache_dir=None):
    """A copy of ``case`` whose lumen mesh is decimated to at most ``max_faces`` triangles (quadric
    decimation, fast_simplification via trimesh); everything else is shared.

    prep-ct meshes come from a 0.1 mm marching cubes (~10⁶ triangles for a left tree): exact, but the
    silhouette raster then costs ~0.6 s per 512² view. Decimated to 5 % the silhouette changes by
    ≈ 0.3 % of its pixels, all on the boundary (sub-pixel), and renders in ~20 ms — what online
    training needs. Evaluation renders keep the full mesh.

    Decimation takes ~1 s a tree, minutes for a training set, so with ``cache_dir`` the result is kept
    there as ``<content key>.npz`` and read back next time (an unreadable file is recomputed). The
    cache is a pure speed-up: the arrays are the ones decimation gives.
    """
    import dataclasses

    import trimesh

    case = case_from(case)
    if len(case.faces) <= max_faces:
        return case
    cached = Path(cache_dir) / f"{_mesh_key(case, max_faces)}.npz" if cache_dir is not None else None
    if cached is not None and cached.exists():
        try:
            with np.load(cached) as z:
                return dataclasses.replace(case, vertices=z["vertices"], faces=z["faces"])
        except (OSError, ValueError, KeyError) as exc:
            log.warning("%s: unreadable cached mesh (%s); decimating again", cached, exc)
    mesh = trimesh.Trimesh(case.vertices, case.faces, process=False)
    small = mesh.simplify_quadric_decimation(face_count=max_faces)
    vertices, faces = np.asarray(small.vertices, np.float32), np.asarray(small.faces, np.int32)
    if cached is not None:
        from ..core.artefacts import atomic_path

        try:
            with atomic_path(cached) as tmp, open(tmp, "wb") as fh:
                np.savez(fh, vertices=vertices, faces=faces)
        except OSError as exc:  # a read-only case folder: train without the cache
            log.warning("%s: cannot cache the decimated mesh (%s)", cached, exc)
    return dataclasses.replace(case, vertices=vertices, faces=faces)


def visible_fraction(points, camera: Camera, margin_px: float = 2.0) -> float:
    rc = camera.project(points)
    return float(np.mean(camera.in_image(rc, margin=margin_px) & np.all(np.isfinite(rc), axis=1)))


def _pose_row(pose) -> list[float]:
    return [pose.alpha, pose.beta, pose.sid, pose.sod, pose.spacing[0], pose.spacing[1], pose.rows, pose.cols]


# ------------------------------------------------------------------------------------------ pairs
def render_pair(case, pose_model, rng: np.random.Generator, size: int = 512, misalign_px: float = 2.0,
                misalign_3d: float = 0.0, translation_mm: float = 10.0, jitter_px: float = 8.0,
                min_visible: float = 0.9, max_tries: int = 20, motion: HeartMotion | None = None) -> dict:
    """One training pair, online.

    * two poses drawn the paper's way (two distinct clusters, one recorded pose each), cameras at
      ``size``×``size`` keeping each detector's physical extent;
    * the whole case translated by ``translation`` ~ U(−translation_mm, translation_mm)³ (random position
      near the isocentre), and each image shifted in-plane by ≤ ``jitter_px``;
    * view b: with probability ``misalign_3d`` the tree at another cardiac phase (dynamic heart model,
      phase ~ U(0.1, 0.5)), and a smooth TPS warp of ``misalign_px`` px RMS (:mod:`.augment`).

    Placements leaving less than ``min_visible`` of the centreline inside either image are redrawn up to
    ``max_tries`` times; then a UserError reports the best fraction reached.

    Returns dict(mask_a, mask_b (bool H×W), camera_a, camera_b (Camera), warp_b (Warp2D),
    translation (3,), phase_b, pose_a, pose_b (Pose), visible (2,), vertices_a, vertices_b (V×3 lumen
    vertices as each view saw them), offset_b (V×2 px warp offsets of view b, or None)).
    """
    case = case_from(case)
    V, F, nodes = case.vertices.astype(float), case.faces, case.nodes.astype(float)
    best = 0.0
    for _ in range(max_tries):
        pose_a, pose_b = pose_model.sample_pair(rng)
        cam_a, cam_b = pose_a.camera(size, size), pose_b.camera(size, size)
        t = rng.uniform(-translation_mm, translation_mm, 3) if translation_mm > 0 else np.zeros(3)
        ja = rng.uniform(-jitter_px, jitter_px, 2) if jitter_px > 0 else np.zeros(2)
        jb = rng.uniform(-jitter_px, jitter_px, 2) if jitter_px > 0 else np.zeros(2)
        cam_a, cam_b = cam_a.shifted(*ja), cam_b.shifted(*jb)
        vis = (visible_fraction(nodes + t, cam_a), visible_fraction(nodes + t, cam_b))
        best = max(best, min(vis))
        if min(vis) >= min_visible:
            break
    else:
        raise UserError(f"case {case.case_id} ({case.path or 'in memory'}): the tree does not fit the field of view "
                        f"at size {size} (best placement shows {best:.0%} of the centreline, need {min_visible:.0%})")
    phase_b = 0.0
    Vb = V
    if misalign_3d > 0 and rng.random() < misalign_3d:
        m = motion or sample_motion(nodes, rng, case.heart, duration=1.0, breath_hold=True)
        phase_b = float(rng.uniform(0.1, 0.5))
        Vb = m.apply(V, phase_b)
    warp = random_warp(rng, size, size, misalign_px) if misalign_px > 0 else identity_warp(size, size)
    mask_a = rasterise_mask(V + t, F, cam_a)
    offset = None
    if not warp.is_identity:
        offset = warp.displacement(np.nan_to_num(cam_b.project(Vb + t)))
    mask_b = rasterise_mask(Vb + t, F, cam_b, offset_rc=offset)
    return {"mask_a": mask_a, "mask_b": mask_b, "camera_a": cam_a, "camera_b": cam_b, "warp_b": warp,
            "translation": t, "phase_b": phase_b, "pose_a": pose_a, "pose_b": pose_b,
            "visible": np.array(vis, dtype=np.float32),
            # the lumen each view was rasterised from (and view b's warp offsets), so other images of
            # exactly this geometry can be rendered (stages.render.segmenter_masks)
            "vertices_a": V + t, "vertices_b": Vb + t, "offset_b": offset}


# ------------------------------------------------------------------------------------------ shards
def write_pair_shard(path, cases, pose_model, n_pairs: int, seed: int, size: int = 512, misalign_px: float = 2.0,
                     misalign_3d: float = 0.0, translation_mm: float = 10.0, jitter_px: float = 8.0,
                     min_visible: float = 0.9, progress=None, inputs=()) -> Path:
    """Render ``n_pairs`` pairs (cases used round-robin) into one ``autocar.render-pairs`` zarr shard."""
    from ..core.artefacts import write_zarr

    loaded = [case_from(c) for c in cases]
    if not loaded:
        raise UserError("no prepared cases given")
    model = pose_model_from(pose_model)
    n_ctrl = 16
    out = {k: [] for k in ("mask_a", "mask_b", "K_a", "R_a", "S_a", "P_a", "K_b", "R_b", "S_b", "P_b", "pose_a", "pose_b",
                           "cluster", "warp_b", "translation", "phase_b", "case_index", "visible")}
    for i in range(n_pairs):
        ci = i % len(loaded)
        rng = np.random.default_rng([seed, i])
        p = render_pair(loaded[ci], model, rng, size, misalign_px, misalign_3d, translation_mm, jitter_px, min_visible)
        out["mask_a"].append(p["mask_a"].astype(np.uint8))
        out["mask_b"].append(p["mask_b"].astype(np.uint8))
        for s, cam in (("a", p["camera_a"]), ("b", p["camera_b"])):
            out[f"K_{s}"].append(cam.K)
            out[f"R_{s}"].append(cam.R)
            out[f"S_{s}"].append(cam.source)
            out[f"P_{s}"].append(cam.matrix)
        out["pose_a"].append(_pose_row(p["pose_a"]))
        out["pose_b"].append(_pose_row(p["pose_b"]))
        out["cluster"].append([p["pose_a"].cluster, p["pose_b"].cluster])
        w = p["warp_b"].params()
        wp = np.zeros((n_ctrl, 4))
        wp[: len(w)] = w
        out["warp_b"].append(wp)
        out.setdefault("warp_n", []).append(len(w))
        out["translation"].append(p["translation"])
        out["phase_b"].append(p["phase_b"])
        out["case_index"].append(ci)
        out["visible"].append(p["visible"])
        if progress is not None:
            progress()
    params = {"size": size, "n_pairs": n_pairs, "seed": seed, "misalign_px": misalign_px, "misalign_3d": misalign_3d,
              "translation_mm": translation_mm, "jitter_px": jitter_px, "min_visible": min_visible}
    extra = dict(params, cases=[str(c.path) if c.path else c.case_id for c in loaded],
                 case_ids=[c.case_id for c in loaded], warp_scale=float(size))
    with write_zarr(path, kind=PAIRS_KIND, schema_version=PAIRS_SCHEMA, stage="render",
                    inputs=list(inputs) or extra["cases"], parameters=params, extra_attrs=extra) as g:
        chunks = (1, size, size)
        g.create_array("mask_a", data=np.stack(out["mask_a"]), chunks=chunks)
        g.create_array("mask_b", data=np.stack(out["mask_b"]), chunks=chunks)
        for s in ("a", "b"):
            cg = g.require_group(f"camera_{s}")
            cg.create_array("K", data=np.stack(out[f"K_{s}"]))
            cg.create_array("R", data=np.stack(out[f"R_{s}"]))
            cg.create_array("source", data=np.stack(out[f"S_{s}"]))
            cg.create_array("matrix", data=np.stack(out[f"P_{s}"]))
        g.create_array("pose_a", data=np.asarray(out["pose_a"], float))
        g.create_array("pose_b", data=np.asarray(out["pose_b"], float))
        g.create_array("cluster", data=np.asarray(out["cluster"], np.int32))
        g.create_array("warp_b", data=np.stack(out["warp_b"]))
        g.create_array("warp_n", data=np.asarray(out["warp_n"], np.int32))
        g.create_array("translation", data=np.stack(out["translation"]))
        g.create_array("phase_b", data=np.asarray(out["phase_b"], float))
        g.create_array("case_index", data=np.asarray(out["case_index"], np.int32))
        g.create_array("visible", data=np.stack(out["visible"]).astype(np.float32))
    return Path(path)


def load_pair_shard(path) -> dict:
    """Read a pair shard into memory: arrays plus ``cameras_a``/``cameras_b`` (lists of Camera) and attrs."""
    from ..core.artefacts import read_zarr

    g = read_zarr(path, kind=PAIRS_KIND, schema_version=PAIRS_SCHEMA)
    attrs = dict(g.attrs)
    out = {k: g[k][...] for k in ("mask_a", "mask_b", "pose_a", "pose_b", "cluster", "warp_b", "translation",
                                   "phase_b", "case_index", "visible", "warp_n")}
    size = int(attrs["size"])
    for s in ("a", "b"):
        K, R, S = g[f"camera_{s}/K"][...], g[f"camera_{s}/R"][...], g[f"camera_{s}/source"][...]
        out[f"cameras_{s}"] = [Camera(K=K[i], R=R[i], source=S[i], rows=size, cols=size) for i in range(len(K))]
    out["warps_b"] = [Warp2D.from_params(w[:n], float(attrs.get("warp_scale", size)))
                      for w, n in zip(out["warp_b"], out["warp_n"])]
    out["attrs"] = attrs
    return out
