"""End-to-end evaluation on a simulated two-run set (data-re, ``make data-re``) — Table 2's protocol.

Rows are ``NAME=METHOD[:WEIGHTS]`` (methods of :mod:`stages.methods3d`). Each (row, case) runs the whole
pipeline (:func:`stages.reconstruct.reconstruct`: our segmentation, our key frames, the 3D method, graph
optimisation) into ``<out>/<NAME>/<case>/`` and is scored by :func:`stages.evaluate.score_dynamic_reconstruction`
(a ``graph`` row after graph optimisation, a ``nograph`` row on the per-frame predictions before it).

Reads: ``<data>/case_*/run_{a,b}.dcm`` and ``truth.zarr`` (``autocar.xa-truth``). Writes every
reconstruction's folder, and its ``cache_key.txt``: a reconstruction is reused when that file matches the
hash of everything that decides it — the two DICOM runs, the 3D method and its weights file, the
segmenter's weights and :data:`PIPELINE_VERSION` (bump it when the pipeline's code changes what it writes).
:func:`process_pool` runs cases in worker processes (one torch thread each). The caller
(benchmarks/table2.py) writes the documents.
"""

from __future__ import annotations

import hashlib
import time
from pathlib import Path

from ..core.artefacts import hash_file
from ..segment.weights import DEFAULT_WEIGHTS as SEG_WEIGHTS

STAGES = Path(__file__).resolve().parents[1]

