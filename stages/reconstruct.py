"""Stage ``reconstruct``: two XA runs in, a time-resolved 3D coronary model out, end to end.

Reads: two runs (XA DICOM, or frame folders/stacks with a geometry JSON — :func:`stages.core.runs.load_run`).
Writes, in the output folder (every stage's artefact, so any stage can be rerun on its own):

* ``masks_a.zarr``, ``masks_b.zarr`` — vessel masks (``autocar segment``), with overlay PNGs;
* ``keyframes.zarr`` + ``keyframes.png`` — phase-matched frame pairs (``autocar keyframe``);
* ``predictions.zarr`` — per key frame the sparse 3D prediction with the two masks (2 marks the pixels that are
  the catheter a run showed in its frames before the contrast arrived: :func:`stages.core.catheter.precontrast_catheter`;
  graph-opt drops the tree's stretch on it) and cameras
  (``autocar.sparse-prediction``; view B's camera shifted to agree with view A, :mod:`stages.view_alignment`,
  unless ``align_views=False``; a shift is kept only if the prediction with it explains more of the two views
  than with the header geometry: :func:`stages.methods3d.load_evidence_predictor`), from the explicit two-view correspondence method (the default,
  :mod:`stages.twoview`) or, with ``--method sbp``, the SBP network (shipped weights), or with
  ``--method visual-hull`` / ``--method dense``, a baseline (:mod:`stages.methods3d`);
* ``graphs.zarr`` — the tracked vascular graphs (``autocar graph-opt``) and, per key frame,
  ``graphs_<k>.vtp`` (centreline with radius), ``graphs_<k>.stl`` (lumen), ``graphs_<k>.json``
  (graph + 2D↔2D correspondences);
* ``overlay_<k>.png`` — the model reprojected on both runs, coloured by position along the tree;
* ``report.html`` — one self-contained page (:mod:`stages.report`) with the 3D viewer (three.js, embedded),
  the quality checks, the overlays and QCA figures (embedded) and the stage timings;
* ``summary.json`` — key-frame pairs, view B's shift per key frame (``view_b_shifts``; ``rejected_across_px``
  where the prediction overruled the fitted shift; ``further_runs_px``, with three or more runs, where the further
  runs moved it: along its epipolar lines by the breathing they imply, across them onto their own model,
  :mod:`stages.twoview.multiview`), ``catheter_px`` (per run with frames before the contrast, the pixels per key
  frame its catheter took), timings, warnings
  and ``quality`` (the reconstruction's own checks, :mod:`stages.quality`: pieces, far pieces, branches outside
  both masks, catheter-like branches, reprojection distance per view, a verdict) and ``table_offsets_mm`` (when the table moved
  between the runs — the header's table position or ``TablePosition`` in a geometry JSON — run B's camera
  is placed in run A's patient frame: :func:`stages.core.geometry.cameras_on_one_table`).

The output folder follows :mod:`stages.core.outputs`: every input and option is checked before it is touched; a
non-empty folder needs ``existing="force"`` (clear what autocar wrote there) or ``"resume"`` (reuse every
stage whose inputs and parameters match, recompute the rest); ``RUNNING`` marks it while the run works and
``summary.json`` replaces it at the end. The Python default is ``"force"`` (a rerun into the same folder
replaces the earlier run, stale files included); the CLI refuses unless told.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from . import __version__
from .core.catheter import vessel_labels
from .core.errors import UserError
from .core.outputs import OutputFolder, file_identity, fingerprint
from .methods3d import DEFAULT_METHOD, KEY_FRAME_THREADED, METHODS, load_evidence_predictor
from .report import write_report  # noqa: F401  (kept importable from here)
from .view_alignment import ViewShift, estimate_run_shifts, mismatch_curve

log = logging.getLogger(__name__)

SEG_METHODS = ("unet", "vesselness", "threshold")
SIDES = ("left", "right")
EXISTING = ("refuse", "force", "resume")
# what reconstruct writes, for --force in a folder an older autocar wrote without a manifest
OUTPUT_PATTERNS = ("masks_*.zarr", "masks_*.png", "masks_*.gif", "keyframes.zarr", "keyframes.png",
                   "predictions.zarr", "graphs.zarr", "graphs_*.vtp", "graphs_*.stl", "graphs_*.json",
                   "overlay_*.png", "qca.json", "qca.csv", "qca_*.png", "qca_sr.dcm", "report.html", "summary.json",
                   "RUNNING")


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


def run_names(n: int) -> list[str]:
    """'run A', 'run B', 'run C' … for n runs (the first is the reference, the second its partner)."""
    return [f"run {chr(ord('A') + k)}" for k in range(n)]


def view_keys(n: int) -> list[str]:
    """The artefacts' view names of n runs: 'a', 'b', 'c' …"""
    return [chr(ord("a") + k) for k in range(n)]


