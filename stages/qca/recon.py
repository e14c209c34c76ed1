"""QCA of a reconstruction folder (what ``autocar qca RECON_DIR`` and the end of ``reconstruct`` run).

Reads, in the folder written by ``autocar reconstruct`` (stages/reconstruct.py): ``graphs.zarr`` (tracked
vascular graphs, one topology for every key frame), ``keyframes.zarr`` (the cardiac phase of every
key-frame pair, optional) and ``predictions.zarr`` (the two views' masks and cameras per key frame,
optional). Writes there: ``qca.json`` (:data:`QCA_KIND`, schema :data:`QCA_SCHEMA`), ``qca.csv``
(one row per lesion) and, unless ``plots=False``, ``qca_profiles.png``, ``qca_views.png``,
``qca_3d.png`` (:mod:`stages.qca.report`), ``qca_sr.dcm`` (the figures as a DICOM Structured Report when the
runs were DICOM files, :mod:`stages.qca.sr`), and it adds the vessel names to every ``graphs_<k>.vtp``.

* **Key frame analysed**: the end-diastolic one — the pair whose run-A cardiac phase (0 = R wave,
  from the ECG or the image-based phase estimate of ``keyframe``) is circularly nearest to 0; without
  ``keyframes.zarr``, the frame with the longest tree (the heart is relaxed and the vessels longest at
  end-diastole). ``frame=`` overrides it.
* **Across key frames**: the tracked graphs share their topology, so the vessels and names of the
  analysed frame are re-profiled with every other frame's node positions and radii; each lesion is
  followed to the deepest narrowing within its own extent there, and its %DS, MLD and length ranges
  over the key frames are reported (``over_frames``).
* **Radius**: the analysed frame's graph-opt radii (``radius="frame"``, the default) or, with
  ``radius="mean"``, every node's radius averaged over the key frames (the lumen does not change with
  the cardiac phase; the reconstruction noise does, ~0.08 mm SD on the bundled example).
* **Two-view uncertainty**: where predictions.zarr has the masks and cameras of the analysed frame,
  every node is projected into both views and the lumen width there measured on each mask (distance
  transform, scaled to mm at the node's depth); ``uncertainty_mm`` of a lesion is half the difference
  of the two views' widths at its MLD point, and the profile carries both views' widths.
* **Confirmed by the views**: a narrowing of the model is reported as a lesion only where no view's own width
  stays normal there and at least one view shows the narrowing (a view that sees the stretch over other vessels
  cannot tell either way; :func:`confirm_in_views`); the others are listed per vessel as
  ``unconfirmed_narrowings`` with the reason.
* A reconstruction with no usable tree (no graph, or nothing ≥ 10 mm) writes a valid qca.json with an
  empty ``vessels`` list and a ``message`` saying why; only a missing or unreadable folder is an error.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from ..core.artefacts import write_json
from ..core.errors import UserError
from .analysis import GraphQCA, QCAParams, analyse_graph
from .profile import vessel_profile

log = logging.getLogger(__name__)

# a view in which this much of a lesion's stretch lies over other vessels cannot show its width: it neither
# confirms nor refutes the lesion (on data-re's default reconstructions, 29 false lesions ≥ 50 % DS → 18 and no
# true one ≥ 50 % lost at 90 %; at 50 % the false ones were 22)
BLIND_OVERLAP_PERCENT = 90.0
QCA_KIND = "autocar.qca"
QCA_SCHEMA = 1
RECON_PARAMS = QCAParams(smooth_mm=1.0, min_reference_mm=1.5, min_vessel_mm=10.0, skip_end_mm=3.0)

__all__ = ["qca_for_reconstruction", "QCA_KIND", "QCA_SCHEMA", "RECON_PARAMS", "choose_frame", "profile_frame"]


def _phases(recon: Path):
    path = recon / "keyframes.zarr"
    if not path.exists():
        return None
    try:
        from ..core.artefacts import read_zarr

        g = read_zarr(path, kind=None, schema_version=None)
        return np.asarray(g["phase"][...], float) if "phase" in g else None
    except (UserError, KeyError, ValueError, OSError):
        return None


def choose_frame(tracked, phases=None) -> tuple[int, str]:
    """(index, reason) of the end-diastolic key frame (module docstring)."""
    n = len(tracked.graphs)
    if phases is not None and len(phases) == n:
        dist = np.minimum(np.mod(phases, 1.0), 1.0 - np.mod(phases, 1.0))
        k = int(np.argmin(dist))
        return k, f"end-diastolic key frame: cardiac phase {float(np.mod(phases[k], 1.0)):.2f} (nearest to the R wave)"
    lengths = []
    for g in tracked.graphs:
        e = g.edges
        lengths.append(float(np.linalg.norm(g.nodes[e[:, 0]] - g.nodes[e[:, 1]], axis=1).sum()) if len(e) else 0.0)
    k = int(np.argmax(lengths))
    return k, f"longest tree ({lengths[k]:.0f} mm): no key-frame phases, end-diastole taken as the most relaxed frame"


def profile_frame(qca: GraphQCA, nodes, radius) -> dict:
    """Profiles of the analysed vessels recomputed with another key frame's node positions and radii."""
    out = {}
    p = qca.params
    for v in qca.reported():
        pts = np.asarray(nodes)[v.nodes]
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        scale = s[-1] / max(v.length, 1e-9)
        junctions = [(sj * scale, rb) for sj, _, rb in v.junctions]
        out[v.index] = vessel_profile(s, np.asarray(radius)[v.nodes], junctions, spurs=[x * scale for x in v.spurs],
                                      step_mm=p.step_mm, smooth_mm=p.smooth_mm, min_ds=0.0,
                                      skip_start_mm=0.0, skip_end_mm=0.0, murray_weight=p.murray_weight)
    return out


