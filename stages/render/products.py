"""The project's seeded data products: bundled example, synthetic evaluation set (SE), real-world-like set (RE).

Reads: prepared cases (made here from seeds by ``prep-ct``'s procedural trees when missing), a pose
model (the built-in default unless given). Writes:

* ``examples/`` (:func:`make_example`): ``run_a.dcm``, ``run_b.dcm`` (256², 49 frames at 15 frames/s,
  8-bit, 3.2 MB each; one study, RAO caudal + LAO cranial) and ``truth.zarr`` (``autocar.xa-truth``) of
  one dynamic case — what ``make demo`` reconstructs.
* ``data/se`` (:func:`make_se`, Table 1): ``cases/`` with 90 prepared trees and ``pairs.zarr``
  (``autocar.render-pairs``): one static two-view pair per tree (no misalignment, no translation or
  jitter; pair i belongs to case i), plus ``manifest.json``.
* ``data/re`` (:func:`make_re`, Table 2): ``cases/`` with 21 prepared trees and ``case_XXXXXXX/``
  folders each holding two XA runs and their truth (7 key-frame pairs with ≥ 50 correspondences), plus
  ``manifest.json``.

Everything is deterministic from the seeds. Reserved seed ranges (training must stay below 1 000 000):

    training cases   0 – 999 999
    data-se          1 000 000 + i   (i = 0…89)
    data-re          2 000 000 + i   (i = 0…20)
    examples         3 000 000
    shape shift      5 000 000 + i   (benchmarks/bench_shape_shift.py; trees outside the generator's range)

A product is skipped when its ``manifest.json`` exists and records the same parameters and package
version, whatever ``resume`` says (``force=True`` rebuilds it). Otherwise its folder follows the policy of
:mod:`stages.core.outputs` (the CLI passes ``resume=False`` unless ``--resume``): a non-empty folder is refused
unless ``force`` (first remove what the product writes there — ``cases/``, ``pairs.zarr``, ``case_*/``,
the runs and truth, ``manifest.json`` — and nothing else, e.g. ``examples/README.md``) or ``resume`` (keep
the prepared cases, and data-re's finished cases, and make the rest); while it is built the folder holds
``RUNNING`` and ``manifest.json``, the record of a complete product, replaces it at the end.
:func:`simulate_runs` (``render xa``) follows the same policy, its up-to-date check being the manifest's
per-case fingerprints.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import time
from pathlib import Path

import numpy as np

from .. import __version__
from ..core.errors import UserError
from ..core.outputs import MANIFEST, OutputFolder, complete, file_identity, fingerprint

log = logging.getLogger(__name__)

SEED_SE = 1_000_000
SEED_RE = 2_000_000
SEED_EXAMPLE = 3_000_000
TRAINING_SEED_LIMIT = 1_000_000
# cases for tuning pipeline parameters (docs/benchmarks/graph_threshold.md; the tuning scripts were removed in
# 4cf1374: git show 4cf1374:benchmarks/tune_graph_threshold.py): data-re-like, but never
# evaluated on and disjoint from the training trees (seeds 0–59)
SEED_RE_TUNING = 900_000

__all__ = ["make_example", "example_pose_model", "EXAMPLE_VIEWS", "make_se", "make_re", "simulate_runs", "ensure_case",
           "SEED_SE", "SEED_RE", "SEED_RE_TUNING", "SEED_EXAMPLE"]

PRODUCT_MANIFEST = "manifest.json"
# what each product writes in its folder (--force removes these and nothing else)
SE_FILES = ("cases", "pairs.zarr")
RE_FILES = ("cases", "case_[0-9]*")
EXAMPLE_FILES = ("run_a.dcm", "run_b.dcm", "truth.zarr", ".cases")
XA_FILES = ("run_a.dcm", "run_b.dcm", "truth.zarr")


def _side(seed: int) -> str:
    return "left" if seed % 3 != 2 else "right"


def ensure_case(folder, seed: int, side: str | None = None):
    """Path of the prepared case for ``seed`` in ``folder``, creating it with ``prep-ct`` if missing.

    Uses ``stages.prep_ct.pipeline.prepare_synthetic`` (the procedural trees; it writes both sides).
    If that stage is not installed, falls back to :func:`stages.render.phantom.tube_case` with a warning.
    """
    from ..core.prepared_case import PreparedCase

    side = side or _side(seed)
    folder = Path(folder)
    path = folder / f"case_{seed:07d}_{side}.zarr"
    if path.exists():
        return path
    folder.mkdir(parents=True, exist_ok=True)
    try:
        from ..prep_ct.pipeline import prepare_synthetic as make
    except ImportError:
        make = None
    if make is not None:
        # prep-ct writes {case_id}_{side}.zarr; only the tree this data set uses is prepared
        make(int(seed), folder, case_id=f"case_{seed:07d}", sides=(side,))
        if not path.exists():
            raise UserError(f"{path}: prep-ct did not write the {side} tree of synthetic seed {seed}")
    else:
        from .phantom import tube_case

        log.warning("stages.prep_ct.prepare_synthetic not available: seed %d uses the simple tube tree", seed)
        case = tube_case(seed)
        case.case_id = f"case_{seed:07d}_{side}"
        case.side = side
        case.save(path, stage="render", parameters={"seed": seed, "fallback": "tube_case"})
    PreparedCase.load(path)  # validate
    return path


def _up_to_date(manifest: Path, params: dict) -> bool:
    if not manifest.exists():
        return False
    try:
        old = json.loads(manifest.read_text())
    except ValueError:
        return False
    return old.get("parameters") == params and old.get("version") == __version__ and old.get("complete", False)


def _manifest(command: str, params: dict, items: list) -> dict:
    """A complete product's ``manifest.json`` (the command is not part of the up-to-date check)."""
    return {"parameters": params, "version": __version__, "complete": True, "items": items, "command": command}


