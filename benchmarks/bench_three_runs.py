"""Benchmark: every run of a study — data-re with a third run, Table 2's protocol, two runs beside three → docs/benchmarks/three_runs.md.

The set (`autocar render re --runs 3 -o data/re3`) is data-re with a third run per case (`run_c.dcm`, another
standard angle, acquired between the two); its runs A and B are data-re's. Each case is reconstructed end to end
(:func:`stages.evaluate.end_to_end.run_case`) from runs A + B, and from A + B + C, by the default 3D method, and
scored on A and B's annotated correspondences and the 3D truth exactly as Table 2 scores it. Then the real
phantom: `autocar reconstruct` from two and from three runs, -k 1, on a few run sets (pieces, far pieces, the
quality verdict, time).

Run:  python benchmarks/bench_three_runs.py [--data data/re3] [--jobs 2] [--limit N] [--force] [--no-phantom]
Missing data: says so and measures what it can.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
PHANTOM = ROOT.parent / "shared" / "data" / "phantom_xa"
KEYS = (("coverage", "coverage"), ("epe_mm", "EPE (mm)"), ("accuracy", "accuracy"),
        ("centreline_error_mm", "3D centreline error (mm)"), ("centreline_pred_to_truth_mm", "recon → truth (mm)"),
        ("centreline_truth_to_pred_mm", "truth → recon (mm)"))
# phantom run sets (two runs, and the same two with a third): pairs the issue and docs/TWOVIEW.md measured
PHANTOM_SETS = [("IM1", "IM3", "IM6"), ("IM2", "IM4", "IM7"), ("IM1", "IM6", "IM3"), ("IM5", "IM8", "IM2")]


def data_re_rows(data: Path, cache: Path, jobs: int, limit, force: bool) -> tuple[dict, dict]:
    from stages.evaluate.end_to_end import process_pool, re_cases_or_say, run_case

    cases = [c for c in re_cases_or_say(data, limit) if (c / "run_c.dcm").exists()]
    if not cases:
        print(f"no three-run cases under {data}: run `autocar render re --runs 3 -o {data}` first")
        return {}, {}
    jobs_list = [(f"{n}runs", "correspondence", None, str(c), str(cache / f"{n}runs" / c.name), 60, force, n)
                 for n in (2, 3) for c in cases]
    results: dict = {"2runs": [], "3runs": []}
    refused: dict = {"2runs": [], "3runs": []}
    with process_pool(jobs) as pool:
        for done, res in enumerate(pool.map(run_case, jobs_list), 1):
            if "refused" in res:
                refused[res["name"]].append({"case": res["case"], "reason": res["refused"]})
            else:
                results[res["name"]].append(res["rows"]["graph"])
            print(f"{done}/{len(jobs_list)} {res['name']} {res['case']}", flush=True)
    return results, refused


def pieces_of(summary: dict) -> tuple[int, int]:
    pieces = summary["quality"]["frames"][0]["pieces"]
    return len(pieces), sum(p["distance_mm"] > 10.0 for p in pieces[1:])


def phantom_rows(out: Path) -> list[dict]:
    from stages.reconstruct import reconstruct

    rows = []
    for names in PHANTOM_SETS:
        for n in (2, 3):
            runs = [PHANTOM / f"{x}.dcm" for x in names[:n]]
            t0 = time.perf_counter()
            summary = reconstruct(runs[0], runs[1], out / "+".join(names[:n]), k=1, qca=False, more_runs=runs[2:])
            total, far = pieces_of(summary)
            timings = dict(summary["timings"])
            rows.append({"runs": "+".join(names[:n]), "pieces": total, "far_pieces": far,
                         "passed": summary["quality"]["passed"], "seconds": time.perf_counter() - t0,
                         "3d_step_s": timings.get("3D prediction (correspondence)"),
                         "reprojection_mm": summary["quality"]["frames"][0]["reprojection_mm"]})
            print(rows[-1], flush=True)
    return rows


def mean(rows, key):
    vals = [r[key] for r in rows if r.get(key) is not None and r[key] == r[key]]
    return statistics.mean(vals) if vals else float("nan")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "re3"))
    ap.add_argument("--jobs", type=int, default=2)
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--force", action="store_true", help="ignore the cached reconstructions")
    ap.add_argument("--no-phantom", action="store_true")
    ap.add_argument("--cache", default=str(ROOT / "out" / "three_runs"))
    args = ap.parse_args(argv)

    from machine import load_average, write_section

    cache = Path(args.cache)
    load_before = load_average()
    t0 = time.perf_counter()
    results, refused = data_re_rows(Path(args.data), cache, args.jobs, args.limit, args.force)
    body = []
    if results.get("2runs"):
        n = len(results["3runs"])
        body += [f"### data-re with a third run ({n} cases, Table 2's protocol; scored on runs A and B's annotations)",
                 "", "| runs | cases | " + " | ".join(label for _, label in KEYS) + " | s per case |",
                 "|---|---|" + "---|" * (len(KEYS) + 1)]
        for name in ("2runs", "3runs"):
            rows = results[name]
            walls = [r["wall_s"] for r in rows if r.get("wall_s")]
            body.append(f"| {name[0]} (A + B{' + C' if name == '3runs' else ''}) | {len(rows)} | "
                        + " | ".join(f"{mean(rows, k):.3f}" if not k.endswith("_mm") else f"{mean(rows, k):.2f}"
                                     for k, _ in KEYS)
                        + (f" | {statistics.median(walls):.1f} |" if walls else " | cached |"))
        for name, items in refused.items():
            for item in items:
                body.append(f"\n{name}: {item['case']} refused: {item['reason']}")
        (cache / "rows.json").write_text(json.dumps({"results": results, "refused": refused}, indent=1))
    if not args.no_phantom and (PHANTOM / "IM1.dcm").exists():
        rows = phantom_rows(cache / "phantom")
        body += ["", "### The real phantom, `autocar reconstruct -k 1`, two runs and the same with a third", "",
                 "| runs | pieces | > 10 mm from the tree | own check | reprojection per view (mm) | 3D step (s) | "
                 "whole run (s) |", "|---|---|---|---|---|---|---|"]
        for r in rows:
            rep = ", ".join(f"{v} {d:.2f}" for v, d in r["reprojection_mm"].items() if d is not None)
            body.append(f"| {r['runs']} | {r['pieces']} | {r['far_pieces']} | {'passed' if r['passed'] else 'fails'} "
                        f"| {rep} | {r['3d_step_s']:.2f} | {r['seconds']:.1f} |")
    if not body:
        print("nothing measured")
        return 0
    body.append(f"\nLoad average before: {load_before}; after: {load_average()}; "
                f"{time.perf_counter() - t0:.0f} s in all, {args.jobs} worker process(es), one thread each.")
    path = write_section("three_runs", "Every run of the same tree: two runs beside three",
                         "python benchmarks/bench_three_runs.py " + " ".join(argv or sys.argv[1:]), "\n".join(body))
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
