"""Where Table 2's accuracy is lost: every ground-truth query of every key frame of one row, by cause.

Reads the reconstructions Table 2 left in ``out/table2/<row>/<case>/`` (``python benchmarks/table2.py``
first) and the simulator's truth of each data-re case, and scores each query as Table 2 does
(:func:`stages.evaluate.truth_correspondences`, the pipeline's per-key-frame view-B camera; the nearest
model point in view A within the cover radius wins, where Table 2's ties within 0.5 px may pick another
of equal weight). A query that misses ε is put in one class:

* **uncovered** — no model point within the cover radius in view A (a missed vessel);
* **a correct partner was nearer second** — some model point within the cover radius in view A has
  its view-B partner within ε, but another one projects nearer the query in view A and wins: two
  model branches overlap in view A there. Split by whether the winner lies on the true tree elsewhere
  (two real vessels overlapping in A) or off it (a ghost overlapping a real vessel);
* **ghost** — no candidate is right and the winner lies more than 10 mm from the query's true 3D point;
* **misplaced** — no candidate is right, the winner is nearer than that (depth or shape error).

Run:  python benchmarks/diagnose_re_errors.py [--row L8] [--data data/re] [--cache out/table2]
Writes docs/benchmarks/re_errors_<row>.md. Cases without a reconstruction are skipped and counted.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from re_eval import re_cases_or_say  # noqa: E402

from stages.metrics import COVER_MM, EPSILON_MM  # noqa: E402

ON_TREE_MM = 2.0  # a model point this close to the true tree lies on a real vessel
GHOST_MM = 10.0  # a wrong winner this far from its query's true 3D point is on another structure
CLASSES = ("correct", "uncovered", "correct partner nearer second, winner on another true vessel",
           "correct partner nearer second, winner off the tree (ghost)", "ghost (no correct candidate)",
           "misplaced (no correct candidate)")


def classify_case(case: Path, out: Path, n_points: int = 60) -> np.ndarray:
    """Counts per class (order of :data:`CLASSES`) over the key frames of one reconstructed case."""
    from scipy.spatial import cKDTree

    from stages.evaluate import truth_correspondences
    from stages.graph.io import read_sparse_predictions, read_vascular_graphs
    from stages.metrics import sample_graph
    from stages.render.acquire import load_truth
    from stages.segment import load_run

    truth = load_truth(case / "truth.zarr")
    cam_a, cam_b_header = load_run(case / "run_a.dcm").camera, load_run(case / "run_b.dcm").camera
    pairs = json.loads((out / "summary.json").read_text())["pairs"]
    _, tracked = read_vascular_graphs(out / "graphs.zarr")
    _, frames = read_sparse_predictions([out / "predictions.zarr"])
    seed = int(truth["attrs"]["seed"])
    counts = np.zeros(len(CLASSES), int)
    for k, (ia, ib) in enumerate(pairs):
        ann = truth_correspondences(truth, cam_a, cam_b_header, ia, ib, n_points, [seed, k])
        cam_b = frames[k].cameras.get("b", cam_b_header)
        mid = 0.5 * (truth["a"]["nodes"][ia].astype(float) + truth["b"]["nodes"][ib].astype(float))
        g = tracked.graphs[k]
        pts, _ = sample_graph(g.nodes, g.radius, g.edges)
        if len(pts) == 0:
            counts[1] += len(ann["nodes"])
            continue
        qa, qb = cam_a.project(pts), cam_b.project(pts)
        in_a = cKDTree(qa)
        on_tree = cKDTree(mid).query(pts)[0] < ON_TREE_MM
        cover_px = COVER_MM / cam_a.isocentre_spacing
        for query_a, truth_b, node in zip(ann["pairs"][:, :2], ann["pairs"][:, 2:], ann["nodes"]):
            d0, win = in_a.query(query_a)
            if d0 > cover_px:
                counts[1] += 1
                continue
            err = np.linalg.norm(qb - truth_b, axis=1) * cam_b.isocentre_spacing
            if err[win] < EPSILON_MM:
                counts[0] += 1
            elif (err[in_a.query_ball_point(query_a, cover_px)] < EPSILON_MM).any():
                counts[2 if on_tree[win] else 3] += 1
            else:
                counts[4 if np.linalg.norm(pts[win] - mid[node]) > GHOST_MM else 5] += 1
    return counts


def main(argv=None) -> int:
    from machine import write_section

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--row", default="L8", help="a Table 2 row whose reconstructions are in the cache")
    ap.add_argument("--data", default=str(ROOT / "data" / "re"))
    ap.add_argument("--cache", default=str(ROOT / "out" / "table2"))
    args = ap.parse_args(argv)
    cases = re_cases_or_say(Path(args.data))
    if not cases:
        return 0
    per_case, missing = {}, []
    for case in cases:
        out = Path(args.cache) / args.row / case.name
        if not (out / "summary.json").exists():
            missing.append(case.name)  # refused by the pipeline, or not reconstructed yet
            continue
        per_case[case.name] = classify_case(case, out)
        print(case.name, dict(zip(CLASSES, per_case[case.name].tolist())), flush=True)
    if not per_case:
        print(f"{args.cache}/{args.row}: no reconstructions (run benchmarks/table2.py first)")
        return 0
    total = np.sum(list(per_case.values()), axis=0)
    lines = ["| query | share of all queries | queries |", "|---|---|---|"]
    lines += [f"| {c} | {n / total.sum():.3f} | {n} |" for c, n in zip(CLASSES, total)]
    worst = sorted(per_case, key=lambda c: per_case[c][0] / per_case[c].sum())[:5]
    lines += ["", "Least accurate cases (share of their queries per class, in the order above):", ""]
    lines += [f"- {c}: " + " / ".join(f"{v:.2f}" for v in per_case[c] / per_case[c].sum()) for c in worst]
    body = (f"Row {args.row}, {len(per_case)} data-re cases ({len(missing)} without a reconstruction: "
            f"{', '.join(missing) or 'none'}), {total.sum()} ground-truth queries (60 per key frame), scored as "
            f"in Table 2 (cover {COVER_MM:g} mm in view A, ε = {EPSILON_MM:g} mm); 'on the tree' is within "
            f"{ON_TREE_MM:g} mm of the simulator's centreline at the midpoint of the two frames, 'ghost' "
            f"more than {GHOST_MM:g} mm from the query's own true point.\n\n" + "\n".join(lines))
    share = total / total.sum()
    body += (f"\n\nReading it: ghosts cost {share[3] + share[4]:.1%} of the queries (off-tree structures that "
             f"project onto a real vessel in view A and win it), overlaps of two real vessels in view A "
             f"{share[2]:.1%}, missed vessels {share[1]:.1%} and misplaced ones {share[5]:.1%}. The first two "
             "are the two-view ambiguity a network must resolve from the vessels' shapes (more training, "
             "more trees); where both a ghost and the true branch are in the model, the true one usually "
             "projects a few tenths of a millimetre further from the query in view A (pipeline version 8: "
             "median 0.38 mm against the winner's 0.15 mm).")
    cmd = "python benchmarks/diagnose_re_errors.py" + (f" --row {args.row}" if args.row != "L8" else "")
    path = write_section(f"re_errors_{args.row}", f"Where data-re accuracy is lost ({args.row})", cmd, body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