# bump when the pipeline's code changes what it writes. 2: field of view = convex hull (stages.segment.infer);
# 3: key frames skip wash-out (stages.keyframe); 4: graph occupancy threshold 0.2; 5: key frames relax the
# fill fraction to cover every phase (stages.keyframe); 6: graph-opt adds branches from the 2D views
# (stages.graph.complete); 7: graph-opt drops ghost branches (stages.graph.redundancy). (Dropping unpredicted
# branches, drop_unsupported_branches, is opt-in and off in the pipeline: the default graphs are unchanged.)
# 8: inter-run motion correction (stages.view_alignment); 9: its joint fit follows a slope and prefers small shifts;
# 10: a shift is kept only if the 3D prediction with it holds more confident voxels than without (the
# correspondence method: more matched points, its key says "shift-by-matches").
# 11: graph-opt: rotation smoothness in the deformation regulariser, a converging inverse warp.
# 12: graph-opt drops far pieces one view explains by the tree, and keeps later frames' floating pieces out.
# 13: and again on the tracked topology (stages.graph.stage.drop_far_tracked).
# 14: graph-opt joins each key frame's pieces through the views' vessels (stages.graph.join).
# 15: graph-opt's registration rounds in SciPy's L-BFGS-B (same energy and gradients).
# 16: graph-opt drops the guiding catheter's straight stretch (stages.graph.redundancy.drop_catheter_runs).
# 17: the registration's gradients in closed form (NumPy), the segmenter's batch norms folded (probabilities
#     within 2e-6), QCA reports only what both views show and what has lumen on both sides.
# 18: the predictions carry the key frames' X-ray images; graph-opt drops far pieces that are not contrast-filled
#     (stages.graph.redundancy.drop_faint_pieces); QCA needs one view to show a lesion.
# 19: a catheter cut near the image edge is found from its collinear pieces; graph-opt's completion from the views
#     grows branches from the tree only, is not vetoed by tubes of one occupancy level, skips catheters and
#     walks again what a failed path crossed.
# 20: the two-view selection finds implausible depths against the tree's own extent (stages.twoview.select.tree_extent),
#     not a fixed 130 mm from the isocentre.
# 21: graph-opt drops far pieces shorter than four lumen diameters (stages.graph.redundancy.drop_stubs since 40).
# 22: with three or more runs, pooled points that other pairs of views contradict and none corroborates are
#     dropped (stages.twoview.multiview.drop_contradicted); two runs unchanged.
# 23: with three or more runs, graph-opt's completion from the views keeps only depths that the further runs also
#     show as vessel (stages.graph.complete.GATE_PX).
# 24: two views: a point one direction found alone is kept only within 20 mm of a point both directions agree on
#     (stages.twoview.method.kept_points).
# 25: key frames: the contrast filling is measured on frames smoothed by 1 px (noise had made the noisiest frame look
#     the most filled; stages.keyframe.contrast_filling).
# 26: with three or more runs, a 3D point or tracked node that projects outside a view's image away from where that
#     view's vessels leave it is dropped (stages.core.geometry.outside_away_from_exits); two runs unchanged.
# 27: with three or more runs, graph-opt keeps a piece first seen in a later key frame only where three key frames'
#     own graphs pass it (stages.graph.stage.default_min_support_frames); two runs unchanged.
# 28: with three or more runs, view B is moved along its epipolar lines to where the further runs' shifts and the
#     breathing prior place the heart (stages.twoview.multiview.breathing_correction); two runs unchanged.
# 29: a further run whose filled frames miss a key frame's phase gives a frame filled to a lower fraction there
#     (down to 0.85, as for runs A and B; stages.keyframe.match_further_run); two runs unchanged.
# 30: graph-opt drops every piece apart from the main tree (not only far ones) that a view's image shows fainter than
#     half the tree's contrast per mm of radius (stages.graph.redundancy.drop_faint_pieces); with three or more runs
#     the joining accepts paths up to 100 mm (stages.graph.join.MAX_PATH_MM_MORE_VIEWS).
# 31: with three or more runs, the breathing prior weighs every run's offset from the mean breathing position, the
#     first run's too (stages.twoview.multiview.breathing_correction); two runs unchanged.
# 32: with three or more runs, where every further run's shift onto runs A + B's model lies beyond the search, view B
#     is first moved along its epipolar lines in steps (stages.twoview.multiview.ALONG_SEARCH_PX).
# 33: with three or more runs, view B is moved across its epipolar lines onto the model of run A with the further runs
#     (stages.twoview.multiview.across_from_further_views); two runs unchanged.
# 34: graph-opt prunes the spurs left on the tracked topology (stages.graph.stage.prune_spurs_tracked).
# 35: view B's shift across its epipolar lines is measured on the further runs' model a second time after it moved
#     (stages.twoview.multiview.ACROSS_ROUNDS); two runs unchanged.
# 36: graph-opt drops the tree's stretch on the catheter a run shows before its contrast arrives (masks label it,
#     stages.core.catheter.precontrast_catheter; stages.graph.stage.drop_catheter_tracked).
# 37: the straight-catheter rule takes only stretches climbing towards the head from the tree
#     (stages.core.catheter.CATHETER_MIN_RISE): straight vessels leaving the image downwards stay.
# 38: with one view showing the catheter before the contrast, graph-opt drops the stretch from a free end along it
#     (a catheter attached at a junction goes too); the quality check judges the segmenter's masks again.
# 39: with three or more views, graph-opt places the nodes another part of the tree overlaps in one view by the
#     views that see them alone (stages.graph.refit)
# 40: graph-opt drops every piece apart from the main tree shorter than four lumen diameters, near ones too
#     (stages.graph.redundancy.drop_stubs)
# 41: graph-opt drops a terminal branch both views explain elsewhere along half its length (was 0.7;
#     stages.graph.redundancy.drop_doubly_explained)
PIPELINE_VERSION = 41
# bump when the scoring of a reconstruction changes (the cached reconstructions stay valid; the committed
# per-case numbers do not). 2: view B's partners taken with the pipeline's motion-corrected view-B camera.
SCORING_VERSION = 2
# bump when the reconstruction from three runs changes (stages.twoview.multiview, the further runs' frames)
MULTIVIEW_VERSION = 1


def parse_rows(spec: str, default_weights=None) -> list[tuple[str, str, str | None]]:
    """``"sbp,VH=visual-hull,L7=sbp:w.pt"`` → [(name, method, weights)]."""
    rows = []
    for item in (s.strip() for s in spec.split(",") if s.strip()):
        name, _, rest = item.rpartition("=")
        method, _, weights = rest.partition(":")
        rows.append((name or method, method, weights or (default_weights if method == "sbp" else None)))
    return rows


def re_cases_or_say(data: Path, limit: int | None = None) -> list[Path]:
    """The data-re cases (with their truth sidecar), the first ``limit``; none: says so (nothing measured)."""
    cases = sorted(p for p in Path(data).glob("case_*") if (p / "truth.zarr").exists())
    if not cases:
        print(f"no cases with truth.zarr under {data}: run `make data-re` first. Nothing measured.")
    return cases[:limit] if limit else cases


