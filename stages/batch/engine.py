"""Running a batch's tasks on Dask distributed: an embedded ``LocalCluster`` (N worker processes × 1 thread)
or a running cluster reached at its scheduler's address.

One task per study pair (:func:`stages.batch.study.run_study`). A task whose worker process dies is run again
on another worker, up to ``retries`` more times (the scheduler's ``allowed-failures``); a study that fails
by itself comes back as a failed row and is not retried. Studies whose folders are complete and up to date
are skipped before any cluster starts, so a rerun over a finished cohort starts none.

Reads/writes: through :mod:`stages.batch.study` and :mod:`stages.batch.cohort`.
"""

from __future__ import annotations

import contextlib
import logging
import os
import uuid
from pathlib import Path
from typing import Callable

from ..core.errors import UserError
from .cohort import write_cohort
from .plan import Plan
from .study import one_line, rows_from_folder, run_study, study_result, up_to_date

log = logging.getLogger(__name__)

DEFAULT_RETRIES = 2


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        return os.cpu_count() or 1


def check_output(out) -> None:
    """The batch's output folder may be new or a batch's own; refuse a file or another command's folder."""
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise UserError(f"{out}: exists and is not a folder; give an output folder")
    for name in ("summary.json", "RUNNING", "manifest.json"):
        if (out / name).exists():
            raise UserError(f"{out}: holds another autocar command's output ({name}); give a batch its own folder")


def run_batch(plan: Plan, out, options: dict, *, workers: int | None = None, scheduler: str | None = None,
              force: bool = False, retries: int = DEFAULT_RETRIES, on_event: Callable | None = None) -> list[dict]:
    """Reconstruct every task of ``plan`` into ``out``; returns the results in plan order.

    ``options``: the per-study ``reconstruct`` options (:data:`stages.batch.study.RECONSTRUCT_OPTIONS`).
    ``force``: redo every study, complete or not. ``on_event(kind, **info)`` is told ``"start"`` (``total``,
    ``skipped``, ``failed``, ``to_run``, ``dashboard``, ``workers``) and ``"result"`` (``result``, ``running``).
    """
    out = Path(out)
    tell = on_event or (lambda kind, **info: None)
    check_output(out)
    if workers is not None and int(workers) < 1:
        raise UserError(f"--workers must be ≥ 1, got {workers}")
    if int(retries) < 0:
        raise UserError(f"--retries must be ≥ 0, got {retries}")
    results: dict[str, dict] = {}
    todo = []
    for task in plan.tasks:
        t = task.as_dict()
        if task.error:
            results[task.key] = study_result(t, "failed", task.error)
        elif not force and up_to_date(t, options):
            results[task.key] = study_result(t, "skipped", rows=rows_from_folder(task.folder))
        else:
            todo.append(task)
    order = [t.key for t in plan.tasks]

    def save():
        write_cohort(out, [results[k] for k in order if k in results], plan.extra_columns)

    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise UserError(f"{out}: cannot create the output folder ({exc.strerror or exc})") from None
    save()
    counts = {"skipped": sum(r["study"]["status"] == "skipped" for r in results.values()),
              "failed": sum(r["study"]["status"] == "failed" for r in results.values())}
    if not todo:
        tell("start", total=len(order), to_run=0, dashboard=None, workers=0, **counts)
        return [results[k] for k in order]
    existing = "force" if force else "resume"
    with _quiet_dask(), _client(workers, scheduler, retries) as (client, n_workers):
        # the local scheduler serves its status page only with bokeh installed
        dashboard = _dashboard(client) if scheduler or _has_bokeh() else None
        tell("start", total=len(order), to_run=len(todo), dashboard=dashboard, workers=n_workers, **counts)
        from distributed import as_completed

        tag = uuid.uuid4().hex[:8]  # keys unique on a cluster shared with other batches
        futures = {client.submit(run_study, t.as_dict(), options, existing, key=f"autocar-batch-{tag}-{t.key}",
                                 pure=False): t for t in todo}
        pending = len(futures)
        for fut in as_completed(futures):
            task = futures[fut]
            try:
                result = fut.result()
            except Exception as exc:  # the task never returned: its workers kept dying, or the cluster went away
                result = study_result(task.as_dict(), "failed", _task_error(exc, retries))
            finally:
                fut.release()
            results[task.key] = result
            pending -= 1
            save()
            tell("result", result=result, running=min(pending, _worker_count(client, n_workers)))
    return [results[k] for k in order]


def _task_error(exc: BaseException, retries: int) -> str:
    from distributed.scheduler import KilledWorker

    if isinstance(exc, KilledWorker):
        return (f"the worker running it died {retries + 1} time(s) (out of memory? killed?); "
                "rerun the batch to try again")
    return one_line(f"{type(exc).__name__}: {exc}")


@contextlib.contextmanager
def _quiet_dask():
    """Dask's own INFO/WARNING lines (workers starting, a dead worker restarted) would bury the progress bar and
    the per-study lines: they stop at Dask's own handler, set to errors only, instead of reaching ours."""
    loggers = [logging.getLogger(n) for n in ("distributed", "tornado", "bokeh")]
    saved = [(lg, lg.propagate, [(h, h.level) for h in lg.handlers]) for lg in loggers]
    for lg in loggers:
        lg.propagate = False
        for h in lg.handlers:
            h.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, propagate, handlers in saved:
            lg.propagate = propagate
            for h, level in handlers:
                h.setLevel(level)


@contextlib.contextmanager
def _client(workers: int | None, scheduler: str | None, retries: int):
    """A Dask client on a running cluster (``scheduler``) or on a local cluster started here and closed on
    the way out (Ctrl-C and SIGTERM included: its worker processes end with it)."""
    import dask
    from distributed import Client

    if scheduler:
        try:
            client = Client(scheduler, timeout="20s")
        except (OSError, TimeoutError) as exc:
            raise UserError(f"--scheduler {scheduler}: cannot reach the Dask scheduler ({one_line(exc)})") from None
        with client:
            yield client, _worker_count(client, 0)
        return
    from distributed import LocalCluster

    n = int(workers or usable_cores())
    environ = dict(dask.config.get("distributed.nanny.pre-spawn-environ", {}))
    environ.update({var: 1 for var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS",
                                       "NUMEXPR_NUM_THREADS", "NUMBA_NUM_THREADS")})
    config = {"distributed.scheduler.allowed-failures": int(retries),
              "distributed.nanny.pre-spawn-environ": environ,
              # a study is a long task: never move it to another worker while it runs
              "distributed.scheduler.work-stealing": False}
    with dask.config.set(config):
        # any free port: several batches (or other programs) may share a machine
        dashboard = "127.0.0.1:0" if _has_bokeh() else None
        # the worker processes log only what is critical: a study's failure comes back through its future (the
        # studies table's error column), while at shutdown a worker's heartbeat can race the closing scheduler
        # and log a harmless traceback at ERROR level
        with LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=dashboard,
                          silence_logs=logging.CRITICAL) as cluster, Client(cluster) as client:
            yield client, n


def _has_bokeh() -> bool:
    import importlib.util

    return importlib.util.find_spec("bokeh") is not None


def _dashboard(client) -> str | None:
    try:
        if "dashboard" not in (client.scheduler_info().get("services") or {}):
            return None
        return client.dashboard_link
    except Exception:  # no dashboard is no reason to stop a batch
        return None


def _worker_count(client, default: int) -> int:
    try:
        return sum(client.nthreads().values()) or default
    except Exception:
        return default
