"""``autocar evaluate``: score predictions against ground truth and tabulate the metrics.

Reads
-----
* 3D predictions: ``autocar.sparse-prediction`` artefacts (layout below; the visual hull and the
  reconstruction stages write this kind).
* 3D ground truth: a prepared case (``autocar.prepared-case``: ``labels/`` occupancy for the voxel
  metrics, ``centreline/`` for the graph metrics), another sparse-prediction artefact, or a lumen
  surface mesh (``.stl``/``.ply``/``.obj``, world mm LPS), voxelised at the metric grid (voxel
  centres inside the mesh).
* 2D ground truth: correspondence annotations, a JSON file (layout below).

Writes
------
* ``<out>.zarr`` — kind ``autocar.metrics``, schema 1: one float64 array per numeric metric (one entry
  per case, NaN where undefined — the ``status`` attribute says why), root attrs ``case_ids``, ``rows``
  (the full per-case records), ``aggregate`` and ``metric_notes``;
* ``<out>.json`` (rows + aggregate), ``<out>.csv`` (one line per case), ``<out>.md`` (a Markdown table
  of the cases and the aggregate: mean ± sd, median, n).

``autocar.sparse-prediction`` (schema 1), a zarr group::

    attrs      standard header + case_id (str)
    voxels/    SparseVoxels group: features ``occupancy`` (float32 probability, required) and
               optionally ``centreness`` (float32)
    graph/     optional: ``nodes`` N×3 float32 (mm), ``radius`` N float32 (mm), ``edges`` E×2 int32

Correspondence annotations (``autocar.correspondence-annotations``), a JSON object::

    {"kind": "autocar.correspondence-annotations", "case_id": "...",
     "camera_a": {...}, "camera_b": {...},        # Camera.to_dict() or a geometry JSON object
     "pairs": [[row_a, col_a, row_b, col_b], ...]}   # pixel centres at integer indices

Undefined numbers: see :mod:`stages.core.metrics` (empty prediction/truth → distance metrics NaN with a
status; no covered query → EPE NaN with a status). Aggregates skip NaN and report how many cases
each mean is over, so a NaN never enters a table without its reason.
"""

from __future__ import annotations

import csv
import io
import json
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.artefacts import artefact_attributes, atomic_path, read_json, read_zarr, write_json, write_zarr
from ..core.errors import UserError
from ..core.geometry import Camera
from ..core.metrics import (COVER_MM, EPSILON_MM, GRID_MM, correspondence_metrics, graph_metrics, match_partners,
                      metrics_3d, sample_graph)
from ..core.voxels import SparseVoxels

PREDICTION_KIND = "autocar.sparse-prediction"
PREDICTION_SCHEMA = 1
METRICS_KIND = "autocar.metrics"
METRICS_SCHEMA = 1
ANNOTATION_KIND = "autocar.correspondence-annotations"
PREPARED_KIND = "autocar.prepared-case"
MESH_SUFFIXES = (".stl", ".ply", ".obj")

# column order of the tables; anything else in a row is kept in JSON only
METRIC_COLUMNS = ["dice", "cldice", "tprec", "tsens", "chamfer_mm", "hd95_mm",
                  "centreline_error_mm", "radius_error_mm", "coverage", "epe_mm", "accuracy"]

__all__ = ["Prediction", "Truth", "save_prediction", "load_prediction", "load_truth", "voxelise_mesh",
           "load_annotations", "evaluate_case", "aggregate", "write_metrics", "markdown_table",
           "PREDICTION_KIND", "METRICS_KIND", "ANNOTATION_KIND", "METRIC_COLUMNS", "truth_side",
           "truth_correspondences", "score_dynamic_reconstruction"]


@dataclass
class Prediction:
    case_id: str
    voxels: SparseVoxels | None
    graph: tuple | None = None  # (nodes, radius, edges)
    path: Path | None = None