def _product_folder(out: Path, command: str, params: dict, *, force: bool, resume: bool, files, hint: str,
                    manifest: bool = True) -> OutputFolder:
    """The product's folder under the output policy, opened (``RUNNING`` written; an old ``manifest.json`` goes:
    the product is incomplete until the run's last act writes it again)."""
    folder = OutputFolder(out, force=force, resume=resume and not force, known_patterns=(*files, PRODUCT_MANIFEST),
                          kind=command, summary=PRODUCT_MANIFEST, manifest=manifest, resume_hint=hint)
    folder.open(command, params)
    return folder


# The example's view pair: the classic two-view study of a left tree, RAO 30° caudal 25° + LAO 45° cranial
# 25° (≈ 90° apart; on the example tree < 5 % of the centreline length is foreshortened below half, against
# 37 % in the LAO-caudal "spider" view).
EXAMPLE_VIEWS = ((-30.0, -25.0), (45.0, 25.0))


def example_pose_model(case, pose_model=None, views=EXAMPLE_VIEWS, margin: float = 0.08):
    """The pose model the example is drawn from: the two clusters of ``pose_model`` (built-in default) whose
    centres are nearest ``views`` (α, β), keeping only the recorded poses whose image holds the whole
    reference tree at least ``margin`` of the image size inside the border (room for cardiac and
    respiratory motion), so the tree is well inside both fields of view."""
    from ..poses import PoseModel
    from .pairs import case_from, pose_model_from, visible_fraction

    model = pose_model_from(pose_model)
    nodes = case_from(case).nodes.astype(float)
    picked = [int(np.argmin(np.hypot(*(model.centres - np.asarray(v)).T))) for v in views]
    if picked[0] == picked[1]:
        raise UserError(f"the pose model has no two distinct clusters near the views {views}")
    keep, labels = [], []
    for new_label, k in enumerate(picked):
        members = [i for i in np.flatnonzero(model.labels == k)
                   if visible_fraction(nodes, model.pose(int(i)).camera(), margin * model.table["rows"][i]) == 1.0]
        if not members:
            raise UserError(f"no pose of cluster {model.cluster_names[k]!r} holds the whole tree "
                            f"{margin:.0%} inside the image")
        keep += members
        labels += [new_label] * len(members)
    keep = np.asarray(keep)
    return PoseModel({f: v[keep] for f, v in model.table.items()}, np.asarray(labels, np.int32),
                     model.centres[picked], [model.cluster_names[k] for k in picked], np.full(2, 0.5),
                     "clusters", model.sources)