def _check_runs(runs, paths) -> list[str]:
    from .core.geometry import MIN_VIEW_SEPARATION_DEG, view_separation_deg

    warnings = []
    names = run_names(len(runs))
    for run, name in zip(runs, names):
        if run.camera is None:
            raise UserError(f"{run.path}: no C-arm geometry; pass a geometry JSON for {name}")
    seen: dict = {}
    for run, path, name in zip(runs, paths, names):
        uid = run.metadata.get("SOPInstanceUID") or None
        for ident in (("file", Path(path).resolve()), ("SOPInstanceUID", uid)):
            if ident[1] is None:
                continue
            if ident in seen:
                raise UserError(f"{path}: the same run as {seen[ident]} ({ident[0]} {ident[1]}); give each run once")
            seen[ident] = path
    sep = view_separation_deg(runs[0].camera, runs[1].camera)
    if sep < MIN_VIEW_SEPARATION_DEG:
        raise UserError(f"{runs[0].path} and {runs[1].path} are only {sep:.1f}° apart (need ≥ {MIN_VIEW_SEPARATION_DEG:.0f}°): "
                        "two nearly parallel views cannot triangulate vessels")
    for run, name in zip(runs[2:], names[2:]):
        sep = min(view_separation_deg(other.camera, run.camera) for other in runs[:2])
        if sep < MIN_VIEW_SEPARATION_DEG:
            msg = (f"{name} ({run.path}) is only {sep:.1f}° from run A or B: it adds little depth evidence (it is used "
                   "with the run it is far enough from)")
            log.warning(msg)
            warnings.append(msg)
    for key in ("PatientID", "StudyInstanceUID"):
        values = {name: run.metadata.get(key) for run, name in zip(runs, names) if run.metadata.get(key)}
        if len(set(values.values())) > 1:
            msg = (f"the runs have different {key} ({', '.join(f'{n}: {v}' for n, v in values.items())}): are they "
                   "the same patient and study?")
            log.warning(msg)
            warnings.append(msg)
    return warnings


def _overlay_png(path, frames, cameras, graph, titles):
    """The model's centreline projected on every run's frame, coloured by position along the tree (paper Fig. 4):
    the runs side by side at their own resolution, each under its title."""
    from .core.figures import draw_overlay_panels

    pos = graph.position_along_tree()
    edges = np.asarray(graph.edges, int).reshape(-1, 2)
    segments = [cam.project(graph.nodes)[edges].reshape(-1, 4) if len(edges) else np.zeros((0, 4)) for cam in cameras]
    draw_overlay_panels(path, frames, titles, segments, 0.5 * (pos[edges[:, 0]] + pos[edges[:, 1]]))


def predict_with_checked_shift(predict_3d, mask_a, mask_b, cam_a, cam_b, shift: ViewShift, side: str = "left",
                               extra=(), report: dict | None = None):
    """The 3D prediction with view B shifted by ``shift``, unless the one with the header geometry explains
    more of the views (``predict_3d``: :func:`stages.methods3d.load_evidence_predictor`). Returns (voxels, view
    B's camera used, whether the shift was kept). ``extra``: (mask, camera) of the further runs' frames at this key
    frame's phase; ``report`` receives, per further view (2, 3 …), how consistent it was with runs A and B and
    whether it was used (and, under 1, view B's image shift where they moved it).

    Why: a wrong shift (flat or misleading crossing profiles) makes the two views agree less
    (docs/benchmarks/view_alignment.md, "checked by the prediction").
    """
    cameras = [cam_b.shifted(*shift.shift_px), cam_b] if shift.applied else [cam_b]
    kw = {"extra": extra, "report": report} if extra else {}
    vox, k = predict_3d(mask_a, mask_b, cam_a, cameras, side, **kw)
    return vox, cameras[k], bool(shift.applied and k == 0)


def check_options(*, method: str, seg_method: str, side: str, k: int, weights=None, geometry_a=None,
                  geometry_b=None, existing: str = "refuse", more_runs=(), more_geometries=()) -> None:
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
    for path, option in ((weights, "--weights"), (geometry_a, "--geometry-a"), (geometry_b, "--geometry-b"),
                         *((g, "--geometry-more") for g in more_geometries or ())):
        if path is not None and not Path(path).is_file():
            raise UserError(f"{path}: no such file ({option})")
    if more_runs:
        from .methods3d import MULTI_VIEW_METHODS

        if method not in MULTI_VIEW_METHODS:
            raise UserError(f"--method {method} reconstructs from two runs; with {2 + len(more_runs)} runs use "
                            f"--method {MULTI_VIEW_METHODS[0]} (it takes every run's evidence)")
    if more_geometries and len(more_geometries) > len(more_runs or ()):
        raise UserError(f"{len(more_geometries)} --geometry-more file(s) for {len(more_runs or ())} further run(s): "
                        "give one per further run, in order")


