"""Benchmark: the ceiling of Table 2's 2D metrics on data-re — what a *perfect* static 3D model scores.

The two runs of a data-re case are acquired at different times, so breathing and the heartbeat move
the tree between them. A single 3D model per key frame cannot then project exactly onto both runs.
This script puts the simulator's own centreline in place of a reconstruction and scores it exactly
as Table 2 scores a reconstruction (:func:`stages.evaluate.truth_correspondences` +
:func:`stages.evaluate.evaluate_correspondences`): the tree at run A's frame, at the midpoint of the
two frames' configurations, and at run B's frame, each scored with the header cameras (no motion
correction); and the tree at run A's frame scored with view B's camera shifted by the *true* shift across
its epipolar lines (``tune_view_alignment.true_shifts``): what a perfect model with a perfect inter-run
motion correction of the kind ``autocar reconstruct`` applies (one rigid image shift of run B per key frame,
stages/view_alignment.py) would score. Key-frame pairs: the simulator's own phase-matched pairs
(``truth.zarr`` ``keyframes/pairs``), so nothing of the pipeline is involved.

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

MODELS = ("run A's frame", "midpoint", "run B's frame", "run A's frame, view B shifted by the true shift")
METRICS = ("coverage", "epe_mm", "accuracy")


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
        models = (at_a, 0.5 * (at_a + at_b), at_b, at_a)
        for name, nodes in zip(MODELS, models):
            # the truth pairs stay on the header cameras; only the model's partner moves with the shift
            scored = {**ann, "camera_b": cam_b.shifted(*(oracle[k] * across))} if name == MODELS[3] else ann
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
    lines = ["| the simulator's tree at | coverage ↑ | EPE (mm) ↓ | accuracy ↑ |", "|---|---|---|---|"]
    for m in MODELS:
        a = np.asarray(per_case[m])
        mean, sd = np.nanmean(a, 0), np.nanstd(a, 0)
        lines.append(f"| {m} | {mean[0]:.3f} ± {sd[0]:.3f} | {mean[1]:.2f} ± {sd[1]:.2f} "
                     f"| {mean[2]:.3f} ± {sd[2]:.3f} |")
    body = (f"{len(cases)} data-re cases, the simulator's phase-matched key-frame pairs (7 per case), 60 "
            f"ground-truth correspondences per pair; covered within {COVER_MM:g} mm in view A, accuracy "
            f"ε = {EPSILON_MM:g} mm; mean ± sd over cases. The reconstruction is replaced by the true "
            "centreline, so these are what a perfect static model per key frame would score.\n\n"
            + "\n".join(lines) + "\n\n"
            "Reading it: the runs are acquired at different times, so the tree moves between them "
            "(breathing, and the residual cardiac phase difference). Even the exact tree of run A's frame "
            "places its partners in run B off by the motion: it misses ε on about a sixth of the points. "
            "A model between the two configurations also loses coverage in view A. The last row is the "
            "ceiling of the shipped pipeline's design: a perfect model plus a perfect rigid shift of run B "
            "per key frame (what stages/view_alignment.py estimates); what it still misses is the motion "
            "no rigid image shift absorbs (rotation, deformation, the part along the epipolar lines) and "
            "queries where two vessels overlap in view A. Table 2's accuracy should be read against these "
            "ceilings rather than against 1.\n")
    cmd = "python benchmarks/bench_re_ceiling.py" + (f" --limit {args.limit}" if args.limit else "")
    path = write_section("re_ceiling", "Ceiling of the 2D correspondence metrics on data-re", cmd, body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
