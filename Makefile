# AutoCAR — every entry point a user or CI needs. `make help` lists them.
# torch 2.13.0 (CPU build) is installed first: a plain `torch` requirement could pull a multi-GB CUDA build.

PYTHON ?= python3
VENV   ?= .venv
PY     := $(VENV)/bin/python
AUTOCAR := $(VENV)/bin/autocar
STAMP  := $(VENV)/.autocar-installed
OUT    ?= out
export PYTHONUNBUFFERED := 1

.PHONY: help install test test-fast demo bench clean

help:  ## list the targets
	@grep -hE '^[a-zA-Z0-9_-]+:.*## ' $(MAKEFILE_LIST) | sed 's/:.*## /\t/' | sort

install: $(STAMP)  ## create .venv and install torch 2.13.0 (CPU) + autocar with dev extras

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q torch==2.13.0
	$(PY) -m pip install -q -e '.[dev]'
	touch $@

test: install  ## set up and run the whole test suite
	$(PY) -m pytest -q

test-fast: install  ## the tests without the slow ones
	$(PY) -m pytest -q -m "not slow"

demo: install  ## run the furthest working stages on bundled / built-in data
	bash examples/demo.sh $(OUT)/demo

bench: install  ## run every benchmark script and refresh docs/BENCHMARKS.md
	@for b in benchmarks/bench_*.py; do echo "== $$b"; $(PY) $$b || exit 1; done
	$(PY) benchmarks/collect.py

clean:  ## remove generated outputs (keeps .venv and data/)
	rm -rf $(OUT) .pytest_cache

-include mk/*.mk