def make_example(out="examples", seed: int = SEED_EXAMPLE, size: int = 256, n_frames: int = 49, force: bool = False,
                 pose_model=None, progress=None, resume: bool = True) -> dict:
    """The bundled example: one dynamic case, two 8-bit runs of ``size``² × ``n_frames`` frames, from the
    two clusters of :func:`example_pose_model`. 49 frames (3.3 s) is the shortest length, of 42–54 tried,
    at which both runs of seed 3 000 000 hold ≥ 1.5 heartbeats of fully opacified frames (the bolus
    draws and wash-out time depend on the run length), so key frames can be found at every phase.

    The folder keeps no hidden manifest (it ships): ``force`` removes the runs, the truth and
    ``manifest.json``; ``resume`` renders the example again in place."""
    from .acquire import simulate_acquisition

    out = Path(out)
    params = {"seed": seed, "size": size, "n_frames": n_frames, "views": [list(v) for v in EXAMPLE_VIEWS],
              "transfer_syntax": "JPEG Lossless SV1"}
    if not force and _up_to_date(out / PRODUCT_MANIFEST, params):
        return {"skipped": True, "out": out}
    folder = _product_folder(out, "render example", params, force=force, resume=resume, files=EXAMPLE_FILES,
                             hint="render the example again in place", manifest=False)
    try:
        cases = Path(out) / ".cases"
        case = ensure_case(cases, seed, "left")
        model = example_pose_model(case, pose_model)
        res = simulate_acquisition(case, model, out, seed, size=size, n_frames=n_frames, fps=15.0, bits=8,
                                   n_keyframes=7, n_correspondences=60, progress=progress)
        import shutil

        from ..core.dicom_io import compress_lossless

        for run in ("run_a.dcm", "run_b.dcm"):  # lossless JPEG: the two runs stay under 5 MB together
            compress_lossless(out / run)
        shutil.rmtree(cases, ignore_errors=True)  # the example ships DICOMs + truth only
        folder.finish(_manifest("render example", params,
                                [{"run_a": "run_a.dcm", "run_b": "run_b.dcm", "truth": "truth.zarr"}]))
    except BaseException:
        folder.abandon()
        raise
    res.update(skipped=False, out=out)
    return res


def _in_pool(fn, arg_list, jobs: int, progress=None, on_result=None) -> list:
    """``fn(*args)`` for every tuple of ``arg_list``, ``jobs`` processes at a time; results in input order
    (``on_result(index, result)`` as each is taken, in that order).

    Every task depends only on its own arguments (seeds included), so the outputs are the same for
    any number of jobs. The first failure cancels the tasks not yet started and is re-raised. One task
    runs in this process.
    """
    if jobs <= 1 or len(arg_list) <= 1:
        out = []
        for i, args in enumerate(arg_list):
            out.append(fn(*args))
            if on_result:
                on_result(i, out[-1])
            if progress:
                progress()
        return out
    from concurrent.futures import ProcessPoolExecutor

    import multiprocessing as mp

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(fn, *args) for args in arg_list]
        out = []
        try:
            for i, f in enumerate(futures):
                out.append(f.result())
                if on_result:
                    on_result(i, out[-1])
                if progress:
                    progress()
        except BaseException:
            for f in futures:
                f.cancel()
            raise
    return out


def _ensure_cases(folder, seeds, jobs: int, progress=None) -> list[Path]:
    """ensure_case for many seeds, ``jobs`` processes at a time (results in seed order)."""
    return _in_pool(ensure_case, [(folder, s) for s in seeds], jobs, progress)


def make_se(out="data/se", n: int = 90, size: int = 512, force: bool = False, pose_model=None, progress=None,
            jobs: int = 2, resume: bool = True) -> dict:
    """Synthetic evaluation set: ``n`` held-out trees, one static two-view silhouette pair each
    (cases prepared ``jobs`` at a time; ``resume`` keeps the prepared cases in ``cases/`` and renders
    the pairs again)."""
    from .pairs import pose_model_from, write_pair_shard

    out = Path(out)
    params = {"n": n, "size": size, "seed": SEED_SE}
    if not force and _up_to_date(out / PRODUCT_MANIFEST, params):
        return {"skipped": True, "out": out}
    model = pose_model_from(pose_model)
    folder = _product_folder(out, "render se", params, force=force, resume=resume, files=SE_FILES,
                             hint="keep its prepared cases and render the pairs again")
    folder.add_files(SE_FILES)
    try:
        case_paths = _ensure_cases(out / "cases", [SEED_SE + i for i in range(n)], jobs, progress)
        write_pair_shard(out / "pairs.zarr", case_paths, model, n_pairs=n, seed=SEED_SE, size=size, misalign_px=0.0,
                         misalign_3d=0.0, translation_mm=0.0, jitter_px=0.0, min_visible=0.9, progress=progress)
        folder.finish(_manifest("render se", params,
                                [{"case": str(p.relative_to(out)), "pair": i} for i, p in enumerate(case_paths)]))
    except BaseException:
        folder.abandon()
        raise
    return {"skipped": False, "out": out, "cases": case_paths, "pairs": out / "pairs.zarr"}