@dataclass
class Truth:
    case_id: str
    voxels: SparseVoxels | None
    graph: tuple | None = None
    path: Path | None = None


# ---------------------------------------------------------------------------- prediction artefact
def save_prediction(path, voxels: SparseVoxels, case_id: str, graph=None, *, stage: str,
                    inputs=(), parameters=None) -> Path:
    """Write an ``autocar.sparse-prediction`` artefact (layout in the module docstring)."""
    if "occupancy" not in voxels.features:
        raise ValueError("a sparse prediction needs an 'occupancy' feature")
    feats = {k: np.asarray(v, np.float32) for k, v in voxels.features.items()}
    vox = SparseVoxels(voxels.coords, voxels.voxel_size, voxels.origin, feats)
    with write_zarr(path, kind=PREDICTION_KIND, schema_version=PREDICTION_SCHEMA, stage=stage, inputs=inputs,
                    parameters=parameters, extra_attrs={"case_id": str(case_id)}) as group:
        vox.write_to_group(group.require_group("voxels"))
        if graph is not None:
            nodes, radius, edges = graph
            g = group.require_group("graph")
            g.create_array("nodes", data=np.asarray(nodes, np.float32).reshape(-1, 3))
            g.create_array("radius", data=np.asarray(radius, np.float32).reshape(-1))
            g.create_array("edges", data=np.asarray(edges, np.int32).reshape(-1, 2))
    return Path(path)


def _read_graph(group, path):
    if "graph" not in group:
        return None
    try:
        g = group["graph"]
        return (g["nodes"][...], g["radius"][...], g["edges"][...])
    except KeyError as exc:
        raise UserError(f"{path}: incomplete graph/ group (missing {exc})") from None


def load_prediction(path) -> Prediction:
    path = Path(path)
    group = read_zarr(path, kind=PREDICTION_KIND, schema_version=PREDICTION_SCHEMA)
    attrs = dict(group.attrs)
    if "voxels" not in group:
        raise UserError(f"{path}: sparse prediction has no voxels/ group")
    try:
        vox = SparseVoxels.read_from_group(group["voxels"])
    except (KeyError, ValueError) as exc:
        raise UserError(f"{path}: unreadable voxels/ group ({exc})") from None
    if "occupancy" not in vox.features:
        raise UserError(f"{path}: voxels/ has no 'occupancy' feature")
    return Prediction(str(attrs.get("case_id", path.stem)), vox, _read_graph(group, path), path)


# ---------------------------------------------------------------------------- ground truth
def voxelise_mesh(vertices, faces, voxel_size: float = GRID_MM) -> SparseVoxels:
    """Voxels (grid aligned with the world origin) whose centres lie inside a watertight mesh."""
    import trimesh

    mesh = trimesh.Trimesh(np.asarray(vertices, float), np.asarray(faces, np.int64), process=False)
    if len(mesh.faces) == 0:
        return SparseVoxels(np.zeros((0, 3), np.int32), voxel_size, np.zeros(3), {"occupancy": np.zeros(0, np.float32)})
    lo = np.floor(mesh.bounds[0] / voxel_size).astype(np.int64)
    hi = np.ceil(mesh.bounds[1] / voxel_size).astype(np.int64)
    # Shell voxels from trimesh's surface voxelisation need the exact inside test; the filled interior
    # beyond one voxel from the surface is inside by construction.
    vg = mesh.voxelized(pitch=voxel_size)
    shell = np.rint(vg.points / voxel_size).astype(np.int64)
    filled = np.rint(vg.copy().fill().points / voxel_size).astype(np.int64)
    # widen the shell by one voxel in every direction so no boundary voxel skips the exact test
    offs = np.stack(np.meshgrid(*[[-1, 0, 1]] * 3, indexing="ij"), -1).reshape(-1, 3)
    band = np.unique((shell[:, None, :] + offs[None]).reshape(-1, 3), axis=0)
    band = band[np.all((band >= lo - 1) & (band <= hi + 1), axis=1)]
    inside_band = band[mesh.contains(band * voxel_size)]
    band_set = {tuple(b) for b in band.tolist()}
    interior = np.array([f for f in filled.tolist() if tuple(f) not in band_set], np.int64).reshape(-1, 3)
    coords = np.unique(np.concatenate([inside_band, interior]), axis=0)
    return SparseVoxels(coords, voxel_size, np.zeros(3), {"occupancy": np.ones(len(coords), np.float32)})


