"""`make install`'s torch source (issue 36, finding 2): the local resolve is used only when it is a CPU build;
a resolve holding CUDA packages sends the install to $(TORCH_INDEX). Checks the Makefile's own decision
snippet on the two resolves measured in docs/benchmarks/torch_install.md."""

from __future__ import annotations

import json
import re
import subprocess
import sys

from conftest import REPO


def _makefile_var(name: str) -> str:
    text = (REPO / "Makefile").read_text()
    m = re.search(rf"^{name} \S?= ?(.*)$", text, flags=re.M)
    assert m, f"{name} not in the Makefile"
    return m.group(1).strip()


def _report(tmp_path, names):
    path = tmp_path / "r.json"
    path.write_text(json.dumps({"version": "1", "install": [{"metadata": {"name": n, "version": "1"}} for n in names]}))
    return path


def _is_cpu(tmp_path, names) -> bool:
    code = _makefile_var("TORCH_IS_CPU")
    return subprocess.run([sys.executable, "-c", code, str(_report(tmp_path, names))]).returncode == 0


def test_local_cpu_resolve_is_used(tmp_path):
    assert _is_cpu(tmp_path, ["torch", "fsspec", "networkx", "sympy", "filelock", "Jinja2", "MarkupSafe", "mpmath"])
    assert _is_cpu(tmp_path, [])  # torch already installed: nothing to resolve


def test_cuda_resolve_goes_to_the_cpu_index(tmp_path):
    assert not _is_cpu(tmp_path, ["torch", "nvidia-cudnn-cu13", "triton", "sympy"])
    assert not _is_cpu(tmp_path, ["torch", "cuda-toolkit"])


def test_the_index_is_overridable_and_points_at_pytorchs_cpu_wheels():
    text = (REPO / "Makefile").read_text()
    assert _makefile_var("TORCH_INDEX") == "https://download.pytorch.org/whl/cpu"
    assert re.search(r"^TORCH_INDEX \?=", text, flags=re.M)  # `make install TORCH_INDEX=...` overrides it
    assert "--index-url $(TORCH_INDEX) torch==$(TORCH_VERSION)" in text
