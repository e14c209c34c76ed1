"""One study pair of a batch: run ``reconstruct`` on a Dask worker, tell whether its folder is already complete,
and read the cohort rows out of a finished folder.

The folder is the one ``autocar reconstruct -o`` writes (same function, same output-folder policy), so a
batch folder and a single reconstruction of the same runs are interchangeable; ``--resume`` semantics by
default, so a study interrupted by a killed worker or a stopped batch continues from its last complete stage.

Reads: the study's runs; ``summary.json``, ``qca.json`` and the manifest of a finished folder.
Writes: the study's output folder (through :func:`stages.reconstruct.reconstruct`).
"""

from __future__ import annotations

import logging
import os
import socket
import sys
import time
from pathlib import Path

from ..core.errors import UserError
from ..core.outputs import read_json_dict
from ..core.threads import use_threads

log = logging.getLogger(__name__)

# the per-study options of `reconstruct` a batch passes through, with reconstruct's defaults
RECONSTRUCT_OPTIONS = {"method": None, "weights": None, "seg_method": "unet", "k": 7, "side": "left",
                       "align_views": True, "qca": True, "calibrate": False}


def one_line(text) -> str:
    return " ".join(str(text).split())


def _one_thread() -> None:
    """One compute thread in this worker process: every worker owns one core, and torch, BLAS or numba pools
    of their own would oversubscribe the machine (a worker started by hand or by a job queue does not
    have the local cluster's environment, hence also here)."""
    use_threads(1, keep_env=True)


def run_study(task: dict, options: dict, existing: str = "resume") -> dict:
    """The Dask task: reconstruct one study pair into ``task["folder"]``; returns its cohort rows.

    A user error (bad file, refused geometry, no vessel) or any other exception of the study becomes a failed
    row with a one-line error, so it neither stops the batch nor gets retried (a retry would fail the same
    way); only the death of the worker process itself makes Dask run the task again elsewhere.
    """
    _one_thread()
    for name in ("stages", "autocar", "py.warnings"):  # the worker's terminal is the batch's: keep it for the bar
        logging.getLogger(name).setLevel(logging.ERROR)
    start = time.perf_counter()
    worker = f"{socket.gethostname()}:{os.getpid()}"
    try:
        from ..reconstruct import reconstruct

        reconstruct(task["run_a"], task["run_b"], task["folder"], geometry_a=task.get("geometry_a"),
                    geometry_b=task.get("geometry_b"), existing=existing, workers=1,
                    more_runs=task.get("more_runs") or (),
                    **{k: v for k, v in options.items() if v is not None})
        rows = rows_from_folder(task["folder"])
        status, error = "ok", ""
    except UserError as exc:
        rows, status, error = None, "failed", one_line(exc)
    except Exception as exc:  # a bug in one study must not stop the cohort: record it and where it happened
        log.debug("%s: reconstruct failed", task["folder"], exc_info=True)
        rows, status, error = None, "failed", one_line(f"{type(exc).__name__}: {exc} (internal error at "
                                                      f"{_innermost(exc)}; please report)")
    result = study_result(task, status, error, rows, seconds=round(time.perf_counter() - start, 2), worker=worker)
    result["study"]["worker_peak_rss_mb"] = _peak_rss_mb()
    return result


def _peak_rss_mb():
    """This worker process's peak resident memory so far (MB; Linux and macOS), for sizing workers."""
    try:
        import resource
    except ImportError:  # Windows
        return ""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return round(peak / (2**20 if sys.platform == "darwin" else 1024), 1)


def _innermost(exc: BaseException) -> str:
    """file:line of the innermost frame of our own code (else of any code) that raised ``exc``."""
    import traceback

    frames = traceback.extract_tb(exc.__traceback__)
    ours = [f for f in frames if "/stages/" in f.filename.replace("\\", "/")] or frames
    if not ours:
        return "?"
    f = ours[-1]
    return f"{Path(f.filename).name}:{f.lineno}"


def study_result(task: dict, status: str, error: str = "", rows: dict | None = None, seconds=None,
                 worker: str = "") -> dict:
    """A study's result: its ``studies.csv`` row and its vessel and lesion rows."""
    rows = rows or {"study": {}, "vessels": [], "lesions": []}
    row = {"study": task["study"], "pair": task["pair"], "run_a": task["run_a"], "run_b": task["run_b"],
           "more_runs": ";".join(task.get("more_runs") or []),
           "status": status, "error": error, "seconds": "" if seconds is None else seconds, "worker": worker,
           **rows["study"], "pairing": task.get("pairing", ""),
           "separation_deg": "" if task.get("separation_deg") is None else task["separation_deg"],
           "folder": task.get("folder", ""), **task.get("extra", {})}
    key = {"study": task["study"], "pair": task["pair"]}
    return {"study": row, "vessels": [{**key, **v} for v in rows["vessels"]],
            "lesions": [{**key, **les} for les in rows["lesions"]]}