def load_truth(path, voxel_size: float = GRID_MM) -> Truth:
    """Ground truth from a prepared case, a sparse-prediction artefact or a mesh file (see module doc)."""
    path = Path(path)
    if path.suffix.lower() in MESH_SUFFIXES:
        import trimesh

        if not path.exists():
            raise UserError(f"{path}: no such mesh file")
        try:
            mesh = trimesh.load(path, force="mesh")  # processing merges STL vertices (watertight test)
        except Exception as exc:
            raise UserError(f"{path}: unreadable mesh ({type(exc).__name__}: {exc})") from None
        if not mesh.is_watertight:
            raise UserError(f"{path}: mesh is not watertight, its inside is undefined")
        return Truth(path.stem, voxelise_mesh(mesh.vertices, mesh.faces, voxel_size), None, path)
    attrs = artefact_attributes(path)
    kind = attrs.get("kind")
    if kind == PREPARED_KIND:
        from ..core.prepared_case import PreparedCase

        case = PreparedCase.load(path)
        return Truth(case.case_id, case.labels, (case.nodes, case.radius, case.edges), path)
    if kind == PREDICTION_KIND:
        p = load_prediction(path)
        return Truth(p.case_id, p.voxels, p.graph, path)
    raise UserError(f"{path}: ground truth must be a {PREPARED_KIND!r} or {PREDICTION_KIND!r} artefact "
                    f"or a mesh ({', '.join(MESH_SUFFIXES)}), found kind {kind!r}")


def load_annotations(path) -> dict:
    """Read a correspondence-annotation JSON: returns {case_id, camera_a, camera_b, pairs (K×4)}."""
    path = Path(path)
    d = read_json(path, "annotation file")
    if not isinstance(d, dict) or d.get("kind", ANNOTATION_KIND) != ANNOTATION_KIND:
        raise UserError(f"{path}: expected a JSON object of kind {ANNOTATION_KIND!r}")
    for key in ("camera_a", "camera_b", "pairs"):
        if key not in d:
            raise UserError(f"{path}: correspondence annotations lack {key!r}")
    pairs = np.asarray(d["pairs"], float)
    if pairs.size == 0:
        raise UserError(f"{path}: no annotated pairs (\"pairs\" is empty)")
    if pairs.ndim != 2 or pairs.shape[1] != 4 or not np.all(np.isfinite(pairs)):
        raise UserError(f"{path}: \"pairs\" must be a list of [row_a, col_a, row_b, col_b] numbers")
    try:
        cam_a = Camera.from_dict(d["camera_a"])
        cam_b = Camera.from_dict(d["camera_b"])
    except (KeyError, TypeError, ValueError) as exc:
        raise UserError(f"{path}: unreadable camera ({type(exc).__name__}: {exc})") from None
    return {"case_id": str(d.get("case_id", path.stem)), "camera_a": cam_a, "camera_b": cam_b, "pairs": pairs}


# ---------------------------------------------------------------------------- evaluation
def prediction_points(pred: Prediction):
    """3D points that stand for a prediction in the 2D metrics, with weights.

    A graph is preferred (its edges sampled every 0.25 mm, weight 1); else occupied voxel centres
    with weight occupancy × centreness (centreness 1 when absent).
    """
    if pred.graph is not None and len(pred.graph[0]):
        pts, _ = sample_graph(*pred.graph)
        return pts, np.ones(len(pts))
    if pred.voxels is None or len(pred.voxels) == 0:
        return np.zeros((0, 3)), np.zeros(0)
    occ = np.asarray(pred.voxels.features["occupancy"], float)
    keep = occ >= 0.5
    w = occ.copy()
    if "centreness" in pred.voxels.features:
        w = w * np.asarray(pred.voxels.features["centreness"], float)
    return pred.voxels.world_points()[keep], w[keep]


