# AutoCAR — every entry point a user or CI needs. `make help` lists them.
# torch 2.13.0 (CPU build) is installed first: a plain `torch` requirement could pull a multi-GB CUDA build.
# Where it comes from: what pip resolves locally (a wheel on disk, the configured index) when that is a CPU
# build; otherwise (a plain PyPI resolve on Linux takes the CUDA wheel + ~17 nvidia-* packages) PyTorch's CPU
# index, $(TORCH_INDEX). `make torch-source` says which, without installing anything.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
AUTOCAR := $(VENV)/bin/autocar
STAMP  := $(VENV)/.autocar-installed
OUT    ?= out
TORCH_VERSION ?= 2.13.0
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
TORCH_RESOLVE_ARGS ?=
export PYTHONUNBUFFERED := 1

# exit 0 when a `pip install --dry-run --report` installs no CUDA package (nvidia-*, cuda-*, triton)
TORCH_IS_CPU := import json, sys; r = json.load(open(sys.argv[1])); n = [i["metadata"]["name"].lower() for i in r["install"]]; sys.exit(1 if any(x.startswith(("nvidia-", "cuda-", "triton")) for x in n) else 0)

.PHONY: help install test test-fast demo bench clean torch-source

help:  ## list the targets
	@grep -hE '^[a-zA-Z0-9_-]+:.*## ' $(MAKEFILE_LIST) | sed 's/:.*## /\t/' | sort

install: $(STAMP)  ## create .venv and install torch 2.13.0 (CPU) + autocar with dev extras

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	@if $(PY) -m pip install -q --dry-run --report $(VENV)/torch-resolve.json $(TORCH_RESOLVE_ARGS) torch==$(TORCH_VERSION) \
	      && $(PY) -c '$(TORCH_IS_CPU)' $(VENV)/torch-resolve.json; then \
	  echo "torch $(TORCH_VERSION): the local resolve is a CPU build"; \
	  $(PY) -m pip install -q $(TORCH_RESOLVE_ARGS) torch==$(TORCH_VERSION); \
	else \
	  echo "torch $(TORCH_VERSION): the local resolve would take a CUDA build (or none); installing from $(TORCH_INDEX)"; \
	  $(PY) -m pip install -q --index-url $(TORCH_INDEX) torch==$(TORCH_VERSION); \
	fi
	$(PY) -m pip install -q -e '.[dev]'
	touch $@

torch-source:  ## say where `make install` would take torch from (local CPU build, or $(TORCH_INDEX)); installs nothing
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	@$(PY) -m pip install -q --dry-run --report $(VENV)/torch-resolve.json $(TORCH_RESOLVE_ARGS) torch==$(TORCH_VERSION) 2>/dev/null; \
	$(PY) -c 'import json, sys; r = json.load(open(sys.argv[1])); print("local resolve:", ", ".join(i["metadata"]["name"] + " " + i["metadata"]["version"] for i in r["install"]) or "nothing to install")' $(VENV)/torch-resolve.json; \
	if $(PY) -c '$(TORCH_IS_CPU)' $(VENV)/torch-resolve.json; then echo "source: local (CPU build)"; \
	else echo "source: $(TORCH_INDEX) (the local resolve holds CUDA packages)"; fi

test: install  ## set up and run the whole test suite
	$(PY) -m pytest -q

test-fast: install  ## the tests without the slow ones
	$(PY) -m pytest -q -m "not slow"

demo: install  ## reconstruct the bundled example end to end -> out/demo (report.html, per key frame .vtp/.stl/.json)
	bash examples/demo.sh $(OUT)/demo

bench: install  ## run every benchmark script and refresh docs/BENCHMARKS.md
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done
	$(PY) benchmarks/collect.py

clean:  ## remove generated outputs (keeps .venv and data/)
	rm -rf $(OUT) .pytest_cache

-include mk/*.mk
