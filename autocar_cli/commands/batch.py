"""``autocar batch``: ``reconstruct`` over a cohort of studies, on a local Dask cluster or a running one."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Optional

import typer

from ..common import check_choice, choice_option, console, module_constants, user_errors

METHODS, DEFAULT_METHOD = module_constants("stages.methods3d", "METHODS", "DEFAULT_METHOD")  # without numpy
PAIRS, = module_constants("stages.batch.plan", "PAIRS")
DEFAULT_RETRIES, = module_constants("stages.batch.engine", "DEFAULT_RETRIES")
SEG_METHODS = ("unet", "vesselness", "threshold")  # = stages.reconstruct.SEG_METHODS (that module is heavy)
SIDES = ("left", "right")


@user_errors
def batch_command(
    source: Path = typer.Argument(..., metavar="INPUT",
                                  help="A folder of study folders (each holding one study's XA runs), or a CSV manifest "
                                       "with the columns study, run_a, run_b (optional geometry_a, geometry_b; any other "
                                       "column is copied into studies.csv)."),
    output: Path = typer.Option(Path("autocar-batch"), "-o", "--output",
                                help="Output folder: one reconstruction folder per study, plus studies.csv, vessels.csv, "
                                     "lesions.csv and index.html."),
    workers: Optional[int] = typer.Option(None, "--workers", "-w", min=1,
                                          help="Worker processes of the local cluster, one study and one thread each "
                                               "(default: the usable CPU cores). Ignored with --scheduler."),
    scheduler: Optional[str] = typer.Option(None, "--scheduler",
                                            help="Address of a running Dask scheduler (tcp://HOST:PORT) to run the "
                                                 "studies on instead of a local cluster; its workers must see INPUT "
                                                 "and the output folder at the same paths (docs/BATCH.md)."),
    pairs: str = choice_option("best", "--pairs", choices=PAIRS,
                               help="For a study folder with more than two runs: 'best' reconstructs the pair of "
                                    "runs furthest apart in viewing angle, 'all' every pair at least 10° apart "
                                    "(into <study>/<run>__<run>/), 'every' that best pair with every other run "
                                    "of the study as further evidence (one reconstruction from all its runs)."),
    force: bool = typer.Option(False, "--force",
                               help="Redo every study, even those whose folders are complete and up to date "
                                    "(by default they are skipped and interrupted ones continued)."),
    retries: int = typer.Option(DEFAULT_RETRIES, "--retries", min=0,
                                help="How many more times a study is started on another worker when the worker "
                                     "running it dies (local cluster; a running cluster uses its own setting)."),
    quiet: bool = typer.Option(False, "--quiet", "-q", help="No progress and no summary; only errors and the exit code."),
    method: str = choice_option(DEFAULT_METHOD, "--method", choices=METHODS,
                                help="3D prediction of every study, as in autocar reconstruct."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="Weights of the learned --method (default: the shipped file)."),
    seg_method: str = choice_option("unet", "--seg-method", choices=SEG_METHODS, help="Vessel segmentation of every study."),
    keyframes: int = typer.Option(7, "--keyframes", "-k", min=1, help="Phase-matched key-frame pairs per study."),
    side: str = choice_option("left", "--side", choices=SIDES, help="Tree side the SBP network is conditioned on."),
    align_views: bool = typer.Option(True, "--align-views/--no-align-views",
                                     help="Per key frame, shift run B to be epipolar-consistent with run A."),
    calibrate: bool = typer.Option(False, "--calibrate/--no-calibrate",
                                   help="Refine run B's C-arm geometry from the vessels first (static scenes; "
                                        "docs/CALIBRATION.md)."),
    qca: bool = typer.Option(True, "--qca/--no-qca",
                             help="Quantitative coronary analysis per study (fills vessels.csv and lesions.csv)."),
):
    """Reconstruct a cohort of studies, one autocar reconstruct per study pair, in parallel on Dask: a local cluster by default (--workers processes × 1 thread), or a running cluster with --scheduler.

    Each study's folder OUTPUT/<study> is the folder autocar reconstruct -o writes. A study whose folder is complete and up to date is skipped; one that was interrupted continues where it stopped; --force redoes all. A study that fails (a bad file, refused geometry) is recorded with its one-line error and the others go on; a study whose worker dies is started again on another worker.

    studies.csv (status ok, failed or skipped, error, seconds, quality), vessels.csv, lesions.csv and index.html are rewritten as results arrive. Exit code 0 when every study succeeded, 1 when some failed, 2 when the batch itself cannot run.

    Examples:

      autocar batch studies/ -o cohort --workers 2

      autocar batch cohort.csv -o cohort --method sbp -k 5

      autocar batch studies/ -o cohort --scheduler tcp://10.0.0.5:8786

      autocar batch studies/ -o cohort --pairs all --no-qca
    """
    from stages.core.errors import UserError

    check_choice(method, METHODS, "--method")
    check_choice(seg_method, SEG_METHODS, "--seg-method")
    check_choice(side, SIDES, "--side")
    check_choice(pairs, PAIRS, "--pairs")
    if weights is not None and not weights.is_file():
        raise UserError(f"{weights}: no such file (--weights)")
    if scheduler is not None and "://" not in scheduler:
        raise UserError(f"--scheduler {scheduler!r}: give the scheduler's address as tcp://HOST:PORT")
    from stages.batch.engine import check_output, run_batch
    from stages.batch.plan import plan_batch

    check_output(output)
    plan = plan_batch(source, output, pairs)
    options = {"method": method, "weights": str(weights) if weights else None, "seg_method": seg_method,
               "k": keyframes, "side": side, "align_views": align_views, "qca": qca, "calibrate": calibrate}
    if not quiet:
        for task in plan.tasks:
            if task.error:
                console.print(f"[bold red]cannot run[/] {_escape(task.key)}: {_escape(task.error)}", highlight=False)
    view = _Progress(quiet, output)
    start = time.monotonic()
    with view:
        results = run_batch(plan, output, options, workers=workers, scheduler=scheduler, force=force, retries=retries,
                            on_event=view)
    statuses = [r["study"]["status"] for r in results]
    n_failed = statuses.count("failed")
    if not quiet:
        if plan.ignored:
            console.print(f"not studies (no XA run inside): {', '.join(plan.ignored)}", highlight=False)
        console.print(f"{statuses.count('ok')} reconstructed, {statuses.count('skipped')} already complete (skipped), "
                      f"{n_failed} failed, in {time.monotonic() - start:.0f} s; {output}/studies.csv, vessels.csv, "
                      "lesions.csv, index.html", highlight=False, markup=False)
    if n_failed:
        raise typer.Exit(code=1)


class _Progress:
    """What the batch shows while it runs: a bar (studies done / failed / running, ETA) on a terminal, plain
    lines elsewhere, a line per failed study; nothing with --quiet."""

    def __init__(self, quiet: bool, output: Path):
        self.quiet, self.output = quiet, output
        self.bar = self.task = None
        self.done = self.failed = 0

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        if self.bar is not None:
            self.bar.__exit__(*exc)
        return False

    def __call__(self, kind: str, **info) -> None:
        if self.quiet:
            return
        if kind == "start":
            if info["dashboard"]:
                console.print(f"Dask dashboard: {info['dashboard']}", highlight=False, markup=False)
            line = f"{info['total']} study pair(s): {info['to_run']} to run"
            if info["to_run"]:
                line += f" on {info['workers']} worker(s)"
            if info["skipped"]:
                line += f", {info['skipped']} already complete (skipped)"
            if info["failed"]:
                line += f", {info['failed']} cannot run"
            console.print(line, highlight=False, markup=False)
            if info["to_run"]:
                from ..common import progress

                self.bar = progress()
                self.bar.__enter__()
                self.task = self.bar.add_task(self._label(min(info["to_run"], info["workers"])), total=info["to_run"])
            return
        row = info["result"]["study"]
        if row["status"] == "failed":
            self.failed += 1
            name = f"{row['study']}/{row['pair']}" if row["pair"] else row["study"]
            console.print(f"[bold red]failed[/] {_escape(name)}: {_escape(row['error'])}", highlight=False)
        else:
            self.done += 1
        if self.bar is not None:
            self.bar.update(self.task, advance=1, description=self._label(info["running"]))

    def _label(self, running: int) -> str:
        return f"studies ({self.done} done, {self.failed} failed, {running} running)"


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(str(text))


def register(app: typer.Typer) -> None:
    app.command("batch")(batch_command)