def reconstruct(run_a, run_b, out_dir, *, geometry_a=None, geometry_b=None, method: str = DEFAULT_METHOD, weights=None,
                seg_method: str = "unet", k: int = 7, side: str = "left", align_views: bool = True,
                qca: bool = True, calibrate: bool = False, existing: str = "force", progress=None,
                step=None, workers: int = 1, more_runs=(), more_geometries=()) -> dict:
    """Run the whole pipeline; returns a summary with per-stage timings. See the module docstring.

    ``more_runs`` (with ``more_geometries``, one geometry JSON or None per run when they are not DICOM): further
    runs of the same study (run C, D …). At each key frame every further run's frame of the same cardiac phase
    (:func:`stages.keyframe.match_further_run`) is added as evidence to the 3D step
    (:mod:`stages.twoview.multiview`), and the masks, cameras, overlays, quality checks and summary carry it;
    run A stays the reference frame and run A + B the key-frame pairs. A further run's frame whose phase does not
    match is left out of that key frame, with a warning.

    ``align_views``: per key frame, shift view B's image to be epipolar-consistent with view A before the
    3D prediction (:mod:`stages.view_alignment`: the heart moves between the two runs' acquisitions).
    ``workers``: key frames processed at once, in threads, by the 3D step (methods of
    :data:`stages.methods3d.KEY_FRAME_THREADED`) and graph-opt's per-frame graphs and exports (the outputs do not
    depend on it; `autocar reconstruct --threads`).
    ``calibrate``: refine run B's geometry from the two runs' vessels first (:mod:`stages.calibration`, on the
    first key-frame pair's masks: the shift across the epipolar lines that two views can observe), reported
    under ``calibration``. Off by default: on dynamic runs it cannot tell a header offset from the heart's
    motion between the runs, which view alignment already follows per key frame, and on data-re (exact
    headers) it made false corrections and raised CO's EPE 4.53 → 4.82 mm (docs/CALIBRATION.md).
    ``qca``: run the quantitative coronary analysis on the graphs (:mod:`stages.qca`: qca.json, qca.csv,
    plots, a report section). ``existing``: what to do with a non-empty ``out_dir`` — ``"refuse"``, ``"force"`` or ``"resume"``.
    ``progress(message)`` is told each stage; ``step(stage, done, total)`` each key frame of the slow ones.
    """
    from .core.runs import load_run, place_on_one_table

    more_runs = [Path(p) for p in more_runs or ()]
    more_geometries = list(more_geometries or ()) + [None] * (len(more_runs) - len(more_geometries or ()))
    check_options(method=method, seg_method=seg_method, side=side, k=k, weights=weights, geometry_a=geometry_a,
                  geometry_b=geometry_b, existing=existing, more_runs=more_runs, more_geometries=more_geometries)
    folder = OutputFolder(out_dir, force=existing == "force", resume=existing == "resume",
                          known_patterns=OUTPUT_PATTERNS)
    timer = _Timer()
    note = progress or (lambda msg: None)
    tick = step or (lambda stage, done, total: None)

    # every input is read and checked before the output folder is touched
    run_paths = [run_a, run_b, *more_runs]
    geometries = [geometry_a, geometry_b, *more_geometries]
    with timer("read runs"):
        runs = [load_run(path, geometry) for path, geometry in zip(run_paths, geometries)]
    warnings = _check_runs(runs, run_paths)
    # a table that moved between the runs (header or geometry JSON) moves the later runs' cameras into run A's frame
    table_offsets = place_on_one_table(runs, run_names(len(runs)))
    with timer(f"load {method}"):
        predict_3d = load_evidence_predictor(method, weights)

    parameters = {"method": method, "weights": str(weights) if weights else None, "seg_method": seg_method, "k": int(k),
                  "side": side, "align_views": bool(align_views), "qca": bool(qca), "calibrate": bool(calibrate),
                  "table_offsets_mm": table_offsets}
    if more_runs:
        parameters["more_runs"] = [str(p) for p in more_runs]
    folder.open("reconstruct", {"run_a": str(run_a), "run_b": str(run_b), **parameters})
    ctx = _Context(folder, runs, run_paths, geometries, parameters, timer, note, tick, warnings,
                   max(1, int(workers)))
    try:
        masks = _segment(ctx)
        kf = _keyframes(ctx, masks)
        masks["catheter"] = _catheter_maps(ctx, masks, kf)
        calibration = _calibrate(ctx, masks, kf) if calibrate else None
        pred = _predict(ctx, predict_3d, masks, kf)
        graphs = _graph_opt(ctx, pred)
        analysis = _qca(ctx) if qca else None
        return _finish(ctx, masks, kf, pred, graphs, analysis, calibration)
    except BaseException:
        folder.abandon()
        raise