def shipped_weights(method: str) -> Path | None:
    """The weights file a learned method loads when none is given."""
    if method == "sbp":
        from ..sbp.train import SHIPPED_WEIGHTS

        return SHIPPED_WEIGHTS
    if method == "dense":
        from ..baselines import default_weights

        return default_weights("dense")
    return None


def _inputs_key(method: str, weights, files=(), tag: str = "") -> str:
    """Hash of the pipeline version, ``method``, ``files``, the segmenter, the method's weights (and ``tag``)."""
    # the correspondence method's view-B shift is checked by its matched points (stages.methods3d), since v13
    checked_by = " shift-by-matches" if method == "correspondence" else ""
    h = hashlib.sha256(f"v{PIPELINE_VERSION} {method}{checked_by}{' ' + tag if tag else ''}".encode())
    if method == "correspondence":  # no weights: its code is what decides
        files = (*files, *sorted((STAGES / "twoview").glob("*.py")))
    for f in (*files, SEG_WEIGHTS, Path(weights) if weights else shipped_weights(method)):
        if f is not None and f.exists():
            h.update(f.name.encode())
            hash_file(h, f)
    return h.hexdigest()[:16]


def case_runs(case: Path, n_runs: int = 2) -> list[Path]:
    """The DICOM runs of a data-re case a reconstruction uses: run A, run B (and run C with three runs)."""
    runs = [case / "run_a.dcm", case / "run_b.dcm"] + ([case / "run_c.dcm"] if n_runs == 3 else [])
    for path in runs:
        if not path.exists():
            from ..core.errors import UserError

            raise UserError(f"{path}: missing ({n_runs} runs per case asked; `autocar render re --runs {n_runs}` "
                            "makes them)")
    return runs


def case_key(case: Path, method: str, weights, n_runs: int = 2) -> str:
    """Hash of everything that decides the reconstruction of ``case`` by ``method`` (see module doc)."""
    return _inputs_key(method, weights, tuple(case_runs(case, n_runs)),
                       tag="" if n_runs == 2 else f"{n_runs} runs, multiview {MULTIVIEW_VERSION}")


def inputs_fingerprint(method: str, weights) -> str:
    """What decides a row's numbers apart from the runs themselves — its reconstructions' inputs and the
    scoring version (recorded in docs/table2/<row>.json)."""
    return _inputs_key(method, weights, tag=f"scoring v{SCORING_VERSION}")


def run_case(job: tuple) -> dict:
    """One (row, case): reconstruct unless cached, then score. Returns {name, case, rows | refused}. ``job``: (name,
    method, weights, case, dst, points, fresh[, n_runs]); with 3 runs, run C adds its evidence (scored on A and B's
    annotations as with two)."""
    name, method, weights, case, dst, points, fresh, *more = job
    n_runs = int(more[0]) if more else 2
    from ..core.errors import UserError
    from ..core.threads import use_threads
    from . import score_dynamic_reconstruction, truth_side
    from ..reconstruct import reconstruct
    from ..render.acquire import load_truth
    from ..core.runs import load_run

    use_threads(1)  # the CLI's default: the same graphs whatever the environment says
    case, dst = Path(case), Path(dst)
    truth = load_truth(case / "truth.zarr")
    key = case_key(case, method, weights, n_runs)
    stamp = dst / "cache_key.txt"
    cached = not fresh and (dst / "summary.json").exists() and stamp.exists() and stamp.read_text().strip() == key
    t0 = time.perf_counter()
    if not cached:
        try:
            run_paths = case_runs(case, n_runs)
            reconstruct(run_paths[0], run_paths[1], dst, method=method, weights=weights, side=truth_side(truth),
                        more_runs=run_paths[2:])
        except UserError as exc:  # e.g. two runs too close in angle: the pipeline refuses, and says why
            return {"name": name, "case": case.name, "refused": str(exc)}
        stamp.write_text(key + "\n")
    wall = None if cached else time.perf_counter() - t0  # a cached case's time was not measured here
    runs = [load_run(case / "run_a.dcm"), load_run(case / "run_b.dcm")]
    rows = score_dynamic_reconstruction(dst, truth, runs, points, int(truth["attrs"]["seed"]))
    return {"name": name, "case": case.name, "cached": cached, "rows": {k: {"case": case.name, "wall_s": wall, **r}
                                                                          for k, r in rows.items()}}