def _lesion_in(prof, les, scale):
    """The same lesion in another frame's profile: its deepest narrowing within the lesion's own extent."""
    lo, hi = les["start_mm"] * scale, les["end_mm"] * scale
    sel = (prof.s >= lo) & (prof.s <= hi)
    if not sel.any():
        return None
    delta = 1 - prof.diameter / np.maximum(prof.reference, 1e-6)
    k = np.flatnonzero(sel)[int(np.argmax(delta[sel]))]
    return {"ds_percent": float(100 * delta[k]), "mld_mm": float(prof.diameter[k]), "reference_mm": float(prof.reference[k])}


def _views_of_frame(path: Path, k: int):
    """Masks and cameras of key frame ``k`` of predictions.zarr (its voxels are not needed), or None."""
    from types import SimpleNamespace

    from ..core.artefacts import read_zarr
    from ..core.geometry import Camera

    if not path.exists():
        return None
    try:
        root = read_zarr(path, kind="autocar.sparse-prediction", schema_version=1)
        attrs = dict(root.attrs)
        keys = [str(x) for x in attrs.get("frame_keys") or []]
        if k >= len(keys) or keys[k] not in root.get("frames", {}):
            return None
        g = root["frames"][keys[k]]
        cams = dict(attrs.get("cameras") or {})
        cams.update(dict(g.attrs).get("cameras") or {})
        masks = {name: np.asarray(arr[...]) for name, arr in g["masks"].arrays()} if "masks" in g else {}
        return SimpleNamespace(masks=masks, cameras={v: Camera.from_dict(d) for v, d in cams.items()})
    except (UserError, KeyError, TypeError, ValueError) as exc:
        log.warning("%s: views of key frame %d unreadable (%s); no two-view widths or run angles", path, k, exc)
        return None


def _view_widths(frame, nodes) -> dict | None:
    """Per node, the lumen diameter (mm) each view's mask shows at its projection (None without masks)."""
    from scipy.ndimage import distance_transform_edt, maximum_filter

    if frame is None or not frame.masks:
        return None
    out = {}
    for view in ("a", "b"):
        mask, cam = frame.masks.get(view), frame.cameras.get(view)
        if mask is None or cam is None:
            return None
        edt = maximum_filter(distance_transform_edt(np.asarray(mask) > 0), size=3)
        rc, depth = cam.project(nodes, return_depth=True)
        ok = np.all(np.isfinite(rc), axis=1)
        rr = np.clip(np.rint(np.nan_to_num(rc[:, 0])).astype(int), 0, mask.shape[0] - 1)
        cc = np.clip(np.rint(np.nan_to_num(rc[:, 1])).astype(int), 0, mask.shape[1] - 1)
        px_mm = depth / (0.5 * (cam.K[0, 0] + cam.K[1, 1]))
        width = np.maximum(2 * edt[rr, cc] - 1, 0) * px_mm
        width[~ok | (edt[rr, cc] == 0)] = np.nan
        out[view] = width
    return out