@dataclass
class _Context:
    """What every stage of one reconstruction shares."""

    folder: OutputFolder
    runs: list
    run_paths: list
    geometries: list
    p: dict  # the parameters (method, weights, seg_method, k, side, align_views)
    timer: _Timer
    note: Callable
    tick: Callable
    warnings: list
    workers: int = 1  # key frames processed at once (threads); not a parameter: the outputs do not depend on it

    @property
    def out(self) -> Path:
        return self.folder.path


# Each stage below reuses its artefact on --resume when its fingerprint (inputs, parameters, the fingerprints
# of the stages it reads, the package version) matches the manifest's (stages.core.outputs), and otherwise
# computes and records it. Each returns a dict the later stages read, with its fingerprint under "fp".

def segment_fingerprint(run_path, geometry, seg_method: str) -> str:
    """The segmentation stage's fingerprint: a run's file, its geometry JSON, the method and the version (also
    what `autocar batch` compares to tell an up-to-date study folder without reading its runs)."""
    return fingerprint("segment", run=file_identity(run_path), geometry=file_identity(geometry) if geometry else None,
                       method=seg_method, version=__version__)


def _segment(ctx: _Context) -> dict:
    """Vessel masks of every run: masks_a.zarr, masks_b.zarr (masks_c.zarr … for further runs)."""
    from .segment import read_masks, segment_run, write_masks

    ctx.note("segmenting vessels")
    res, fps = [], []
    with ctx.timer("segment"):
        n_runs = len(ctx.runs)
        ctx.tick("segmentation, runs", 0, n_runs)
        for n, (run, name) in enumerate(zip(ctx.runs, view_keys(n_runs))):
            fp = segment_fingerprint(ctx.run_paths[n], ctx.geometries[n], ctx.p["seg_method"])
            path = ctx.out / f"masks_{name}.zarr"
            if ctx.folder.reusable(f"masks_{name}", fp):
                m = read_masks(path)
            else:
                m = segment_run(run, method=ctx.p["seg_method"])
                if not np.asarray(m["mask"]).any():
                    raise UserError(f"{run.path}: no vessel found in any frame (a run without contrast?)")
                write_masks(path, m)
                ctx.folder.record(f"masks_{name}", fp, [path])
            res.append(m)
            fps.append(fp)
            ctx.tick("segmentation, runs", n + 1, n_runs)
    return {"masks": [m["mask"] for m in res], "prob": [m["prob"] for m in res], "fp": fps}


def _keyframes(ctx: _Context, masks: dict) -> dict:
    """Phase-matched frame pairs: keyframes.zarr + keyframes.png. ``pairs`` without repeats; ``more``: per further
    run, its frame at each pair's phase (None where none matches)."""
    from .keyframe import keyframe_pairs, match_further_run, plot_keyframes, write_keyframes

    ctx.note("selecting key frames")
    fp = fingerprint("keyframe", masks=masks["fp"], k=ctx.p["k"])
    with ctx.timer("keyframe"):
        if ctx.folder.reusable("keyframes", fp):
            d = ctx.folder.data("keyframes")
        else:
            res = keyframe_pairs(ctx.runs[0], ctx.runs[1], masks_a={"prob": masks["prob"][0], "mask": masks["masks"][0]},
                                 masks_b={"prob": masks["prob"][1], "mask": masks["masks"][1]}, k=ctx.p["k"])
            write_keyframes(ctx.out / "keyframes.zarr", res)
            plot_keyframes(ctx.out / "keyframes.png", res)
            d = {"pairs": [[int(i), int(j)] for i, j in res["pairs"]], "warnings": list(res["warnings"]),
                 "phase": {key: [float(v) for v in np.asarray(res["estimates"][key]["phase"])] for key in "ab"}}
            pairs = list(dict.fromkeys((int(i), int(j)) for i, j in d["pairs"]))
            d["more"] = []
            for n, name in zip(range(2, len(ctx.runs)), run_names(len(ctx.runs))[2:]):
                m = match_further_run(res["estimates"]["a"]["phase"], [i for i, _ in pairs], ctx.runs[n],
                                      {"prob": masks["prob"][n], "mask": masks["masks"][n]}, name=name)
                d["more"].append(m)
                d["warnings"] += m["warnings"]
            ctx.folder.record("keyframes", fp, ["keyframes.zarr", "keyframes.png"], data=d)
    ctx.warnings.extend(d["warnings"])
    pairs = list(dict.fromkeys((int(i), int(j)) for i, j in d["pairs"]))  # repeats add nothing to a static model
    return {"pairs": pairs, "phase": d["phase"], "more": d.get("more", []), "fp": fp}


