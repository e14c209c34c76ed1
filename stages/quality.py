"""How good is a reconstruction, by its own evidence: checks of a vascular graph against the two vessel
masks and cameras it was built from. No ground truth is needed.

Per key frame (:func:`frame_quality`):

* ``pieces`` — the graph's connected pieces (nodes, centreline length in mm, gap in mm to the main tree:
  the largest piece and every piece that a chain of gaps ≤ ``FAR_PIECE_MM`` joins to it); a coronary tree
  is one piece, so extra ones are suspect, and a piece no such chain reaches is flagged (a floating ghost);
* ``branches_outside_masks`` — curve segments (between junctions/end points) whose projection lies
  mostly (> ``OUTSIDE_FRACTION``) outside the vessel mask in *both* views: neither image supports them;
* ``one_view_segments`` — indices (in ``graph.segments()`` order) of the curve segments mostly outside the
  vessel mask of some views but not all: with two runs, branches one run alone shows (the report draws them
  apart);
* ``catheter_like`` — a long, almost straight stretch from a free end of the graph that enters the field of
  view climbing towards the head (:func:`stages.core.catheter.catheter_runs`): what a guiding catheter reconstructs as. graph-opt
  drops such stretches, so one here came back another way (tracking from another key frame);
* ``reprojection_mm`` — per view, the mean distance of the projected centreline to the mask's own
  centreline (its skeleton), in mm at the isocentre (pixels × the view's isocentre spacing).

A frame *fails* its checks when it has a far piece, a branch outside both masks, a catheter-like branch
or a mean reprojection distance above ``MAX_REPROJECTION_MM`` in a view; :func:`summarise` makes the
run's ``quality`` object (summary.json) and its one-line verdict.

Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np

from .core.catheter import CATHETER_BORDER_FRACTION, CATHETER_MIN_MM, CATHETER_STRAIGHTNESS, catheter_runs
from .graph.redundancy import FAR_PIECE_MM  # graph-opt drops such pieces when a view explains them

OUTSIDE_FRACTION = 0.5
MASK_TOLERANCE_PX = 2.0
MAX_REPROJECTION_MM = 2.0
SAMPLE_MM = 0.5


def _path_length(points: np.ndarray) -> float:
    return float(np.linalg.norm(np.diff(points, axis=0), axis=1).sum()) if len(points) > 1 else 0.0


def _resample(points: np.ndarray, step: float = SAMPLE_MM) -> np.ndarray:
    """Points every ≤ ``step`` mm along a polyline (its nodes included)."""
    if len(points) < 2:
        return points
    out = [points[:1]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        t = np.arange(1, n + 1)[:, None] / n
        out.append(a + t * (b - a))
    return np.concatenate(out)


def pieces(graph) -> list[dict]:
    """Connected pieces, largest (by centreline length) first: nodes, length_mm and distance_mm, the gap to
    the main tree — the largest piece grown by every piece within ``FAR_PIECE_MM`` of it, transitively (a
    vessel broken into pieces stays one tree; a piece is far only when no chain of short gaps reaches it;
    :meth:`stages.graph.vascular.VascularGraph.pieces`)."""
    label, lengths, gaps, order = graph.pieces(FAR_PIECE_MM)
    return [{"nodes": int(np.count_nonzero(label == c)), "length_mm": round(float(lengths[c]), 1),
             "distance_mm": round(float(gaps[c]), 1)} for c in order]


def _inside(mask_dist_px: np.ndarray, cam, points: np.ndarray) -> np.ndarray:
    """Whether each 3D point projects within ``MASK_TOLERANCE_PX`` of the view's mask (False off the image)."""
    rc = np.asarray(cam.project(points), float).reshape(-1, 2)
    r, c = np.rint(rc[:, 0]).astype(int), np.rint(rc[:, 1]).astype(int)
    H, W = mask_dist_px.shape
    ok = (r >= 0) & (r < H) & (c >= 0) & (c < W)
    inside = np.zeros(len(points), bool)
    inside[ok] = mask_dist_px[r[ok], c[ok]] <= MASK_TOLERANCE_PX
    return inside


def _distance_maps(mask):
    """(distance to the mask, distance to the mask's skeleton) in pixels."""
    from scipy import ndimage
    from skimage.morphology import skeletonize

    m = np.asarray(mask, bool)
    if not m.any():
        inf = np.full(m.shape, np.inf)
        return inf, inf
    to_mask = ndimage.distance_transform_edt(~m)
    skel = skeletonize(m)
    to_skel = ndimage.distance_transform_edt(~skel)
    return to_mask, to_skel


