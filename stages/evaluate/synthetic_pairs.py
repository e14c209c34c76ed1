"""Evaluation of a 3D method on a rendered two-view set (data-se, ``make data-se``) — Table 1's protocol.

Reads: ``<data>/pairs.zarr`` (``autocar.render-pairs``) and the prepared cases it names (``<data>/cases/``).
Writes nothing; callers (benchmarks/table1.py, the data-se benchmarks, training/compare_sbp_se.py) write
their documents and per-case JSON.

* :func:`se_pairs` yields, per pair, the two masks and cameras and the ground truth: view A's stored
  silhouette, view B re-rendered from the case's full mesh with the default temporal-misalignment
  augmentation (a ``misalign_px`` px RMS TPS warp seeded per pair with ``[1_000_000, i]``; 0 keeps the
  stored silhouette), and the case's labels shifted by the pair's recorded translation. With
  ``mask_noise`` both masks then get segmenter-style errors (:mod:`stages.render.mask_noise`, seeded
  per pair with ``[1_000_000, i, 2]``): how a method copes with masks like the segmenter's.
* :func:`evaluate_many` runs prediction functions on every pair and scores them with
  :func:`stages.core.metrics.metrics_3d` (Dice, clDice, Tprec, Tsens, Chamfer, HD95 on the 0.5 mm grid);
  the ``*_predictor`` functions wrap the 3D methods for it.
* :func:`data_hash` fingerprints a set (for caches that must survive a regeneration of the same data).
"""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..core.artefacts import hash_file

ROOT = Path(__file__).resolve().parents[2]
SE_SEED = 1_000_000
METRIC_KEYS = ("dice", "cldice", "tprec", "tsens", "chamfer_mm", "hd95_mm")


def _without_created(node):
    """A zarr.json header without its ``created`` timestamps (they differ between identical regenerations)."""
    if isinstance(node, dict):
        return {k: _without_created(v) for k, v in node.items() if k != "created"}
    if isinstance(node, list):
        return [_without_created(v) for v in node]
    return node


def data_hash(data: Path) -> str:
    """Every file of pairs.zarr plus the header (zarr.json) of every prepared case it names; headers are
    hashed without their creation time, so a fresh regeneration of the same data keeps the same hash."""
    h = hashlib.sha256()
    headers = sorted((data / "cases").glob("*.zarr/zarr.json")) + [f for f in sorted((data / "pairs.zarr").rglob("*"))
                                                                   if f.is_file()]
    for f in headers:
        h.update(str(f.relative_to(data)).encode())
        if f.name == "zarr.json":
            h.update(json.dumps(_without_created(json.loads(f.read_text())), sort_keys=True).encode())
        else:
            hash_file(h, f)
    return h.hexdigest()


def find_se(data=None) -> Path | None:
    """The data-se folder holding ``pairs.zarr`` (``data`` if given, else data/se or data/data-se)."""
    options = [Path(data)] if data else [ROOT / "data" / "se", ROOT / "data" / "data-se"]
    return next((c for c in options if (c / "pairs.zarr").exists()), None)


def add_se_arguments(ap, misalign_px: float = 2.0, threads: int = 2) -> None:
    """The options every data-se benchmark takes: --data, --limit, --misalign-px, --threads."""
    ap.add_argument("--data", default=None, help="data-se folder (default: data/se, else data/data-se)")
    ap.add_argument("--limit", type=int, default=None, help="only the first N pairs")
    ap.add_argument("--misalign-px", type=float, default=misalign_px,
                    help="re-render view B with this TPS misalignment (px RMS, seeded per pair; 0: stored silhouettes)")
    ap.add_argument("--threads", type=int, default=threads, help="torch threads and metric workers")


def se_or_say(data=None) -> Path | None:
    """:func:`find_se`, printing what to do when data-se is missing (benchmarks then exit 0)."""
    found = find_se(data)
    if found is None:
        print("data-se pairs.zarr not found (data/se or data/data-se): run `make data-se` first. Nothing measured.")
    return found


@dataclass
class SEPair:
    index: int
    case: object  # PreparedCase
    mask_a: np.ndarray
    mask_b: np.ndarray
    cam_a: object  # Camera
    cam_b: object
    truth: object  # SparseVoxels


def _case_path(data: Path, name: str) -> Path:
    p = Path(name)
    for c in (p, ROOT / p, data / "cases" / p.name):
        if c.exists():
            return c
    return p  # PreparedCase.load names the missing file


