"""The 3D methods of a two-view reconstruction, in one place (used by ``reconstruct`` and the held-out check).

Every method turns one pair of vessel masks with their cameras into a sparse 0.5 mm prediction
(:class:`~stages.core.voxels.SparseVoxels` with ``occupancy`` and ``centreness`` features), the input of graph
initialisation:

* ``correspondence`` — explicit two-view correspondence (:mod:`stages.twoview`: 2D centrelines, epipolar
  candidates, a labelling per 2D branch both ways, tubes from both views' radii); geometric, no weights;
* ``sbp`` — the sparse backward projection network (L8 with the shipped ``stages/weights/sbp.pt``, or any
  SBP weights file, e.g. the uniform-pose L7 ``stages/weights/sbp_uniform.pt``);
* ``visual-hull`` — the geometric baseline (occupancy 1, centreness from the hull's distance map);
* ``dense`` — the L2-style dense back-projection baseline (``stages/weights/baseline_dense.pt``, 2 mm
  grid upsampled to 0.5 mm).

Reads: the weights file of the learned methods. Writes: nothing.
"""

from __future__ import annotations

import threading
from typing import Callable

import numpy as np

from .core.errors import UserError
from .core.voxels import SparseVoxels

METHODS = ("sbp", "correspondence", "visual-hull", "dense")
# What `autocar reconstruct` uses unless told otherwise: the explicit two-view correspondence method. It is
# geometric (nothing learned from our procedural generator), and it is ahead of the SBP network wherever the
# images or the anatomy are not the generator's: the real phantom's held-out views, trees outside the
# generator's range, the bundled example; SBP stays ahead on data-se and data-re, the generator's own data
# it was trained for (docs/TWOVIEW.md, "Why it is the default").
DEFAULT_METHOD = "correspondence"
# methods whose key frames `reconstruct --threads N` predicts N at a time, in threads (compiled kernels and NumPy
# release the GIL: 1.6× on 2 cores); the torch methods use the threads inside each prediction instead
KEY_FRAME_THREADED = {"correspondence"}
# methods that take the evidence of every run of a study (three or more views), not just two
MULTI_VIEW_METHODS = ("correspondence",)

# (mask_a, mask_b, cam_a, cam_b, side) -> SparseVoxels with occupancy + centreness
Predictor = Callable[..., SparseVoxels]


def confident_voxels(vox, threshold: float = 0.5) -> int:
    """Voxels a 3D prediction holds occupied with occupancy ≥ ``threshold`` (all of them without one)."""
    occ = vox.features.get("occupancy")
    return len(vox) if occ is None else int(np.count_nonzero(np.asarray(occ) >= threshold))


def load_evidence_predictor(method: str, weights=None):
    """``(mask_a, mask_b, cam_a, cams_b, side, extra=(), report=None) -> (prediction, k)``: the prediction under
    the camera of view B (of ``cams_b``) that explains the most of the views, the first of equals, and that
    camera's index; `reconstruct` offers view B with and without its shift
    (stages.reconstruct.predict_with_checked_shift). For the volumetric methods the evidence is the confident
    voxels (two views that agree back-project onto more of the same vessel). For the correspondence method its
    matched centreline points: its tubes' voxel count does not tell a right shift from a wrong one (on data-re the
    voxel check rejected 24 fitted shifts of which 20 matched the true motion), the match count rises with 81 % of
    the right shifts and 27 % of the wrong ones (docs/TWOVIEW.md); only the prediction kept is rasterised.
    ``extra``: (mask, camera) of further views (the correspondence method only); ``report`` receives their
    consistency and use under the camera kept (:func:`stages.twoview.multiview.multiview_polylines`)."""
    if method == "correspondence":
        from .twoview.centreline2d import extract_centreline
        from .twoview.method import correspondence_polylines, tubes_to_voxels
        from .twoview.multiview import multiview_polylines

        extracted: dict = {}  # id(mask) → (mask, centreline) of the last few masks: each is extracted once
        lock = threading.Lock()  # key frames may be predicted in threads (`--threads`)

        def centreline_of(mask, source):
            with lock:
                hit = extracted.get(id(mask))
            if hit is not None and hit[0] is mask:
                return hit[1]
            centreline = extract_centreline(mask, source=source)
            with lock:
                while len(extracted) >= 16:
                    extracted.pop(next(iter(extracted)))
                extracted[id(mask)] = (mask, centreline)
            return centreline

        def run_correspondence(mask_a, mask_b, cam_a, cams_b, side="left", extra=(), report=None):
            # the masks are the same under every camera (and in every call for one key frame): their 2D centrelines
            # are extracted once
            centrelines = (centreline_of(mask_a, "view A"), centreline_of(mask_b, "view B"))
            centrelines += tuple(centreline_of(m, f"view {k + 3}") for k, (m, _) in enumerate(extra))
            found, reports = [], []
            for cam_b in cams_b:
                if extra:
                    reports.append({})
                    polylines = multiview_polylines([mask_a, mask_b, *(m for m, _ in extra)],
                                                    [cam_a, cam_b, *(c for _, c in extra)], centrelines=centrelines,
                                                    report=reports[-1])
                    found.append((polylines, sum(len(p.points) for p in polylines)))
                else:
                    found.append(correspondence_polylines(mask_a, mask_b, cam_a, cam_b, centrelines=centrelines))
            k = int(np.argmax([count for _, count in found]))
            if report is not None and reports:
                report.update(reports[k])
            return tubes_to_voxels(found[k][0]), k

        return run_correspondence
    predict = load_predictor(method, weights)

    def run(mask_a, mask_b, cam_a, cams_b, side="left", extra=(), report=None):
        _two_views_only(method, extra)
        predictions = [predict(mask_a, mask_b, cam_a, cam_b, side) for cam_b in cams_b]
        k = int(np.argmax([confident_voxels(vox) for vox in predictions]))
        return predictions[k], k

    return run