def frame_quality(graph, masks: dict, cameras: dict, key: str = "") -> dict:
    """The checks above for one key frame; ``masks``/``cameras``: view name → H×W mask / Camera."""
    views = [v for v in sorted(masks) if v in cameras]
    maps = {v: _distance_maps(masks[v]) for v in views}
    result: dict = {"key": key, "nodes": int(len(graph)), "length_mm": round(float(graph.length()), 1) if len(graph) else 0.0}
    result["pieces"] = pieces(graph)
    result["far_pieces"] = [p for p in result["pieces"][1:] if p["distance_mm"] > FAR_PIECE_MM]

    outside, one_view = [], []
    for index, seg in enumerate(graph.segments()):
        pts = graph.nodes[seg]
        length = _path_length(pts)
        if length <= 0:
            continue
        samples = _resample(pts)
        outside_frac = {v: float(1.0 - _inside(maps[v][0], cameras[v], samples).mean()) for v in views}
        entry = {"length_mm": round(length, 1), "start": np.round(pts[0], 1).tolist(), "end": np.round(pts[-1], 1).tolist()}
        if len(views) >= 2 and all(f > OUTSIDE_FRACTION for f in outside_frac.values()):
            outside.append({**entry, "outside_fraction": {v: round(f, 2) for v, f in outside_frac.items()}})
        elif len(views) >= 2 and any(f > OUTSIDE_FRACTION for f in outside_frac.values()):
            one_view.append(index)
    result["branches_outside_masks"] = outside
    result["one_view_segments"] = one_view
    catheter = [{"length_mm": round(length, 1), "straightness": round(straightness, 3),
                 "start": np.round(graph.nodes[run[-1]], 1).tolist(), "end": np.round(graph.nodes[run[0]], 1).tolist()}
                for run, length, straightness in catheter_runs(graph, [cameras[v] for v in views])]
    result["catheter_like"] = catheter

    reproj = {}
    if len(graph):
        pts = graph.sample(SAMPLE_MM)[0]
        for v in views:
            rc = np.asarray(cameras[v].project(pts), float).reshape(-1, 2)
            to_skel = maps[v][1]
            H, W = to_skel.shape
            r, c = np.clip(np.rint(rc[:, 0]).astype(int), 0, H - 1), np.clip(np.rint(rc[:, 1]).astype(int), 0, W - 1)
            d = to_skel[r, c]
            reproj[v] = round(float(np.mean(d) * cameras[v].isocentre_spacing), 2) if np.isfinite(d).all() else None
    result["reprojection_mm"] = reproj

    problems = []
    if result["far_pieces"]:
        problems.append(f"{len(result['far_pieces'])} piece(s) > {FAR_PIECE_MM:.0f} mm from the main tree "
                        f"(up to {max(p['distance_mm'] for p in result['far_pieces']):.0f} mm)")
    if outside:
        problems.append(f"{len(outside)} branch(es) outside both vessel masks ({sum(b['length_mm'] for b in outside):.0f} mm)")
    if catheter:
        problems.append(f"{len(catheter)} straight catheter-like branch(es) ({', '.join('%.0f' % b['length_mm'] for b in catheter)} mm)")
    for v, d in reproj.items():
        if d is None or d > MAX_REPROJECTION_MM:
            problems.append(f"view {v} reprojection {'undefined' if d is None else f'{d:.1f} mm'} > {MAX_REPROJECTION_MM:.0f} mm")
    if not len(graph):
        problems.append("empty graph")
    result["problems"] = problems
    result["passed"] = not problems
    return result


def summarise(frames: list[dict]) -> dict:
    """The run's ``quality`` object: thresholds, per-frame results and a one-line verdict."""
    failed = [f["key"] for f in frames if not f["passed"]]
    if not frames:
        verdict = "quality: no key frame to check"
    elif failed:
        worst = next(f for f in frames if not f["passed"])
        verdict = (f"quality: FAILS its own checks on {len(failed)} of {len(frames)} key frame(s) "
                   f"({', '.join(failed)}); e.g. key frame {worst['key']}: {'; '.join(worst['problems'])}")
    else:
        verdict = f"quality: passes its own checks on all {len(frames)} key frame(s)"
    reproj = {}
    for f in frames:
        for v, d in f["reprojection_mm"].items():
            if d is not None:
                reproj.setdefault(v, []).append(d)
    return {"passed": bool(frames) and not failed, "verdict": verdict, "failed_frames": failed,
            "mean_reprojection_mm": {v: round(float(np.mean(d)), 2) for v, d in reproj.items()},
            "thresholds": {"far_piece_mm": FAR_PIECE_MM, "outside_fraction": OUTSIDE_FRACTION,
                           "mask_tolerance_px": MASK_TOLERANCE_PX, "catheter_min_mm": CATHETER_MIN_MM,
                           "catheter_straightness": CATHETER_STRAIGHTNESS,
                           "catheter_border_fraction": CATHETER_BORDER_FRACTION, "max_reprojection_mm": MAX_REPROJECTION_MM},
            "frames": frames}
