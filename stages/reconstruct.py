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
* ``report.html`` — one page with the 3D model (drag to rotate), the overlays and the stage timings;
* ``summary.json`` — key-frame pairs, view B's shift per key frame (``view_b_shifts``; ``rejected_across_px``
  where the prediction overruled the fitted shift), timings, warnings.
"""

from __future__ import annotations

import html
import json
import logging
import time
from pathlib import Path

import numpy as np

from .artefacts import atomic_path, write_json
from .errors import UserError
from .methods3d import METHODS, load_predictor
from .view_alignment import ViewShift, estimate_run_shifts, mismatch_curve

log = logging.getLogger(__name__)



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


_VIEWER_JS = """
const model = JSON.parse(document.getElementById('model').textContent);
const canvas = document.getElementById('view3d'); const ctx = canvas.getContext('2d');
let yaw = 0.6, pitch = -0.3, frame = 0, drag = null;
function colour(t) { const h = 240 - 240 * t; return `hsl(${h},90%,50%)`; }
function draw() {
  const f = model.frames[frame]; ctx.fillStyle = '#111'; ctx.fillRect(0, 0, canvas.width, canvas.height);
  if (!f || f.nodes.length === 0) { return; }
  const c = model.centre, s = canvas.width / (1.2 * model.extent);
  const cy = Math.cos(yaw), sy = Math.sin(yaw), cp = Math.cos(pitch), sp = Math.sin(pitch);
  const P = f.nodes.map(p => { const x = p[0] - c[0], y = p[1] - c[1], z = p[2] - c[2];
    const x1 = cy * x + sy * y, y1 = -sy * x + cy * y; const y2 = cp * y1 - sp * z, z2 = sp * y1 + cp * z;
    return [canvas.width / 2 + s * x1, canvas.height / 2 - s * z2, y2]; });
  const order = f.edges.map((e, i) => i).sort((i, j) => (P[f.edges[j][0]][2] - P[f.edges[i][0]][2]));
  for (const i of order) { const [a, b] = f.edges[i]; ctx.strokeStyle = colour(0.5 * (f.pos[a] + f.pos[b]));
    ctx.lineWidth = Math.max(1, s * (f.radius[a] + f.radius[b])); ctx.lineCap = 'round';
    ctx.beginPath(); ctx.moveTo(P[a][0], P[a][1]); ctx.lineTo(P[b][0], P[b][1]); ctx.stroke(); }
}
canvas.onmousedown = e => drag = [e.clientX, e.clientY, yaw, pitch];
window.onmouseup = () => drag = null;
window.onmousemove = e => { if (drag) { yaw = drag[2] + (e.clientX - drag[0]) / 150; pitch = drag[3] + (e.clientY - drag[1]) / 150; draw(); } };
const slider = document.getElementById('frame'); slider.max = model.frames.length - 1;
slider.oninput = () => { frame = +slider.value; document.getElementById('frame_label').textContent = model.frames[frame].key; draw(); };
document.getElementById('frame_label').textContent = model.frames.length ? model.frames[0].key : '';
draw();
"""


def write_report(path, *, title: str, summary_rows, timings, frames_model, overlays, warnings) -> Path:
    """A self-contained HTML page: 3D model (canvas, drag to rotate, slider over key frames), overlays, tables."""
    allpts = np.concatenate([np.asarray(f["nodes"]) for f in frames_model if len(f["nodes"])]) if any(
        len(f["nodes"]) for f in frames_model) else np.zeros((1, 3))
    centre = allpts.mean(0)
    extent = float(np.ptp(allpts, axis=0).max()) if len(allpts) > 1 else 100.0
    model = {"centre": centre.tolist(), "extent": max(extent, 10.0), "frames": frames_model}
    rows = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(str(v))}</td></tr>" for k, v in summary_rows)
    trows = "".join(f"<tr><td>{html.escape(n)}</td><td>{t:.2f} s</td></tr>" for n, t in timings)
    imgs = "".join(f'<figure><img src="{html.escape(Path(p).name)}" alt="overlay {html.escape(k)}"><figcaption>key frame '
                   f"{html.escape(k)}</figcaption></figure>" for k, p in overlays)
    warn = "".join(f"<li>{html.escape(w)}</li>" for w in warnings) or "<li>none</li>"
    page = f"""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>