def se_pairs(data, limit: int | None = None, misalign_px: float = 2.0, mask_noise: bool = False):
    """Iterate over the pairs of data-se as :class:`SEPair` (see the module docstring)."""
    from ..core.prepared_case import PreparedCase
    from ..render.augment import random_warp
    from ..render.mask_noise import corrupt_mask
    from ..render.pairs import load_pair_shard
    from ..render.raster import rasterise_mask
    from ..core.voxels import SparseVoxels

    data = Path(data)
    shard = load_pair_shard(data / "pairs.zarr")
    cases = shard["attrs"]["cases"]
    n = len(shard["mask_a"]) if limit is None else min(limit, len(shard["mask_a"]))
    for i in range(n):
        case = PreparedCase.load(_case_path(data, cases[int(shard["case_index"][i])]))
        t = np.asarray(shard["translation"][i], float)
        cam_a, cam_b = shard["cameras_a"][i], shard["cameras_b"][i]
        mask_a = shard["mask_a"][i].astype(bool)
        mask_b = shard["mask_b"][i].astype(bool)
        if misalign_px > 0:
            rng = np.random.default_rng([SE_SEED, i])
            warp = random_warp(rng, mask_b.shape[0], mask_b.shape[1], misalign_px)
            V = case.vertices.astype(float) + t
            mask_b = rasterise_mask(V, case.faces, cam_b, offset_rc=warp.displacement(np.nan_to_num(cam_b.project(V))))
        if mask_noise:
            noise_rng = np.random.default_rng([SE_SEED, i, 2])
            mask_a, mask_b = corrupt_mask(mask_a, noise_rng), corrupt_mask(mask_b, noise_rng)
        lab = case.labels
        truth = SparseVoxels(lab.coords, lab.voxel_size, lab.origin + t, lab.features)
        yield SEPair(i, case, mask_a, mask_b, cam_a, cam_b, truth)


def evaluate_se(predict, data, limit: int | None = None, misalign_px: float = 2.0, label: str = "",
                workers: int = 1, verbose: bool = True, mask_noise: bool = False) -> list[dict]:
    """Score ``predict(pair: SEPair) -> (SparseVoxels with occupancy, extra dict)`` on data-se.

    Returns one row per pair: case_id, pair, the metrics of :func:`stages.core.metrics.metrics_3d`,
    ``seconds`` (the prediction's wall time), ``metric_seconds`` and the ``extra`` entries.
    """
    return evaluate_many({label: predict}, data, limit, misalign_px, workers, verbose, mask_noise)[label]


def evaluate_many(predictors: dict, data, limit: int | None = None, misalign_px: float = 2.0, workers: int = 1,
                  verbose: bool = True, mask_noise: bool = False) -> dict:
    """:func:`evaluate_se` for several ``{name: predict}`` at once: each pair is loaded and re-rendered
    once for all of them. Returns ``{name: rows}``."""
    from ..core.metrics import metrics_3d
    from ..core.voxels import SparseVoxels

    out = {name: [] for name in predictors}
    for p in se_pairs(data, limit, misalign_px, mask_noise):
        for name, predict in predictors.items():
            t0 = time.perf_counter()
            pred, extra = predict(p)
            t1 = time.perf_counter()
            occ = SparseVoxels(pred.coords, pred.voxel_size, pred.origin,
                               {"occupancy": np.asarray(pred.features["occupancy"], np.float32)})
            r = {"case_id": p.case.case_id, "pair": p.index}
            r.update(metrics_3d(occ, p.truth, workers=workers))
            r.update(seconds=round(t1 - t0, 3), metric_seconds=round(time.perf_counter() - t1, 3), **extra)
            out[name].append(r)
            if verbose:
                print(f"{name + ' ' if name else ''}pair {p.index}: {r['case_id']} Dice {r['dice']:.3f} "
                      f"clDice {r['cldice']:.3f} CD {r['chamfer_mm']:.2f} HD95 {r['hd95_mm']:.2f} "
                      f"({t1 - t0:.2f} s)", flush=True)
    return out


# ------------------------------------------------------------------------------ predictors
def hull_predictor(voxel_size: float = 0.5):
    """The visual hull of the two silhouettes (:func:`stages.visual_hull.visual_hull`)."""
    from ..visual_hull import visual_hull

    def predict(p):
        hull = visual_hull([p.mask_a, p.mask_b], [p.cam_a, p.cam_b], voxel_size=voxel_size)
        return hull, {"voxels": len(hull)}

    return predict


def method_predictor(method: str):
    """A 3D method of :mod:`stages.methods3d` by name (its shipped weights), on the pair's two masks."""
    from ..methods3d import load_predictor

    predict_3d = load_predictor(method)

    def predict(p):
        pred = predict_3d(p.mask_a, p.mask_b, p.cam_a, p.cam_b, p.case.side)
        return pred, {"voxels": len(pred)}

    return predict


def sbp_predictor(model):
    """The SBP network (:class:`stages.sbp.SBPNet`); extras: candidate voxels and their share of the
    dense box they span."""
    from ..sbp.model import prepare_pair

    def predict(p):
        pair = prepare_pair(p.mask_a, p.mask_b, p.cam_a, p.cam_b, model.config)
        pred = model.predict(pair, side=p.case.side)
        lo, hi = pair.candidates.bounds() if len(pair.candidates) else (np.zeros(3), np.zeros(3))
        return pred, {"voxels": len(pair.candidates),
                      "dense_ratio": len(pair.candidates) / float(np.prod(hi - lo + 1))}

    return predict


def baseline_predictor(model):
    """A Table 1 baseline (:mod:`stages.baselines`): dense 2 mm or concatenation, upsampled to 0.5 mm."""
    from ..baselines import predict as baseline_predict

    def predict(p):
        pred = baseline_predict(model, p.mask_a, p.mask_b, p.cam_a, p.cam_b, side=p.case.side)
        return pred, {"voxels": len(pred)}

    return predict
