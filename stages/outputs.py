"""The output-folder policy of every stage command that writes a folder (``reconstruct`` first).

One rule for all of them:

* every input and option is validated *before* the folder is touched (the caller's job: build the
  :class:`OutputFolder` only after validation, then call :meth:`OutputFolder.open`);
* a non-empty folder is refused unless ``--force`` (which first removes what autocar wrote there, as
  listed in the folder's manifest, and nothing else) or ``--resume`` (which keeps the complete stage
  artefacts whose inputs and parameters match and recomputes the rest);
* while a run works, the folder holds a file named ``RUNNING``; the run's last act replaces it with
  ``summary.json``, so a folder with ``RUNNING`` in it is an interrupted or failed run;
* a run that fails before it wrote anything leaves no folder it created.

The manifest (``.autocar-manifest.json``, hidden) records per stage a fingerprint of its inputs and
parameters (including the fingerprints of the stages it read), the files it wrote and a little JSON
the next stages need (so a resumed run does not have to re-read every artefact). A stage is reused on
``--resume`` only when its fingerprint matches and all its files are present.

Reads/writes: the output folder, ``RUNNING``, ``summary.json``, ``.autocar-manifest.json``.
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
import shutil
from pathlib import Path
from typing import Any

from .artefacts import _json_ready, write_json
from .errors import UserError

MARKER = "RUNNING"
SUMMARY = "summary.json"
MANIFEST = ".autocar-manifest.json"


def file_identity(path) -> dict:
    """What identifies an input file for a fingerprint: resolved path, size and modification time."""
    p = Path(path)
    try:
        st = p.stat()
    except OSError:
        return {"path": str(p)}
    if p.is_dir():  # a frame folder: its files' names, sizes and times
        entries = sorted((q.name, q.stat().st_size, q.stat().st_mtime_ns) for q in p.iterdir() if q.is_file())
        return {"path": str(p.resolve()), "entries": entries}
    return {"path": str(p.resolve()), "size": st.st_size, "mtime_ns": st.st_mtime_ns}


def fingerprint(stage: str, **parts: Any) -> str:
    """A stable hash of a stage's name, inputs and parameters (any JSON-ready values)."""
    text = json.dumps({"stage": stage, **_json_ready(parts)}, sort_keys=True, default=str)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def _os_error(path: Path, exc: OSError, what: str) -> UserError:
    return UserError(f"{path}: cannot {what} ({exc.strerror or exc})")