def _re_case(out: Path, seed: int, model, size: int, n_frames: int, n_runs: int = 2) -> dict:
    """One case of the RE set: prepare its tree (if missing), then simulate its two (or three) runs."""
    from .acquire import simulate_acquisition

    case = ensure_case(out / "cases", seed)
    case_dir = out / f"case_{seed:07d}"
    simulate_acquisition(case, model, case_dir, seed, size=size, n_frames=n_frames, fps=15.0, bits=8,
                         n_keyframes=7, n_correspondences=60, n_runs=n_runs)
    return {"case": str(case.relative_to(out)), "dir": case_dir.name}


def make_re(out="data/re", n: int = 21, size: int = 512, n_frames: int = 42, force: bool = False, pose_model=None,
            progress=None, jobs: int = 2, seed: int = SEED_RE, resume: bool = True, n_runs: int = 2) -> dict:
    """Real-world-like set: ``n`` dynamic cases, two XA runs each, 7 key-frame pairs with correspondences
    (case seeds ``seed``, ``seed`` + 1, …; :data:`SEED_RE_TUNING` gives the parameter-tuning set).
    ``n_runs`` 3: each case also has a third run (``run_c.dcm``, another standard angle); its runs A and B are
    the two-run set's.

    Cases are prepared and simulated ``jobs`` at a time (one process per case); every case depends only
    on its seed, so the files are byte-identical for any ``jobs``. Each finished case is recorded in the
    folder's manifest (seed, size, frames, version); ``resume`` keeps those and makes the rest.
    """
    from .pairs import pose_model_from

    out = Path(out)
    params = {"n": n, "size": size, "n_frames": n_frames, "seed": seed, **({"runs": n_runs} if n_runs != 2 else {})}
    if not force and _up_to_date(out / PRODUCT_MANIFEST, params):
        return {"skipped": True, "out": out}
    model = pose_model_from(pose_model)
    folder = _product_folder(out, "render re", params, force=force, resume=resume, files=RE_FILES,
                             hint="keep its finished cases and make the rest")
    runs_kw = {"runs": n_runs} if n_runs != 2 else {}  # two-run sets keep their fingerprints
    fps = {f"case_{seed + i:07d}": fingerprint("render re case", seed=seed + i, size=size, n_frames=n_frames,
                                               version=__version__, **runs_kw) for i in range(n)}
    folder.add_files(["cases", *fps])
    try:
        items: dict[int, dict] = {}
        todo = []
        for i, (key, fp) in enumerate(fps.items()):
            if folder.reusable(key, fp):
                items[i] = folder.data(key)["item"]
                if progress:
                    progress()
            else:
                todo.append(i)

        def got(j, item):
            i = todo[j]
            key = f"case_{seed + i:07d}"
            folder.record(key, fps[key], [item["dir"]], data={"item": item})
            items[i] = item

        _in_pool(_re_case, [(out, seed + i, model, size, n_frames, n_runs) for i in todo], jobs, progress,
                 on_result=got)
        items_list = [items[i] for i in range(n)]
        folder.finish(_manifest("render re", params, items_list))
    except BaseException:
        folder.abandon()
        raise
    return {"skipped": False, "out": out, "items": items_list, "kept": list(folder.reused)}