def qca_for_reconstruction(recon_dir, *, frame=None, params: QCAParams | None = None, plots: bool = True,
                           views: bool = True, view_step_deg: float = 5.0, radius: str = "frame") -> dict:
    """Analyse ``recon_dir`` and write qca.json / qca.csv / plots there (module docstring); returns the
    qca.json content."""
    from ..graph.io import read_vascular_graphs

    t0 = time.perf_counter()
    recon = Path(recon_dir)
    if not recon.is_dir():
        raise UserError(f"{recon}: no such reconstruction folder")
    params = params or RECON_PARAMS
    graphs_path = recon / "graphs.zarr"
    doc = {"kind": QCA_KIND, "schema_version": QCA_SCHEMA, "reconstruction": str(recon),
           "parameters": params.to_dict(), "frame": None, "frame_reason": None, "side": "unknown", "vessels": [],
           "message": None, "run_angles": {}, "timings_s": {}}
    if not graphs_path.exists():
        doc["message"] = f"{graphs_path}: no vascular graphs in this folder (was the reconstruction finished?)"
        return _finish(recon, doc, None, plots, t0)
    attrs, tracked = read_vascular_graphs(graphs_path)
    if not tracked.graphs or all(len(g) == 0 for g in tracked.graphs):
        doc["message"] = f"{graphs_path}: the reconstruction holds no vessel tree"
        return _finish(recon, doc, None, plots, t0)
    if frame is None:
        k, reason = choose_frame(tracked, _phases(recon))
    else:
        if str(frame) not in tracked.keys:
            raise UserError(f"{graphs_path}: no key frame {frame!r} (frames: {', '.join(tracked.keys)})")
        k, reason = tracked.keys.index(str(frame)), "chosen by the user"
    doc["frame"], doc["frame_reason"] = tracked.keys[k], reason
    graph = tracked.graphs[k]
    if radius == "mean":  # the lumen does not change with the phase, the reconstruction's noise does
        from ..graph.vascular import VascularGraph

        graph = VascularGraph(graph.nodes, np.mean([g.radius for g in tracked.graphs], axis=0), graph.edges, graph.node_id)
    elif radius != "frame":
        raise UserError(f"unknown radius source {radius!r} (choose from frame, mean)")
    doc["radius_source"] = radius
    qca = analyse_graph(graph, params)
    doc["side"] = qca.side
    if not qca.reported() or max(v.length for v in qca.reported()) < params.min_vessel_mm:
        doc["message"] = f"{graphs_path}: no usable vessel tree (nothing ≥ {params.min_vessel_mm:.0f} mm long in key frame {tracked.keys[k]})"
        return _finish(recon, doc, None, plots, t0)
    body = qca.to_dict()
    doc["vessels"] = body["vessels"]
    doc["timings_s"]["analysis"] = time.perf_counter() - t0

    # the two views: cameras (run angles) and per-node widths
    pred_frame = _views_of_frame(recon / "predictions.zarr", k)
    if pred_frame is not None:
        from .views import carm_angles

        for view, cam in pred_frame.cameras.items():
            a, b = carm_angles(cam)
            doc["run_angles"][view] = {"alpha_deg": round(a, 2), "beta_deg": round(b, 2)}
    widths = _view_widths(pred_frame, graph.nodes)

    by_id = {qca.vessel_id(v): v for v in qca.reported()}
    for vd in doc["vessels"]:
        v = by_id[vd["id"]]
        if widths is not None:
            s = np.asarray(vd["profile"]["s_mm"])
            for view in ("a", "b"):
                w = widths[view][v.nodes]
                good = np.isfinite(w)
                vd["profile"][f"view_{view}_mm"] = (np.round(np.interp(s, v.s[good], w[good]), 3).tolist()
                                                    if good.sum() >= 2 else None)
            for les in vd["lesions"]:
                wa, wb = vd["profile"]["view_a_mm"], vd["profile"]["view_b_mm"]
                if wa is not None and wb is not None:
                    les["uncertainty_mm"] = round(0.5 * abs(float(np.interp(les["position_mm"], s, wa))
                                                            - float(np.interp(les["position_mm"], s, wb))), 3)
    # every other key frame, on the same vessels
    t1 = time.perf_counter()
    lesion_rows = [(vd, les, by_id[vd["id"]]) for vd in doc["vessels"] for les in vd["lesions"]]
    per_frame = {les["id"]: [] for _, les, _ in lesion_rows}
    vessel_len = {vd["id"]: [] for vd in doc["vessels"]}
    for j, g in enumerate(tracked.graphs):
        profs = qca.profiles if j == k else profile_frame(qca, g.nodes, g.radius)
        for vd in doc["vessels"]:
            v = by_id[vd["id"]]
            vessel_len[vd["id"]].append(float(profs[v.index].s[-1]))
        for vd, les, v in lesion_rows:
            prof = profs[v.index]
            scale = prof.s[-1] / max(v.length, 1e-9)
            hit = les if j == k else _lesion_in(prof, les, scale)
            if hit is not None:
                per_frame[les["id"]].append({"frame": tracked.keys[j], "ds_percent": round(float(hit["ds_percent"]), 2),
                                             "mld_mm": round(float(hit["mld_mm"]), 3)})
    for vd, les, _ in lesion_rows:
        rows = per_frame[les["id"]]
        ds = np.array([r["ds_percent"] for r in rows])
        mld = np.array([r["mld_mm"] for r in rows])
        les["over_frames"] = {"frames": rows, "ds_min": round(float(ds.min()), 2), "ds_max": round(float(ds.max()), 2),
                              "ds_sd": round(float(ds.std()), 2), "mld_min": round(float(mld.min()), 3),
                              "mld_max": round(float(mld.max()), 3)}
    for vd in doc["vessels"]:
        L = np.array(vessel_len[vd["id"]])
        vd["length_over_frames_mm"] = {"min": round(float(L.min()), 2), "max": round(float(L.max()), 2)}
    doc["timings_s"]["key_frames"] = time.perf_counter() - t1

    if widths is not None:
        confirm_in_views(doc, by_id, qca.tree, params.min_ds)
    maps = {}
    if views:
        t2 = time.perf_counter()
        maps = add_views(qca, doc, by_id, view_step_deg)
        doc["timings_s"]["views"] = time.perf_counter() - t2
    from .report import label_centrelines
    from .sr import write_qca_sr

    doc["labelled_exports"] = label_centrelines(recon, tracked, doc, k)  # vessel names into the .vtp files
    doc["sr"] = write_qca_sr(recon, doc)  # qca_sr.dcm when the runs were DICOM
    return _finish(recon, doc, (qca, maps), plots, t0)


