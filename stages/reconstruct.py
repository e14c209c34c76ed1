"""Stage ``reconstruct``: two XA runs in, a time-resolved 3D coronary model out, end to end.

Reads: two runs (XA DICOM, or frame folders/stacks with a geometry JSON — :func:`stages.segment.load_run`).
Writes, in the output folder (every stage's artefact, so any stage can be rerun on its own):

* ``masks_a.zarr``, ``masks_b.zarr`` — vessel masks (``autocar segment``), with overlay PNGs;
* ``keyframes.zarr`` + ``keyframes.png`` — phase-matched frame pairs (``autocar keyframe``);
* ``predictions.zarr`` — per key frame the sparse 3D prediction with the two masks and cameras
  (``autocar.sparse-prediction``; view B's camera shifted to agree with view A, :mod:`stages.view_alignment`,
  unless ``align_views=False``; a shift is kept only if the prediction with it holds more confident voxels
  than with the header geometry), from the SBP network (shipped weights) or, with
  ``--method visual-hull`` / ``--method dense``, a baseline (:mod:`stages.methods3d`);
* ``graphs.zarr`` — the tracked vascular graphs (``autocar graph-opt``) and, per key frame,
  ``graphs_<k>.vtp`` (centreline with radius), ``graphs_<k>.stl`` (lumen), ``graphs_<k>.json``
  (graph + 2D↔2D correspondences);
* ``overlay_<k>.png`` — the model reprojected on both runs, coloured by position along the tree;
* ``report.html`` — one self-contained page (:mod:`stages.report`) with the 3D model (drag to rotate), the
  quality checks, the overlays (embedded) and the stage timings;
* ``summary.json`` — key-frame pairs, view B's shift per key frame (``view_b_shifts``; ``rejected_across_px``
  where the prediction overruled the fitted shift), timings, warnings and ``quality`` (the reconstruction's
  own checks, :mod:`stages.quality`: pieces, far pieces, branches outside both masks, catheter-like
  branches, reprojection distance per view, a verdict).

The output folder follows :mod:`stages.outputs`: every input and option is checked before it is touched; a
non-empty folder needs ``existing="force"`` (clear what autocar wrote there) or ``"resume"`` (reuse every
stage whose inputs and parameters match, recompute the rest); ``RUNNING`` marks it while the run works and
``summary.json`` replaces it at the end. The Python default is ``"force"`` (a rerun into the same folder
replaces the earlier run, stale files included); the CLI refuses unless told.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np

from . import __version__
from .artefacts import atomic_path
from .errors import UserError
from .methods3d import DEFAULT_METHOD, METHODS, load_predictor
from .outputs import OutputFolder, file_identity, fingerprint
from .report import write_report  # noqa: F401  (kept importable from here)
from .view_alignment import ViewShift, estimate_run_shifts, mismatch_curve

log = logging.getLogger(__name__)

SEG_METHODS = ("unet", "vesselness", "threshold")
SIDES = ("left", "right")
EXISTING = ("refuse", "force", "resume")
# what reconstruct writes, for --force in a folder an older autocar wrote without a manifest
OUTPUT_PATTERNS = ("masks_*.zarr", "masks_*.png", "masks_*.gif", "keyframes.zarr", "keyframes.png",
                   "predictions.zarr", "graphs.zarr", "graphs_*.vtp", "graphs_*.stl", "graphs_*.json",
                   "overlay_*.png", "report.html", "summary.json", "RUNNING")


class _Timer:
    def __init__(self):
        self.rows: list[tuple[str, float]] = []

    def __call__(self, name: str):
        timer = self

        class _Ctx:
            def __enter__(self):
                self.t = time.perf_counter()

            def __exit__(self, *exc):
                if exc[0] is None:
                    timer.rows.append((name, time.perf_counter() - self.t))

        return _Ctx()


def _check_runs(run_a, run_b) -> list[str]:
    from .sbp.model import MIN_VIEW_SEPARATION_DEG, view_separation_deg

    warnings = []
    for run, name in ((run_a, "run A"), (run_b, "run B")):
        if run.camera is None:
            raise UserError(f"{run.path}: no C-arm geometry; pass a geometry JSON for {name}")
    sep = view_separation_deg(run_a.camera, run_b.camera)
    if sep < MIN_VIEW_SEPARATION_DEG:
        raise UserError(f"{run_a.path} and {run_b.path} are only {sep:.1f}° apart (need ≥ {MIN_VIEW_SEPARATION_DEG:.0f}°): "
                        "two nearly parallel views cannot triangulate vessels")
    for key in ("PatientID", "StudyInstanceUID"):
        va, vb = run_a.metadata.get(key), run_b.metadata.get(key)
        if va and vb and va != vb:
            msg = f"the runs have different {key} ({va} vs {vb}): are they the same patient and study?"
            log.warning(msg)
            warnings.append(msg)
    return warnings


def _overlay_png(path, frames, cameras, graph, titles):
    """The model's centreline projected on both frames, coloured by position along the tree (paper Fig. 4)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from matplotlib.collections import LineCollection

    pos = graph.position_along_tree()
    edges = np.asarray(graph.edges, int).reshape(-1, 2)
    colours = plt.cm.turbo(0.5 * (pos[edges[:, 0]] + pos[edges[:, 1]])) if len(edges) else None
    fig, axes = plt.subplots(1, 2, figsize=(10, 5.2))
    for ax, frame, cam, title in zip(axes, frames, cameras, titles):
        ax.imshow(frame, cmap="gray")
        if len(edges):
            rc = cam.project(graph.nodes)
            segments = np.stack([rc[edges[:, 0]][:, ::-1], rc[edges[:, 1]][:, ::-1]], axis=1)  # (x=col, y=row)
            ax.add_collection(LineCollection(segments, colors=colours, linewidths=1.6))
        ax.set_title(title, fontsize=9)
        ax.set_axis_off()
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=90, format="png")
    plt.close(fig)


