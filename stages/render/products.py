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

A product is skipped when its ``manifest.json`` exists and records the same parameters and package
version (``force=True`` rebuilds it).
"""

from __future__ import annotations

import json
import logging
from pathlib import Path

import numpy as np

from .. import __version__
from ..errors import UserError

log = logging.getLogger(__name__)

SEED_SE = 1_000_000
SEED_RE = 2_000_000
SEED_EXAMPLE = 3_000_000
TRAINING_SEED_LIMIT = 1_000_000
# cases for tuning pipeline parameters (docs/benchmarks/graph_threshold.md; the tuning scripts were removed in
# 4cf1374: git show 4cf1374:benchmarks/tune_graph_threshold.py): data-re-like, but never
# evaluated on and disjoint from the training trees (seeds 0–59)
SEED_RE_TUNING = 900_000

__all__ = ["make_example", "example_pose_model", "EXAMPLE_VIEWS", "make_se", "make_re", "ensure_case", "SEED_SE",
           "SEED_RE", "SEED_RE_TUNING", "SEED_EXAMPLE"]


def _side(seed: int) -> str:
    return "left" if seed % 3 != 2 else "right"


def ensure_case(folder, seed: int, side: str | None = None):
    """Path of the prepared case for ``seed`` in ``folder``, creating it with ``prep-ct`` if missing.

    Uses ``stages.prep_ct.pipeline.prepare_synthetic`` (the procedural trees; it writes both sides).
    If that stage is not installed, falls back to :func:`stages.render.phantom.tube_case` with a warning.
    """
    from ..prepared_case import PreparedCase

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


def _write_manifest(manifest: Path, params: dict, items: list) -> None:
    from ..artefacts import write_json

    write_json(manifest, {"parameters": params, "version": __version__, "complete": True, "items": items})


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
                 pose_model=None, progress=None) -> dict:
    """The bundled example: one dynamic case, two 8-bit runs of ``size``² × ``n_frames`` frames, from the
    two clusters of :func:`example_pose_model`. 49 frames (3.3 s) is the shortest length, of 42–54 tried,
    at which both runs of seed 3 000 000 hold ≥ 1.5 heartbeats of fully opacified frames (the bolus
    draws and wash-out time depend on the run length), so key frames can be found at every phase."""
    from .acquire import simulate_acquisition

    out = Path(out)
    params = {"seed": seed, "size": size, "n_frames": n_frames, "views": [list(v) for v in EXAMPLE_VIEWS],
              "transfer_syntax": "JPEG Lossless SV1"}
    manifest = out / "manifest.json"
    if not force and _up_to_date(manifest, params):
        return {"skipped": True, "out": out}
    cases = Path(out) / ".cases"
    case = ensure_case(cases, seed, "left")
    model = example_pose_model(case, pose_model)
    res = simulate_acquisition(case, model, out, seed, size=size, n_frames=n_frames, fps=15.0, bits=8,
                               n_keyframes=7, n_correspondences=60, progress=progress)
    import shutil

    from ..dicom_io import compress_lossless

    for run in ("run_a.dcm", "run_b.dcm"):  # lossless JPEG: the two runs stay under 5 MB together
        compress_lossless(out / run)
    shutil.rmtree(cases, ignore_errors=True)  # the example ships DICOMs + truth only
    _write_manifest(manifest, params, [{"run_a": "run_a.dcm", "run_b": "run_b.dcm", "truth": "truth.zarr"}])
    res.update(skipped=False, out=out)
    return res


def _in_pool(fn, arg_list, jobs: int, progress=None) -> list:
    """``fn(*args)`` for every tuple of ``arg_list``, ``jobs`` processes at a time; results in input order.

    Every task depends only on its own arguments (seeds included), so the outputs are the same for
    any number of jobs. The first failure cancels the tasks not yet started and is re-raised.
    """
    if jobs <= 1:
        out = []
        for args in arg_list:
            out.append(fn(*args))
            if progress:
                progress()
        return out
    from concurrent.futures import ProcessPoolExecutor

    import multiprocessing as mp

    with ProcessPoolExecutor(max_workers=jobs, mp_context=mp.get_context("spawn")) as pool:
        futures = [pool.submit(fn, *args) for args in arg_list]
        out = []
        try:
            for f in futures:
                out.append(f.result())
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
            jobs: int = 2) -> dict:
    """Synthetic evaluation set: ``n`` held-out trees, one static two-view silhouette pair each
    (cases prepared ``jobs`` at a time)."""
    from .pairs import pose_model_from, write_pair_shard

    out = Path(out)
    params = {"n": n, "size": size, "seed": SEED_SE}
    manifest = out / "manifest.json"
    if not force and _up_to_date(manifest, params):
        return {"skipped": True, "out": out}
    model = pose_model_from(pose_model)
    case_paths = _ensure_cases(out / "cases", [SEED_SE + i for i in range(n)], jobs, progress)
    write_pair_shard(out / "pairs.zarr", case_paths, model, n_pairs=n, seed=SEED_SE, size=size, misalign_px=0.0,
                     misalign_3d=0.0, translation_mm=0.0, jitter_px=0.0, min_visible=0.9, progress=progress)
    _write_manifest(manifest, params, [{"case": str(p.relative_to(out)), "pair": i} for i, p in enumerate(case_paths)])
    return {"skipped": False, "out": out, "cases": case_paths, "pairs": out / "pairs.zarr"}


def _re_case(out: Path, seed: int, model, size: int, n_frames: int) -> dict:
    """One case of the RE set: prepare its tree (if missing), then simulate its two runs."""
    from .acquire import simulate_acquisition

    case = ensure_case(out / "cases", seed)
    case_dir = out / f"case_{seed:07d}"
    simulate_acquisition(case, model, case_dir, seed, size=size, n_frames=n_frames, fps=15.0, bits=8,
                         n_keyframes=7, n_correspondences=60)
    return {"case": str(case.relative_to(out)), "dir": case_dir.name}


def make_re(out="data/re", n: int = 21, size: int = 512, n_frames: int = 42, force: bool = False, pose_model=None,
            progress=None, jobs: int = 2, seed: int = SEED_RE) -> dict:
    """Real-world-like set: ``n`` dynamic cases, two XA runs each, 7 key-frame pairs with correspondences
    (case seeds ``seed``, ``seed`` + 1, …; :data:`SEED_RE_TUNING` gives the parameter-tuning set).

    Cases are prepared and simulated ``jobs`` at a time (one process per case); every case depends only
    on its seed, so the files are byte-identical for any ``jobs``.
    """
    from .pairs import pose_model_from

    out = Path(out)
    params = {"n": n, "size": size, "n_frames": n_frames, "seed": seed}
    manifest = out / "manifest.json"
    if not force and _up_to_date(manifest, params):
        return {"skipped": True, "out": out}
    model = pose_model_from(pose_model)
    items = _in_pool(_re_case, [(out, seed + i, model, size, n_frames) for i in range(n)], jobs, progress)
    _write_manifest(manifest, params, items)
    return {"skipped": False, "out": out, "items": items}


def check_training_seed(seed: int) -> None:
    """Training must not reuse the evaluation/example seeds."""
    if seed >= TRAINING_SEED_LIMIT:
        raise UserError(f"seed {seed} is reserved for the evaluation sets and examples (training seeds are < {TRAINING_SEED_LIMIT})")
