"""Which studies and run pairs a batch holds, from a folder of study folders or from a CSV manifest.

Every problem with the batch's own input (a manifest column missing, a file it names missing, two rows for one
pair) is a :class:`UserError` raised before anything runs. A problem of one study (fewer than two runs, no
admissible pair) only marks that study failed: the others go on.

Pairs, per study folder: exactly two runs make one pair; with more, ``pairs="best"`` keeps the pair with the
largest view separation that ``reconstruct`` accepts, ``pairs="all"`` every admissible pair, ``pairs="every"``
that best pair with every other run of the study as further evidence (one reconstruction from all its runs). The reason is
recorded per study (``Task.pairing``), and lands in ``studies.csv``.

Reads: folder listings, DICOM headers (not their pixels) of studies with more than two runs. Writes nothing.
"""

from __future__ import annotations

import csv
import logging
import re
from dataclasses import asdict, dataclass, field
from itertools import combinations
from pathlib import Path

from ..core.errors import UserError

log = logging.getLogger(__name__)

PAIRS = ("best", "all", "every")
REQUIRED_COLUMNS = ("study", "run_a", "run_b")
OPTIONAL_COLUMNS = ("geometry_a", "geometry_b")
FRAME_SUFFIXES = {".png", ".tif", ".tiff", ".jpg", ".jpeg", ".bmp"}  # = stages.core.runs.IMAGE_SUFFIXES
NOT_DICOM = {".json", ".txt", ".md", ".csv", ".html", ".png", ".jpg", ".jpeg", ".gif", ".py", ".zip", ".xml",
             ".pdf", ".log"}
# a study or pair name becomes a folder name: keep it a plain one
_SAFE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._+=@,-]*$")


@dataclass
class Task:
    """One study pair: what to reconstruct and where. ``error`` set: a study that cannot run (no task)."""

    study: str
    pair: str  # "" when the study has a single pair (its folder is then OUT/<study>)
    run_a: str = ""
    run_b: str = ""
    geometry_a: str | None = None
    geometry_b: str | None = None
    folder: str = ""
    pairing: str = ""  # which pair and why
    separation_deg: float | None = None
    extra: dict = field(default_factory=dict)  # the manifest's extra columns, carried into the outputs
    more_runs: list = field(default_factory=list)  # further runs of the study, as evidence (pairs="every")
    error: str | None = None

    @property
    def key(self) -> str:
        return f"{self.study}/{self.pair}" if self.pair else self.study

    def as_dict(self) -> dict:
        return asdict(self)


@dataclass
class Plan:
    tasks: list[Task]
    extra_columns: list[str]
    ignored: list[str]  # folders of INPUT that hold no run at all (e.g. data-re's prepared cases)
    source: str


def plan_batch(input_path, out, pairs: str = "best") -> Plan:
    """The batch's tasks, in a fixed order (folder: study names sorted; manifest: its row order)."""
    if pairs not in PAIRS:
        raise UserError(f"unknown --pairs {pairs!r} (choose from {', '.join(PAIRS)})")
    src = Path(input_path)
    if not src.exists():
        raise UserError(f"{src}: no such file or folder")
    out = Path(out)
    if src.is_dir():
        plan = _plan_folder(src, out, pairs)
    elif src.suffix.lower() == ".csv":
        plan = _plan_manifest(src, out)
    else:
        raise UserError(f"{src}: give a folder of study folders or a CSV manifest (study, run_a, run_b)")
    if not plan.tasks:
        raise UserError(f"{src}: no study found (a study is a folder holding two or more XA runs)")
    return plan


