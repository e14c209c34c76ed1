"""Start-up cost of the CLI (import time of `autocar_cli.main`, wall time of `autocar --help`) → docs/benchmarks/cli_startup.md.

Minimum and median of repeated runs (issue 36: under 0.3 s of import time).
"""

from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import load_average, min_median, timed, write_section  # noqa: E402


def import_seconds() -> float:
    """Cumulative import time of autocar_cli.main from `python -X importtime` (seconds)."""
    out = subprocess.run([sys.executable, "-X", "importtime", "-c", "import autocar_cli.main"], cwd=REPO,
                         capture_output=True, text=True, check=True).stderr
    for line in out.splitlines()[::-1]:
        m = re.match(r"import time:\s+\d+ \|\s+(\d+) \| autocar_cli\.main$", line)
        if m:
            return int(m.group(1)) / 1e6
    raise RuntimeError("autocar_cli.main not in the import-time report")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=7)
    args = ap.parse_args(argv)
    load = load_average()
    imp = [import_seconds() for _ in range(args.repeat)]
    hlp = [timed(subprocess.run, [sys.executable, "-m", "autocar_cli.main", "--help"], cwd=REPO, capture_output=True,
                 check=True)[1] for _ in range(args.repeat)]
    body = (f"{load} at the start.\n\n| measure | min (s) | median (s) |\n|---|---|---|\n"
            f"| import of autocar_cli.main (`python -X importtime`) | {min_median(imp, '{:.3f}')} |\n"
            f"| `autocar --help`, whole process | {min_median(hlp, '{:.3f}')} |\n\n"
            "Target (issue 36): under 0.3 s of import time. No numpy, scipy, torch, zarr, matplotlib, scikit-image or "
            "pydicom is imported by the CLI before a command runs (tests/test_cli_help.py checks). The rest of "
            "`--help`'s time is the interpreter and typer/rich rendering the help.")
    print(write_section("cli_startup", "CLI start-up", f"python benchmarks/bench_cli_import.py --repeat {args.repeat}",
                        body).read_text())
    return 0


if __name__ == "__main__":
    sys.exit(main())
