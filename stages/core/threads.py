"""How many CPU threads this process computes with: torch, numpy's BLAS/OpenMP pools and numba.

One place for the CLI's ``--threads``, the cohort workers and the benchmark workers. The count also decides the
last bits of BLAS reductions, and through graph-opt's discrete choices the graphs themselves (data-re
case_2000010: 1011 tracked nodes with one BLAS thread, 1010 with two), so every benchmark worker uses one thread,
as the CLI does by default.
"""

from __future__ import annotations

import os
import sys

THREAD_ENV = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS",
              "VECLIB_MAXIMUM_THREADS", "NUMBA_NUM_THREADS")


def use_threads(n: int, *, keep_env: bool = False) -> None:
    """Compute with ``n`` threads from now on: the environment variables the pools read when they start (kept where
    already set with ``keep_env``, e.g. by a cluster that placed the worker), and the pools already started (torch,
    numba, BLAS/OpenMP through threadpoolctl)."""
    n = max(int(n), 1)
    for var in THREAD_ENV:
        if keep_env:
            os.environ.setdefault(var, str(n))
        else:
            os.environ[var] = str(n)
    if "torch" in sys.modules:
        sys.modules["torch"].set_num_threads(n)
    if "numba" in sys.modules:
        try:
            sys.modules["numba"].set_num_threads(n)
        except (ValueError, AttributeError):  # its pool was started with fewer threads: nothing to lower
            pass
    if "numpy" in sys.modules:
        try:
            from threadpoolctl import threadpool_limits

            threadpool_limits(limits=n)
        except ImportError:
            pass