def up_to_date(task: dict, options: dict) -> bool:
    """Is the study's folder a finished reconstruction of these runs with these options? Reads only small
    JSON files and the runs' sizes and times (what ``reconstruct`` fingerprints its segmentation with), so a
    rerun over a finished cohort costs milliseconds per study."""
    from ..core.outputs import MANIFEST, MARKER, SUMMARY
    from ..reconstruct import segment_fingerprint

    folder = Path(task["folder"])
    if (folder / MARKER).exists() or not (folder / SUMMARY).is_file():
        return False
    summary, manifest = read_json_dict(folder / SUMMARY), read_json_dict(folder / MANIFEST)
    if summary is None or manifest is None or manifest.get("command") != "reconstruct":
        return False
    wanted = {**RECONSTRUCT_OPTIONS, **{k: v for k, v in options.items() if v is not None}}
    if wanted["method"] is None:
        from ..methods3d import DEFAULT_METHOD

        wanted["method"] = DEFAULT_METHOD
    wanted["weights"] = str(wanted["weights"]) if wanted["weights"] else None
    have = summary.get("parameters") or {}
    if any(have.get(k) != v for k, v in wanted.items()):
        return False
    if [str(r) for r in have.get("more_runs") or []] != [str(r) for r in task.get("more_runs") or []]:
        return False  # reconstructed from other further runs (or none)
    stages = manifest.get("stages") or {}
    further = [(f"masks_{chr(ord('c') + n)}", run, None) for n, run in enumerate(task.get("more_runs") or [])]
    for name, run, geometry in (("masks_a", task["run_a"], task.get("geometry_a")),
                                ("masks_b", task["run_b"], task.get("geometry_b")), *further):
        if (stages.get(name) or {}).get("fingerprint") != segment_fingerprint(run, geometry, wanted["seg_method"]):
            return False  # another run, a changed file or another version of autocar
    files = [f for entry in stages.values() for f in entry.get("files", [])] + list(manifest.get("files", []))
    return all((folder / f).exists() for f in files)


def rows_from_folder(folder) -> dict:
    """The cohort rows of a finished reconstruction folder: quality (summary.json) and QCA (qca.json)."""
    folder = Path(folder)
    summary = read_json_dict(folder / "summary.json") or {}
    quality = summary.get("quality") or {}
    frames = quality.get("frames") or []
    reproj = quality.get("mean_reprojection_mm") or {}
    study = {"key_frames": len(summary.get("pairs") or []),
             "quality": "" if not quality else ("passed" if quality.get("passed") else "failed"),
             "verdict": quality.get("verdict", ""),
             "pieces": max((len(f.get("pieces") or []) for f in frames), default=""),
             "reprojection_a_mm": reproj.get("a", ""), "reprojection_b_mm": reproj.get("b", ""),
             "total_seconds_recorded": round(float(summary.get("total_seconds", 0.0)), 2),
             "lesion_count": 0, "report": str(folder / "report.html")}
    vessels, lesions = [], []
    qca = read_json_dict(folder / "qca.json") if (folder / "qca.json").is_file() else None
    for v in (qca or {}).get("vessels", []):
        diam = [float(d) for d in ((v.get("profile") or {}).get("diameter_mm") or [])]
        vessels.append({"key_frame": qca.get("frame", ""), "vessel": v.get("name", ""),
                        "length_mm": v.get("length_mm", ""),
                        "mean_diameter_mm": round(sum(diam) / len(diam), 3) if diam else "",
                        "min_diameter_mm": v.get("min_diameter_mm", "")})
        for les in v.get("lesions", []):
            bv = les.get("best_view") or {}
            lesions.append({"vessel": v.get("name", ""), "segment": les.get("segment", ""),
                            "ds_percent": _round(les.get("ds_percent"), 1), "mld_mm": _round(les.get("mld_mm"), 2),
                            "reference_mm": _round(les.get("reference_mm"), 2),
                            "length_mm": _round(les.get("length_mm"), 1),
                            "position_mm": _round(les.get("position_mm"), 1),
                            "best_view": _view_name(bv), "best_alpha_deg": bv.get("alpha_deg", ""),
                            "best_beta_deg": bv.get("beta_deg", "")})
    study["lesion_count"] = len(lesions)
    return {"study": study, "vessels": vessels, "lesions": lesions}


def _round(value, digits: int):
    return "" if value is None else round(float(value), digits)


def _view_name(bv: dict) -> str:
    if not bv or "alpha_deg" not in bv or "beta_deg" not in bv:
        return ""
    a, b = float(bv["alpha_deg"]), float(bv["beta_deg"])
    return f"{'LAO' if a >= 0 else 'RAO'} {abs(a):.0f}° {'CRA' if b >= 0 else 'CAU'} {abs(b):.0f}°"