def confident_voxels(vox, threshold: float = 0.5) -> int:
    """Voxels a 3D prediction holds occupied with occupancy ≥ ``threshold`` (all of them without one)."""
    occ = vox.features.get("occupancy")
    return len(vox) if occ is None else int(np.count_nonzero(np.asarray(occ) >= threshold))


def predict_with_checked_shift(predict_3d, mask_a, mask_b, cam_a, cam_b, shift: ViewShift, side: str = "left"):
    """The 3D prediction with view B shifted by ``shift``, unless the one with the header geometry holds
    more confident voxels. Returns (voxels, view B's camera used, whether the shift was kept).

    Why: two views that agree back-project onto more confident voxels; a wrong shift (flat or misleading
    crossing profiles) loses them (docs/benchmarks/view_alignment.md, "checked by the prediction").
    """
    if not shift.applied:
        return predict_3d(mask_a, mask_b, cam_a, cam_b, side), cam_b, False
    shifted_cam = cam_b.shifted(*shift.shift_px)
    shifted = predict_3d(mask_a, mask_b, cam_a, shifted_cam, side)
    header = predict_3d(mask_a, mask_b, cam_a, cam_b, side)
    if confident_voxels(header) > confident_voxels(shifted):
        return header, cam_b, False
    return shifted, shifted_cam, True


def check_options(*, method: str, seg_method: str, side: str, k: int, weights=None, geometry_a=None,
                  geometry_b=None, existing: str = "refuse") -> None:
    """Every option of :func:`reconstruct` checked before any work or any write."""
    if method not in METHODS:
        raise UserError(f"unknown --method {method!r} (choose from {', '.join(METHODS)})")
    if seg_method not in SEG_METHODS:
        raise UserError(f"unknown --seg-method {seg_method!r} (choose from {', '.join(SEG_METHODS)})")
    if side not in SIDES:
        raise UserError(f"unknown --side {side!r} (choose from {', '.join(SIDES)})")
    if existing not in EXISTING:
        raise ValueError(f"existing must be one of {EXISTING}, got {existing!r}")
    if int(k) < 1:
        raise UserError(f"--keyframes must be ≥ 1, got {k}")
    for path, option in ((weights, "--weights"), (geometry_a, "--geometry-a"), (geometry_b, "--geometry-b")):
        if path is not None and not Path(path).is_file():
            raise UserError(f"{path}: no such file ({option})")


