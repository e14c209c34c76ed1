"""What every command shares: the console, logging, threads, progress and the error → exit-code wrapper.

Kept light on purpose: ``autocar --help`` imports this module, so nothing heavy (numpy, scipy, torch,
zarr) is imported at module level here or in any command module.
"""

from __future__ import annotations

import functools
import logging
import signal
import time

import typer
from rich.console import Console
from rich.logging import RichHandler

from stages.core.errors import UserError

console = Console(stderr=True, soft_wrap=True)  # log lines are not cut at 80 columns when piped
log = logging.getLogger("autocar")

# Default threads of a compute command: 1. On a shared 2-core machine with other work running, the 3D
# stage of `make demo` took 456-706 s with 2 threads against 58 s with 1 (issue 36); measured again here
# under load, the SBP network on one key frame took 9-12 s with 1 thread and 76-102 s with 2
# (docs/benchmarks/threads_under_load.md): every extra thread of the chunked gather + matmul loop waits for
# a core another process holds, and the barriers between chunks turn the waits into a collapse. One
# thread cannot collapse; ask for more with --threads (or AUTOCAR_THREADS) on a quiet machine.
DEFAULT_THREADS = 1


def module_constants(module: str, *names: str) -> tuple:
    """Module-level literal constants of a stages module, read from its source without importing it.

    Why: the options' choices and defaults come from the library (e.g. ``stages.methods3d.METHODS``), but
    importing that module imports numpy, a third of ``autocar --help``'s start-up. The values are plain
    literals, so they are read from the source; tests/test_cli_help.py checks they equal the imported ones.
    """
    import ast
    import importlib.util

    spec = importlib.util.find_spec(module)
    tree = ast.parse(open(spec.origin, encoding="utf-8").read())
    found = {}
    for node in tree.body:
        if isinstance(node, ast.Assign) and len(node.targets) == 1 and isinstance(node.targets[0], ast.Name):
            if node.targets[0].id in names:
                found[node.targets[0].id] = ast.literal_eval(node.value)
    return tuple(found[n] for n in names)


def _no_bool_metavar() -> None:
    """Flags take no value, so the help must not show a ``<bool>`` metavar after them (typer shows one)."""
    try:
        from typer.core import TyperOption
    except ImportError:  # another typer layout: nothing to fix
        return
    original = getattr(TyperOption, "display_type_rich", None)
    if original is None or getattr(original, "_autocar", False):
        return

    def display_type_rich(self, ctx):
        if getattr(self, "is_flag", False) or getattr(self, "is_bool_flag", False):
            return None
        return original(self, ctx)

    display_type_rich._autocar = True
    TyperOption.display_type_rich = display_type_rich


_no_bool_metavar()


def choice_option(default, *names: str, choices, help: str):
    """An option taking one of ``choices``; --help lists them (as the metavar). Check the value with
    :func:`check_choice` so a wrong one is one ``error:`` line like every other bad input."""
    return typer.Option(default, *names, metavar="[" + "|".join(choices) + "]", help=help)


def check_choice(value, choices, option: str) -> None:
    if value is not None and value not in choices:
        raise UserError(f"unknown {option} {value!r} (choose from {', '.join(choices)})")


def force_option():
    return typer.Option(False, "--force", help="Replace the output artefact if it exists.")


def require_inputs(*paths) -> None:
    """Inputs are checked before the output: a missing one is named first."""
    from pathlib import Path

    for p in paths:
        if p is not None and not Path(p).exists():
            raise UserError(f"{p}: no such file or folder")


def refuse_existing(path, force: bool) -> None:
    """The single-artefact form of the output policy: an existing output is replaced only with --force."""
    from pathlib import Path

    if Path(path).exists() and not force:
        raise UserError(f"{path}: already exists; pass --force to replace it")


def threads_option():
    return typer.Option(DEFAULT_THREADS, "--threads", min=1, envvar="AUTOCAR_THREADS",
                        help="CPU threads for torch and the numpy pools. Default 1: more threads collapse on a "
                             "shared machine (see autocar_cli/common.py); raise it on a quiet one.")


def set_threads(n: int) -> None:
    """Use ``n`` threads in torch and in numpy's BLAS/OpenMP pools, now and in anything imported later."""
    from stages.core.threads import use_threads

    use_threads(n)