class OutputFolder:
    """An output folder under the policy above. Use::

        folder = OutputFolder(out, force=force, resume=resume)   # after validating every input
        folder.open(command="reconstruct", parameters={...})
        try:
            if not folder.reusable("masks_a", fp):
                ... write masks_a.zarr ...
                folder.record("masks_a", fp, ["masks_a.zarr"], data={...})
            ...
            folder.finish(summary)
        except BaseException:
            folder.abandon()
            raise
    """

    def __init__(self, path, *, force: bool = False, resume: bool = False, known_patterns=()):
        """``known_patterns``: glob patterns of what the command writes, cleared by ``force`` in a folder an
        older autocar wrote without a manifest."""
        if force and resume:
            raise UserError("--force and --resume exclude each other: --force starts afresh, --resume reuses")
        self.path = Path(path)
        self.force, self.resume = bool(force), bool(resume)
        self.created = False
        self.manifest: dict = {"stages": {}}
        self.reused: list[str] = []
        self.known_patterns = tuple(known_patterns)
        self._check()

    # ------------------------------------------------------------------ before anything is written
    def _check(self) -> None:
        p = self.path
        if p.exists() and not p.is_dir():
            raise UserError(f"{p}: exists and is not a folder; give an output folder")
        if not p.exists():
            return
        try:
            entries = list(p.iterdir())
        except OSError as exc:
            raise _os_error(p, exc, "list the output folder") from None
        if entries and not (self.force or self.resume):
            raise UserError(f"{p}: output folder is not empty; pass --force to replace what autocar wrote there, "
                            f"or --resume to reuse its complete stages")
        mf = p / MANIFEST
        if self.resume and mf.exists():
            try:
                self.manifest = json.loads(mf.read_text())
                self.manifest.setdefault("stages", {})
            except (OSError, ValueError):
                self.manifest = {"stages": {}}  # unreadable manifest: nothing is reused

    def _clear_ours(self) -> None:
        """``--force``: remove what the manifest says autocar wrote, our marker/summary and our temporaries."""
        names = {MARKER, SUMMARY, MANIFEST}
        mf = self.path / MANIFEST
        if mf.exists():
            try:
                old = json.loads(mf.read_text())
                for entry in old.get("stages", {}).values():
                    names.update(entry.get("files", []))
                names.update(old.get("files", []))
            except (OSError, ValueError):
                pass
        else:  # written before manifests existed: what the command's own file names match
            for pattern in self.known_patterns:
                names.update(c.name for c in self.path.glob(pattern))
        for child in self.path.iterdir():
            ours = child.name in names or (child.name.startswith(".") and ".tmp-" in child.name)
            if not ours:
                continue
            try:
                if child.is_dir() and not child.is_symlink():
                    shutil.rmtree(child)
                else:
                    child.unlink()
            except OSError as exc:
                raise _os_error(child, exc, "remove (--force)") from None

    def open(self, command: str, parameters: dict | None = None) -> "OutputFolder":
        """Create the folder if needed, clear it with --force, and write the ``RUNNING`` marker."""
        p = self.path
        try:
            if not p.exists():
                p.mkdir(parents=True)
                self.created = True
            elif self.force:
                self._clear_ours()
            (p / SUMMARY).unlink(missing_ok=True)  # a summary belongs to a finished run only
        except UserError:
            raise
        except OSError as exc:
            raise _os_error(p, exc, "create the output folder") from None
        marker = {"command": command, "pid": os.getpid(), "parameters": parameters or {},
                  "started": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
                  "note": "this run has not finished; summary.json replaces this file when it does"}
        write_json(p / MARKER, marker)
        self._save_manifest()
        return self

    # ------------------------------------------------------------------ stages
    def reusable(self, stage: str, fp: str) -> bool:
        """With --resume: is ``stage`` complete here with the same fingerprint (and all its files present)?"""
        entry = self.manifest["stages"].get(stage)
        ok = (self.resume and entry is not None and entry.get("fingerprint") == fp
              and all((self.path / f).exists() for f in entry.get("files", [])))
        if ok:
            self.reused.append(stage)
        elif entry is not None:
            self.invalidate(stage)  # it is recomputed now; until recorded again it is not complete
        return ok

    def data(self, stage: str) -> dict:
        """The JSON a completed stage left for the next ones."""
        return self.manifest["stages"][stage].get("data", {})

    def record(self, stage: str, fp: str, files, data: dict | None = None) -> None:
        """Note that ``stage`` completed with fingerprint ``fp`` and wrote ``files`` (names in the folder)."""
        names = [Path(f).name for f in files]
        self.manifest["stages"][stage] = {"fingerprint": fp, "files": names, "data": _json_ready(data or {})}
        self._save_manifest()

    def add_files(self, files) -> None:
        """Files written outside any reusable stage (report, overlays), so --force can clear them."""
        known = set(self.manifest.setdefault("files", []))
        self.manifest["files"] = sorted(known | {Path(f).name for f in files})
        self._save_manifest()

    def invalidate(self, stage: str) -> None:
        self.manifest["stages"].pop(stage, None)
        self._save_manifest()

    def _save_manifest(self) -> None:
        write_json(self.path / MANIFEST, self.manifest)

    # ------------------------------------------------------------------ the end
    def finish(self, summary: dict) -> Path:
        """Write ``summary.json`` and remove ``RUNNING`` (in that order: the folder is never unmarked)."""
        out = write_json(self.path / SUMMARY, summary)
        self.add_files([SUMMARY])
        (self.path / MARKER).unlink(missing_ok=True)
        return out

    def abandon(self) -> None:
        """A failed or interrupted run: a folder this run created and wrote nothing useful in is removed;
        otherwise ``RUNNING`` stays so the folder says it is incomplete (``--resume`` continues it)."""
        if not self.created or not self.path.exists():
            return
        try:
            leftovers = [c for c in self.path.iterdir() if c.name not in (MARKER, MANIFEST)
                         and not (c.name.startswith(".") and ".tmp-" in c.name)]
            if not leftovers:
                shutil.rmtree(self.path, ignore_errors=True)
        except OSError:
            pass