def _key_phases(kf) -> dict:
    return {key: [float(v) for v in np.asarray(kf["estimates"][key]["phase"])] for key in "ab"}


def reconstruct(run_a, run_b, out_dir, *, geometry_a=None, geometry_b=None, method: str = DEFAULT_METHOD, weights=None,
                seg_method: str = "unet", k: int = 7, side: str = "left", align_views: bool = True,
                existing: str = "force", progress=None, step=None) -> dict:
    """Run the whole pipeline; returns a summary with per-stage timings. See the module docstring.

    ``align_views``: per key frame, shift view B's image to be epipolar-consistent with view A before the
    3D prediction (:mod:`stages.view_alignment`: the heart moves between the two runs' acquisitions).
    ``existing``: what to do with a non-empty ``out_dir`` — ``"refuse"``, ``"force"`` or ``"resume"``.
    ``progress(message)`` is told each stage; ``step(stage, done, total)`` each key frame of the slow ones.
    """
    from .segment import load_run

    check_options(method=method, seg_method=seg_method, side=side, k=k, weights=weights, geometry_a=geometry_a,
                  geometry_b=geometry_b, existing=existing)
    folder = OutputFolder(out_dir, force=existing == "force", resume=existing == "resume",
                          known_patterns=OUTPUT_PATTERNS)
    out = folder.path
    timer = _Timer()
    note = progress or (lambda msg: None)
    tick = step or (lambda stage, done, total: None)

    # every input is read and checked before the output folder is touched
    with timer("read runs"):
        runs = [load_run(run_a, geometry_a), load_run(run_b, geometry_b)]
    warnings = _check_runs(*runs)
    with timer(f"load {method}"):
        predict_3d = load_predictor(method, weights)

    parameters = {"method": method, "weights": str(weights) if weights else None, "seg_method": seg_method, "k": int(k),
                  "side": side, "align_views": bool(align_views)}
    folder.open("reconstruct", {"run_a": str(run_a), "run_b": str(run_b), **parameters})
    try:
        summary = _pipeline(folder, runs, [run_a, run_b], [geometry_a, geometry_b], predict_3d, parameters, warnings,
                            timer, note, tick)
    except BaseException:
        folder.abandon()
        raise
    return summary


