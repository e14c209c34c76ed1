"""On-disk forms read and written by the graph optimisation.

Input — kind ``"autocar.sparse-prediction"``, schema 1 (written by the SBP inference through
:func:`write_sparse_predictions`; one artefact holds one or several key frames)::

    attrs   standard header + case_id (str), frame_keys [str, ...] (key frames in cardiac order),
            cameras (optional) {"a": Camera.to_dict(), "b": ...}: default cameras of every frame
    frames/<key>/voxels/          SparseVoxels group: features occupancy, centreness (float in [0, 1])
    frames/<key>/masks/a, masks/b optional H×W uint8 2D vessel masks of the two views (and c … of further
                                  runs); non-zero is vessel, 2 marks the pixels that are the catheter the run
                                  showed before its contrast arrived (:mod:`stages.core.catheter`)
    frames/<key>/images/a, images/b optional H×W float32 X-ray frames the masks were segmented from (the
                                  image contrast tells a contrast-filled vessel from a faint structure)
    frames/<key>.attrs            optional cameras {"a": ..., "b": ...} overriding the root ones;
                                  optional source_frames {"a": i, "b": j}: the frame of each run it came from

A single-frame artefact may instead hold ``voxels/`` and ``masks/`` at its root (key: the root attr
``frame_key``, else "0"); several such artefacts can be given together, in cardiac order.

Output — kind ``"autocar.vascular-graphs"``, schema 1 (:func:`write_vascular_graphs`)::

    attrs   standard header + case_id, frame_keys, reference (key of the template frame),
            units "mm", frame "LPS", history (per frame: the registration rounds, for diagnostics)
    topology/edges        E×2 int32   shared by every frame
    topology/node_id      N int64     node identity, the same node in every frame
    topology/first_frame  N int32     index of the key frame where the node was first seen
    frames/<key>/nodes    N×3 float32 world mm
    frames/<key>/radius   N float32   mm
    frames/<key>/edges    E×2 int32   (= topology/edges)
    frames/<key>/node_id  N int64     (= topology/node_id)
    frames/<key>/deformation/         all frames but the reference: the deformation graph that takes the
        nodes M×3, edges P×2, params M×6 (axis-angle rad, translation mm); attrs sigma_mm, n_anchors,
        from_frame (key of the frame it starts from)
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..core.artefacts import read_zarr, write_zarr
from ..core.errors import UserError
from ..core.voxels import SparseVoxels
from .deformation import DeformationGraph
from .optimise import TrackedGraphs
from .vascular import VascularGraph

PREDICTION_KIND = "autocar.sparse-prediction"
GRAPHS_KIND = "autocar.vascular-graphs"
SCHEMA_VERSION = 1

__all__ = ["PREDICTION_KIND", "GRAPHS_KIND", "PredictionFrame", "write_sparse_predictions", "read_sparse_predictions",
           "write_vascular_graphs", "read_vascular_graphs"]


@dataclass
class PredictionFrame:
    """One key frame's prediction: sparse voxels, optional per-view masks and cameras (view name → ...)."""

    key: str
    voxels: SparseVoxels
    masks: dict[str, np.ndarray] = field(default_factory=dict)
    cameras: dict = field(default_factory=dict)  # view → stages.core.geometry.Camera
    source_frames: dict = field(default_factory=dict)  # view → index of the run's frame it was taken from
    images: dict[str, np.ndarray] = field(default_factory=dict)  # view → the X-ray frame (H×W), optional