def _two_views_only(method: str, extra) -> None:
    if extra:
        raise UserError(f"the {method} method reconstructs from two runs; with more runs use --method "
                        f"{MULTI_VIEW_METHODS[0]}")


def hull_prediction(mask_a, mask_b, cam_a, cam_b, voxel_size: float = 0.5) -> SparseVoxels:
    """Visual-hull baseline as a prediction: occupancy 1, centreness from the hull's own distance map
    (distance to the hull boundary over its local maximum — 1 on the hull's medial axis, → 0 at the wall)."""
    from scipy import ndimage

    from .visual_hull import visual_hull

    hull = visual_hull([mask_a, mask_b], [cam_a, cam_b], voxel_size=voxel_size)
    if len(hull) == 0:
        return SparseVoxels(hull.coords, voxel_size, hull.origin, {"occupancy": np.zeros(0, np.float32),
                                                                  "centreness": np.zeros(0, np.float32)})
    dense, lo = hull.to_dense(pad=1)
    dist = ndimage.distance_transform_edt(dense)
    local_max = ndimage.maximum_filter(dist, size=5)
    cen = np.where(dense, dist / np.maximum(local_max, 1e-6), 0.0)
    idx = hull.coords - lo
    return SparseVoxels(hull.coords, voxel_size, hull.origin,
                        {"occupancy": np.ones(len(hull), np.float32),
                         "centreness": cen[idx[:, 0], idx[:, 1], idx[:, 2]].astype(np.float32)})


def load_predictor(method: str, weights=None) -> Predictor:
    """The predictor of ``method``, its weights loaded once (``weights``: None → the shipped file)."""
    if method == "visual-hull":
        return lambda mask_a, mask_b, cam_a, cam_b, side="left": hull_prediction(mask_a, mask_b, cam_a, cam_b)
    if method == "sbp":
        from .sbp.model import prepare_pair
        from .sbp.train import load_weights

        model = load_weights(weights)
        return lambda mask_a, mask_b, cam_a, cam_b, side="left": model.predict(
            prepare_pair(mask_a, mask_b, cam_a, cam_b, model.config), side=side)
    if method == "correspondence":
        from .twoview import correspondence_prediction
        from .twoview.multiview import multiview_prediction

        def correspondence(mask_a, mask_b, cam_a, cam_b, side="left", prob_a=None, prob_b=None, extra=()):
            if extra:  # (mask, camera) of every further view of the same phase
                probs = None if prob_a is None and prob_b is None else [prob_a, prob_b, *([None] * len(extra))]
                return multiview_prediction([mask_a, mask_b, *(m for m, _ in extra)],
                                            [cam_a, cam_b, *(c for _, c in extra)], probs)
            return correspondence_prediction(mask_a, mask_b, cam_a, cam_b, prob_a=prob_a, prob_b=prob_b)

        return correspondence
    if method == "dense":
        from .baselines import default_weights, load_baseline, predict

        model = load_baseline(weights or default_weights("dense"))
        return lambda mask_a, mask_b, cam_a, cam_b, side="left": predict(model, mask_a, mask_b, cam_a, cam_b, side)
    raise UserError(f"unknown 3D method {method!r} (choose from {', '.join(METHODS)})")
