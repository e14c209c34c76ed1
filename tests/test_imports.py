"""Every module of stages/ and autocar_cli/ imports on its own, in any order, and no two import each other.

Two checks:

* each seed shuffles the list of all modules and imports them one after another in a fresh interpreter:
  a circular import that only breaks when entered from one side, or a module that only imports after
  another one happened to run first, fails under some order;
* the import graph read with :mod:`ast` (every ``import`` statement, module level or inside a function)
  has no cycle. Function-level imports count: a lazy import that closes a circle still ties the two
  modules together. Imports of a module's own parent packages (``from . import KIND``) are left out; a
  package's ``__init__`` re-exporting its submodules is not a circle.
"""

from __future__ import annotations

import ast
import os
import random
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("stages", "autocar_cli")


def find_modules(root: Path, packages=PACKAGES) -> dict[str, tuple[Path, bool]]:
    """Dotted module name -> (file, is a package ``__init__``) for every .py file under ``packages``."""
    out = {}
    for pkg in packages:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            is_pkg = parts[-1] == "__init__"
            if is_pkg:
                parts = parts[:-1]
            out[".".join(parts)] = (path, is_pkg)
    return out


def import_graph(modules: dict[str, tuple[Path, bool]]) -> dict[str, set[str]]:
    """module -> the modules (of ``modules``) it imports anywhere in its source, parents excluded."""
    graph = {name: set() for name in modules}
    for name, (path, is_pkg) in modules.items():
        package = name if is_pkg else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom):
                if node.level:
                    parts = package.split(".")
                    base = ".".join(parts[: len(parts) - node.level + 1] + ([node.module] if node.module else []))
                else:
                    base = node.module or ""
                # ``from pkg import sub`` imports the submodule when there is one, else a name of pkg
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
            else:
                continue
            for target in targets:
                while target and target not in modules:  # ``import stages.core.geometry.x`` -> nearest module
                    target = target.rpartition(".")[0]
                if target and target != name and not name.startswith(target + "."):
                    graph[name].add(target)
    return graph


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (each one holds an import circle)."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []
    counter = 0

    def visit(v):  # Tarjan's algorithm (the graph is ~100 nodes: recursion depth is no concern)
        nonlocal counter
        index[v] = low[v] = counter
        counter += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                found.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_import_cycle_among_stages_and_cli():
    graph = import_graph(find_modules(ROOT))
    assert len(graph) > 50, "module discovery found too few modules"
    assert graph["stages.segment.train"], "the graph should see function-level imports too"
    found = cycles(graph)
    assert not found, "import circles (each group imports itself through the others): " + "; ".join(
        " ↔ ".join(c) for c in found)


def test_the_core_imports_no_stage():
    """stages/core/ sits below the stages: its modules import each other (and the stages package's
    ``__version__``), never a stage module or package."""
    graph = import_graph(find_modules(ROOT))
    core = [name for name in graph if name == "stages.core" or name.startswith("stages.core.")]
    assert len(core) >= 10, "stages/core/ should hold the shared modules"
    outside = {name: sorted(t for t in graph[name] if not t.startswith("stages.core")) for name in core}
    assert not any(outside.values()), {k: v for k, v in outside.items() if v}


def test_cycle_finder_sees_a_lazy_circle(tmp_path):
    """The check above can fail: a circle closed by an import inside a function is found, a package
    ``__init__`` importing its submodules (which import the package back) is not a circle."""
    pkg = tmp_path / "stages" / "pkg"
    pkg.mkdir(parents=True)
    (tmp_path / "stages" / "__init__.py").write_text("")
    (pkg / "__init__.py").write_text("from .a import f\nKIND = 'k'\n")
    (pkg / "a.py").write_text("from . import KIND\n\ndef f():\n    from .b import g\n    return g()\n")
    (pkg / "b.py").write_text("import numpy\nfrom stages.pkg.c import h\n\ndef g():\n    from .a import f\n")
    (pkg / "c.py").write_text("def h():\n    pass\n")
    graph = import_graph(find_modules(tmp_path, ("stages",)))
    assert graph["stages.pkg.b"] == {"stages.pkg.a", "stages.pkg.c"}
    assert cycles(graph) == [["stages.pkg.a", "stages.pkg.b"]]
    (pkg / "b.py").write_text("def g():\n    pass\n")
    assert cycles(import_graph(find_modules(tmp_path, ("stages",)))) == []


IMPORT_ALL = """
import importlib, sys, traceback
for name in sys.argv[1:]:
    try:
        importlib.import_module(name)
    except BaseException:
        print(f"importing {name} failed (order: {' '.join(sys.argv[1:])})")
        traceback.print_exc()
        sys.exit(1)
"""


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_every_module_imports_in_a_random_order(seed):
    names = sorted(find_modules(ROOT))
    random.Random(seed).shuffle(names)
    env = dict(os.environ, OMP_NUM_THREADS="1", MPLBACKEND="Agg")
    proc = subprocess.run([sys.executable, "-c", IMPORT_ALL, *names], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-4000:] + proc.stderr[-4000:]