<style>body{{font-family:sans-serif;margin:1.5em;background:#fafafa}} table{{border-collapse:collapse;margin:0.5em 0}}
td{{border:1px solid #ccc;padding:2px 8px}} figure{{display:inline-block;margin:4px}} img{{max-width:900px}}
canvas{{border:1px solid #444;cursor:grab}}</style></head><body>
<h1>{html.escape(title)}</h1>
<h2>3D model</h2><p>Drag to rotate; the slider steps through the key frames. Colour: position along the tree.</p>
<canvas id="view3d" width="640" height="640"></canvas><br>
<input type="range" id="frame" min="0" value="0"> key frame <span id="frame_label"></span>
<h2>Summary</h2><table>{rows}</table>
<h2>Reprojection on both runs</h2>{imgs}
<h2>Stage timings</h2><table>{trows}</table>
<h2>Warnings</h2><ul>{warn}</ul>
<script type="application/json" id="model">{json.dumps(model)}</script>
<script>{_VIEWER_JS}</script>
</body></html>
"""
    with atomic_path(path) as tmp:
        tmp.write_text(page)
    return Path(path)


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


def reconstruct(run_a, run_b, out_dir, *, geometry_a=None, geometry_b=None, method: str = "sbp", weights=None,
                seg_method: str = "unet", k: int = 7, side: str = "left", align_views: bool = True,
                progress=None) -> dict:
    """Run the whole pipeline; returns a summary with per-stage timings. See the module docstring.

    ``align_views``: per key frame, shift view B's image to be epipolar-consistent with view A before the
    3D prediction (:mod:`stages.view_alignment`: the heart moves between the two runs' acquisitions).
    """
    from .graph.io import PredictionFrame, write_sparse_predictions
    from .graph.stage import run_graph_opt
    from .keyframe import keyframe_pairs, plot_keyframes, write_keyframes
    from .segment import load_run, save_overlays, segment_run, write_masks

    if method not in METHODS:
        raise UserError(f"unknown --method {method!r} (choose from {', '.join(METHODS)})")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    timer = _Timer()
    note = progress or (lambda msg: None)

    with timer("read runs"):
        runs = [load_run(run_a, geometry_a), load_run(run_b, geometry_b)]
    warnings = _check_runs(*runs)
    with timer(f"load {method}"):
        predict_3d = load_predictor(method, weights)

    note("segmenting vessels")
    masks = []
    with timer("segment"):
        for run, name in zip(runs, ("a", "b")):
            res = segment_run(run, method=seg_method)
            if not np.asarray(res["mask"]).any():
                raise UserError(f"{run.path}: no vessel found in any frame (a run without contrast?)")
            write_masks(out / f"masks_{name}.zarr", res)
            masks.append(res)
    note("selecting key frames")
    with timer("keyframe"):
        kf = keyframe_pairs(runs[0], runs[1], masks_a={"prob": masks[0]["prob"], "mask": masks[0]["mask"]},
                            masks_b={"prob": masks[1]["prob"], "mask": masks[1]["mask"]}, k=k)
        write_keyframes(out / "keyframes.zarr", kf)
        plot_keyframes(out / "keyframes.png", kf)
    warnings += kf["warnings"]
    pairs = list(dict.fromkeys(kf["pairs"]))  # repeated pairs add nothing to a static reconstruction

    note(f"3D prediction ({method}) on {len(pairs)} key frame(s)")
    cams = [runs[0].camera, runs[1].camera]
    frames, frame_cams, shifts = [], [], [None] * len(pairs)
    fitted = [ViewShift.none()] * len(pairs)
    if align_views:
        note("aligning view B to view A per key frame")
        with timer("align views"):
            curves = [mismatch_curve(masks[0]["mask"][ia], masks[1]["mask"][ib], cams[0], cams[1]) for ia, ib in pairs]
            fitted = estimate_run_shifts(curves, [ia for ia, _ in pairs], [ib for _, ib in pairs])
            shifts = [est.to_dict(cams[1].isocentre_spacing) for est in fitted]
    with timer(f"3D prediction ({method})"):
        for n, (ia, ib) in enumerate(pairs):
            ma, mb = np.asarray(masks[0]["mask"][ia], bool), np.asarray(masks[1]["mask"][ib], bool)
            vox, cam_b, kept = predict_with_checked_shift(predict_3d, ma, mb, cams[0], cams[1], fitted[n], side)
            if fitted[n].applied and not kept:
                shifts[n] = {**ViewShift.none(fitted[n].mismatch_header).to_dict(cams[1].isocentre_spacing),
                             "rejected_across_px": shifts[n]["across_px"]}
            frame_cams.append((cams[0], cam_b))  # the overlays reproject with the cameras the model was built for
            frames.append(PredictionFrame(f"{n:02d}", vox, {"a": ma.astype(np.uint8), "b": mb.astype(np.uint8)},
                                          {"a": cams[0], "b": cam_b}, {"a": int(ia), "b": int(ib)}))
        case_id = Path(str(runs[0].path)).stem
        write_sparse_predictions(out / "predictions.zarr", frames, case_id=case_id, stage="reconstruct",
                                 inputs=[str(runs[0].path), str(runs[1].path)],
                                 parameters={"method": method, "pairs": [list(p) for p in pairs],
                                             "align_views": bool(align_views), "view_b_shifts": shifts})
    note("graph optimisation")
    with timer("graph-opt"):
        graph_summary = run_graph_opt(out / "predictions.zarr", out / "graphs.zarr")
    from .graph.io import read_vascular_graphs

    _, tracked = read_vascular_graphs(out / "graphs.zarr")

    note("overlays and report")
    overlays, frames_model = [], []
    with timer("overlays + report"):
        for n, ((ia, ib), key) in enumerate(zip(pairs, tracked.keys)):
            graph = tracked.graphs[n]
            png = out / f"overlay_{key}.png"
            _overlay_png(png, [runs[0].frames[ia], runs[1].frames[ib]], frame_cams[n], graph,
                         [f"run A frame {ia} (phase {kf['estimates']['a']['phase'][ia]:.2f})",
                          f"run B frame {ib} (phase {kf['estimates']['b']['phase'][ib]:.2f})"])
            overlays.append((key, png))
            frames_model.append({"key": key, "nodes": np.round(graph.nodes, 2).tolist(),
                                 "radius": np.round(graph.radius, 2).tolist(), "edges": np.asarray(graph.edges).tolist(),
                                 "pos": np.round(graph.position_along_tree(), 3).tolist()})
        summary_rows = [("run A", runs[0].path), ("run B", runs[1].path), ("3D method", method),
                        ("segmentation", seg_method), ("key frames (A, B)", pairs)]
        if align_views:
            summary_rows.append(("run B aligned (shift across the epipolar lines, mm)",
                                 ", ".join(f"{s['across_mm']:+.2f}" for s in shifts)))
        summary_rows += [(f"graph {f['key']}", f"{f['nodes']} nodes, {f['bifurcations']} bifurcations, {f['length_mm']:.0f} mm")
                         for f in graph_summary.get("frames", []) if isinstance(f, dict) and "key" in f]
        write_report(out / "report.html", title="AutoCAR reconstruction", summary_rows=summary_rows,
                     timings=timer.rows, frames_model=frames_model, overlays=overlays, warnings=warnings)
    summary = {"output": str(out), "method": method, "pairs": [list(p) for p in pairs], "view_b_shifts": shifts,
               "timings": timer.rows,
               "total_seconds": float(sum(t for _, t in timer.rows)), "warnings": warnings, "graph": graph_summary}
    write_json(out / "summary.json", summary)
    return summary