def view_narrowing(s: np.ndarray, width: np.ndarray, lesion: dict) -> float | None:
    """How much one view's vessel width narrows at a lesion (%): its narrowest width inside the lesion against the
    median width on either side (as far as max(5 mm, the lesion's length)); None where either is not measured."""
    start, end = lesion["start_mm"], lesion["end_mm"]
    reach = max(5.0, lesion["length_mm"])
    inside = (s >= start) & (s <= end) & np.isfinite(width)
    around = (((s >= start - reach) & (s < start)) | ((s > end) & (s <= end + reach))) & np.isfinite(width)
    if not inside.any() or not around.any():
        return None
    ref = float(np.median(width[around]))
    return 100.0 * (1.0 - float(width[inside].min()) / ref) if ref > 0 else None


def confirm_in_views(doc: dict, by_id: dict, tree, min_ds: float) -> None:
    """Keep as lesions only the narrowings the views confirm.

    The 3D lumen is the narrower of the two views' widths at each node, so one view's thin mask (a faint or
    badly segmented stretch) narrows the model where the other view sees a normal vessel. A view *cannot tell*
    when at its run's angle at least :data:`BLIND_OVERLAP_PERCENT` % of the lesion's stretch lies over other
    vessels (:func:`stages.qca.views.overlap_at`; an overlap widens that view's mask); otherwise it *shows* the
    narrowing when its own width narrows there too (:func:`view_narrowing` ≥ ``min_ds``, the threshold lesions
    are graded from) and *refutes* it when it does not. A lesion stays when no view refutes it and at least one
    view shows it. Every lesion gets ``views`` (per view: its ``ds_percent``, ``overlap_percent``); the others
    move to the vessel's ``unconfirmed_narrowings`` with ``refuted_by`` (the views that show no narrowing,
    possibly none) and ``reason`` (a sentence for the report)."""
    from .views import overlap_at

    angles = doc.get("run_angles") or {}
    for vd in doc["vessels"]:
        prof = vd["profile"]
        s = np.asarray(prof["s_mm"], float)
        kept, unconfirmed = [], []
        for les in vd["lesions"]:
            half = max(5.0, 0.5 * les["length_mm"])
            seen = [view for view in ("a", "b") if prof.get(f"view_{view}_mm") is not None and view in angles]
            if not seen:  # no view to check against: nothing to decide with
                kept.append(les)
                continue
            overlaps = overlap_at(tree, by_id[vd["id"]], les["position_mm"] - half, les["position_mm"] + half,
                                  [(angles[v]["alpha_deg"], angles[v]["beta_deg"]) for v in seen])
            checks = {}
            for view, ov in zip(seen, overlaps):
                ds = view_narrowing(s, np.asarray(prof[f"view_{view}_mm"], float), les)
                checks[view] = {"ds_percent": None if ds is None else round(ds, 2), "overlap_percent": round(ov, 1)}
            les["views"] = checks
            clear = {v: c["ds_percent"] for v, c in checks.items()
                     if c["overlap_percent"] < BLIND_OVERLAP_PERCENT and c["ds_percent"] is not None}
            refuted = [v for v, ds in clear.items() if ds < min_ds]
            if refuted:
                les["refuted_by"] = refuted
                les["reason"] = f"view {', '.join(v.upper() for v in refuted)} shows no narrowing here"
            elif not clear:
                les["refuted_by"] = []
                les["reason"] = "neither view can show it (each sees it over other vessels or does not measure it)"
            else:
                kept.append(les)
                continue
            unconfirmed.append(les)
        vd["lesions"] = kept
        vd["unconfirmed_narrowings"] = unconfirmed