def write_sparse_predictions(path, frames: list[PredictionFrame], *, case_id: str, stage: str = "sbp",
                             inputs=(), parameters=None, cameras: dict | None = None) -> Path:
    """Write key-frame predictions as one ``autocar.sparse-prediction`` artefact (layout: module docstring).

    ``cameras`` (view → Camera) are stored once at the root when every frame shares them.
    """
    keys = [str(f.key) for f in frames]
    if len(set(keys)) != len(keys):
        raise ValueError(f"duplicate frame keys {keys}")
    root_cams = {k: c.to_dict() for k, c in (cameras or {}).items()}
    with write_zarr(path, kind=PREDICTION_KIND, schema_version=SCHEMA_VERSION, stage=stage, inputs=inputs,
                    parameters=parameters, extra_attrs={"case_id": case_id, "frame_keys": keys,
                                                        **({"cameras": root_cams} if root_cams else {})}) as root:
        fr = root.require_group("frames")
        for f in frames:
            g = fr.require_group(str(f.key))
            f.voxels.write_to_group(g.require_group("voxels"))
            if f.masks:
                m = g.require_group("masks")
                for view, mask in f.masks.items():
                    mask = np.asarray(mask)  # integer labels are kept (module docstring), anything else is vessel or not
                    m.create_array(view, data=mask.astype(np.uint8) if mask.dtype.kind in "iu" else
                                   (mask > 0).astype(np.uint8))
            if f.images:
                im = g.require_group("images")
                for view, image in f.images.items():
                    im.create_array(view, data=np.asarray(image, np.float32))
            if f.cameras:
                g.attrs.update({"cameras": {k: c.to_dict() for k, c in f.cameras.items()}})
            if f.source_frames:
                g.attrs.update({"source_frames": {k: int(i) for k, i in f.source_frames.items()}})
    return Path(path)


