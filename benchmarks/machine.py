"""Shared by the benchmark scripts: the machine line, timing and memory measurement, the section writer.

Sections go to docs/benchmarks/<topic>.md; ``AUTOCAR_BENCH_DOCS=DIR`` sends them to DIR instead (a trial run).
"""

from __future__ import annotations

import datetime as dt
import os
import platform
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DOCS = Path(os.environ.get("AUTOCAR_BENCH_DOCS") or ROOT / "docs" / "benchmarks")


def machine_description() -> str:
    cpu, mem = platform.processor() or "unknown CPU", ""
    try:
        cpu = next(ln.split(":", 1)[1].strip() for ln in Path("/proc/cpuinfo").read_text().splitlines()
                   if ln.startswith("model name"))
    except (OSError, StopIteration):
        pass
    try:
        mem = f", {int(Path('/proc/meminfo').read_text().split()[1]) / 2**20:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    return f"{os.cpu_count()} CPU cores ({cpu}){mem}, Python {platform.python_version()}, {platform.system()}"


def _status_kib(field: str) -> int:
    """A field of /proc/self/status in KiB (-1 when it is not there)."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    return -1


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB) since it started: VmHWM on Linux (``ru_maxrss`` of a
    fresh child starts at its parent's peak, carried across fork and exec)."""
    try:
        kib = _status_kib("VmHWM")
    except OSError:
        kib = -1
    if kib < 0:
        import resource

        kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / 1024


def peak_memory_mb(fn) -> float:
    """Peak resident memory (MB) used by fn above the resident size just before it (NaN off Linux)."""
    import gc

    gc.collect()
    try:
        Path("/proc/self/clear_refs").write_text("5")  # resets VmHWM to the current RSS
    except OSError:
        return float("nan")
    before = _status_kib("VmRSS")
    fn()
    return (_status_kib("VmHWM") - before) / 1024.0


def run_child(cmd: list[str], cwd: Path = ROOT) -> tuple[float, float, int, float]:
    """Run ``cmd``: (wall s, peak RSS GiB of the child, return code, CPU s of the child and its workers).

    Through a wrapper process, so RUSAGE_CHILDREN of the wrapper is that command's own peak and CPU time
    (the CPU time tells how much of a slow wall time was waiting for cores taken by other jobs)."""
    import subprocess
    import sys

    code = ("import resource, subprocess, sys, time\n"
            "t = time.perf_counter(); rc = subprocess.call(sys.argv[1:]); dt = time.perf_counter() - t\n"
            "u = resource.getrusage(resource.RUSAGE_CHILDREN)\n"
            "print(dt, u.ru_maxrss, rc, u.ru_utime + u.ru_stime)")
    out = subprocess.run([sys.executable, "-c", code, *cmd], capture_output=True, text=True, cwd=cwd)
    last = out.stdout.strip().splitlines()[-1].split()
    return float(last[0]), int(last[1]) / 2**20, int(last[2]), float(last[3])


def timed(fn, *args, **kw):
    """(fn(*args, **kw), its wall time in seconds)."""
    t = time.perf_counter()
    out = fn(*args, **kw)
    return out, time.perf_counter() - t


def repeat_timing(fn, repeats: int = 5, warmup: int = 1) -> dict:
    """Run fn repeatedly: min and median wall time in seconds and every time (timing noise here is large)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return {"min": min(times), "median": statistics.median(times), "repeats": repeats, "times": times}


def load_average() -> str:
    """The 1-minute load average and the core count, for a section on a shared machine."""
    return f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores"


def min_median(times, fmt: str = "{:.2f}", sep: str = " | ") -> str:
    """Min and median of repeated timings, for two table cells (``sep=" / "``: one)."""
    return fmt.format(min(times)) + sep + fmt.format(statistics.median(times))


def write_section(topic: str, title: str, command: str, body: str) -> Path:
    """Write DOCS/<topic>.md with the standard header (command, machine, date)."""
    path = DOCS / f"{topic}.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = (f"## {title}\n\n- command: `{command}`\n- machine: {machine_description()}\n"
            f"- date: {dt.datetime.now().strftime('%Y-%m-%d %H:%M')}\n\n{body.strip()}\n")
    path.write_text(text)
    return path
