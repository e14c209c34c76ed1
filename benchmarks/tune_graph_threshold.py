"""Tune the graph stage's occupancy threshold on cases that are never evaluated on.

The graph initialisation (:func:`stages.graph.init.init_graph`) keeps predicted voxels with occupancy
≥ a threshold. The network's occupancy is not calibrated for that use (it is trained for voxel Dice), so
the threshold is chosen here, on a *tuning set* of data-re-like cases (seeds
:data:`stages.render.products.SEED_RE_TUNING` +, disjoint from the training trees and from data-re):
each case is reconstructed once with the shipped SBP weights (``autocar reconstruct``, as Table 2 does),
then ``graph-opt`` is rerun on its predictions with each candidate threshold and scored with the
paper's coverage / EPE / accuracy (Eqs. 22–24) on the simulator's correspondences. The chosen threshold
maximises accuracy (points placed within ε over all points: it rewards both covering and placing).

Run:  python benchmarks/tune_graph_threshold.py [--cases 6] [--thresholds 0.2,0.3,0.4,0.5]
Writes data/re_tuning (the cases, once; ~40 s each), out/tune_graph/ (reconstructions) and
docs/benchmarks/graph_threshold.md.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))


def score_settings(recon: Path, case: Path, settings: dict, points: int = 60) -> dict:
    """{name: [per key frame (coverage, EPE mm, accuracy, 3D centreline error mm, branches from 2D, ghost branches
    dropped, unsupported branches dropped)]} for one reconstructed case: graph-opt rerun on its predictions with
    each setting (keyword arguments of :func:`stages.graph.stage.run_graph_opt`), scored as Table 2 scores
    (:func:`stages.evaluate.score_dynamic_reconstruction`)."""
    from stages.evaluate import score_dynamic_reconstruction
    from stages.graph.stage import run_graph_opt
    from stages.render.acquire import load_truth
    from stages.segment import load_run

    truth = load_truth(case / "truth.zarr")
    runs = [load_run(case / "run_a.dcm"), load_run(case / "run_b.dcm")]
    out = {}
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        for name in ("predictions.zarr", "summary.json"):  # the reconstruction's, shared by every setting
            (work / name).symlink_to((recon / name).resolve())
        for name, kw in settings.items():
            summary = run_graph_opt(work / "predictions.zarr", work / "graphs.zarr", exports=False, **kw)
            seed = int(truth["attrs"]["seed"])
            frames = score_dynamic_reconstruction(work, truth, runs, points, seed)["graph"]["frames"]
            out[name] = [(f["coverage"], f["epe_mm"], f["accuracy"], f["centreline_error_mm"], s["branches_from_views"],
                          s["ghost_branches_dropped"], s["unsupported_branches_dropped"])
                         for f, s in zip(frames, summary["frames"])]
    return out


def score_tuning_cases(data: Path, out: Path, n_cases: int, settings: dict) -> tuple[list[Path], dict]:
    """Make the first ``n_cases`` tuning cases (once), reconstruct each with the shipped SBP weights
    (cached by content, in ``out``) and score every setting on it (:func:`score_settings`).
    Returns (cases, {setting: rows over all key frames of all cases})."""
    from re_eval import case_jobs, run_case

    from stages.render.products import SEED_RE_TUNING, make_re

    make_re(data, n=n_cases, seed=SEED_RE_TUNING, jobs=1)
    cases = sorted(p for p in Path(data).glob("case_*") if (p / "truth.zarr").exists())[:n_cases]
    scores = {name: [] for name in settings}
    for job in case_jobs([("L8", "sbp", None)], cases, out):
        res = run_case(job)
        if "refused" in res:
            print(f"{res['case']}: refused: {res['refused']}")
            continue
        per = score_settings(Path(job[4]), Path(job[3]), settings)
        for name in settings:
            scores[name] += per[name]
        print(res["case"], {n: np.round(np.nanmean(per[n], 0), 3).tolist() for n in settings}, flush=True)
    return cases, scores


def paired_note(scores: dict, best: float, default: float) -> str:
    """How far the best threshold's accuracy is from the default's: the mean of the per-key-frame-pair
    differences ± its standard error (the same pairs are scored at every threshold)."""
    match = [t for t in scores if abs(t - default) < 1e-9]
    if not match or match[0] == best:
        return ""
    diff = np.asarray(scores[best], float)[:, 2] - np.asarray(scores[match[0]], float)[:, 2]
    diff = diff[np.isfinite(diff)]
    if len(diff) < 2:
        return ""
    se = diff.std(ddof=1) / np.sqrt(len(diff))
    return (f" Accuracy at {best:g} minus at {default:g}, paired over {len(diff)} key-frame pairs: "
            f"{diff.mean():+.3f} ± {se:.3f} (standard error); better on {np.mean(diff > 0):.0%} of the pairs, "
            f"worse on {np.mean(diff < 0):.0%}.")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=6, help="tuning cases (seeds SEED_RE_TUNING + 0 … n−1)")
    ap.add_argument("--thresholds", default="0.2,0.3,0.4,0.5")
    ap.add_argument("--data", default=str(ROOT / "data" / "re_tuning"))
    ap.add_argument("--out", default=str(ROOT / "out" / "tune_graph"))
    args = ap.parse_args(argv)
    thresholds = [float(t) for t in args.thresholds.split(",")]

    from machine import write_section

    from stages.graph.init import DEFAULT_OCCUPANCY_THRESHOLD
    from stages.render.products import SEED_RE_TUNING

    cases, rows = score_tuning_cases(Path(args.data), Path(args.out), args.cases,
                                     {t: {"occupancy_threshold": t} for t in thresholds})
    scores = {t: [row[:3] for row in r] for t, r in rows.items()}  # coverage, EPE, accuracy

    means = {t: np.nanmean(np.asarray(scores[t], float), 0) for t in thresholds}
    best = max(thresholds, key=lambda t: means[t][2])
    lines = ["| occupancy threshold | coverage ↑ | EPE (mm) ↓ | accuracy ↑ |", "|---|---|---|---|"]
    for t in thresholds:
        c, e, a = means[t]
        mark = " (best)" if t == best else ""
        cur = " (the default when this ran)" if abs(t - DEFAULT_OCCUPANCY_THRESHOLD) < 1e-9 else ""
        lines.append(f"| {t:g}{mark}{cur} | {c:.3f} | {e:.2f} | {a:.3f} |")
    n_frames = len(scores[thresholds[0]])
    body = (f"{len(cases)} tuning cases (data/re_tuning, seeds {SEED_RE_TUNING}+; never part of an evaluation), "
            f"{n_frames} key-frame pairs, shipped SBP weights, our segmentation and key frames; `graph-opt` rerun "
            f"on the same predictions per threshold. Means over key-frame pairs.\n\n" + "\n".join(lines) +
            f"\n\nHighest accuracy at threshold {best:g}; the pipeline's default "
            f"(`stages.graph.init.DEFAULT_OCCUPANCY_THRESHOLD`) is {DEFAULT_OCCUPANCY_THRESHOLD:g}."
            + paired_note(scores, best, DEFAULT_OCCUPANCY_THRESHOLD) + "\n")
    cmd = "python benchmarks/tune_graph_threshold.py" + (f" --cases {args.cases}" if args.cases != 6 else "")
    write_section("graph_threshold", "Graph-initialisation occupancy threshold, tuned on held-apart cases", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
