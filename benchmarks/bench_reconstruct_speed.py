"""Speed of the whole `autocar reconstruct`, one thread → docs/benchmarks/reconstruct_speed.md.

What a user waits for: the command as users run it (`autocar reconstruct A B -o OUT --threads 1`, a fresh
process each time, OMP_NUM_THREADS=1), on

* the real phantom's runs IM1 + IM3 with one key frame (`-k 1`: the phantom is static), and
* data-re cases (two 42-frame 512² runs, 7 key frames each),

one at a time, each run ``--repeat`` times. Per run: the pipeline's own time (`total_seconds` in summary.json: from
reading the runs to the report, every import the stages make included, so torch's ~1 s too) and the wall time
of the process (plus the interpreter and CLI start-up); the minimum over the repeats is the figure (the
machine is shared: others' jobs only ever add time), and the stage times are those of that run. Beside it, the
same reconstruction in a warm process (`stages.reconstruct.reconstruct` called a second time in one Python
process, one thread): what each study costs a worker of `autocar batch`, which imports once.

Run:  python benchmarks/bench_reconstruct_speed.py [--data data/re3] [--cases 5] [--repeat 2]
Missing phantom or data-re: that part is said to be missing and skipped.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import load_average, run_child, write_section  # noqa: E402

PHANTOM = REPO.parent / "shared" / "data" / "phantom_xa"


def time_reconstruct(runs: list[Path], k: int, repeat: int) -> dict:
    """The fastest of ``repeat`` runs of the CLI: pipeline seconds, wall seconds, key frames, stage times."""
    best = None
    env_cmd = [sys.executable, "-m", "autocar_cli.main", "reconstruct", *map(str, runs), "-k", str(k),
               "--threads", "1", "--force"]
    for _ in range(repeat):
        out = Path(tempfile.mkdtemp(prefix="autocar_speed_"))
        try:
            wall, _, rc, _ = run_child([*env_cmd, "-o", str(out)])
            if rc != 0:
                raise SystemExit(f"error: reconstruct {' '.join(map(str, runs))} failed (exit {rc})")
            summary = json.loads((out / "summary.json").read_text())
        finally:
            shutil.rmtree(out, ignore_errors=True)
        row = {"total_s": float(summary["total_seconds"]), "wall_s": wall, "key_frames": len(summary["pairs"]),
               "stages": {name: float(s) for name, s in summary["timings"]}}
        if best is None or row["total_s"] < best["total_s"]:
            best = row
    return best


def warm_seconds(runs: list[Path], k: int) -> float:
    """The pipeline time of a second reconstruction in one process (imports and compiled kernels warm)."""
    import subprocess

    code = ("import json, sys, tempfile, torch\n"
            "torch.set_num_threads(1)\n"
            "from stages.reconstruct import reconstruct\n"
            "for _ in range(2):\n"
            "    out = tempfile.mkdtemp(prefix='autocar_speed_')\n"
            "    s = reconstruct(sys.argv[1], sys.argv[2], out, k=int(sys.argv[3]))\n"
            "print(s['total_seconds'])")
    res = subprocess.run([sys.executable, "-c", code, *map(str, runs), str(k)], cwd=REPO, capture_output=True, text=True,
                         env={**os.environ, "OMP_NUM_THREADS": "1"})
    if res.returncode:
        raise SystemExit(f"error: warm reconstruct of {' '.join(map(str, runs))} failed: {res.stderr.strip()[-300:]}")
    return float(res.stdout.strip().splitlines()[-1])


def stage_table(rows: list[dict]) -> str:
    names = list(rows[0]["stages"])
    lines = ["| stage | " + " | ".join(r["name"] for r in rows) + " |", "|---|" + "---|" * len(rows)]
    for n in names:
        lines.append(f"| {n} | " + " | ".join(f"{r['stages'].get(n, float('nan')):.2f}" for r in rows) + " |")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(REPO / "data" / "re3"), help="data-re cases (run_a.dcm, run_b.dcm)")
    ap.add_argument("--cases", type=int, default=5, help="data-re cases timed (the first N)")
    ap.add_argument("--repeat", type=int, default=2, help="runs per input; the fastest counts")
    args = ap.parse_args(argv)
    os.environ["OMP_NUM_THREADS"] = "1"
    load_before = load_average()
    rows, notes = [], []
    if (PHANTOM / "IM1.dcm").exists():
        runs = [PHANTOM / "IM1.dcm", PHANTOM / "IM3.dcm"]
        row = time_reconstruct(runs, 1, args.repeat)
        rows.append({"name": "phantom IM1+IM3", **row, "warm_s": warm_seconds(runs, 1)})
        print(rows[-1], flush=True)
    else:
        notes.append(f"No phantom runs under {PHANTOM}: the phantom row is missing.")
    cases = sorted(p for p in Path(args.data).glob("case_*") if (p / "run_b.dcm").exists())[:args.cases]
    if not cases:
        notes.append(f"No data-re cases under {args.data} (`make data-re`): the data-re rows are missing.")
    for case in cases:
        runs = [case / "run_a.dcm", case / "run_b.dcm"]
        row = time_reconstruct(runs, 7, args.repeat)
        rows.append({"name": case.name, **row, "warm_s": warm_seconds(runs, 7)})
        print(rows[-1], flush=True)
    if not rows:
        print(" ".join(notes) + " Nothing measured.")
        return 0
    table = ["| input | key frames | pipeline s | per key frame s | process wall s | warm process: pipeline s (per key "
             "frame) |", "|---|---|---|---|---|---|"]
    for r in rows:
        table.append(f"| {r['name']} | {r['key_frames']} | {r['total_s']:.2f} | {r['total_s'] / r['key_frames']:.2f} | "
                     f"{r['wall_s']:.2f} | {r['warm_s']:.2f} ({r['warm_s'] / r['key_frames']:.2f}) |")
    re_rows = [r for r in rows if r["name"].startswith("case_")]
    summary = []
    if re_rows:
        per_kf = [r["total_s"] / r["key_frames"] for r in re_rows]
        per_kf_wall = [r["wall_s"] / r["key_frames"] for r in re_rows]
        per_kf_warm = [r["warm_s"] / r["key_frames"] for r in re_rows]
        summary.append(f"data-re, {len(re_rows)} cases: **{statistics.mean(per_kf):.2f} s per key frame** (pipeline; "
                       f"max {max(per_kf):.2f}), {statistics.mean(per_kf_wall):.2f} s with the process start-up, "
                       f"{statistics.mean(per_kf_warm):.2f} s in a warm process (target ≤ 1.5 s per key frame).")
    ph = [r for r in rows if r["name"].startswith("phantom")]
    if ph:
        summary.append(f"Phantom, one key frame: **{ph[0]['total_s']:.2f} s** (pipeline), {ph[0]['wall_s']:.2f} s "
                       f"with the process start-up, {ph[0]['warm_s']:.2f} s in a warm process (target ≤ 6 s).")
    body = (f"{load_before} at the start, {load_average()} at the end. One thread (`--threads 1`, "
            f"OMP_NUM_THREADS=1), the fastest of {args.repeat} runs per input.\n\n" + "\n".join(table) + "\n\n"
            + " ".join(summary + notes) + "\n\nStage times (s) of those runs:\n\n" + stage_table(rows))
    cmd = f"python benchmarks/bench_reconstruct_speed.py --cases {args.cases} --repeat {args.repeat}"
    print(write_section("reconstruct_speed", "Speed of `autocar reconstruct` (one thread)", cmd, body).read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