def _frame_from_group(path, g, key, default_cams) -> PredictionFrame:
    from ..core.geometry import Camera

    if "voxels" not in g:
        raise UserError(f"{path}: key frame {key!r} has no 'voxels' group")
    try:
        vox = SparseVoxels.read_from_group(g["voxels"])
    except KeyError as exc:
        raise UserError(f"{path}: key frame {key!r}: voxels group lacks {exc}") from None
    if "occupancy" not in vox.features:
        raise UserError(f"{path}: key frame {key!r}: voxels have no 'occupancy' feature")
    masks = {name: np.asarray(arr[...]) for name, arr in g["masks"].arrays()} if "masks" in g else {}
    images = {name: np.asarray(arr[...], np.float32) for name, arr in g["images"].arrays()} if "images" in g else {}
    cam_dicts = dict(default_cams)
    cam_dicts.update(dict(g.attrs).get("cameras", {}) or {})
    try:
        cams = {k: Camera.from_dict(d) for k, d in cam_dicts.items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: key frame {key!r}: unreadable camera ({exc})") from None
    for what, arrays in (("mask", masks), ("image", images)):
        for view, arr in arrays.items():
            if view in cams and arr.shape != (cams[view].rows, cams[view].cols):
                raise UserError(f"{path}: key frame {key!r}: {what} {view!r} is {arr.shape[0]}×{arr.shape[1]}, "
                                f"its camera is {cams[view].rows}×{cams[view].cols}")
    try:
        sources = {str(k): int(i) for k, i in (dict(g.attrs).get("source_frames") or {}).items()}
    except (AttributeError, TypeError, ValueError):
        raise UserError(f"{path}: key frame {key!r}: source_frames must map view names to frame indices") from None
    return PredictionFrame(str(key), vox, masks, cams, sources, images)


def read_sparse_predictions(paths) -> tuple[str, list[PredictionFrame]]:
    """(case_id, key frames in order) from one or several ``autocar.sparse-prediction`` artefacts."""
    paths = [paths] if isinstance(paths, (str, Path)) else list(paths)
    frames: list[PredictionFrame] = []
    case_ids = []
    for path in paths:
        root = read_zarr(path, kind=PREDICTION_KIND, schema_version=SCHEMA_VERSION)
        attrs = dict(root.attrs)
        case_ids.append(str(attrs.get("case_id", Path(path).stem)))
        cams = attrs.get("cameras", {}) or {}
        if "frames" in root:
            keys = attrs.get("frame_keys") or sorted(root["frames"].group_keys())
            for key in keys:
                if str(key) not in root["frames"]:
                    raise UserError(f"{path}: frame_keys lists {key!r} but frames/{key} is missing")
                frames.append(_frame_from_group(path, root["frames"][str(key)], str(key), cams))
        else:
            frames.append(_frame_from_group(path, root, str(attrs.get("frame_key", "0")), cams))
    keys = [f.key for f in frames]
    if len(set(keys)) != len(keys):  # several single-frame artefacts without keys: number them
        for i, f in enumerate(frames):
            f.key = str(i)
    if len(set(case_ids)) > 1:
        raise UserError(f"{', '.join(map(str, paths))}: predictions of different cases {sorted(set(case_ids))}")
    return case_ids[0], frames


def write_vascular_graphs(path, tracked: TrackedGraphs, *, case_id: str, reference: int = 0, inputs=(),
                          parameters=None, stage: str = "graph-opt") -> Path:
    """Write tracked key-frame graphs as one ``autocar.vascular-graphs`` artefact (layout: module docstring)."""
    g0 = tracked.graphs[reference]
    history = {k: h for k, h in zip(tracked.keys, tracked.histories)} if tracked.histories else {}
    with write_zarr(path, kind=GRAPHS_KIND, schema_version=SCHEMA_VERSION, stage=stage, inputs=inputs,
                    parameters=parameters,
                    extra_attrs={"case_id": case_id, "frame_keys": list(tracked.keys),
                                 "reference": tracked.keys[reference], "units": "mm", "frame": "LPS",
                                 "history": history}) as root:
        topo = root.require_group("topology")
        topo.create_array("edges", data=g0.edges.astype(np.int32))
        topo.create_array("node_id", data=g0.node_id.astype(np.int64))
        topo.create_array("first_frame", data=np.asarray(tracked.first_frame, np.int32))
        fr = root.require_group("frames")
        for i, (key, g, d) in enumerate(zip(tracked.keys, tracked.graphs, tracked.deformations)):
            grp = fr.require_group(str(key))
            grp.create_array("nodes", data=g.nodes.astype(np.float32))
            grp.create_array("radius", data=g.radius.astype(np.float32))
            grp.create_array("edges", data=g.edges.astype(np.int32))
            grp.create_array("node_id", data=g.node_id.astype(np.int64))
            if d is not None:
                dg = grp.require_group("deformation")
                dg.create_array("nodes", data=d.nodes)
                dg.create_array("edges", data=d.edges.astype(np.int32))
                dg.create_array("params", data=d.params)
                src = i - 1 if i > reference else i + 1
                dg.attrs.update({"sigma_mm": d.sigma, "n_anchors": d.n_anchors, "from_frame": tracked.keys[src]})
    return Path(path)


def read_vascular_graphs(path) -> tuple[dict, TrackedGraphs]:
    """(root attributes, TrackedGraphs) of an ``autocar.vascular-graphs`` artefact."""
    root = read_zarr(path, kind=GRAPHS_KIND, schema_version=SCHEMA_VERSION)
    attrs = dict(root.attrs)
    keys = [str(k) for k in attrs["frame_keys"]]
    graphs, defs = [], []
    for key in keys:
        g = root["frames"][key]
        graphs.append(VascularGraph(g["nodes"][...].astype(float), g["radius"][...].astype(float),
                                    g["edges"][...].astype(np.int64), g["node_id"][...]))
        if "deformation" in g:
            d = g["deformation"]
            da = dict(d.attrs)
            defs.append(DeformationGraph(d["nodes"][...], d["edges"][...], float(da["sigma_mm"]), d["params"][...],
                                         int(da["n_anchors"])))
        else:
            defs.append(None)
    first = root["topology"]["first_frame"][...].astype(np.int64)
    return attrs, TrackedGraphs(keys, graphs, defs, first, [attrs.get("history", {}).get(k, []) for k in keys])
