"""Assemble docs/BENCHMARKS.md from the sections each benchmark script wrote to docs/benchmarks/*.md."""

from __future__ import annotations

import datetime as dt
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    sections = sorted((ROOT / "docs" / "benchmarks").glob("*.md"))
    parts = [
        "# AutoCAR benchmarks\n",
        f"Assembled by `make bench` (benchmarks/collect.py) on {dt.date.today().isoformat()} from the sections "
        "below; each section names the command that produced it, the machine and the date it ran. The paper's "
        "two tables reproduced on our data: docs/TABLE1.md (`make reproduce-table1`) and docs/TABLE2.md "
        "(`make reproduce-table2`).\n",
    ]
    for section in sections:
        parts.append(section.read_text().strip() + "\n")
    (ROOT / "docs" / "BENCHMARKS.md").write_text("\n".join(parts))
    print(f"wrote docs/BENCHMARKS.md from {len(sections)} section(s)")


if __name__ == "__main__":
    main()