def simulate_runs(cases, pose_model, out, seed: int, *, size: int = 512, n_frames: int = 42, bits: int = 8,
                  force: bool = False, resume: bool = True, pose_source=None, on_start=None) -> dict:
    """``render xa``: two simulated XA runs (+ truth) of each prepared case into the folder ``out`` (one case:
    ``run_a.dcm``, ``run_b.dcm``, ``truth.zarr`` there; several: a subfolder per case, named by its stem),
    case i with seed ``seed + i``, under the output policy (``resume`` keeps the cases already simulated
    with the same case file, seed, size, frames, bits, pose model and version; all of them so: nothing to
    do, ``skipped``). ``on_start(case) -> tick`` gives a per-frame progress callback for a case.
    Returns ``{"skipped", "out", "runs": [{"case", "dir", "reused", "clusters", "heart_rate_bpm",
    "median_phase_error"}]}``.
    """
    from .acquire import simulate_acquisition

    out, paths = Path(out), [Path(c) for c in cases]
    single = len(paths) == 1
    keys = ["runs" if single else p.stem for p in paths]
    if len(set(keys)) < len(keys):
        raise UserError("render xa: two prepared cases share a file name; their runs would share a folder")
    poses = file_identity(pose_source) if pose_source and str(pose_source) != "default" else "default"
    fps = {key: fingerprint("render xa", case=file_identity(p), seed=seed + i, size=size, n_frames=n_frames,
                            bits=bits, poses=poses, version=__version__)
           for i, (key, p) in enumerate(zip(keys, paths))}
    files = {key: list(XA_FILES) if single else [key] for key in keys}

    def row(key, p, data, reused):
        return {"case": p, "dir": out if single else out / key, "reused": reused, **data}

    if not force and complete(out, "render xa", fps):
        stages = json.loads((out / MANIFEST).read_text())["stages"]
        return {"skipped": True, "out": out,
                "runs": [row(k, p, stages[k].get("data", {}), True) for k, p in zip(keys, paths)]}
    folder = OutputFolder(out, force=force, resume=resume and not force,
                          known_patterns=XA_FILES if single else tuple(keys), kind="render xa",
                          resume_hint="keep the cases simulated with the same settings and simulate the rest")
    folder.open("render xa", {"cases": [str(p) for p in paths], "seed": seed, "size": size, "n_frames": n_frames,
                              "bits": bits})
    folder.add_files(XA_FILES if single else keys)
    runs = []
    try:
        for i, (key, p) in enumerate(zip(keys, paths)):
            if folder.reusable(key, fps[key]):
                runs.append(row(key, p, folder.data(key), True))
                continue
            d = out if single else out / key
            r = simulate_acquisition(p, pose_model, d, seed + i, size=size, n_frames=n_frames, bits=bits,
                                     progress=on_start(p) if on_start else None)
            data = {"clusters": [r["poses"][0]["cluster"], r["poses"][1]["cluster"]],
                    "heart_rate_bpm": float(r["heart_rate_bpm"]),
                    "median_phase_error": float(sorted(r["phase_error"])[len(r["phase_error"]) // 2])}
            folder.record(key, fps[key], files[key], data=data)
            runs.append(row(key, p, data, False))
        folder.finish({"command": "render xa", "version": __version__,
                       "runs": [{"case": str(r["case"]), "dir": str(r["dir"]), "reused": r["reused"]} for r in runs]})
    except BaseException:
        folder.abandon()
        raise
    return {"skipped": False, "out": out, "runs": runs}


def check_training_seed(seed: int) -> None:
    """Training must not reuse the evaluation/example seeds."""
    if seed >= TRAINING_SEED_LIMIT:
        raise UserError(f"seed {seed} is reserved for the evaluation sets and examples (training seeds are < {TRAINING_SEED_LIMIT})")


SEED_SHIFT = 5_000_000


def make_shape_shift(out, n: int, shift) -> Path:
    """The shape-shift set: ``n`` procedural trees deformed by ``shift`` (:class:`stages.anatomy.ShapeShift`),
    one static pair each rendered like data-se into ``out`` (``cases/``, ``pairs.zarr``); skipped when complete.
    Seeds from 5 000 000 on; a tree grown past the field of view is skipped for the next seed."""
    from ..core.artefacts import write_json
    from ..prep_ct.pipeline import prepare_synthetic
    from .pairs import case_from, pose_model_from, render_pair, write_pair_shard

    out = Path(out)
    manifest = out / "manifest.json"
    params = {"n": n, "seed": SEED_SHIFT, "shift": dataclasses.asdict(shift) | {"wavelength_mm": list(shift.wavelength_mm)}}
    if manifest.exists():
        if json.loads(manifest.read_text()).get("parameters") == params:
            return out
    model = pose_model_from(None)
    cases, seed = [], SEED_SHIFT
    while len(cases) < n:
        side = "left" if seed % 3 != 2 else "right"
        path = out / "cases" / f"case_{seed:07d}_{side}.zarr"
        if not path.exists():
            t0 = time.perf_counter()
            prepare_synthetic(seed, out / "cases", case_id=f"case_{seed:07d}", sides=(side,), shape_shift=shift)
            log.info("prepared %s (%.1f s)", path.name, time.perf_counter() - t0)
        # a tree grown past the field of view is skipped (the pair would be rendered with this very seed)
        try:
            render_pair(case_from(path), model, np.random.default_rng([SEED_SHIFT, len(cases)]), 512, 0.0, 0.0, 0.0, 0.0, 0.9)
            cases.append(path)
        except UserError as e:
            log.warning("skipped %s: %s", path.name, e)
        seed += 1
    write_pair_shard(out / "pairs.zarr", cases, model, n_pairs=n, seed=SEED_SHIFT, size=512,
                     misalign_px=0.0, misalign_3d=0.0, translation_mm=0.0, jitter_px=0.0, min_visible=0.9)
    write_json(manifest, {"parameters": params, "complete": True})
    return out