def _pipeline(folder, runs, run_paths, geometries, predict_3d, p, warnings, timer, note, tick) -> dict:
    """The stages in order; each one is skipped on resume when its fingerprint matches (see stages.outputs)."""
    from .graph.io import PredictionFrame, read_sparse_predictions, read_vascular_graphs, write_sparse_predictions
    from .graph.stage import run_graph_opt
    from .keyframe import keyframe_pairs, plot_keyframes, write_keyframes
    from .quality import frame_quality, summarise
    from .segment import read_masks, segment_run, write_masks

    out = folder.path
    method, seg_method = p["method"], p["seg_method"]

    # -- segment: one masks artefact per run
    note("segmenting vessels")
    masks, seg_fp = [], []
    with timer("segment"):
        tick("segmentation, runs", 0, 2)
        for n, (run, name) in enumerate(zip(runs, ("a", "b"))):
            fp = fingerprint("segment", run=file_identity(run_paths[n]),
                             geometry=file_identity(geometries[n]) if geometries[n] else None,
                             method=seg_method, version=__version__)
            path = out / f"masks_{name}.zarr"
            if folder.reusable(f"masks_{name}", fp):
                res = read_masks(path)
            else:
                res = segment_run(run, method=seg_method)
                if not np.asarray(res["mask"]).any():
                    raise UserError(f"{run.path}: no vessel found in any frame (a run without contrast?)")
                write_masks(path, res)
                folder.record(f"masks_{name}", fp, [path])
            masks.append(res)
            seg_fp.append(fp)
            tick("segmentation, runs", n + 1, 2)

    # -- key frames
    note("selecting key frames")
    kf_fp = fingerprint("keyframe", masks=seg_fp, k=p["k"])
    with timer("keyframe"):
        if folder.reusable("keyframes", kf_fp):
            d = folder.data("keyframes")
            kf = {"pairs": [tuple(x) for x in d["pairs"]], "warnings": d["warnings"],
                  "estimates": {key: {"phase": np.asarray(d["phase"][key])} for key in "ab"}}
        else:
            kf = keyframe_pairs(runs[0], runs[1], masks_a={"prob": masks[0]["prob"], "mask": masks[0]["mask"]},
                                      masks_b={"prob": masks[1]["prob"], "mask": masks[1]["mask"]}, k=p["k"])
            write_keyframes(out / "keyframes.zarr", kf)
            plot_keyframes(out / "keyframes.png", kf)
            folder.record("keyframes", kf_fp, ["keyframes.zarr", "keyframes.png"],
                          data={"pairs": [list(map(int, q)) for q in kf["pairs"]], "warnings": kf["warnings"],
                                "phase": _key_phases(kf)})
    warnings = warnings + list(kf["warnings"])
    pairs = list(dict.fromkeys(tuple(int(v) for v in q) for q in kf["pairs"]))  # repeats add nothing to a static reconstruction
    phases = _key_phases(kf)

    # -- 3D prediction per key frame
    pred_fp = fingerprint("predict", keyframes=kf_fp, method=method, side=p["side"], align_views=p["align_views"],
                          weights=file_identity(p["weights"]) if p["weights"] else None, version=__version__)
    cams = [runs[0].camera, runs[1].camera]
    if folder.reusable("predictions", pred_fp):
        note(f"3D prediction ({method}): reused from {out / 'predictions.zarr'}")
        _, frames = read_sparse_predictions(out / "predictions.zarr")
        frame_cams = [(f.cameras["a"], f.cameras["b"]) for f in frames]
        shifts = folder.data("predictions")["view_b_shifts"]
    else:
        note(f"3D prediction ({method}) on {len(pairs)} key frame(s)")
        frames, frame_cams, shifts = [], [], [None] * len(pairs)
        fitted = [ViewShift.none()] * len(pairs)
        if p["align_views"]:
            note("aligning view B to view A per key frame")
            with timer("align views"):
                curves = [mismatch_curve(masks[0]["mask"][ia], masks[1]["mask"][ib], cams[0], cams[1]) for ia, ib in pairs]
                fitted = estimate_run_shifts(curves, [ia for ia, _ in pairs], [ib for _, ib in pairs])
                shifts = [est.to_dict(cams[1].isocentre_spacing) for est in fitted]
        with timer(f"3D prediction ({method})"):
            tick(f"3D prediction ({method}), key frames", 0, len(pairs))
            for n, (ia, ib) in enumerate(pairs):
                ma, mb = np.asarray(masks[0]["mask"][ia], bool), np.asarray(masks[1]["mask"][ib], bool)
                vox, cam_b, kept = predict_with_checked_shift(predict_3d, ma, mb, cams[0], cams[1], fitted[n], p["side"])
                if fitted[n].applied and not kept:
                    shifts[n] = {**ViewShift.none(fitted[n].mismatch_header).to_dict(cams[1].isocentre_spacing),
                                 "rejected_across_px": shifts[n]["across_px"]}
                frame_cams.append((cams[0], cam_b))  # the overlays reproject with the cameras the model was built for
                frames.append(PredictionFrame(f"{n:02d}", vox, {"a": ma.astype(np.uint8), "b": mb.astype(np.uint8)},
                                                    {"a": cams[0], "b": cam_b}, {"a": int(ia), "b": int(ib)}))
                tick(f"3D prediction ({method}), key frames", n + 1, len(pairs))
            case_id = Path(str(runs[0].path)).stem
            write_sparse_predictions(out / "predictions.zarr", frames, case_id=case_id, stage="reconstruct",
                                           inputs=[str(runs[0].path), str(runs[1].path)],
                                           parameters={"method": method, "pairs": [list(q) for q in pairs],
                                                       "align_views": bool(p["align_views"]), "view_b_shifts": shifts})
        folder.record("predictions", pred_fp, ["predictions.zarr"], data={"view_b_shifts": shifts})

    # -- graph optimisation
    graph_fp = fingerprint("graph-opt", predictions=pred_fp, version=__version__)
    if folder.reusable("graphs", graph_fp):
        note("graph optimisation: reused")
        graph_summary = folder.data("graphs")["summary"]
    else:
        note("graph optimisation")
        with timer("graph-opt"):
            tick("graph optimisation, key frames", 0, len(pairs))
            graph_summary = run_graph_opt(out / "predictions.zarr", out / "graphs.zarr",
                                                progress=lambda done, total: tick("graph optimisation, key frames", done, total))
        graph_summary["written"] = [Path(w).name for w in graph_summary.get("written", [])]
        folder.record("graphs", graph_fp, graph_summary["written"], data={"summary": graph_summary})
    _, tracked = read_vascular_graphs(out / "graphs.zarr")

    # -- quality checks, overlays and report (cheap: always redone)
    note("quality checks, overlays and report")
    overlays, frames_model, checks = [], [], []
    with timer("quality + overlays + report"):
        for n, ((ia, ib), key) in enumerate(zip(pairs, tracked.keys)):
            graph = tracked.graphs[n]
            checks.append(frame_quality(graph, {"a": masks[0]["mask"][ia], "b": masks[1]["mask"][ib]},
                                              {"a": frame_cams[n][0], "b": frame_cams[n][1]}, key=key))
            png = out / f"overlay_{key}.png"
            _overlay_png(png, [runs[0].frames[ia], runs[1].frames[ib]], frame_cams[n], graph,
                         [f"run A frame {ia} (phase {phases['a'][ia]:.2f})",
                          f"run B frame {ib} (phase {phases['b'][ib]:.2f})"])
            overlays.append((key, png))
            frames_model.append({"key": key, "nodes": np.round(graph.nodes, 2).tolist(),
                                 "radius": np.round(graph.radius, 2).tolist(), "edges": np.asarray(graph.edges).tolist(),
                                 "pos": np.round(graph.position_along_tree(), 3).tolist()})
        quality = summarise(checks)
        summary_rows = [("run A", Path(str(runs[0].path))), ("run B", Path(str(runs[1].path))), ("3D method", method),
                        ("segmentation", seg_method), ("key frames (A, B)", pairs), ("quality", quality["verdict"])]
        if folder.reused:
            summary_rows.append(("reused from an earlier run (--resume)", ", ".join(folder.reused)))
        if p["align_views"]:
            summary_rows.append(("run B aligned (shift across the epipolar lines, mm)",
                                 ", ".join(f"{s['across_mm']:+.2f}" for s in shifts if s)))
        summary_rows += [(f"graph {f['key']}", f"{f['nodes']} nodes, {f['bifurcations']} bifurcations, {f['length_mm']:.0f} mm")
                         for f in graph_summary.get("frames", []) if isinstance(f, dict) and "key" in f]
        write_report(out / "report.html", title="AutoCAR reconstruction", summary_rows=summary_rows,
                     timings=timer.rows, frames_model=frames_model, overlays=overlays, warnings=warnings, quality=quality)
        folder.add_files([png for _, png in overlays] + ["report.html"])
    summary = {"output": str(out), "method": method, "pairs": [list(q) for q in pairs], "view_b_shifts": shifts,
               "timings": timer.rows, "total_seconds": float(sum(t for _, t in timer.rows)), "warnings": warnings,
               "graph": graph_summary, "quality": quality, "reused": list(folder.reused), "parameters": p}
    folder.finish(summary)
    return summary