def add_views(qca: GraphQCA, doc: dict, by_id: dict, step_deg: float = 5.0) -> dict:
    """Best view per lesion (map kept for the plot) and per named-vessel segment (proximal/mid/distal)."""
    from .views import segment_views, value_at

    maps = {}
    runs = doc.get("run_angles") or {}
    for vd in doc["vessels"]:
        v = by_id[vd["id"]]
        for les in vd["lesions"]:
            half = max(5.0, 0.5 * les["length_mm"])
            m = segment_views(qca.tree, v, les["position_mm"] - half, les["position_mm"] + half, step_deg)
            les["best_view"] = m["best"]
            les["at_run_angles"] = {view: {"foreshortening_percent": round(value_at(m, "foreshortening", a["alpha_deg"], a["beta_deg"]), 2),
                                           "overlap_percent": round(value_at(m, "overlap", a["alpha_deg"], a["beta_deg"]), 2)}
                                    for view, a in runs.items()}
            maps[les["id"]] = m
        if vd["name"] != "unlabelled" and v.length >= 6.0:
            segs = []
            for t, part in enumerate(("proximal", "mid", "distal")):
                s0, s1 = v.length * t / 3, v.length * (t + 1) / 3
                m = segment_views(qca.tree, v, s0, s1, 2 * step_deg)  # a coarser grid: 4× fewer views
                segs.append({"segment": f"{part} {vd['name']}", "start_mm": round(s0, 2), "end_mm": round(s1, 2),
                             "best_view": m["best"],
                             "at_run_angles": {view: {"foreshortening_percent": round(value_at(m, "foreshortening", a["alpha_deg"], a["beta_deg"]), 2),
                                                      "overlap_percent": round(value_at(m, "overlap", a["alpha_deg"], a["beta_deg"]), 2)}
                                               for view, a in runs.items()}})
                maps[f"{vd['id']}.{part}"] = m
            vd["segments"] = segs
    doc["view_grid"] = {"alpha_deg": [-60, 60], "beta_deg": [-45, 45], "step_deg": step_deg,
                        "segment_step_deg": 2 * step_deg}
    return maps


def _finish(recon: Path, doc: dict, result, plots: bool, t0: float) -> dict:
    from .report import write_csv, write_plots

    if doc["message"]:
        log.warning("%s", doc["message"])
    doc["timings_s"]["total"] = time.perf_counter() - t0
    if plots and result is not None:
        t = time.perf_counter()
        doc["plots"] = write_plots(recon, doc, *result)
        doc["timings_s"]["plots"] = time.perf_counter() - t
    write_json(recon / "qca.json", _rounded(doc))
    write_csv(recon / "qca.csv", doc)
    return doc


def _rounded(obj):
    if isinstance(obj, dict):
        return {k: _rounded(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_rounded(v) for v in obj]
    if isinstance(obj, (np.floating, float)):
        return round(float(obj), 4)
    if isinstance(obj, np.integer):
        return int(obj)
    return obj
