"""The tree says what it holds: every benchmark script is named somewhere, every bench_ script says on its
first docstring line which doc it writes, docs/README.md links every doc, and the README's layout table
matches the packages and modules under stages/."""

from __future__ import annotations

import ast
import fnmatch
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PATH_IN_CELL = re.compile(r"`([A-Za-z0-9_./-]+)`")
DOC_ON_LINE = re.compile(r"docs/[A-Za-z0-9_./-]+\.md")


# ---------------------------------------------------------------------- helpers (take the repo root)
def naming_texts(root: Path) -> dict[str, str]:
    """What may name a benchmark script: make files, README and docs, tests (this file excepted)."""
    paths = [root / "Makefile", root / "README.md", *sorted((root / "mk").glob("*.mk")),
             *sorted((root / "docs").rglob("*.md")),
             *sorted(p for p in (root / "tests").glob("*.py") if p.name != Path(__file__).name)]
    return {str(p.relative_to(root)): p.read_text() for p in paths if p.is_file()}


def unnamed_benchmarks(root: Path) -> list[str]:
    """benchmarks/*.py that no make target, doc or test names (by path, by a make glob, or a test's import)."""
    texts = naming_texts(root)
    make_text = "\n".join(t for k, t in texts.items() if k == "Makefile" or k.endswith(".mk"))
    globs = [g for g in re.findall(r"benchmarks/[A-Za-z0-9_*]+\.py", make_text) if "*" in g]
    tests = "\n".join(t for k, t in texts.items() if k.startswith("tests"))
    everything = "\n".join(texts.values())
    missing = []
    for script in sorted((root / "benchmarks").glob("*.py")):
        if script.name == "__init__.py":
            continue
        rel = f"benchmarks/{script.name}"
        imported = re.search(rf"^\s*(import|from)\s+(benchmarks\.)?{script.stem}\b", tests, re.M)
        if rel in everything or imported or any(fnmatch.fnmatch(rel, g) for g in globs):
            continue
        missing.append(rel)
    return missing


def bench_docstring_problems(root: Path) -> list[str]:
    """bench_*.py whose docstring's first line names no doc (docs/….md), or a doc that is not there."""
    problems = []
    for script in sorted((root / "benchmarks").glob("bench_*.py")):
        doc = ast.get_docstring(ast.parse(script.read_text()))
        first = doc.splitlines()[0] if doc else ""
        named = DOC_ON_LINE.findall(first)
        if not named:
            problems.append(f"{script.name}: first docstring line names no docs/….md: {first!r}")
        problems += [f"{script.name}: names {d}, which does not exist" for d in named if not (root / d).is_file()]
    return problems


def layout_table(readme: str) -> list[list[str]]:
    """The cells of every row of the table in the README's ``## Layout`` section (header row excluded)."""
    section = readme.split("\n## Layout\n", 1)[1].split("\n## ", 1)[0]
    rows = [line for line in section.splitlines() if line.startswith("|")]
    cells = [[c.strip() for c in row.strip("|").split("|")] for row in rows]
    return [c for c in cells[1:] if not set("".join(c)) <= set("-: ")]  # drop the header and its rule


def layout_problems(root: Path) -> list[str]:
    """Paths in the table's first column that do not exist; packages and modules of stages/ without a row."""
    rows = layout_table((root / "README.md").read_text())
    named = [p for row in rows for p in PATH_IN_CELL.findall(row[0])]
    problems = [f"{p}: named in the README's layout table, not in the tree" for p in named
                if not (root / p).exists()]
    listed = {p.rstrip("/") for p in named}
    stage_dir = root / "stages"
    packages = sorted(d for d in stage_dir.iterdir() if (d / "__init__.py").is_file())
    modules = sorted(p for p in stage_dir.glob("*.py") if p.name != "__init__.py")
    for path in packages + modules:
        rel = str(path.relative_to(root))
        if rel not in listed:
            problems.append(f"{rel}{'/' if path.is_dir() else ''}: in stages/, no row in the README's layout table")
    return problems


def unindexed_docs(root: Path) -> list[str]:
    """docs/*.md and docs/benchmarks/*.md that docs/README.md (the index) does not link to."""
    index = (root / "docs" / "README.md").read_text()
    links = set(re.findall(r"\]\(([^)#]+)\)", index))
    docs = [*sorted((root / "docs").glob("*.md")), *sorted((root / "docs" / "benchmarks").glob("*.md"))]
    return [str(d.relative_to(root)) for d in docs
            if d.name != "README.md" and str(d.relative_to(root / "docs")) not in links]


