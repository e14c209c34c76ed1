"""Benchmark: one connected tree from every set of N of the real phantom's runs → docs/benchmarks/phantom_run_sets.md.

Every set of N of the phantom's eight runs (N = 3: 56 sets; N = 4: 70), the lowest-numbered run as run A, is
reconstructed by `autocar reconstruct A B C … -k 1` (the default pipeline; QCA left out). Its quality check gives
the pieces of the key frame's tree, those more than 10 mm from the main tree, and the verdict. The phantom is one
tree, so every set should give one piece. Each tree is then scored on the runs left out of its set, as
`bench_join_pieces.py` scores the pairs' trees (the held-out check's coverage and distance, each held-out run's pose
fitted to the tree): the tree a user gets, where `autocar evaluate --heldout --views N` scores the 3D step's voxels.

Run:  python benchmarks/bench_phantom_run_sets.py [--runs 3] [--jobs 2] [--force]
(--runs 4 writes docs/benchmarks/phantom_run_sets_4.md). Missing phantom: says so and exits 0.
"""

from __future__ import annotations

import argparse
import itertools
import json
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PHANTOM = ROOT.parent / "shared" / "data" / "phantom_xa"
FAR_MM = 10.0


def reconstruct_set(job) -> dict:
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from stages.reconstruct import reconstruct

    names, out, force = job
    out = Path(out)
    t0 = time.perf_counter()
    if force or not (out / "summary.json").exists():
        runs = [PHANTOM / f"{n}.dcm" for n in names]
        reconstruct(runs[0], runs[1], out, k=1, qca=False, more_runs=runs[2:])
    seconds = time.perf_counter() - t0
    summary = json.loads((out / "summary.json").read_text())
    frame = summary["quality"]["frames"][0]
    pieces = frame["pieces"]
    return {"runs": "+".join(names), "pieces": len(pieces),
            "far": sum(p["distance_mm"] > FAR_MM for p in pieces[1:]),
            "apart_mm": [round(p["distance_mm"], 1) for p in pieces[1:]],
            "apart_length_mm": [round(p["length_mm"], 1) for p in pieces[1:]],
            "length_mm": frame["length_mm"], "passed": summary["quality"]["passed"], "seconds": seconds}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=3, help="runs per set (3 or more)")
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--force", action="store_true", help="ignore the cached reconstructions")
    ap.add_argument("--cache", default=str(ROOT / "out" / "phantom_run_sets"))
    args = ap.parse_args(argv)
    if not (PHANTOM / "IM1.dcm").exists():
        print(f"no phantom runs under {PHANTOM}: nothing to measure")
        return 0
    from machine import load_average, write_section

    names = sorted((p.stem for p in PHANTOM.glob("IM*.dcm")), key=lambda s: int(s[2:]))
    sets = list(itertools.combinations(names, args.runs))
    cache = Path(args.cache) / f"{args.runs}runs"
    jobs = [(s, str(cache / "+".join(s)), args.force) for s in sets]
    load_before = load_average()
    t0 = time.perf_counter()
    rows = []
    with ProcessPoolExecutor(max(1, args.jobs)) as pool:
        for i, row in enumerate(pool.map(reconstruct_set, jobs), 1):
            rows.append(row)
            print(f"{i}/{len(jobs)} {row}", flush=True)
    wall = time.perf_counter() - t0
    from bench_join_pieces import heldout_score

    from stages.evaluate.heldout import load_views
    from stages.graph.io import read_vascular_graphs

    views = load_views(PHANTOM, seg_method="unet")
    for row in rows:
        held = [k for k, v in enumerate(views) if v.name not in row["runs"].split("+")]
        _, tracked = read_vascular_graphs(cache / row["runs"] / "graphs.zarr")
        row["heldout_fitted"] = heldout_score(tracked.graphs[0], views, held, row["runs"].split("+")[0], fit=True)
    (cache / "rows.json").write_text(json.dumps(rows, indent=1))

    one = sum(r["pieces"] == 1 for r in rows)
    body = [f"Key frame 00 of every set of {args.runs} of the phantom's {len(names)} runs ({len(rows)} sets; "
            "U-Net masks, runs on one table, the default 3D method, QCA left out).", "",
            "| | sets |", "|---|---|",
            f"| one piece | {one} of {len(rows)} |",
            f"| a piece > 10 mm from the tree | {sum(r['far'] > 0 for r in rows)} of {len(rows)} |",
            f"| own quality check passed | {sum(r['passed'] for r in rows)} of {len(rows)} |",
            f"| pieces per tree, median (range) | {statistics.median(r['pieces'] for r in rows):.0f} "
            f"({min(r['pieces'] for r in rows)}–{max(r['pieces'] for r in rows)}) |",
            f"| tree length (mm), median (range) | {statistics.median(r['length_mm'] for r in rows):.0f} "
            f"({min(r['length_mm'] for r in rows):.0f}–{max(r['length_mm'] for r in rows):.0f}) |",
            f"| the tree on the runs left out (poses fitted): coverage@3 mm / distance, mean | "
            f"{statistics.mean(r['heldout_fitted'][0] for r in rows):.3f} / "
            f"{statistics.mean(r['heldout_fitted'][1] for r in rows):.2f} mm |", ""]
    apart = [r for r in rows if r["pieces"] > 1 or not r["passed"]]
    if apart:
        body += ["Sets with more than one piece or a failed check:", "",
                 "| runs | pieces | apart from the tree: length / gap (mm) | own check |", "|---|---|---|---|"]
        for r in apart:
            desc = ", ".join(f"{n:.1f} / {g:.1f}" for n, g in zip(r["apart_length_mm"], r["apart_mm"]))
            body.append(f"| {r['runs']} | {r['pieces']} | {desc} | {'passed' if r['passed'] else 'fails'} |")
        body.append("")
    computed = [r["seconds"] for r in rows if r["seconds"] > 1.0]
    body.append(f"Whole `reconstruct` per set, median {statistics.median(computed):.1f} s ({len(computed)} computed, "
                f"{args.jobs} worker process(es), one thread each); {wall:.0f} s in all. Load average before: "
                f"{load_before}; after: {load_average()}." if computed else
                f"All {len(rows)} sets from the cache. Load average before: {load_before}; after: {load_average()}.")
    topic = "phantom_run_sets" if args.runs == 3 else f"phantom_run_sets_{args.runs}"
    command = "python benchmarks/bench_phantom_run_sets.py " + " ".join(argv or sys.argv[1:])
    path = write_section(topic, f"One connected tree from every set of {args.runs} of the real phantom's runs", command,
                         "\n".join(body))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