def evaluate_correspondences(pred: Prediction, ann: dict, epsilon_mm: float = EPSILON_MM,
                             cover_mm: float = COVER_MM) -> dict:
    """2D metrics of a 3D prediction against annotated pairs (see :mod:`stages.core.metrics`)."""
    pts, w = prediction_points(pred)
    cam_a, cam_b = ann["camera_a"], ann["camera_b"]
    qa = cam_a.project(pts)
    qb = cam_b.project(pts)
    cover_px = cover_mm / cam_a.isocentre_spacing
    partners = match_partners(qa, qb, ann["pairs"][:, :2], cover_px, weights=w)
    out = correspondence_metrics(partners, ann["pairs"][:, 2:], cam_b.isocentre_spacing, epsilon_mm)
    out["correspondence_status"] = out.pop("status")
    return out


def evaluate_case(pred: Prediction, truth: Truth | None = None, annotations: dict | None = None,
                  voxel_size: float = GRID_MM, epsilon_mm: float = EPSILON_MM) -> dict:
    """One row of metrics: 3D (with truth), graph (both graphs), 2D (with annotations)."""
    row: dict = {"case_id": pred.case_id, "prediction": str(pred.path or "")}
    if truth is None and annotations is None:
        raise UserError(f"{pred.path or pred.case_id}: no ground truth and no annotations to evaluate against")
    if truth is not None:
        row["truth"] = str(truth.path or "")
        if pred.voxels is not None and truth.voxels is not None:
            row.update(metrics_3d(pred.voxels, truth.voxels, voxel_size))
        if pred.graph is not None and truth.graph is not None:
            row.update(graph_metrics(pred.graph, truth.graph))
    if annotations is not None:
        row["annotations"] = str(annotations.get("path", ""))
        row.update(evaluate_correspondences(pred, annotations, epsilon_mm))
    return row


def aggregate(rows: list[dict], columns=None) -> dict:
    """Per metric: mean, sd (ddof 1), median, min, max over finite values, n used and n undefined."""
    columns = columns or [c for c in METRIC_COLUMNS if any(c in r for r in rows)]
    out = {}
    for c in columns:
        vals = np.array([r.get(c, np.nan) for r in rows if c in r], float)
        fin = vals[np.isfinite(vals)]
        out[c] = {
            "mean": float(fin.mean()) if len(fin) else None,
            "sd": float(fin.std(ddof=1)) if len(fin) > 1 else None,
            "median": float(np.median(fin)) if len(fin) else None,
            "min": float(fin.min()) if len(fin) else None,
            "max": float(fin.max()) if len(fin) else None,
            "n": int(len(fin)),
            "n_undefined": int(len(vals) - len(fin)),
        }
    return out


def _fmt(v, key: str) -> str:
    if v is None or (isinstance(v, float) and not math.isfinite(v)):
        return "n/a"
    return f"{v:.2f}" if key.endswith("_mm") else f"{v:.3f}"


def _status(row: dict) -> str:
    parts = [row.get(k) for k in ("status", "graph_status", "correspondence_status") if row.get(k)]
    parts = [p for p in parts if p != "ok"]
    return ", ".join(parts) if parts else "ok"