# ---------------------------------------------------------------------------------------------- manifest
def _plan_manifest(path: Path, out: Path) -> Plan:
    try:
        text = path.read_text(encoding="utf-8-sig")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{path}: cannot read the manifest ({exc})") from None
    reader = csv.reader(text.splitlines())
    header = [h.strip() for h in next(reader, [])]
    missing = [c for c in REQUIRED_COLUMNS if c not in header]
    if missing:
        raise UserError(f"{path}: no column {', '.join(missing)} (a manifest needs the columns "
                        f"{', '.join(REQUIRED_COLUMNS)}; found {', '.join(header) or 'none'})")
    doubled = sorted({h for h in header if header.count(h) > 1})
    if doubled or "" in header:
        raise UserError(f"{path}: column {', '.join(doubled) or '(empty name)'} appears "
                        f"{'twice' if doubled else 'in the header'}; every column needs one distinct name")
    extra_columns = [h for h in header if h not in REQUIRED_COLUMNS + OPTIONAL_COLUMNS]
    rows = []
    for line, values in enumerate(reader, start=2):
        if not any(v.strip() for v in values):
            continue
        if len(values) != len(header):
            raise UserError(f"{path}, line {line}: {len(values)} value(s) for {len(header)} column(s)")
        row = {h: v.strip() for h, v in zip(header, values)}
        for col in REQUIRED_COLUMNS:
            if not row[col]:
                raise UserError(f"{path}, line {line}: empty {col}")
        _check_name(row["study"], f"{path}, line {line}: study")
        for col in ("run_a", "run_b", *OPTIONAL_COLUMNS):
            if row.get(col):
                p = Path(row[col])
                p = p if p.is_absolute() else path.parent / p
                if not p.exists():
                    raise UserError(f"{path}, line {line}: {col} {row[col]}: no such file or folder")
                row[col] = str(p)
        rows.append((line, row))
    per_study: dict[str, list] = {}
    for line, row in rows:
        per_study.setdefault(row["study"], []).append((line, row))
    tasks, seen = [], {}
    for line, row in rows:
        several = len(per_study[row["study"]]) > 1
        pair = _pair_name(row["run_a"], row["run_b"]) if several else ""
        task = Task(row["study"], pair, row["run_a"], row["run_b"], row.get("geometry_a") or None,
                    row.get("geometry_b") or None, pairing="given by the manifest",
                    extra={c: row[c] for c in extra_columns})
        if task.key in seen:
            raise UserError(f"{path}, lines {seen[task.key]} and {line}: the same pair of study {row['study']} twice")
        seen[task.key] = line
        task.folder = str(out / task.key)
        tasks.append(task)
    return Plan(tasks, extra_columns, [], str(path))


def _check_name(name: str, where: str) -> None:
    if not _SAFE_NAME.match(name) or name in (".", ".."):
        raise UserError(f"{where} {name!r} cannot be a folder name (letters, digits and . _ + = @ , - only, "
                        "not starting with . or -)")


def _pair_name(run_a, run_b) -> str:
    def label(p):
        p = Path(p)
        return p.stem if p.is_file() else p.name

    name = f"{label(run_a)}__{label(run_b)}"
    return name if _SAFE_NAME.match(name) else re.sub(r"[^A-Za-z0-9._+=@,-]", "_", name)


# ---------------------------------------------------------------------------------------------- folder
def _plan_folder(src: Path, out: Path, pairs: str) -> Plan:
    out_resolved = out.resolve()
    tasks, ignored = [], []
    try:
        children = sorted(p for p in src.iterdir() if p.is_dir() and not p.name.startswith("."))
    except OSError as exc:
        raise UserError(f"{src}: cannot list the folder ({exc.strerror or exc})") from None
    for study_dir in children:
        if study_dir.resolve() == out_resolved or study_dir.suffix.lower() == ".zarr":
            continue  # the batch's own output inside its input, or an artefact
        runs = find_runs(study_dir)
        if not runs:
            ignored.append(study_dir.name)
            continue
        study = study_dir.name
        if not _SAFE_NAME.match(study):
            tasks.append(Task(study, "", error=f"{study_dir}: the folder name cannot name an output folder "
                                                "(letters, digits and . _ + = @ , - only)"))
            continue
        tasks.extend(_study_pairs(study, runs, out, pairs))
    if ignored:
        log.info("not studies (no XA run inside): %s", ", ".join(ignored))
    return Plan(tasks, [], ignored, str(src))


def find_runs(folder: Path) -> list[Path]:
    """The runs in one study folder: the files a DICOMDIR names, else DICOM files (``.dcm`` or a DICOM
    preamble), ``.npy``/``.npz`` stacks and sub-folders of frame images; sorted by name."""
    dicomdir = folder / "DICOMDIR"
    if dicomdir.is_file():
        return _dicomdir_runs(dicomdir)
    runs = []
    for p in sorted(folder.iterdir()):
        if p.name.startswith("."):
            continue
        suffix = p.suffix.lower()
        if p.is_dir():
            if suffix != ".zarr" and any(q.suffix.lower() in FRAME_SUFFIXES for q in p.iterdir() if q.is_file()):
                runs.append(p)
        elif suffix in (".npy", ".npz", ".dcm") or (suffix not in NOT_DICOM and _has_dicom_preamble(p)):
            runs.append(p)
    return runs


