"""Diagnosis: what a key frame's final tree is made of, and where its error lies → docs/benchmarks/final_tree_origin.md.

Part 1, the real phantom (the 28 pair reconstructions `bench_join_pieces.py` caches in out/join_pieces/): graph-opt's
per-frame graph is rebuilt from each pair's 3D prediction, and every stretch of it is labelled by where it came
from — the 3D step (thinned from its voxels), the completion (branches both views show that the prediction
missed), or the joining (paths through every view's vessels between pieces). Each stretch, sampled every 0.5 mm,
is scored in the six held-out runs with their poses fitted to the whole tree (as the held-out check fits them):
its mean distance to their centrelines, averaged over the runs.

Part 2, data-re (Table 2's reconstructions of the default method, its row CO, in out/table2/CO/): each key frame's own
graph against the tracked graph graph-opt hands on (the same topology in every key frame, pieces seen in other key
frames included), scored like Table 2 (coverage / EPE / accuracy on the simulator's correspondences, and the two
directed 3D centreline distances to the truth at the key-frame pair's midpoint).

Run:  python benchmarks/diagnose_final_tree.py [--cases 20]   (after bench_join_pieces.py and table2.py --only CO)
"""

from __future__ import annotations

import argparse
import itertools
import json
import os
import sys
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")
ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))
PHANTOM = ROOT.parent / "shared" / "data" / "phantom_xa"
ORIGINS = ("3D step", "completion", "joining")


def labelled_frame_graph(folder: Path):
    """The pair's per-frame graph (graph-opt's inputs, as `reconstruct` builds them) and an origin index per node
    (:data:`ORIGINS`). The completion and the joining give their new nodes new ids; they are read off by wrapping
    the two steps."""
    import numpy as np

    import stages.graph.stage as stage
    from stages.graph.io import read_sparse_predictions

    seen: dict = {}
    complete, join = stage.complete_from_views, stage.join_pieces_through_views

    def completing(g, *args, **kw):
        out = complete(g, *args, **kw)
        seen["completion"] = set(out.node_id.tolist()) - set(g.node_id.tolist())
        return out

    def joining(g, *args, **kw):
        out = join(g, *args, **kw)
        seen["joining"] = set(out.node_id.tolist()) - set(g.node_id.tolist())
        return out

    stage.complete_from_views, stage.join_pieces_through_views = completing, joining
    try:
        _, frames = read_sparse_predictions([folder / "predictions.zarr"])
        g = stage.frames_to_inputs(frames, str(folder))[0].graph
    finally:
        stage.complete_from_views, stage.join_pieces_through_views = complete, join
    origin = np.array([2 if i in seen.get("joining", ()) else 1 if i in seen.get("completion", ()) else 0
                       for i in g.node_id.tolist()])
    return g, origin


def phantom_origins(cache: Path) -> list[str]:
    import numpy as np

    from stages.calibration.views import CAP_PX, fit_view_pose
    from stages.evaluate.heldout import in_views_frame, load_views, projected_distances

    views = load_views(PHANTOM, seg_method="unet")
    dist = {k: [] for k in ORIGINS}
    for a, b in itertools.combinations([v.name for v in views], 2):
        g, origin = labelled_frame_graph(cache / f"{a}+{b}")
        edge_origin = np.maximum(origin[g.edges[:, 0]], origin[g.edges[:, 1]])  # an edge into a new node is its step's
        P, _, owner = g.sample(0.5, with_edges=True)
        P, owner = P[owner >= 0], owner[owner >= 0]  # the points on the edges (not the end nodes appended)
        P = in_views_frame(P, views, a)
        per_run = []
        for v in views:
            if v.name in (a, b):
                continue
            camera = fit_view_pose(P, v.camera, np.minimum(v.dist_to_centreline, CAP_PX), v.fov, centreline=v.centreline)[0]
            per_run.append(projected_distances(P, v, camera))
        with np.errstate(all="ignore"):
            d = np.nanmean(np.array(per_run), axis=0)
        for k, name in enumerate(ORIGINS):
            keep = (edge_origin[owner] == k) & np.isfinite(d)
            dist[name].append(d[keep])
        print(f"{a}+{b}", flush=True)
    total = sum(len(np.concatenate(v)) for v in dist.values())
    lines = ["| origin | share of the tree's length | length per tree (mm, mean) | held-out distance (mm, mean) | "
             "share > 3 mm | its part of the tree's mean distance (mm) |", "|---|---|---|---|---|---|"]
    for name in ORIGINS:
        d = np.concatenate(dist[name])
        lines.append(f"| {name} | {len(d) / total:.2f} | {len(d) * 0.5 / len(dist[name]):.0f} | {d.mean():.2f} | "
                     f"{(d > 3).mean():.2f} | {d.sum() / total:.2f} |")
    return lines