def _predict(ctx: _Context, predict_3d, masks: dict, kf: dict) -> dict:
    """Per key frame the 3D prediction with view B aligned to view A: predictions.zarr. Returns per key frame
    the views the prediction was made with (view key → (frame index, camera)) and view B's shift."""
    from .graph.io import PredictionFrame, read_sparse_predictions, write_sparse_predictions

    method, pairs = ctx.p["method"], kf["pairs"]
    fp = fingerprint("predict", keyframes=kf["fp"], method=method, side=ctx.p["side"], align_views=ctx.p["align_views"],
                     calibrate=ctx.p.get("calibrate", False), table=ctx.p.get("table_offsets_mm") or None,
                     weights=file_identity(ctx.p["weights"]) if ctx.p["weights"] else None, version=__version__)
    if ctx.folder.reusable("predictions", fp):
        ctx.note(f"3D prediction ({method}): reused from {ctx.out / 'predictions.zarr'}")
        _, frames = read_sparse_predictions(ctx.out / "predictions.zarr")
        return {"views": [{v: (int(f.source_frames[v]), f.cameras[v]) for v in sorted(f.cameras)} for f in frames],
                "shifts": ctx.folder.data("predictions")["view_b_shifts"],
                "further_runs": ctx.folder.data("predictions").get("further_runs") or {}, "fp": fp}
    ctx.note(f"3D prediction ({method}) on {len(pairs)} key frame(s)")
    cam_a, cam_b0 = ctx.runs[0].camera, ctx.runs[1].camera
    shifts: list = [None] * len(pairs)
    fitted = [ViewShift.none()] * len(pairs)
    if ctx.p["align_views"]:
        ctx.note("aligning view B to view A per key frame")
        with ctx.timer("align views"):
            curves = [mismatch_curve(masks["masks"][0][ia], masks["masks"][1][ib], cam_a, cam_b0) for ia, ib in pairs]
            fitted = estimate_run_shifts(curves, [ia for ia, _ in pairs], [ib for _, ib in pairs])
            shifts = [est.to_dict(cam_b0.isocentre_spacing) for est in fitted]
    frames, views = [], []
    label = f"3D prediction ({method}), key frames"
    view_masks = [(np.asarray(masks["masks"][0][ia], bool), np.asarray(masks["masks"][1][ib], bool)) for ia, ib in pairs]
    # the further runs' frames of each key frame's phase: view key → (frame index, mask, camera); not aligned per key
    # frame (their shift is not checked like view B's), the table placement and the phase match place them
    further = [{key: (m["frames"][n], np.asarray(masks["masks"][r][m["frames"][n]], bool), ctx.runs[r].camera)
                for r, key, m in zip(range(2, len(ctx.runs)), view_keys(len(ctx.runs))[2:], kf["more"])
                if m["frames"][n] is not None} for n in range(len(pairs))]

    reports = [{} for _ in pairs]  # per key frame: further view index (2, 3 …) → consistency with A + B, used

    def one(n):
        return predict_with_checked_shift(predict_3d, *view_masks[n], cam_a, cam_b0, fitted[n], ctx.p["side"],
                                          extra=[(mask, cam) for _, mask, cam in further[n].values()],
                                          report=reports[n])

    with ctx.timer(f"3D prediction ({method})"):
        ctx.tick(label, 0, len(pairs))
        # key frames are independent: with workers > 1 (`--threads`) the methods of KEY_FRAME_THREADED predict them
        # in threads, whose compiled kernels and NumPy calls release the GIL; results are taken in key-frame order
        workers = ctx.workers if method in KEY_FRAME_THREADED else 1
        with ThreadPoolExecutor(max(1, min(workers, len(pairs)))) as pool:
            futures = [pool.submit(one, n) for n in range(len(pairs))]
            for done, _ in enumerate(as_completed(futures), 1):
                ctx.tick(label, done, len(pairs))
        consistency = {key: [None] * len(pairs) for key in view_keys(len(ctx.runs))[2:]}
        further_shifts = {key: [None] * len(pairs) for key in view_keys(len(ctx.runs))[2:]}
        names = dict(zip(view_keys(len(ctx.runs)), run_names(len(ctx.runs))))
        run_by_view = dict(zip(view_keys(len(ctx.runs)), ctx.runs))  # view key → its run (the key frames' X-ray images)
        run_index = {key: r for r, key in enumerate(view_keys(len(ctx.runs)))}
        for n, ((ia, ib), (ma, mb), fut) in enumerate(zip(pairs, view_masks, futures)):
            vox, cam_b, kept = fut.result()
            moved = reports[n].get(1)  # view B moved to where the further runs place it
            if moved is not None:
                cam_b = cam_b.shifted(*moved["shift_px"])
            for index, key in enumerate(list(further[n])):
                r = reports[n].get(index + 2)
                if r is None:
                    continue
                consistency[key][n] = r["consistency"]
                further_shifts[key][n] = r["shift_px"]
                if r["used"] and any(r["shift_px"]):  # the image shift that placed it on runs A and B's model
                    i, mask, cam = further[n][key]
                    further[n][key] = (i, mask, cam.shifted(*r["shift_px"]))
                if not r["used"]:  # its vessels do not agree with runs A and B: another tree, phase or geometry
                    del further[n][key]
                    share = "none" if r["consistency"] is None else f"{100 * r['consistency']:.0f} %"
                    ctx.warnings.append(f"{names[key]}: key frame {n:02d}: {share} of runs A and B's model lies on its "
                                        "vessels (needs 45 %): not the same tree at this phase (another injection, "
                                        "phase or geometry?); left out of this key frame")
                    log.warning(ctx.warnings[-1])
            if fitted[n].applied and not kept:
                shifts[n] = {**ViewShift.none(fitted[n].mismatch_header).to_dict(cam_b0.isocentre_spacing),
                             "rejected_across_px": shifts[n]["across_px"]}
            if moved is not None:
                shifts[n] = {**(shifts[n] or {}), "further_runs_px": moved["shift_px"]}
            # the overlays and checks reproject with the cameras the model was built for
            views.append({"a": (int(ia), cam_a), "b": (int(ib), cam_b),
                          **{key: (int(i), cam) for key, (i, _, cam) in further[n].items()}})
            labelled = {key: vessel_labels(mask, masks["catheter"][run_index[key]].get(i))
                        for key, i, mask in (("a", ia, ma), ("b", ib, mb),
                                             *((key, i, mask) for key, (i, mask, _) in further[n].items()))}
            frames.append(PredictionFrame(f"{n:02d}", vox, labelled,
                                          {key: cam for key, (_, cam) in views[-1].items()},
                                          {key: i for key, (i, _) in views[-1].items()},
                                          {key: run_by_view[key].frames[i] for key, (i, _) in views[-1].items()}))
        write_sparse_predictions(ctx.out / "predictions.zarr", frames, case_id=Path(str(ctx.runs[0].path)).stem,
                                 stage="reconstruct", inputs=[str(r.path) for r in ctx.runs],
                                 parameters={"method": method, "pairs": [list(q) for q in pairs],
                                             "align_views": bool(ctx.p["align_views"]), "view_b_shifts": shifts})
    further_report = {"consistency": consistency, "shift_px": further_shifts}
    ctx.folder.record("predictions", fp, ["predictions.zarr"], data={"view_b_shifts": shifts,
                                                                     "further_runs": further_report})
    return {"views": views, "shifts": shifts, "further_runs": further_report, "fp": fp}