# ---------------------------------------------------------------------- the checks on this repository
def test_every_benchmark_script_is_named_by_a_make_target_doc_or_test():
    assert not unnamed_benchmarks(ROOT), (
        f"{unnamed_benchmarks(ROOT)}: no make target, doc or test names them — delete them (record the "
        "commit that held them in their doc) or say in a doc what they are for")


def test_every_bench_script_names_the_doc_it_writes_on_its_first_line():
    assert list((ROOT / "benchmarks").glob("bench_*.py")), "no bench_*.py found"
    assert not bench_docstring_problems(ROOT), "\n".join(bench_docstring_problems(ROOT))


def test_readme_layout_table_matches_the_tree():
    rows = layout_table((ROOT / "README.md").read_text())
    assert len(rows) >= 10 and all(len(r) == 4 for r in rows), "the layout table: folder | stage | in | out"
    assert not layout_problems(ROOT), "\n".join(layout_problems(ROOT))


def test_the_docs_index_links_every_doc():
    assert not unindexed_docs(ROOT), f"{unindexed_docs(ROOT)}: add a line for each to docs/README.md"


# ---------------------------------------------------------------------- the checks can fail
def test_the_checks_catch_a_stray_script_a_silent_bench_and_a_stale_table(tmp_path):
    (tmp_path / "benchmarks").mkdir()
    (tmp_path / "docs" / "benchmarks").mkdir(parents=True)
    (tmp_path / "tests").mkdir()
    (tmp_path / "mk").mkdir()
    (tmp_path / "stages" / "graph").mkdir(parents=True)
    (tmp_path / "stages" / "newpkg").mkdir()
    for f in ("stages/__init__.py", "stages/graph/__init__.py", "stages/newpkg/__init__.py", "stages/poses.py"):
        (tmp_path / f).write_text("")
    (tmp_path / "Makefile").write_text("bench:\n\tfor b in benchmarks/bench_*.py; do python $$b; done\n")
    (tmp_path / "docs" / "benchmarks" / "speed.md").write_text("## speed\n")
    (tmp_path / "benchmarks" / "bench_speed.py").write_text('"""Benchmark: speed → docs/benchmarks/speed.md."""\n')
    (tmp_path / "benchmarks" / "bench_quiet.py").write_text('"""Benchmark: something.\n\nWrites docs/x.md."""\n')
    (tmp_path / "benchmarks" / "bench_gone.py").write_text('"""Benchmark: gone → docs/benchmarks/gone.md."""\n')
    (tmp_path / "benchmarks" / "tune_old.py").write_text('"""An experiment."""\n')
    (tmp_path / "benchmarks" / "helper.py").write_text("")
    (tmp_path / "tests" / "test_x.py").write_text("import helper\n")
    (tmp_path / "README.md").write_text(
        "# x\n\n## Layout\n\n| folder | stage | in | out |\n|---|---|---|---|\n"
        "| `stages/graph/`, `stages/poses.py` | graph-opt | a | b |\n| `stages/gone/` | old | a | b |\n\n## Next\n")
    assert unnamed_benchmarks(tmp_path) == ["benchmarks/tune_old.py"]
    problems = bench_docstring_problems(tmp_path)
    assert len(problems) == 2 and problems[0].startswith("bench_gone.py: names docs/benchmarks/gone.md")
    assert problems[1].startswith("bench_quiet.py: first docstring line names no")
    (tmp_path / "docs" / "TABLE1.md").write_text("# t\n")
    (tmp_path / "docs" / "README.md").write_text("[TABLE1.md](TABLE1.md) [x](benchmarks/other.md)\n")
    assert unindexed_docs(tmp_path) == ["docs/benchmarks/speed.md"]
    assert layout_problems(tmp_path) == [
        "stages/gone/: named in the README's layout table, not in the tree",
        "stages/newpkg/: in stages/, no row in the README's layout table"]


def test_every_benchmark_script_answers_help_without_measuring(tmp_path):
    """`--help` prints usage and exits: a script that ignores it would run (its sections go to tmp_path)."""
    import os
    import subprocess
    import sys

    scripts = sorted(p for p in (ROOT / "benchmarks").glob("*.py") if p.name not in ("__init__.py", "machine.py"))
    for script in scripts:
        out = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120,
                             env=os.environ | {"AUTOCAR_BENCH_DOCS": str(tmp_path)})
        assert out.returncode == 0 and out.stdout.lstrip().startswith("usage:"), f"{script.name}: {out.stderr[-300:]}"