def setup_logging(verbose: bool = False) -> None:
    logging.basicConfig(
        level=logging.DEBUG if verbose else logging.INFO,
        format="%(message)s",
        handlers=[RichHandler(console=console, show_path=False, show_time=False)],
        force=True,
    )
    logging.captureWarnings(True)  # library warnings become one log line, not a raw UserWarning with a path


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so every ``finally``/atomic write cleans up the same way."""


def _on_sigterm(signum, frame):
    raise _Terminated()


def _error_line(message: str) -> None:
    console.print(f"[bold red]error:[/] {message}", highlight=False, soft_wrap=True, markup=True)


def user_errors(fn):
    """Decorator for command functions: a UserError (or an OSError on a file) becomes one red ``error:`` line
    on stderr and exit code 2; Ctrl-C and SIGTERM exit 130/143 after temporaries are removed."""

    @functools.wraps(fn)
    def wrapper(*args, **kwargs):
        setup_logging()
        previous = None
        try:
            previous = signal.signal(signal.SIGTERM, _on_sigterm)
        except ValueError:  # not the main thread (tests calling the function directly)
            pass
        try:
            return fn(*args, **kwargs)
        except UserError as exc:
            _error_line(_escape(str(exc)))
            raise typer.Exit(code=exc.exit_code) from None
        except OSError as exc:
            where = exc.filename if exc.filename is not None else "output"
            _error_line(_escape(f"{where}: {exc.strerror or exc}"))
            raise typer.Exit(code=2) from None
        except MemoryError:
            _error_line("out of memory (an input larger than it claims, or too large for this machine)")
            raise typer.Exit(code=2) from None
        except _Terminated:
            console.print("[yellow]terminated[/]")
            raise typer.Exit(code=143) from None
        except KeyboardInterrupt:
            console.print("[yellow]interrupted[/]")
            raise typer.Exit(code=130) from None
        finally:
            if previous is not None:
                signal.signal(signal.SIGTERM, previous)

    return wrapper


def _escape(text: str) -> str:
    from rich.markup import escape

    return escape(text)


def progress():
    """A progress display for slow loops, on stderr so stdout stays clean for data: a rich bar on a terminal,
    plain lines elsewhere (:class:`PlainProgress`). Both take ``add_task``, ``update``, ``advance``."""
    if not console.is_terminal:
        return PlainProgress()
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn, TimeRemainingColumn

    return Progress(
        TextColumn("[progress.description]{task.description}"), BarColumn(), MofNCompleteColumn(),
        TimeElapsedColumn(), TimeRemainingColumn(), console=console, transient=False,
    )


class PlainProgress:
    """The subset of ``rich.progress.Progress`` the commands use, as log lines: one line when a task has
    moved on by a tenth of its total (or every 30 s without a total), and one when it completes."""

    def __init__(self, every_fraction: float = 0.1, every_s: float = 30.0):
        self.every_fraction, self.every_s = every_fraction, every_s
        self.tasks: dict[int, dict] = {}

    def __enter__(self) -> "PlainProgress":
        return self

    def __exit__(self, *exc):
        return False

    def add_task(self, description: str, total=None, **_) -> int:
        tid = len(self.tasks)
        self.tasks[tid] = {"description": description, "total": total, "done": 0, "start": time.monotonic(),
                           "last_line": None, "last_t": time.monotonic()}
        return tid

    def advance(self, task: int, advance: float = 1) -> None:
        self.update(task, completed=self.tasks[task]["done"] + advance)

    def update(self, task: int, completed=None, total=None, description=None, advance=None, **_) -> None:
        t = self.tasks[task]
        if total is not None:
            t["total"] = total
        if description is not None:
            t["description"] = description
        if advance is not None:
            completed = t["done"] + advance
        if completed is None:
            return
        t["done"] = completed
        now = time.monotonic()
        total = t["total"]
        if total:
            step = max(1, int(total * self.every_fraction))
            due = completed >= total or t["last_line"] is None or completed - t["last_line"] >= step
        else:
            due = now - t["last_t"] >= self.every_s
        if not due or completed == t["last_line"] or not completed:
            return
        t["last_line"], t["last_t"] = completed, now
        elapsed = now - t["start"]
        eta = f", ETA {elapsed / completed * (total - completed):.0f} s" if total and completed < total else ""
        of = f"/{total:g}" if total else ""
        console.print(f"{t['description']}: {completed:g}{of}, {elapsed:.0f} s{eta}", highlight=False, markup=False)


class Steps:
    """Progress of the slow stages of a command: ``steps(stage, done, total)``, ``stage`` naming what is
    counted (e.g. "3D prediction, key frames").

    On a terminal a rich bar per stage (done / total, elapsed, ETA); elsewhere (a log file, a batch job)
    one plain line per step: ``3D prediction, key frames: 3/7, 41 s, ETA 55 s``.
    """

    def __init__(self, terminal: bool | None = None):
        self.terminal = console.is_terminal if terminal is None else terminal
        self._bar = None
        self._tasks: dict[str, int] = {}
        self._start: dict[str, float] = {}

    def __enter__(self) -> "Steps":
        if self.terminal:
            self._bar = progress()
            self._bar.__enter__()
        return self

    def __exit__(self, *exc):
        if self._bar is not None:
            self._bar.__exit__(*exc)
        return False

    def __call__(self, stage: str, done: int, total: int | None) -> None:
        start = self._start.setdefault(stage, time.monotonic())
        if self._bar is not None:
            if stage not in self._tasks:
                self._tasks[stage] = self._bar.add_task(stage, total=total)
            self._bar.update(self._tasks[stage], completed=done, total=total)
            return
        if not done:  # the stage starts: the clock runs from here
            return
        elapsed = time.monotonic() - start
        eta = ""
        if total and done:
            eta = f", ETA {elapsed / done * (total - done):.0f} s"
        console.print(f"{stage}: {done}/{total if total else '?'}, {elapsed:.0f} s{eta}", highlight=False)