def _graph_opt(ctx: _Context, pred: dict) -> dict:
    """Tracked vascular graphs: graphs.zarr and graphs_<k>.vtp/.stl/.json."""
    from .graph.io import read_vascular_graphs
    from .graph.stage import run_graph_opt

    fp = fingerprint("graph-opt", predictions=pred["fp"], version=__version__)
    if ctx.folder.reusable("graphs", fp):
        ctx.note("graph optimisation: reused")
        summary = ctx.folder.data("graphs")["summary"]
    else:
        ctx.note("graph optimisation")
        label = "graph optimisation, key frames"
        with ctx.timer("graph-opt"):
            ctx.tick(label, 0, len(pred["views"]))
            summary = run_graph_opt(ctx.out / "predictions.zarr", ctx.out / "graphs.zarr", workers=ctx.workers,
                                    progress=lambda done, total: ctx.tick(label, done, total))
        summary["written"] = [Path(w).name for w in summary.get("written", [])]
        ctx.folder.record("graphs", fp, summary["written"], data={"summary": summary})
    _, tracked = read_vascular_graphs(ctx.out / "graphs.zarr")
    return {"summary": summary, "tracked": tracked, "fp": fp}


def _catheter_maps(ctx: _Context, masks: dict, kf: dict) -> list[dict]:
    """Per run, {key frame index: H×W bool}: the pixels of its vessel mask that are the catheter the run shows
    before its contrast arrives (:func:`stages.core.catheter.precontrast_catheter`; empty for a run without frames
    before the contrast). The masks keep them: a catheter is one 3D object in every view, evidence for aligning
    and placing the runs, and graph-opt drops the tree's stretch that lies on it."""
    from .core.catheter import precontrast_catheter, precontrast_frames

    used = [{i for i, _ in kf["pairs"]}, {j for _, j in kf["pairs"]},
            *({i for i in m["frames"] if i is not None} for m in kf["more"])]
    maps = []
    with ctx.timer("catheter"):
        for stack, frames in zip(masks["masks"], used):
            before = precontrast_frames(stack)
            maps.append({} if before is None else {i: precontrast_catheter(stack[i], before) for i in sorted(frames)})
    found = _catheter_pixels(maps)
    if found:
        ctx.note("catheter seen before the contrast arrived: " + ", ".join(
            f"{name} {px} px per key frame" for name, px in found.items()))
    return maps