def markdown_table(rows: list[dict], agg: dict) -> str:
    cols = list(agg)
    lines = ["| case | " + " | ".join(cols) + " | status |", "|" + "---|" * (len(cols) + 2)]
    for r in rows:
        lines.append(f"| {r['case_id']} | " + " | ".join(
            _fmt(r.get(c), c) if c in r else "–" for c in cols) + f" | {_status(r)} |")
    lines.append("")
    lines.append("| metric | mean ± sd | median | min | max | n | undefined |")
    lines.append("|---|---|---|---|---|---|---|")
    for c, a in agg.items():
        sd = f" ± {_fmt(a['sd'], c)}" if a["sd"] is not None else ""
        lines.append(f"| {c} | {_fmt(a['mean'], c)}{sd} | {_fmt(a['median'], c)} | {_fmt(a['min'], c)} | "
                     f"{_fmt(a['max'], c)} | {a['n']} | {a['n_undefined']} |")
    if any(a["n_undefined"] for a in agg.values()):
        lines.append("")
        lines.append("n/a: undefined for that case (see status: an empty prediction has no surface, so no "
                     "Chamfer/HD95; a prediction covering no annotated query has no EPE). Aggregates are over "
                     "the n cases where the metric is defined.")
    return "\n".join(lines) + "\n"


def write_metrics(out_base, rows: list[dict], agg: dict | None = None, *, inputs=(), parameters=None) -> dict:
    """Write ``<out_base>.zarr`` (autocar.metrics), ``.json``, ``.csv`` and ``.md``; returns the paths."""
    out_base = Path(out_base)
    if out_base.suffix in (".zarr", ".json", ".csv", ".md"):
        out_base = out_base.with_suffix("")
    agg = aggregate(rows) if agg is None else agg
    paths = {k: out_base.with_name(out_base.name + "." + k) for k in ("zarr", "json", "csv", "md")}
    cols = [c for c in METRIC_COLUMNS if any(c in r for r in rows)]
    with write_zarr(paths["zarr"], kind=METRICS_KIND, schema_version=METRICS_SCHEMA, stage="evaluate",
                    inputs=inputs, parameters=parameters,
                    extra_attrs={"case_ids": [r["case_id"] for r in rows], "rows": rows, "aggregate": agg,
                                 "metric_notes": "NaN = undefined for that case, reason in rows[i].status"}) as g:
        for c in cols:
            g.create_array(c, data=np.array([r.get(c, np.nan) for r in rows], np.float64))
    write_json(paths["json"], {"rows": rows, "aggregate": agg, "parameters": parameters or {}})
    fields = ["case_id"] + cols + ["status", "n_pred_voxels", "n_truth_voxels", "n_pairs", "n_covered",
                                   "prediction", "truth", "annotations"]
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=fields, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    for r in rows:
        rec = {k: r.get(k, "") for k in fields}
        rec["status"] = _status(r)
        for c in cols:
            v = r.get(c)
            rec[c] = "" if v is None or (isinstance(v, float) and not math.isfinite(v)) else v
        w.writerow(rec)
    with atomic_path(paths["csv"]) as tmp:
        tmp.write_text(buf.getvalue())
    with atomic_path(paths["md"]) as tmp:
        tmp.write_text(markdown_table(rows, agg))
    return paths


def _case_id_of(path: Path) -> str | None:
    if path.suffix.lower() in MESH_SUFFIXES:
        return path.stem
    if path.suffix == ".json":
        try:
            return str(json.loads(path.read_text()).get("case_id", path.stem))
        except (OSError, ValueError, AttributeError):
            return path.stem
    try:
        return str(artefact_attributes(path).get("case_id", path.stem))
    except UserError:
        return None


def _expand(paths, kinds: tuple[str, ...] | None, suffixes=(".zarr",)) -> list[Path]:
    """Files given directly, plus matching artefacts directly inside given folders."""
    out = []
    for p in map(Path, paths):
        if p.is_dir() and p.suffix != ".zarr":
            for q in sorted(p.iterdir()):
                if q.suffix.lower() not in suffixes:
                    continue
                if kinds is None or (q.suffix == ".zarr" and _kind(q) in kinds) or q.suffix != ".zarr":
                    out.append(q)
        else:
            if not p.exists():
                raise UserError(f"{p}: no such file or folder")
            out.append(p)
    return out