def _has_dicom_preamble(path: Path) -> bool:
    try:
        with open(path, "rb") as fh:
            head = fh.read(132)
    except OSError:
        return False
    return head[128:132] == b"DICM"


def _dicomdir_runs(dicomdir: Path) -> list[Path]:
    """The image files a DICOMDIR references (its IMAGE records), relative to its folder."""
    import pydicom

    try:
        ds = pydicom.dcmread(dicomdir)
        records = ds.DirectoryRecordSequence
    except Exception as exc:  # a corrupt DICOMDIR is that study's problem: list no runs from it
        log.warning("%s: unreadable DICOMDIR (%s)", dicomdir, exc)
        return []
    runs = []
    for rec in records:
        if str(rec.get("DirectoryRecordType", "")).upper() != "IMAGE" or "ReferencedFileID" not in rec:
            continue
        parts = rec.ReferencedFileID
        parts = [parts] if isinstance(parts, str) else list(parts)
        path = dicomdir.parent.joinpath(*parts)
        if path.is_file():
            runs.append(path)
    return sorted(runs)


def _study_pairs(study: str, runs: list[Path], out: Path, pairs: str) -> list[Task]:
    if len(runs) < 2:
        return [Task(study, "", str(runs[0]), error=f"{runs[0].parent}: only one run ({runs[0].name}); a study "
                                                     "needs two runs from different C-arm angles")]
    if len(runs) == 2:
        return [Task(study, "", str(runs[0]), str(runs[1]), folder=str(out / study), pairing="the study's two runs")]
    from ..core.geometry import MIN_VIEW_SEPARATION_DEG, view_separation_deg

    cameras, unreadable = {}, []
    for run in runs:
        try:
            cam = _camera(run)
        except UserError as exc:
            unreadable.append(str(exc))
            continue
        if cam is None:
            unreadable.append(f"{run}: no C-arm geometry")
        else:
            cameras[run] = cam
    admissible = []
    for a, b in combinations(sorted(cameras), 2):
        sep = view_separation_deg(cameras[a], cameras[b])
        if sep >= MIN_VIEW_SEPARATION_DEG:
            admissible.append((a, b, round(sep, 1)))
    left_out = f"; left out: {'; '.join(unreadable)}" if unreadable else ""
    if not admissible:
        return [Task(study, "", error=f"{runs[0].parent}: no two of its {len(runs)} runs are ≥ "
                                      f"{MIN_VIEW_SEPARATION_DEG:.0f}° apart{left_out}")]
    if pairs in ("best", "every"):
        a, b, sep = max(admissible, key=lambda t: t[2])  # the first of equals: the order is the names'
        why = f"best of {len(runs)} runs: the largest view separation ({sep:.1f}°) of {len(admissible)} admissible pair(s)"
        more = [str(r) for r in sorted(cameras) if r not in (a, b)] if pairs == "every" else []
        if more:
            why += f"; every other run as further evidence ({', '.join(Path(r).name for r in more)})"
        return [Task(study, "", str(a), str(b), folder=str(out / study), pairing=why + left_out, separation_deg=sep,
                     more_runs=more)]
    tasks = []
    for a, b, sep in admissible:
        name = _pair_name(a, b)
        tasks.append(Task(study, name, str(a), str(b), folder=str(out / study / name), separation_deg=sep,
                          pairing=f"one of {len(admissible)} admissible pairs of {len(runs)} runs ({sep:.1f}° apart)"
                                  + left_out))
    return tasks


def _camera(run: Path):
    """A run's C-arm camera: from the DICOM header alone, or (frames + geometry JSON) from the loaded run."""
    if run.is_file() and run.suffix.lower() not in (".npy", ".npz"):
        from ..core.dicom_io import read_xa

        return read_xa(run, load_pixels=False).camera
    from ..core.runs import load_run

    return load_run(run).camera