def _catheter_pixels(maps: list[dict]) -> dict:
    """Per run name, the pixels per key frame its catheter took (:func:`_catheter_maps`; runs without any left out)."""
    return {name: round(float(np.mean([m.sum() for m in per.values()])))
            for name, per in zip(run_names(len(maps)), maps) if per and any(m.any() for m in per.values())}


def _calibrate(ctx: _Context, masks: dict, kf: dict) -> dict:
    """Self-calibration of run B (and every further run) against run A on the first key frame; replaces their
    cameras for every later stage when the calibration was applied. Returns its report (corrections, residuals)."""
    from .calibration import calibrate_runs

    ctx.note("self-calibrating the C-arm geometry from the vessels")
    ia, ib = kf["pairs"][0]
    frames = [ia, ib, *(m["frames"][0] for m in kf["more"])]
    used = [(r, i) for r, i in enumerate(frames) if i is not None]
    names = [view_keys(len(ctx.runs))[r].upper() for r, _ in used]  # "A", "B", "C" …
    with ctx.timer("calibrate"):
        try:
            cams, report = calibrate_runs([np.asarray(masks["masks"][r][i], bool) for r, i in used],
                                          [ctx.runs[r].camera for r, _ in used], names)
        except UserError as exc:  # e.g. too little vessel to calibrate on: keep the header geometry, say so
            cams, report = None, {"method": "none", "applied": False, "corrections": {}, "warnings": [str(exc)]}
    if report.get("applied"):
        for (r, _), cam in zip(used, cams):
            ctx.runs[r].camera = cam
    ctx.warnings.extend(f"calibration: {w}" for w in report.get("warnings", []))
    return report


def _qca(ctx: _Context) -> dict | None:
    """Quantitative coronary analysis of the graphs: qca.json, qca.csv and its plots (cheap: always redone)."""
    from .qca import qca_for_reconstruction

    ctx.note("quantitative coronary analysis")
    with ctx.timer("qca"):
        try:
            doc = qca_for_reconstruction(ctx.out)
        except UserError as exc:  # the reconstruction itself is complete: say why the analysis is missing
            ctx.warnings.append(f"QCA not run: {exc}")
            return None
    sr = doc.get("sr") or {}
    ctx.folder.add_files(["qca.json", "qca.csv", *[Path(p).name for p in doc.get("plots") or []],
                          *([sr["file"]] if sr.get("file") else [])])
    if doc.get("message"):
        ctx.warnings.append(f"QCA: {doc['message']}")
    elif sr.get("reason"):
        ctx.warnings.append(f"QCA: {sr['reason']}")
    return doc


def _run_rows(ctx: _Context, pred: dict) -> list[dict]:
    """summary.json's per-run rows: path, view key, C-arm angles, table offset, the frame used per key frame (None:
    no frame of that phase, or left out as inconsistent) and, for further runs, per key frame the share of runs A
    and B's model that lies on its vessels and the image shift that placed it there."""
    from .qca.views import carm_angles

    rows = []
    offsets = ctx.p.get("table_offsets_mm") or {}
    further = pred.get("further_runs") or {}
    for name, key, run in zip(run_names(len(ctx.runs)), view_keys(len(ctx.runs)), ctx.runs):
        alpha, beta = carm_angles(run.camera)
        rows.append({"run": name, "view": key, "path": str(run.path), "alpha_deg": round(float(alpha), 2),
                     "beta_deg": round(float(beta), 2), "table_offset_mm": offsets.get(name),
                     "frames": [views[key][0] if key in views else None for views in pred["views"]],
                     **{field: further[field][key] for field in ("consistency", "shift_px")
                        if key in further.get(field, {})}})
    return rows


