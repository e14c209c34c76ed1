"""Start-up cost of the CLI (import time of `autocar_cli.main`, wall time of `autocar --help`) → docs/benchmarks/cli_startup.md.

What `autocar --help` pays before it prints, minimum and median of repeated runs (issue 36: under 0.3 s
of import time).

    python benchmarks/bench_cli_import.py [--repeat 7]
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def import_seconds() -> float:
    """Cumulative import time of autocar_cli.main from `python -X importtime` (seconds)."""
    out = subprocess.run([sys.executable, "-X", "importtime", "-c", "import autocar_cli.main"], cwd=REPO,
                         capture_output=True, text=True, check=True).stderr
    for line in out.splitlines()[::-1]:
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \| autocar_cli\.main$", line)
        if m:
            return int(m.group(1)) / 1e6
    raise RuntimeError("autocar_cli.main not in the import-time report")


def help_seconds() -> float:
    t0 = time.perf_counter()
    subprocess.run([sys.executable, "-m", "autocar_cli.main", "--help"], cwd=REPO, capture_output=True, check=True)
    return time.perf_counter() - t0


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=7)
    ap.add_argument("--out", type=Path, default=REPO / "docs" / "benchmarks" / "cli_startup.md")
    args = ap.parse_args(argv)
    imp = [import_seconds() for _ in range(args.repeat)]
    hlp = [help_seconds() for _ in range(args.repeat)]
    lines = ["# CLI start-up", "",
             f"Command: `python benchmarks/bench_cli_import.py --repeat {args.repeat}` "
             f"({time.strftime('%Y-%m-%d %H:%M', time.gmtime())} UTC; load average {os.getloadavg()[0]:.2f} on "
             f"{os.cpu_count()} CPUs).", "",
             "| measure | min (s) | median (s) |", "|---|---|---|",
             f"| import of autocar_cli.main (`python -X importtime`) | {min(imp):.3f} | {statistics.median(imp):.3f} |",
             f"| `autocar --help`, whole process | {min(hlp):.3f} | {statistics.median(hlp):.3f} |", "",
             "Target (issue 36): under 0.3 s of import time. No numpy, scipy, torch, zarr, matplotlib, scikit-image or "
             "pydicom is imported by the CLI before a command runs (tests/test_cli_help.py checks). The rest of "
             "`--help`'s time is the interpreter and typer/rich rendering the help."]
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text("\n".join(lines) + "\n")
    print("\n".join(lines[4:8]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