def _kind(path: Path):
    try:
        return artefact_attributes(path).get("kind")
    except UserError:
        return None


def pair_inputs(predictions, truths=(), annotations=()) -> list[tuple[Path, Path | None, Path | None]]:
    """Match predictions to truths and annotation files by case_id (one of each: matched directly)."""
    preds = _expand(predictions, (PREDICTION_KIND,))
    if not preds:
        raise UserError(f"no {PREDICTION_KIND!r} artefacts in {', '.join(map(str, predictions))}")
    gts = _expand(truths, (PREPARED_KIND, PREDICTION_KIND), (".zarr",) + MESH_SUFFIXES) if truths else []
    anns = _expand(annotations, None, (".json",)) if annotations else []
    if not gts and not anns:
        raise UserError("give ground truth (--truth) and/or correspondence annotations (--annotations)")

    def by_id(paths):
        d = {}
        for p in paths:
            d.setdefault(_case_id_of(p), p)
        return d

    gt_by, ann_by = by_id(gts), by_id(anns)
    out = []
    for p in preds:
        cid = _case_id_of(p)
        g = gts[0] if len(preds) == 1 and len(gts) == 1 else gt_by.get(cid)
        a = anns[0] if len(preds) == 1 and len(anns) == 1 else ann_by.get(cid)
        if g is None and a is None:
            raise UserError(f"{p}: no ground truth or annotations with case_id {cid!r}")
        out.append((p, g, a))
    return out


def evaluate_paths(predictions, truths=(), annotations=(), voxel_size: float = GRID_MM,
                   epsilon_mm: float = EPSILON_MM, progress=None) -> list[dict]:
    """Evaluate every prediction against its matched truth/annotations; returns the rows."""
    rows = []
    triples = pair_inputs(predictions, truths, annotations)
    for n, (p, g, a) in enumerate(triples):
        pred = load_prediction(p)
        truth = load_truth(g, voxel_size) if g is not None else None
        ann = None
        if a is not None:
            ann = load_annotations(a)
            ann["path"] = str(a)
        rows.append(evaluate_case(pred, truth, ann, voxel_size, epsilon_mm))
        if progress:
            progress(n + 1, len(triples))
    return rows


# ---------------------------------------------------------------------------- simulated two-run cases
def truth_side(truth: dict) -> str:
    """Tree side of a simulated case (``autocar.xa-truth``): the injected artery, which the operator knows."""
    name = Path(str(truth["attrs"].get("case", ""))).stem
    return "right" if name.endswith("_right") else "left"


def truth_correspondences(truth: dict, cam_a, cam_b, ia: int, ib: int, n_points: int, seed) -> dict:
    """Annotations (as :func:`load_annotations` returns) for frame ``ia`` of run A and ``ib`` of run B
    of a simulated case: the same centreline nodes at both frames, a seeded sample of ``n_points`` of
    those projecting inside both images (``nodes``: their indices)."""
    pa = truth["a"]["nodes"][ia].astype(float)
    pb = truth["b"]["nodes"][ib].astype(float)
    ua, ub = cam_a.project(pa), cam_b.project(pb)
    inside = np.ones(len(pa), bool)
    for uv, cam in ((ua, cam_a), (ub, cam_b)):
        inside &= np.all(np.isfinite(uv), 1) & (uv[:, 0] >= 0) & (uv[:, 1] >= 0)
        inside &= (uv[:, 0] <= cam.rows - 1) & (uv[:, 1] <= cam.cols - 1)
    idx = np.flatnonzero(inside)
    idx = np.sort(np.random.default_rng(seed).choice(idx, size=min(n_points, len(idx)), replace=False))
    return {"camera_a": cam_a, "camera_b": cam_b, "pairs": np.hstack([ua[idx], ub[idx]]), "nodes": idx}


