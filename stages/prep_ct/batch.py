"""prep-ct's folder mode (``autocar prep-ct ... -o FOLDER``) under the output-folder policy of :mod:`stages.core.outputs`.

A batch of cases (procedural seeds or input files, the task dicts of :func:`stages.prep_ct.pipeline.run_batch`)
is prepared into one folder:

* a non-empty folder is refused unless ``force`` (remove what prep-ct wrote there — the files its manifest
  lists, or in a folder without one its ``*_left/right.zarr/.png`` — and prepare every case) or ``resume``
  (keep every case whose fingerprint matches and prepare the others: missing, failed, or from other
  inputs or parameters). Other files (e.g. cases hard-linked from another tree set, training's
  ``.render_meshes`` cache) are kept either way;
* a folder that already holds every case of the batch, up to date (a finished prep-ct run recorded them
  with the same fingerprints), is nothing to do, with or without ``resume``;
* while the batch runs the folder holds ``RUNNING``; ``summary.json`` (cases prepared, kept, failed)
  replaces it at the end. Each case is recorded in the manifest as soon as it is written, so an
  interrupted batch continues with ``resume``.

A case's fingerprint: the task's kind, its seed or its input file (path, size, modification time),
``--spacing/--origin/--side``, the preparation parameters and the package version.

Reads: the tasks' inputs. Writes: ``<case>_<side>.zarr`` (+ ``.png``) per tree, ``RUNNING`` → ``summary.json``,
``.autocar-manifest.json``.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Callable, Optional

from .. import __version__
from ..core.errors import UserError
from ..core.outputs import MANIFEST, OutputFolder, complete, file_identity, fingerprint
from .pipeline import run_batch

COMMAND = "prep-ct"
# what prep-ct writes in a folder, for --force in a folder written before manifests
KNOWN_PATTERNS = ("*_left.zarr", "*_right.zarr", "*_left.png", "*_right.png")


def task_key(task: dict) -> str:
    """The manifest's name for a task: ``synthetic:SEED`` or ``file:PATH`` (resolved)."""
    if task["kind"] == "synthetic":
        return f"synthetic:{int(task['seed'])}"
    return f"file:{Path(task['path']).resolve()}"


def task_fingerprint(task: dict) -> str:
    """Inputs and parameters of one task (not its output folder or label)."""
    source = ({"seed": int(task["seed"])} if task["kind"] == "synthetic"
              else {"file": file_identity(task["path"]), "spacing": task.get("spacing"),
                    "origin": task.get("origin"), "side": task.get("side")})
    return fingerprint(COMMAND, kind=task["kind"], params=task["params"], version=__version__, **source)


def _files_of(paths) -> list[str]:
    """The names a case wrote in the folder: its artefacts and their previews."""
    names = []
    for p in map(Path, paths):
        names.append(p.name)
        if p.with_suffix(".png").exists():
            names.append(p.with_suffix(".png").name)
    return names


def prepare_folder(tasks: list[dict], output, *, force: bool = False, resume: bool = False, jobs: int = 1,
                   on_done: Optional[Callable] = None) -> dict:
    """Run ``tasks`` (each with ``"output": str(output)``) into the folder ``output`` under the policy above.

    ``on_done(result)`` after each case prepared now (``run_batch``'s ``(task, paths, error)``). Returns
    ``{"skipped": bool, "written": [paths], "kept": [paths], "failures": [(label, error)], "out": Path}``;
    ``skipped``: every case was up to date, nothing was touched.
    """
    if force and resume:
        raise UserError("--force and --resume exclude each other: --force starts afresh, --resume reuses")
    out = Path(output)
    fps = {task_key(t): task_fingerprint(t) for t in tasks}
    result = {"skipped": False, "written": [], "kept": [], "failures": [], "out": out}
    if not force and complete(out, COMMAND, fps):
        result.update(skipped=True, kept=[str(out / f) for f in _recorded_zarrs(out, fps)])
        return result
    folder = OutputFolder(out, force=force, resume=resume, known_patterns=KNOWN_PATTERNS, kind=COMMAND,
                          resume_hint="keep its up-to-date cases and prepare the rest")
    folder.open(COMMAND, {"cases": len(tasks), "params": tasks[0]["params"] if tasks else {}})
    try:
        todo = []
        for t in tasks:
            key = task_key(t)
            if folder.reusable(key, fps[key]):
                result["kept"] += [str(out / f) for f in folder.manifest["stages"][key]["files"] if f.endswith(".zarr")]
            else:
                todo.append(t)

        def done(r):
            task, paths, error = r
            if error:
                result["failures"].append((task["label"], error))
            else:
                key = task_key(task)
                folder.record(key, fps[key], _files_of(paths))
                result["written"].extend(paths)
            if on_done:
                on_done(r)

        run_batch(todo, jobs=jobs, on_done=done)
        if result["failures"] and not result["written"] and not result["kept"]:
            folder.abandon()  # nothing prepared: a folder this run made goes; an existing one keeps RUNNING
            return result
        folder.finish({"command": COMMAND, "version": __version__, "cases": len(tasks),
                       "prepared": sorted(Path(p).name for p in result["written"]),
                       "kept": sorted(Path(p).name for p in result["kept"]),
                       "failures": [{"input": label, "error": err} for label, err in result["failures"]]})
    except BaseException:
        folder.abandon()
        raise
    return result


def _recorded_zarrs(out: Path, fps: dict) -> list[str]:
    """The artefacts an up-to-date folder holds for the stages ``fps`` (checked by ``complete``)."""
    stages = json.loads((out / MANIFEST).read_text()).get("stages", {})
    return [f for key in fps for f in stages[key].get("files", []) if f.endswith(".zarr")]
