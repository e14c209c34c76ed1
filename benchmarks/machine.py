"""Machine description and timing helpers shared by the benchmark scripts."""

from __future__ import annotations

import datetime as dt
import os
import platform
import statistics
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def machine_description() -> str:
    cpu = platform.processor() or "unknown CPU"
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    mem = ""
    try:
        kb = int(Path("/proc/meminfo").read_text().split()[1])
        mem = f", {kb / 2**20:.0f} GiB RAM"
    except (OSError, ValueError, IndexError):
        pass
    return f"{os.cpu_count()} CPU cores ({cpu}){mem}, Python {platform.python_version()}, {platform.system()}"


def peak_rss_mb() -> float:
    """This process's peak resident memory (MB) since it started.

    Reads VmHWM (Linux): ``ru_maxrss`` of a process started by a large one (a benchmark's fresh child)
    begins at the parent's peak, because Linux carries it across fork and exec."""
    import resource

    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def repeat_timing(fn, repeats: int = 5, warmup: int = 1) -> dict:
    """Run fn repeatedly; min and median wall time in seconds (timing noise here is large: report both)."""
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return {"min": min(times), "median": statistics.median(times), "repeats": repeats}


def write_section(topic: str, title: str, command: str, body: str) -> Path:
    """Write docs/benchmarks/<topic>.md with the standard header (command, machine, date)."""
    path = ROOT / "docs" / "benchmarks" / f"{topic}.md"
    path.parent.mkdir(parents=True, exist_ok=True)
    text = (f"## {title}\n\n- command: `{command}`\n- machine: {machine_description()}\n"
            f"- date: {dt.datetime.now().strftime('%Y-%m-%d %H:%M')}\n\n{body.strip()}\n")
    path.write_text(text)
    return path
