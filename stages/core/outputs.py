"""The output-folder policy of every stage command that writes a folder: ``reconstruct``, ``prep-ct -o FOLDER``
(:mod:`stages.prep_ct.batch`) and ``render xa/se/re/example`` (:mod:`stages.render.products`).

One rule for all of them:

* every input and option is validated *before* the folder is touched (the caller's job: build the
  :class:`OutputFolder` only after validation, then call :meth:`OutputFolder.open`);
* a non-empty folder is refused unless ``--force`` (which first removes what autocar wrote there, as
  listed in the folder's manifest, and nothing else) or ``--resume`` (which keeps the complete stage
  artefacts whose inputs and parameters match and recomputes the rest);
* while a run works, the folder holds a file named ``RUNNING``; the run's last act replaces it with
  ``summary.json``, so a folder with ``RUNNING`` in it is an interrupted or failed run;
* a run that fails before it wrote anything leaves no folder it created;
* ``--resume`` continues only the same kind of run: a folder whose marker or manifest names another
  command is refused (``kind``);
* a folder that already holds everything a run would write, up to date (:func:`complete`, or a data
  product's own ``manifest.json``), is nothing to do: the command says so and exits 0, whatever the flags
  (``--force`` excepted: it rebuilds).

The manifest (``.autocar-manifest.json``, hidden) records per stage a fingerprint of its inputs and
parameters (including the fingerprints of the stages it read), the files it wrote and a little JSON
the next stages need (so a resumed run does not have to re-read every artefact), and the command that
wrote it. A stage is reused on ``--resume`` only when its fingerprint matches and all its files are
present. A command whose finished-run record is not ``summary.json`` (the data products' ``manifest.json``)
names it with ``summary=``.

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


def read_json_dict(path: Path) -> dict | None:
    """A JSON file holding an object, or None when it is missing, unreadable or not an object."""
    try:
        obj = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None


def written_by(path, summary: str = SUMMARY) -> str | None:
    """The command that wrote the output folder ``path``, as its marker, manifest or summary records it
    (``None``: none of them says, e.g. a folder an older autocar wrote)."""
    p = Path(path)
    for name in (MARKER, MANIFEST, summary):
        command = (read_json_dict(p / name) or {}).get("command")
        if isinstance(command, str) and command:
            return command
    return None


def complete(path, command: str, fingerprints: dict[str, str]) -> bool:
    """Does ``path`` hold a finished run of ``command`` (no ``RUNNING`` marker) in which every stage of
    ``fingerprints`` ({stage: fingerprint}) is recorded with that fingerprint and all its files present?
    Then a new run with these stages has nothing to do."""
    p = Path(path)
    if not p.is_dir() or (p / MARKER).exists():
        return False
    manifest = read_json_dict(p / MANIFEST)
    if manifest is None or manifest.get("command") != command:
        return False
    stages = manifest.get("stages") or {}
    for stage, fp in fingerprints.items():
        entry = stages.get(stage)
        if not isinstance(entry, dict) or entry.get("fingerprint") != fp:
            return False
        if not all((p / f).exists() for f in entry.get("files", [])):
            return False
    return True


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

    def __init__(self, path, *, force: bool = False, resume: bool = False, known_patterns=(), kind: str | None = None,
                 summary: str = SUMMARY, manifest: bool = True, resume_hint: str = "reuse its complete stages"):
        """``known_patterns``: glob patterns of what the command writes, cleared by ``force`` in a folder an
        older autocar wrote without a manifest. ``kind``: the command, checked on ``resume`` against the
        one that wrote the folder. ``summary``: the file that marks a finished run. ``manifest=False``:
        keep no hidden manifest (a folder that ships, like ``examples/``; ``force`` then clears
        ``known_patterns``). ``resume_hint``: what ``--resume`` does, for the refusal message."""
        if force and resume:
            raise UserError("--force and --resume exclude each other: --force starts afresh, --resume reuses")
        self.path = Path(path)
        self.force, self.resume = bool(force), bool(resume)
        self.created = False
        self.manifest: dict = {"stages": {}}
        self.reused: list[str] = []
        self.known_patterns = tuple(known_patterns)
        self.kind, self.summary, self.keep_manifest = kind, summary, bool(manifest)
        self.resume_hint = resume_hint
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
                            f"or --resume to {self.resume_hint}")
        if entries and self.resume and self.kind:
            other = written_by(p, self.summary)
            if other is not None and other != self.kind:
                raise UserError(f"{p}: written by autocar {other}, not {self.kind}; --resume continues only the same "
                                f"kind of run: pass --force to replace what autocar wrote there, or give another folder")
        mf = p / MANIFEST
        if self.resume and mf.exists():
            try:
                self.manifest = json.loads(mf.read_text())
                self.manifest.setdefault("stages", {})
            except (OSError, ValueError):
                self.manifest = {"stages": {}}  # unreadable manifest: nothing is reused

    def _clear_ours(self) -> None:
        """``--force``: remove what the manifest says autocar wrote, our marker/summary and our temporaries."""
        names = {MARKER, MANIFEST, self.summary}
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
            (p / self.summary).unlink(missing_ok=True)  # a summary belongs to a finished run only
        except UserError:
            raise
        except OSError as exc:
            raise _os_error(p, exc, "create the output folder") from None
        marker = {"command": command, "pid": os.getpid(), "parameters": parameters or {},
                  "started": _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
                  "note": f"this run has not finished; {self.summary} replaces this file when it does"}
        write_json(p / MARKER, marker)
        self.manifest["command"] = command
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
        if self.keep_manifest:
            write_json(self.path / MANIFEST, self.manifest)

    # ------------------------------------------------------------------ the end
    def finish(self, summary: dict) -> Path:
        """Write the summary (``summary.json`` unless the command names another file) and remove ``RUNNING``
        (in that order: the folder is never unmarked)."""
        out = write_json(self.path / self.summary, summary)
        self.add_files([self.summary])
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