def tracked_against_own(table2: Path, data: Path, limit: int | None) -> list[str]:
    import numpy as np

    from stages.core.metrics import graph_metrics
    from stages.core.runs import load_run
    from stages.evaluate import Prediction, evaluate_correspondences, truth_correspondences
    from stages.graph.io import read_sparse_predictions, read_vascular_graphs
    from stages.graph.stage import frames_to_inputs
    from stages.render.acquire import load_truth

    keys = ("coverage", "epe_mm", "accuracy", "centreline_pred_to_truth_mm", "centreline_truth_to_pred_mm")
    means: dict = {"own": [], "tracked": []}
    lengths: dict = {"own": [], "tracked": []}
    for out in sorted(p for p in table2.glob("case_*") if (p / "graphs.zarr").exists())[:limit]:
        case = data / out.name
        truth = load_truth(case / "truth.zarr")
        cam_a, cam_b = load_run(case / "run_a.dcm").camera, load_run(case / "run_b.dcm").camera
        pairs = json.loads((out / "summary.json").read_text())["pairs"]
        _, frames = read_sparse_predictions([out / "predictions.zarr"])
        _, tracked = read_vascular_graphs(out / "graphs.zarr")
        own = frames_to_inputs(frames, str(out))
        rows: dict = {"own": [], "tracked": []}
        for k, (ia, ib) in enumerate(pairs):
            ann = truth_correspondences(truth, cam_a, cam_b, ia, ib, 60, [int(truth["attrs"]["seed"]), k])
            ann["camera_b"] = frames[k].cameras.get("b", cam_b)
            mid = 0.5 * (truth["a"]["nodes"][ia].astype(float) + truth["b"]["nodes"][ib].astype(float))
            for name, g in (("own", own[k].graph), ("tracked", tracked.graphs[k])):
                graph = (g.nodes, g.radius, g.edges)
                r = evaluate_correspondences(Prediction("", None, graph), ann)
                r.update(graph_metrics(graph, (mid, truth["radius"].astype(float), truth["edges"])))
                rows[name].append([r[key] for key in keys])
                lengths[name].append(len(g.sample(0.5)[0]) * 0.5)
        for name in rows:
            means[name].append(np.nanmean(np.array(rows[name], float), axis=0))
        print(out.name, flush=True)
    lines = ["| graph | cases | length per key frame (mm, mean) | coverage | EPE (mm) | accuracy | recon → truth (mm) | "
             "truth → recon (mm) |", "|---|---|---|---|---|---|---|---|"]
    for name, label in (("own", "each key frame's own graph"), ("tracked", "the tracked graph (graph-opt's output)")):
        m = np.mean(means[name], axis=0)
        lines.append(f"| {label} | {len(means[name])} | {np.mean(lengths[name]):.0f} | {m[0]:.3f} | {m[1]:.2f} | "
                     f"{m[2]:.3f} | {m[3]:.2f} | {m[4]:.2f} |")
    return lines


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--phantom-cache", type=Path, default=ROOT / "out" / "join_pieces")
    ap.add_argument("--table2", type=Path, default=ROOT / "out" / "table2" / "CO",
                    help="Table 2's reconstructions by the default method (its row CO)")
    ap.add_argument("--data", type=Path, default=ROOT / "data" / "re3", help="the data-re set Table 2 ran on")
    ap.add_argument("--cases", type=int, default=None, help="only the first N data-re cases")
    args = ap.parse_args(argv)
    from machine import load_average, write_section

    before = load_average()
    body = []
    if (args.phantom_cache / "IM1+IM2" / "predictions.zarr").exists() and (PHANTOM / "IM1.dcm").exists():
        body += ["The real phantom: every pair's per-frame graph, by where each stretch came from; distances in the six "
                 "held-out runs (U-Net centrelines, poses fitted to the tree).", "", *phantom_origins(args.phantom_cache), ""]
    else:
        body += [f"No phantom reconstructions under {args.phantom_cache} (run benchmarks/bench_join_pieces.py first).", ""]
    if args.table2.is_dir() and args.data.is_dir():
        body += ["data-re, Table 2's reconstructions: each key frame's own graph against the tracked graph, Table 2's "
                 "measures.", "", *tracked_against_own(args.table2, args.data, args.cases), ""]
    else:
        body += [f"No Table 2 reconstructions under {args.table2} or no data under {args.data}.", ""]
    body.append(f"Load average before: {before}; after: {load_average()}.")
    command = "python benchmarks/diagnose_final_tree.py" + (f" --cases {args.cases}" if args.cases else "")
    path = write_section("final_tree_origin", "What the final tree is made of, and where its error lies", command,
                         "\n".join(body))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