def _finish(ctx: _Context, masks: dict, kf: dict, pred: dict, graphs: dict, analysis: dict | None = None,
            calibration: dict | None = None) -> dict:
    """Quality checks, overlays, report.html and summary.json (cheap: always redone); the run's last act."""
    from .quality import frame_quality, summarise
    from .report import camera_view

    ctx.note("quality checks, overlays and report")
    runs, pairs, phases, tracked = ctx.runs, kf["pairs"], kf["phase"], graphs["tracked"]
    names, keys = run_names(len(runs)), view_keys(len(runs))
    overlays, frames_model, checks = [], [], []
    with ctx.timer("quality + overlays + report"):
        for n, ((ia, ib), key) in enumerate(zip(pairs, tracked.keys)):
            graph, views = tracked.graphs[n], pred["views"][n]  # view key → (frame index, camera)
            run_of = {v: keys.index(v) for v in views}
            cams = [cam for _, cam in views.values()]
            checks.append(frame_quality(graph, {v: masks["masks"][run_of[v]][i] for v, (i, _) in views.items()},
                                        {v: cam for v, (_, cam) in views.items()}, key=key))
            png = ctx.out / f"overlay_{key}.png"
            _overlay_png(png, [runs[run_of[v]].frames[i] for v, (i, _) in views.items()], cams, graph,
                         [f"{names[run_of[v]]} frame {i}" + (f" (phase {phases[v][i]:.2f})" if v in phases else "")
                          for v, (i, _) in views.items()])
            overlays.append((key, png))
            centre = graph.nodes.mean(0) if len(graph) else np.zeros(3)
            frames_model.append({"key": key, "nodes": graph.nodes, "radius": graph.radius, "edges": graph.edges,
                                 "phase": {"a": phases["a"][ia], "b": phases["b"][ib]},
                                 "cameras": {v: camera_view(c, centre) for v, (_, c) in views.items()},
                                 "one_view": checks[-1]["one_view_segments"]})
        quality = summarise(checks)
        rows = [*((name, Path(str(run.path))) for name, run in zip(names, runs)), ("3D method", ctx.p["method"]),
                ("segmentation", ctx.p["seg_method"]), ("key frames (A, B)", pairs)]
        for name, m in zip(names[2:], kf["more"]):
            rows.append((f"{name}: frame at each key frame's phase", ", ".join("—" if i is None else str(i)
                                                                             for i in m["frames"])))
        rows.append(("quality", quality["verdict"]))
        for name, d in (ctx.p.get("table_offsets_mm") or {}).items():
            rows.append((f"{name}: table moved from run A's (x, y, z mm), camera placed accordingly",
                         ", ".join(f"{v:+.1f}" for v in d)))
        if calibration is not None:
            from .calibration.stage import summary_lines

            rows.append(("self-calibration", "; ".join(summary_lines(calibration))))
        if ctx.folder.reused:
            rows.append(("reused from an earlier run (--resume)", ", ".join(ctx.folder.reused)))
        catheter_px = _catheter_pixels(masks["catheter"])
        if catheter_px:
            rows.append(("catheter seen before the contrast arrived (px per key frame; the tree's stretch on it dropped)",
                         ", ".join(f"{name} {px}" for name, px in catheter_px.items())))
        if ctx.p["align_views"]:
            rows.append(("run B aligned (shift across the epipolar lines, mm)",
                         ", ".join(f"{s['across_mm']:+.2f}" for s in pred["shifts"] if s and "across_mm" in s)))
        moved = [np.hypot(*s["further_runs_px"]) for s in pred["shifts"] if s and "further_runs_px" in s]
        if moved:
            rows.append(("run B placed by the further runs (breathing along its epipolar lines, their model across; px)",
                         f"{len(moved)} key frame(s), {min(moved):.1f} … {max(moved):.1f}"))
        rows += [(f"graph {f['key']}", f"{f['nodes']} nodes, {f['bifurcations']} bifurcations, {f['length_mm']:.0f} mm")
                 for f in graphs["summary"].get("frames", []) if isinstance(f, dict) and "key" in f]
        sections = ""
        if analysis is not None:
            from .qca import html_section

            sections = html_section(analysis)
        write_report(ctx.out / "report.html", title="AutoCAR reconstruction", summary_rows=rows, timings=ctx.timer.rows,
                     frames_model=frames_model, overlays=overlays, warnings=ctx.warnings, quality=quality,
                     sections=sections, qca=analysis)
        ctx.folder.add_files([png for _, png in overlays] + ["report.html"])
    summary = {"output": str(ctx.out), "method": ctx.p["method"], "pairs": [list(q) for q in pairs],
               "view_b_shifts": pred["shifts"], "timings": ctx.timer.rows,
               "total_seconds": float(sum(t for _, t in ctx.timer.rows)), "warnings": ctx.warnings,
               "graph": graphs["summary"], "quality": quality, "reused": list(ctx.folder.reused), "parameters": ctx.p,
               "calibration": calibration, "table_offsets_mm": ctx.p.get("table_offsets_mm") or {},
               "runs": _run_rows(ctx, pred), "catheter_px": catheter_px,
               "qca": None if analysis is None else {"vessels": [{"name": v["name"], "length_mm": v["length_mm"],
                                                                  "lesions": len(v.get("lesions", [])),
                                                                  "unconfirmed_narrowings": len(v.get("unconfirmed_narrowings", []))}
                                                                 for v in analysis.get("vessels", [])],
                                                     "message": analysis.get("message")}}
    ctx.folder.finish(summary)
    return summary
