"""Assemble docs/BENCHMARKS.md from the sections each benchmark script wrote to docs/benchmarks/*.md."""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from benchmarks.machine import DOCS  # noqa: E402


def main() -> None:
    argparse.ArgumentParser(description=__doc__.splitlines()[0]).parse_args()  # --help; no options
    sections = sorted(DOCS.glob("*.md"))
    head = (f"# AutoCAR benchmarks\n\nAssembled by `make bench` (benchmarks/collect.py) on {dt.date.today().isoformat()} "
            "from the sections below; each section names the command that produced it, the machine and the date it ran. "
            "The paper's two tables reproduced on our data: docs/TABLE1.md (`make reproduce-table1`) and docs/TABLE2.md "
            "(`make reproduce-table2`).\n")
    (DOCS.parent / "BENCHMARKS.md").write_text("\n".join([head, *(s.read_text().strip() + "\n" for s in sections)]))
    print(f"wrote {DOCS.parent / 'BENCHMARKS.md'} from {len(sections)} section(s)")


if __name__ == "__main__":
    main()