def regraph_case(folder, data, out, points: int = 60, **graph_kw) -> dict:
    """Graph optimisation rerun on a finished reconstruction (``folder``: a :func:`run_case` output, its
    ``predictions.zarr`` reused) into ``out``, scored as :func:`run_case` scores, plus a census of the tracked
    graphs' far pieces (no chain of gaps ≤ FAR_PIECE_MM to the main tree): per piece its length, gap and median
    distance to the true tree at the key-frame pair's midpoint. Tunes graph-opt (``graph_kw`` go to
    :func:`stages.graph.stage.run_graph_opt`) without rerunning the 3D step."""
    import json
    import shutil

    import numpy as np
    from scipy.spatial import cKDTree

    from . import score_dynamic_reconstruction
    from ..core.runs import load_run
    from ..graph.io import read_vascular_graphs
    from ..graph.redundancy import FAR_PIECE_MM
    from ..graph.stage import run_graph_opt
    from ..render.acquire import load_truth

    folder, out = Path(folder), Path(out)
    case = Path(data) / folder.name
    out.mkdir(parents=True, exist_ok=True)
    shutil.copy(folder / "summary.json", out / "summary.json")
    if not (out / "predictions.zarr").exists():
        (out / "predictions.zarr").symlink_to((folder / "predictions.zarr").resolve())
    run_graph_opt(out / "predictions.zarr", out / "graphs.zarr", exports=False, **graph_kw)
    truth = load_truth(case / "truth.zarr")
    runs = [load_run(case / "run_a.dcm"), load_run(case / "run_b.dcm")]
    row = score_dynamic_reconstruction(out, truth, runs, points, int(truth["attrs"]["seed"]))["graph"]
    _, tracked = read_vascular_graphs(out / "graphs.zarr")
    far = []
    for (i, j), g in zip(json.loads((out / "summary.json").read_text())["pairs"], tracked.graphs):
        true_tree = cKDTree(0.5 * (truth["a"]["nodes"][i] + truth["b"]["nodes"][j]))
        label, lengths, gaps, order = g.pieces(FAR_PIECE_MM)
        far += [{"length_mm": float(lengths[c]), "gap_mm": float(gaps[c]),
                 "truth_mm": float(np.median(true_tree.query(g.nodes[label == c])[0]))}
                for c in order[1:] if gaps[c] > FAR_PIECE_MM]
    return {"case": folder.name, **{k: row[k] for k in ("coverage", "epe_mm", "accuracy", "centreline_pred_to_truth_mm",
                                                        "centreline_truth_to_pred_mm")},
            "far_pieces": far, "key_frames": len(tracked.graphs)}


def case_jobs(rows, cases, out, points: int = 60, fresh: bool = False) -> list[tuple]:
    """The :func:`run_case` jobs of every (row, case)."""
    return [(name, method, weights, str(case), str(Path(out) / name / case.name), points, fresh)
            for name, method, weights in rows for case in cases]


def log_result(res: dict, done: int, total: int, log=print) -> None:
    if "refused" in res:
        log(f"[{done}/{total}] {res['name']} {res['case']}: refused: {res['refused']}")
        return
    g = res["rows"]["graph"]
    took = " (cached)" if res["cached"] else f" ({g['seconds']:.1f} s)"
    log(f"[{done}/{total}] {res['name']} {res['case']}: coverage {g['coverage']:.3f} EPE {g['epe_mm']:.2f} mm "
        f"accuracy {g['accuracy']:.3f} centreline {g['centreline_error_mm']:.2f} mm{took}")


def collect(done: list[dict]) -> tuple[dict, dict]:
    """:func:`run_case` results (in job order) → ({row name or name-nograph: [per-case]}, {name: [refusals]})."""
    results, refused = {}, {}
    for res in done:
        if "refused" in res:
            refused.setdefault(res["name"], []).append({"case": res["case"], "reason": res["refused"]})
            continue
        for kind, row in res["rows"].items():
            results.setdefault(res["name"] if kind == "graph" else f"{res['name']}-nograph", []).append(row)
    return results, refused


def process_pool(jobs: int):
    """Worker processes for :func:`run_case` (spawned: each computes with one thread, :mod:`stages.core.threads`)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    return ProcessPoolExecutor(jobs, mp_context=mp.get_context("spawn"))
