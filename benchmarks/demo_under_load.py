"""`make demo`'s reconstruction on a quiet machine and beside a CPU-heavy process, at 1 and 2 threads
(issue 36, finding 1: under load 2 threads took 456–706 s where 1 thread took 58 s).

Needs a quiet machine for its first column (nothing else running): it measures the machine, not only
autocar. Writes docs/benchmarks/demo_under_load.md with the wall times, the load average before each run
and `uptime` at the start.

    python benchmarks/demo_under_load.py                 # default method, threads 1 and 2
    python benchmarks/demo_under_load.py --method visual-hull --threads 1
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
AUTOCAR = [sys.executable, "-m", "autocar_cli.main"]

# the competing load: as many busy processes as there are cores, each a tight numpy matmul loop on one thread
HOG = ("import numpy as np, time\n"
       "a = np.random.rand(400, 400)\n"
       "end = time.time() + {seconds}\n"
       "while time.time() < end:\n"
       "    a = a @ a\n"
       "    a /= np.abs(a).max()\n")  # normalised every step: no overflow to inf/NaN


def reconstruct_seconds(method: str, threads: int, out: Path) -> float:
    env = {**os.environ, "AUTOCAR_THREADS": str(threads)}
    for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        env.pop(var, None)  # --threads alone decides
    cmd = AUTOCAR + ["reconstruct", str(REPO / "examples" / "run_a.dcm"), str(REPO / "examples" / "run_b.dcm"),
                     "-o", str(out), "--force", "--threads", str(threads)]
    if method:
        cmd += ["--method", method]
    t0 = time.perf_counter()
    subprocess.run(cmd, cwd=REPO, env=env, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def with_load(fn, n_hogs: int, seconds: float = 3600.0):
    env = {**os.environ, "OMP_NUM_THREADS": "1", "OPENBLAS_NUM_THREADS": "1"}
    hogs = [subprocess.Popen([sys.executable, "-c", HOG.format(seconds=seconds)], env=env) for _ in range(n_hogs)]
    try:
        time.sleep(2.0)  # let the load settle
        return fn()
    finally:
        for h in hogs:
            h.terminate()
        for h in hogs:
            h.wait()


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--method", default="", help="--method of reconstruct (default: the CLI's default)")
    ap.add_argument("--threads", type=int, nargs="+", default=[1, 2])
    ap.add_argument("--hogs", type=int, default=os.cpu_count() or 2, help="busy processes of the load")
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "demo_under_load.md")
    args = ap.parse_args(argv)
    uptime = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for threads in args.threads:
            load_q = os.getloadavg()[0]
            quiet = reconstruct_seconds(args.method, threads, Path(tmp) / f"q{threads}")
            load_l = os.getloadavg()[0]
            loaded = with_load(lambda: reconstruct_seconds(args.method, threads, Path(tmp) / f"l{threads}"), args.hogs)
            rows.append((threads, quiet, loaded, load_q, load_l))
            print(f"threads {threads}: quiet {quiet:.1f} s, loaded {loaded:.1f} s ({loaded / quiet:.2f}×)", flush=True)
    lines = ["# `make demo`'s reconstruction under load", "",
             f"Command: `python benchmarks/demo_under_load.py{' --method ' + args.method if args.method else ''}` "
             f"({time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC, {os.cpu_count()} CPUs; at the start: `{uptime}`). "
             f"Load: {args.hogs} busy single-thread numpy processes.", "",
             "| --threads | quiet (s) | beside the load (s) | ratio | load average before quiet / loaded run |",
             "|---|---|---|---|---|"]
    for threads, quiet, loaded, lq, ll in rows:
        lines.append(f"| {threads} | {quiet:.1f} | {loaded:.1f} | {loaded / quiet:.2f}× | {lq:.2f} / {ll:.2f} |")
    lines += ["", "Target (issue 36): beside a CPU-heavy process, within 2× of the quiet time. The default is "
              "`--threads 1` (autocar_cli/common.py says why)."]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