def score_dynamic_reconstruction(out_dir, truth: dict, runs, n_points: int = 60, seed: int = 0) -> dict:
    """Score an ``autocar reconstruct`` output folder of a simulated two-run case against its truth.

    Per key-frame pair the reconstruct stage chose: coverage/EPE/accuracy on :func:`truth_correspondences`
    (the model's partners in view B taken with the pipeline's view-B camera of that key frame, as in its
    correspondence JSON),
    the 3D centreline error (both directed means) against the truth at the midpoint of the two frames'
    configurations, and the tracked graph's topology. Returns {"graph": …, "nograph": …}: case means
    (plus per-frame rows) with graph optimisation, and on the per-frame predicted voxels before it.
    """
    from ..graph.io import read_sparse_predictions, read_vascular_graphs
    from ..graph.vascular import VascularGraph
    from ..keyframe import circ_diff

    out_dir = Path(out_dir)
    summary = json.loads((out_dir / "summary.json").read_text())
    pairs = [tuple(p) for p in summary["pairs"]]
    _, tracked = read_vascular_graphs(out_dir / "graphs.zarr")
    _, pred_frames = read_sparse_predictions([out_dir / "predictions.zarr"])
    cam_a, cam_b = runs[0].camera, runs[1].camera
    radius, edges = truth["radius"].astype(float), truth["edges"]
    frames, raw = [], []
    for k, (ia, ib) in enumerate(pairs):
        ann = truth_correspondences(truth, cam_a, cam_b, ia, ib, n_points, [seed, k])
        # the pipeline's partner of a view-A point is its model point projected with the camera the pipeline
        # used for view B at this key frame (shifted by the inter-run motion correction): the 2D↔2D
        # correspondence its graph JSON reports. The truth pairs themselves stay on the header cameras.
        ann["camera_b"] = pred_frames[k].cameras.get("b", cam_b)
        g = tracked.graphs[k]
        graph = (g.nodes, g.radius, g.edges)
        row = {"key": tracked.keys[k], "pair": [int(ia), int(ib)],
               "phase_error": float(circ_diff(truth["a"]["phase"][ia], truth["b"]["phase"][ib]))}
        row.update(evaluate_correspondences(Prediction("", None, graph), ann))
        mid = 0.5 * (truth["a"]["nodes"][ia].astype(float) + truth["b"]["nodes"][ib].astype(float))
        gm = graph_metrics(graph, (mid, radius, edges))
        for key in ("centreline_error_mm", "centreline_pred_to_truth_mm", "centreline_truth_to_pred_mm"):
            row[key] = gm[key]
        row.update(bifurcations=len(g.bifurcations()), end_points=len(g.endpoints()), components=g.n_components())
        frames.append(row)
        r = evaluate_correspondences(Prediction("", pred_frames[k].voxels, None), ann)
        raw.append({"key": tracked.keys[k], "pair": [int(ia), int(ib)], **r})
    shape = [(f["bifurcations"], f["end_points"], f["components"]) for f in frames]
    agree = float(np.mean([s == shape[0] for s in shape])) if shape else float("nan")

    def mean(rows, key):
        vals = [r[key] for r in rows if r.get(key) is not None and np.isfinite(r[key])]
        return float(np.mean(vals)) if vals else float("nan")

    gt_bif = len(VascularGraph(truth["reference_nodes"], radius, edges).bifurcations())
    base = {"seconds": float(summary["total_seconds"]), "n_keyframes": len(pairs), "gt_bifurcations": gt_bif}
    with_graph = {**base, **{k: mean(frames, k) for k in ("coverage", "epe_mm", "accuracy", "centreline_error_mm",
                                                          "centreline_pred_to_truth_mm", "centreline_truth_to_pred_mm",
                                                          "phase_error", "bifurcations")},
                  "topology_agreement": agree, "frames": frames}
    no_graph = {**base, **{k: mean(raw, k) for k in ("coverage", "epe_mm", "accuracy")}, "frames": raw}
    return {"graph": with_graph, "nograph": no_graph}
