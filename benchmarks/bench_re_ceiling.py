"""Benchmark: the ceiling of Table 2's 2D metrics on data-re — what a *perfect* 3D model scores.

The two runs of a data-re case are acquired at different times, so breathing and the heartbeat move
the tree between them. This script puts models built from the simulator's own centreline in place of a
reconstruction and scores them exactly as Table 2 scores a reconstruction
(:func:`stages.evaluate.truth_correspondences` + :func:`stages.evaluate.evaluate_correspondences`):

* the true 3D tree at run A's frame, at the midpoint of the two frames' configurations and at run B's
  frame, scored with the header cameras (no motion correction); and the tree at run A's frame scored
  with view B's camera shifted by the *true* shift across its epipolar lines
  (``tune_view_alignment.true_shifts``, the kind of correction ``autocar reconstruct`` estimates). These
  are perfect *static 3D* models: their partner of a query in run B is off by the tree's motion;
* the true tree *triangulated from its two frames' images*: each centreline point placed where its ray in
  run A's frame meets its ray in run B's frame (view B shifted by the true shift; the midpoint of the two
  rays' closest approach). This is what a perfect image-based reconstruction — exact masks, exact
  correspondences — builds: motion along the epipolar lines goes into its depth (a 3D error, no 2D
  one), so its 2D scores miss only the motion no rigid shift of run B absorbs and the queries where two
  vessels overlap in view A. It is the ceiling for Table 2's 2D metrics; the static rows are not, since a
  reconstruction from the images can beat them in 2D.

Key-frame pairs: the simulator's own phase-matched pairs (``truth.zarr`` ``keyframes/pairs``), so nothing of
the pipeline is involved.

Run:  python benchmarks/bench_re_ceiling.py [--data data/re] [--limit N]
Writes docs/benchmarks/re_ceiling.md. Missing data-re: says so and exits 0.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from re_eval import re_cases_or_say  # noqa: E402

from stages.metrics import COVER_MM, EPSILON_MM  # noqa: E402

MODELS = ("at run A's frame", "at the midpoint", "at run B's frame", "at run A's frame, view B shifted by the true shift",
          "triangulated from run A's and run B's frames, header cameras",
          "triangulated from run A's and run B's frames, view B shifted by the true shift")
METRICS = ("coverage", "epe_mm", "accuracy")


def triangulate(cam_a, px_a, cam_b, px_b):
    """N×3 midpoints of the closest approach of the rays through ``px_a`` in view A and ``px_b`` in view B."""
    import numpy as np

    oa, da = cam_a.rays(px_a)
    ob, db = cam_b.rays(px_b)
    w = oa - ob
    b = np.einsum("ij,ij->i", da, db)
    d, e = np.einsum("ij,ij->i", da, w), np.einsum("ij,ij->i", db, w)
    denom = np.maximum(1.0 - b * b, 1e-12)  # unit directions; views ≥ 10° apart keep this well away from 0
    ta, tb = (b * e - d) / denom, (e - b * d) / denom
    return 0.5 * ((oa + ta[:, None] * da) + (ob + tb[:, None] * db))


def case_scores(case: Path, n_points: int = 60) -> dict[str, list[tuple[float, float, float]]]:
    """Per model, (coverage, EPE, accuracy) of every simulator key-frame pair of one case."""
    import numpy as np

    from stages.evaluate import Prediction, evaluate_correspondences, truth_correspondences
    from stages.render.acquire import load_truth
    from stages.segment import load_run
    from stages.view_alignment import _across_direction, _plane_frame
    from tune_view_alignment import true_shifts

    truth = load_truth(case / "truth.zarr")
    cam_a, cam_b = load_run(case / "run_a.dcm").camera, load_run(case / "run_b.dcm").camera
    radius, edges = truth["radius"].astype(float), truth["edges"]
    seed = int(truth["attrs"]["seed"])
    pairs = np.asarray(truth["keyframes"]["pairs"], int)
    across, _ = _across_direction(cam_b, _plane_frame(cam_a, cam_b))
    oracle = true_shifts(truth, cam_a, cam_b, pairs)
    out: dict[str, list] = {m: [] for m in MODELS}
    for k, (ia, ib) in enumerate(pairs):
        ann = truth_correspondences(truth, cam_a, cam_b, int(ia), int(ib), n_points, [seed, k])
        at_a = truth["a"]["nodes"][ia].astype(float)
        at_b = truth["b"]["nodes"][ib].astype(float)
        aligned_b = cam_b.shifted(*(oracle[k] * across))
        # run B's image of the tree at its frame is what the header camera sees; the shifted camera takes it back
        seen_b = cam_b.project(at_b)
        seen_a = cam_a.project(at_a)
        models = (at_a, 0.5 * (at_a + at_b), at_b, at_a, triangulate(cam_a, seen_a, cam_b, seen_b),
                  triangulate(cam_a, seen_a, aligned_b, seen_b))
        for name, nodes in zip(MODELS, models):
            # the truth pairs stay on the header cameras; only the model's partner moves with the shift
            scored = {**ann, "camera_b": aligned_b} if "true shift" in name else ann
            r = evaluate_correspondences(Prediction("", None, (nodes, radius, edges)), scored)
            out[name].append(tuple(float(r[m]) for m in METRICS))
    return out


def main(argv=None) -> int:
    import numpy as np

    from machine import write_section

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "re"))
    ap.add_argument("--limit", type=int, default=None, help="only the first N cases")
    args = ap.parse_args(argv)
    cases = re_cases_or_say(Path(args.data), args.limit)
    if not cases:
        return 0
    per_case: dict[str, list] = {m: [] for m in MODELS}
    for case in cases:
        scores = case_scores(case)
        for m in MODELS:
            per_case[m].append(np.nanmean(np.asarray(scores[m], float), axis=0))
        print(case.name, {m: np.round(per_case[m][-1], 3).tolist() for m in MODELS}, flush=True)
    lines = ["| the simulator's tree: | coverage ↑ | EPE (mm) ↓ | accuracy ↑ |", "|---|---|---|---|"]
    for m in MODELS:
        a = np.asarray(per_case[m])
        mean, sd = np.nanmean(a, 0), np.nanstd(a, 0)
        lines.append(f"| {m} | {mean[0]:.3f} ± {sd[0]:.3f} | {mean[1]:.2f} ± {sd[1]:.2f} "
                     f"| {mean[2]:.3f} ± {sd[2]:.3f} |")
    body = (f"{len(cases)} data-re cases, the simulator's phase-matched key-frame pairs (7 per case), 60 "
            f"ground-truth correspondences per pair; covered within {COVER_MM:g} mm in view A, accuracy "
            f"ε = {EPSILON_MM:g} mm; mean ± sd over cases. The reconstruction is replaced by the true "
            "centreline: a perfect static 3D model per key frame (first four rows) or a perfect reconstruction from the "
            "two images (last two).\n\n"
            + "\n".join(lines) + "\n\n"
            "Reading it: the runs are acquired at different times, so the tree moves between them "
            "(breathing, and the residual cardiac phase difference). Even the exact tree of run A's frame "
            "places its partners in run B off by the motion: it misses ε on about a sixth of the points. "
            "A model between the two configurations also loses coverage in view A. A perfect rigid shift of "
            "run B (fourth row) recovers part of that. But these are static 3D truths: a reconstruction "
            "from the two images places each point where the two rays meet, so motion along the epipolar "
            "lines becomes a depth error (Table 2's 3D centreline error) and no 2D one, and on cases whose "
            "motion is mostly along those lines it beats the static rows in 2D. The last row is that "
            "perfect image-based reconstruction (the row before it without motion correction), the true ceiling of Table 2's 2D metrics: what it still "
            "misses is the motion no rigid shift of run B absorbs and the queries where two vessels "
            "overlap in view A. Table 2's coverage, EPE and accuracy should be read against it.\n")
    cmd = "python benchmarks/bench_re_ceiling.py" + (f" --limit {args.limit}" if args.limit else "")
    path = write_section("re_ceiling", "Ceiling of the 2D correspondence metrics on data-re", cmd, body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
