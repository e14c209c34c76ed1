"""Evaluation metrics of the AutoCAR paper (Eqs. 17–20 in 3D, Eqs. 22–24 in 2D), plus graph errors.

Reads: nothing from disk — every function takes in-memory data (:class:`~stages.core.voxels.SparseVoxels`,
point arrays, graphs as (nodes, radius, edges), cameras). :mod:`stages.evaluate` does the file I/O.
Writes: nothing.

3D metrics (on a common isotropic grid, 0.5 mm by default)
-------------------------------------------------------------
Prediction and ground truth may live on different grids (voxel size, origin). Both are put on one
grid covering the union of their extents (:func:`common_grid`): a set whose grid already coincides
with the common grid is scattered as is (occupancy ≥ 0.5); any other set is resampled *linearly*
(trilinear interpolation of its soft occupancy, missing voxels = 0) at the common voxel centres and
thresholded at 0.5, as in the paper.

* Dice = 2|P∩G| / (|P|+|G|).
* clDice = 2·Tprec·Tsens / (Tprec+Tsens), Tprec = |S(P)∩G|/|S(P)|, Tsens = |S(G)∩P|/|S(G)|, with S the
  skeleton by morphological thinning: :func:`skimage.morphology.skeletonize` (3D: Lee et al. 1994,
  26-connected). Behaviour on thin vessels (tested): a 1-voxel-thick line is its own skeleton; a
  2×3 or 3×3 bar thins to a 1-voxel line inside it, shortened by about a voxel at each end; an
  isolated voxel stays. skimage deletes objects whose cross-section is an *even×even* symmetric block
  (a 2×2 bar, any axis-aligned tube centred between voxel centres) entirely; :func:`skeleton` repairs
  that per connected component (see there), so S(X) ⊆ X and no component vanishes. A residual quirk:
  an even×even straight section *attached* to a component that keeps a skeleton can still lose its
  part of the skeleton (curved vessels, as in real and synthetic trees, are not affected).
* Chamfer distance = mean_{p∈∂P} min_g ‖p−g‖ + mean_{g∈∂G} min_p ‖g−p‖ (the *sum* of the two directed
  means, as in the paper) and HD95 = max of the two directed 95th percentiles, both on the vertices of
  marching-cubes surfaces (level 0.5 of the binary volumes, padded so every surface is closed), nearest
  neighbours by KD-tree. In mm.

Edge cases (never a silent NaN): both empty → Dice = clDice = 1, CD = HD95 = 0; an empty prediction
with non-empty truth (or the reverse) → Dice = clDice = 0 and CD = HD95 = NaN with
``status = "empty-prediction"`` (``"empty-truth"``); tables print that status instead of a number and
aggregates leave such cases out of the distance means, saying how many.

Graph metrics (both sides given as centreline graphs)
-----------------------------------------------------
Each graph's edges are resampled every ``step`` mm (radius interpolated linearly along each edge).
Centreline error = ½(mean_{a∈A} d(a,B) + mean_{b∈B} d(b,A)) (mean symmetric distance, mm). Radius error =
the same symmetric mean of |r(a) − r(nearest b)| (mm).

2D correspondence metrics (Eqs. 22–24)
--------------------------------------
For annotated pairs (p_A, p_B) the *query* is p_A in view A. A prediction is any set of predicted
pairs (q_A, q_B) (from a 3D prediction: q_A, q_B = projections of its points into A and B; from a
2D method: its matches). The predicted partner of p_A is the q_B of the predicted pair whose q_A lies
nearest p_A, provided that it is within ``cover_mm`` (isocentre mm in view A, default 1 mm); otherwise
the query is *uncovered*. (The paper's text indexes the prediction with view B; that would make EPE a
nearest-point distance in B rather than a correspondence error, so view A is used here.) Among
predicted points that project equally close to p_A (within ``tie_px``), the one with the largest
weight is taken (weight = occupancy·centreness for voxel predictions, so the lumen's centre wins).

* coverage = covered queries / all queries;
* EPE = mean over covered queries of ‖q_B − p_B‖ × (isocentre pixel spacing of view B), mm;
* accuracy = queries whose error < ε (3 mm) / all queries (uncovered count as wrong);
  ``accuracy_covered`` gives the same over covered queries only.
With no covered query EPE is NaN with status ``"no-covered-query"``; with no annotated pair the
function raises (missing annotations are an input error).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from .errors import UserError
from .voxels import SparseVoxels

__all__ = [
    "GRID_MM",
    "EPSILON_MM",
    "COVER_MM",
    "DenseGrid",
    "common_grid",
    "dice",
    "skeleton",
    "cldice",
    "surface_points",
    "directed_distances",
    "chamfer_hd95",
    "metrics_3d",
    "sample_graph",
    "graph_metrics",
    "match_partners",
    "correspondence_metrics",
]

GRID_MM = 0.5
EPSILON_MM = 3.0  # accuracy: a predicted partner within this distance (view B, isocentre mm) is correct
COVER_MM = 1.0  # coverage: a query is covered by a reprojected prediction within this distance (view A)
MAX_DENSE_VOXELS = 600_000_000  # ~600 MB of booleans; beyond that the two sets can't be a sensible pair


@dataclass
class DenseGrid:
    """Two boolean volumes on one grid: ``pred`` and ``truth`` indexed [i, j, k] with world centre
    ``origin + (ijk) * voxel_size``."""

    pred: np.ndarray
    truth: np.ndarray
    origin: np.ndarray
    voxel_size: float
    notes: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------- common grid
def _occupancy(vox: SparseVoxels, feature: str | None) -> np.ndarray:
    if feature and feature in vox.features:
        return np.asarray(vox.features[feature], dtype=np.float32).reshape(len(vox))
    return np.ones(len(vox), dtype=np.float32)  # a bare coordinate set: every listed voxel is occupied


def _aligned(vox: SparseVoxels, origin: np.ndarray, voxel_size: float) -> bool:
    if abs(vox.voxel_size - voxel_size) > 1e-6 * voxel_size:
        return False
    shift = (vox.origin - origin) / voxel_size
    return bool(np.all(np.abs(shift - np.rint(shift)) < 1e-4))


def _on_common(vox: SparseVoxels, occ: np.ndarray, origin: np.ndarray, vs: float):
    """Occupied voxels of ``vox`` as integer indices of the common grid (before the union offset)."""
    if _aligned(vox, origin, vs):
        shift = np.rint((vox.origin - origin) / vs).astype(np.int64)
        return vox.coords[occ >= 0.5].astype(np.int64) + shift, False
    # Linear resampling: dense soft occupancy on the native grid (padded by one voxel so values fall
    # to zero at the edge), trilinear samples at the common voxel centres inside its extent.
    keep = occ > 0
    if not np.any(keep):
        return np.zeros((0, 3), np.int64), True
    coords = vox.coords[keep].astype(np.int64)
    lo = coords.min(0) - 1
    hi = coords.max(0) + 1
    dense = np.zeros(tuple((hi - lo + 1).tolist()), np.float32)
    idx = coords - lo
    dense[idx[:, 0], idx[:, 1], idx[:, 2]] = occ[keep]
    w_lo = vox.origin + lo * vox.voxel_size
    w_hi = vox.origin + hi * vox.voxel_size
    c_lo = np.ceil((w_lo - origin) / vs - 1e-9).astype(np.int64)
    c_hi = np.floor((w_hi - origin) / vs + 1e-9).astype(np.int64)
    if np.any(c_hi < c_lo):
        return np.zeros((0, 3), np.int64), True
    axes = [np.arange(a, b + 1) for a, b in zip(c_lo, c_hi)]
    n = int(np.prod([len(a) for a in axes]))
    if n > MAX_DENSE_VOXELS:
        raise UserError(f"resampling a {vox.voxel_size} mm set onto the {vs} mm grid needs {n} voxels; too large")
    out = []
    # Slab by slab along the first axis to keep memory small.
    for i0 in axes[0]:
        g1, g2 = np.meshgrid(axes[1], axes[2], indexing="ij")
        world = np.stack([np.full(g1.shape, float(i0)), g1, g2]).astype(np.float64)
        world = origin[:, None, None] + world * vs
        native = (world - vox.origin[:, None, None]) / vox.voxel_size - lo[:, None, None]
        vals = ndimage.map_coordinates(dense, native.reshape(3, -1), order=1, mode="constant", cval=0.0)
        hit = vals.reshape(g1.shape) >= 0.5
        if np.any(hit):
            jj, kk = np.nonzero(hit)
            out.append(np.stack([np.full(len(jj), i0), axes[1][jj], axes[2][kk]], 1))
    return (np.concatenate(out) if out else np.zeros((0, 3), np.int64)), True


def common_grid(pred: SparseVoxels, truth: SparseVoxels, voxel_size: float = GRID_MM,
                pred_feature: str | None = "occupancy", truth_feature: str | None = "occupancy",
                pad: int = 1) -> DenseGrid:
    """Put prediction and truth on one ``voxel_size`` grid covering both (see module docstring).

    The grid is anchored on the truth's origin when the truth is already at ``voxel_size`` (so labels
    are never resampled), else on the prediction's, else on the world origin.
    """
    vs = float(voxel_size)
    if abs(truth.voxel_size - vs) < 1e-6 * vs:
        anchor = truth.origin
    elif abs(pred.voxel_size - vs) < 1e-6 * vs:
        anchor = pred.origin
    else:
        anchor = np.zeros(3)
    notes = []
    p_idx, p_res = _on_common(pred, _occupancy(pred, pred_feature), anchor, vs)
    g_idx, g_res = _on_common(truth, _occupancy(truth, truth_feature), anchor, vs)
    if p_res:
        notes.append(f"prediction resampled linearly from {pred.voxel_size} mm onto the {vs} mm grid")
    if g_res:
        notes.append(f"truth resampled linearly from {truth.voxel_size} mm onto the {vs} mm grid")
    both = np.concatenate([p_idx, g_idx]) if len(p_idx) + len(g_idx) else np.zeros((1, 3), np.int64)
    lo = both.min(0) - pad
    hi = both.max(0) + pad
    shape = tuple((hi - lo + 1).tolist())
    if int(np.prod(shape)) > MAX_DENSE_VOXELS:
        raise UserError(
            f"prediction and truth span {shape} voxels of {vs} mm together; are they in the same world frame?")
    P = np.zeros(shape, bool)
    G = np.zeros(shape, bool)
    if len(p_idx):
        q = p_idx - lo
        P[q[:, 0], q[:, 1], q[:, 2]] = True
    if len(g_idx):
        q = g_idx - lo
        G[q[:, 0], q[:, 1], q[:, 2]] = True
    return DenseGrid(P, G, anchor + lo * vs, vs, notes)


# ---------------------------------------------------------------------------- overlap metrics
def dice(P: np.ndarray, G: np.ndarray) -> float:
    """2|P∩G|/(|P|+|G|); 1.0 when both are empty."""
    sp, sg = int(np.count_nonzero(P)), int(np.count_nonzero(G))
    if sp + sg == 0:
        return 1.0
    return 2.0 * int(np.count_nonzero(P & G)) / (sp + sg)


def _bbox(mask: np.ndarray, pad: int = 1):
    """Slices of the bounding box of ``mask`` grown by ``pad`` (clipped), or None if empty."""
    nz = [np.flatnonzero(mask.any(axis=tuple(a for a in range(mask.ndim) if a != ax))) for ax in range(mask.ndim)]
    if any(len(n) == 0 for n in nz):
        return None
    return tuple(slice(max(int(n[0]) - pad, 0), min(int(n[-1]) + pad + 1, s)) for n, s in zip(nz, mask.shape))


def _thin(mask: np.ndarray) -> np.ndarray:
    from skimage.morphology import skeletonize

    return skeletonize(np.ascontiguousarray(mask)) > 0


def skeleton(mask: np.ndarray) -> np.ndarray:
    """Morphological thinning skeleton (skimage, Lee 1994 in 3D) on the bounding box, S(X) ⊆ X.

    skimage 0.26 deletes whole objects whose cross-section is an even×even symmetric block (a
    2×2-voxel bar, an axis-aligned tube centred between voxel centres). So every 26-connected
    component of ``mask`` left without a skeleton voxel is thinned again after growing it by one
    voxel towards +i, then +j, then +k, then all three (which breaks the symmetry; the result is
    intersected with the component); if that still leaves nothing, its voxel nearest the centroid
    stands for it. No component ever vanishes.
    """
    out = np.zeros(mask.shape, bool)
    box = _bbox(mask, pad=2)
    if box is None:
        return out
    sub = np.ascontiguousarray(mask[box])
    sk = _thin(sub)
    lab, n = ndimage.label(sub, structure=np.ones((3, 3, 3)))
    have = np.zeros(n + 1, bool)
    have[np.unique(lab[sk])] = True
    for comp in np.flatnonzero(~have[1:]) + 1:
        cbox = ndimage.find_objects((lab == comp).astype(np.int8))[0]
        cbox = tuple(slice(max(s.start - 2, 0), min(s.stop + 2, n_)) for s, n_ in zip(cbox, sub.shape))
        part = lab[cbox] == comp
        found = None
        for shift in ((1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 1)):
            grown = part.copy()
            for ax, d in enumerate(shift):
                if d:
                    grown[tuple(slice(1, None) if a == ax else slice(None) for a in range(3))] |= \
                        part[tuple(slice(None, -1) if a == ax else slice(None) for a in range(3))]
            cand = _thin(grown) & part
            if cand.any():
                found = cand
                break
        if found is None:
            idx = np.argwhere(part)
            found = np.zeros(part.shape, bool)
            found[tuple(idx[np.argmin(np.linalg.norm(idx - idx.mean(0), axis=1))])] = True
        sk[cbox] |= found
    out[box] = sk
    return out


def cldice(P: np.ndarray, G: np.ndarray, SP: np.ndarray | None = None, SG: np.ndarray | None = None) -> dict:
    """clDice with topology precision/sensitivity. Returns {cldice, tprec, tsens} (see module docstring)."""
    SP = skeleton(P) if SP is None else SP
    SG = skeleton(G) if SG is None else SG
    np_, ng = int(np.count_nonzero(SP)), int(np.count_nonzero(SG))
    if np_ == 0 and ng == 0:
        return {"cldice": 1.0, "tprec": 1.0, "tsens": 1.0}
    tprec = int(np.count_nonzero(SP & G)) / np_ if np_ else 0.0
    tsens = int(np.count_nonzero(SG & P)) / ng if ng else 0.0
    cl = 2 * tprec * tsens / (tprec + tsens) if tprec + tsens > 0 else 0.0
    return {"cldice": cl, "tprec": tprec, "tsens": tsens}


# ---------------------------------------------------------------------------- surface distances
def surface_points(mask: np.ndarray, origin=(0, 0, 0), voxel_size: float = 1.0) -> np.ndarray:
    """Vertices (world mm) of the marching-cubes surface at level 0.5 of a binary volume; (0,3) if empty.

    The volume is cropped to its bounding box padded by one background voxel, so the surface is closed
    even where the object touches the array's edge.
    """
    from skimage.measure import marching_cubes

    box = _bbox(mask, pad=0)
    if box is None:
        return np.zeros((0, 3))
    crop = np.pad(mask[box], 1).astype(np.float32)
    verts, _, _, _ = marching_cubes(crop, level=0.5, allow_degenerate=False)
    offset = np.array([s.start for s in box], float) - 1.0
    return np.asarray(origin, float) + (verts + offset) * voxel_size


def directed_distances(src: np.ndarray, dst: np.ndarray, workers: int = -1) -> np.ndarray:
    """For each point of ``src`` the distance to the nearest point of ``dst`` (KD-tree)."""
    src = np.asarray(src, float).reshape(-1, 3)
    dst = np.asarray(dst, float).reshape(-1, 3)
    if len(src) == 0:
        return np.zeros(0)
    if len(dst) == 0:
        return np.full(len(src), np.inf)
    d, _ = cKDTree(dst).query(src, k=1, workers=workers)
    return d


def chamfer_hd95(points_p: np.ndarray, points_g: np.ndarray, workers: int = -1) -> dict:
    """Chamfer (sum of the two directed means) and HD95 (max of the two directed 95th percentiles).

    Both empty → 0, 0; exactly one empty → NaN with a status saying which (see module docstring).
    """
    n_p, n_g = len(points_p), len(points_g)
    if n_p == 0 and n_g == 0:
        return {"chamfer_mm": 0.0, "hd95_mm": 0.0, "status": "ok"}
    if n_p == 0 or n_g == 0:
        return {"chamfer_mm": float("nan"), "hd95_mm": float("nan"),
                "status": "empty-prediction" if n_p == 0 else "empty-truth"}
    d_pg = directed_distances(points_p, points_g, workers)
    d_gp = directed_distances(points_g, points_p, workers)
    return {
        "chamfer_mm": float(d_pg.mean() + d_gp.mean()),
        "hd95_mm": float(max(np.percentile(d_pg, 95), np.percentile(d_gp, 95))),
        "status": "ok",
    }


def metrics_3d(pred: SparseVoxels, truth: SparseVoxels, voxel_size: float = GRID_MM,
               pred_feature: str | None = "occupancy", truth_feature: str | None = "occupancy",
               workers: int = -1) -> dict:
    """Dice, clDice (+Tprec, Tsens), Chamfer and HD95 of a prediction against the truth, plus voxel counts.

    ``status`` is "ok", "empty-prediction", "empty-truth" or "both-empty"; ``notes`` lists resampling.
    """
    grid = common_grid(pred, truth, voxel_size, pred_feature, truth_feature)
    P, G = grid.pred, grid.truth
    n_p, n_g = int(P.sum()), int(G.sum())
    out = {"dice": dice(P, G)}
    out.update(cldice(P, G))
    sp = surface_points(P, grid.origin, grid.voxel_size)
    sg = surface_points(G, grid.origin, grid.voxel_size)
    dist = chamfer_hd95(sp, sg, workers)
    status = dist.pop("status")
    if n_p == 0 and n_g == 0:
        status = "both-empty"
    out.update(dist)
    out.update({"n_pred_voxels": n_p, "n_truth_voxels": n_g, "grid_mm": grid.voxel_size,
                "status": status, "notes": "; ".join(grid.notes)})
    return out


# ---------------------------------------------------------------------------- graphs
def sample_graph(nodes, radius, edges, step: float = 0.25):
    """Points every ≤ ``step`` mm along each edge (both end nodes included) with interpolated radius.

    Isolated nodes are kept as single points. Returns (points M×3, radius M).
    """
    nodes = np.asarray(nodes, float).reshape(-1, 3)
    radius = np.zeros(len(nodes)) if radius is None else np.asarray(radius, float).reshape(-1)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    pts, rad = [nodes], [radius]
    if len(edges):
        a, b = nodes[edges[:, 0]], nodes[edges[:, 1]]
        length = np.linalg.norm(b - a, axis=1)
        nseg = np.maximum(np.ceil(length / step).astype(np.int64), 1)
        # interior samples of every edge, vectorised via repeat
        rep = nseg - 1
        if rep.sum() > 0:
            e_idx = np.repeat(np.arange(len(edges)), rep)
            start = np.cumsum(rep) - rep
            k = np.arange(rep.sum()) - np.repeat(start, rep) + 1
            t = (k / nseg[e_idx])[:, None]
            pts.append(a[e_idx] * (1 - t) + b[e_idx] * t)
            ra, rb = radius[edges[:, 0]], radius[edges[:, 1]]
            rad.append(ra[e_idx] * (1 - t[:, 0]) + rb[e_idx] * t[:, 0])
    return np.concatenate(pts), np.concatenate(rad)


def graph_metrics(pred_graph, truth_graph, step: float = 0.25, workers: int = -1) -> dict:
    """Centreline error and radius error (mm) between two graphs given as (nodes, radius, edges)."""
    pa, ra = sample_graph(*pred_graph, step=step)
    pb, rb = sample_graph(*truth_graph, step=step)
    if len(pa) == 0 or len(pb) == 0:
        return {"centreline_error_mm": float("nan"), "radius_error_mm": float("nan"),
                "graph_status": "empty-prediction" if len(pa) == 0 else "empty-truth"}
    da, ia = cKDTree(pb).query(pa, workers=workers)
    db, ib = cKDTree(pa).query(pb, workers=workers)
    cl = 0.5 * (da.mean() + db.mean())
    rad = 0.5 * (np.abs(ra - rb[ia]).mean() + np.abs(rb - ra[ib]).mean())
    # the two directed means separately: how far the reconstruction strays (pred → truth) and how much
    # of the truth it misses (truth → pred)
    return {"centreline_error_mm": float(cl), "centreline_pred_to_truth_mm": float(da.mean()),
            "centreline_truth_to_pred_mm": float(db.mean()), "radius_error_mm": float(rad), "graph_status": "ok"}


# ---------------------------------------------------------------------------- 2D correspondences
def match_partners(pred_a, pred_b, queries_a, cover_px: float, weights=None, tie_px: float = 0.5):
    """Predicted partner in view B of each query in view A (NaN rows for uncovered queries).

    ``pred_a``/``pred_b``: M×2 (row, col) of the predicted pairs; ``queries_a``: Q×2. The predicted pair
    whose A-point is nearest the query wins if within ``cover_px``; among pairs within ``tie_px`` of the
    nearest distance, the one with the largest weight.
    """
    pred_a = np.asarray(pred_a, float).reshape(-1, 2)
    pred_b = np.asarray(pred_b, float).reshape(-1, 2)
    queries_a = np.asarray(queries_a, float).reshape(-1, 2)
    out = np.full((len(queries_a), 2), np.nan)
    ok = np.all(np.isfinite(pred_a), 1) & np.all(np.isfinite(pred_b), 1)
    pred_a, pred_b = pred_a[ok], pred_b[ok]
    w = np.ones(len(pred_a)) if weights is None else np.asarray(weights, float).reshape(-1)[ok]
    if len(pred_a) == 0 or len(queries_a) == 0:
        return out
    tree = cKDTree(pred_a)
    d0, _ = tree.query(queries_a, k=1)
    for q in np.flatnonzero(d0 <= cover_px):  # loop over annotated queries (tens to hundreds)
        cand = tree.query_ball_point(queries_a[q], d0[q] + tie_px)
        cand = np.asarray(cand)
        best = cand[np.argmax(w[cand])]
        out[q] = pred_b[best]
    return out


def correspondence_metrics(partners_b, truth_b, spacing_b_mm: float, epsilon_mm: float = EPSILON_MM) -> dict:
    """Coverage, EPE (mm) and accuracy (error < ε) from predicted partners (NaN = uncovered)."""
    partners_b = np.asarray(partners_b, float).reshape(-1, 2)
    truth_b = np.asarray(truth_b, float).reshape(-1, 2)
    n = len(truth_b)
    if n == 0:
        raise UserError("no annotated correspondence pairs: the 2D metrics need at least one (p_A, p_B)")
    if len(partners_b) != n:
        raise ValueError("one predicted partner (or NaN) per annotated pair is needed")
    covered = np.all(np.isfinite(partners_b), axis=1)
    err = np.linalg.norm(partners_b[covered] - truth_b[covered], axis=1) * float(spacing_b_mm)
    n_cov = int(covered.sum())
    good = int(np.count_nonzero(err < epsilon_mm))
    return {
        "coverage": n_cov / n,
        "epe_mm": float(err.mean()) if n_cov else float("nan"),
        "accuracy": good / n,
        "accuracy_covered": good / n_cov if n_cov else float("nan"),
        "n_pairs": n,
        "n_covered": n_cov,
        "epsilon_mm": float(epsilon_mm),
        "status": "ok" if n_cov else "no-covered-query",
    }


RADIUS_BINS_MM = {"small": (0.0, 0.9), "medium": (0.9, 1.5), "large": (1.5, np.inf)}  # true lumen radius


def centreline_by_radius(points, radius, truth_points, truth_radius, found_mm: float = 1.0,
                         matched_mm: float = 0.5) -> dict:
    """Centreline recall and radius error of a reconstruction by the true radius's bin (:data:`RADIUS_BINS_MM`).

    ``recall_<bin>``: share of the bin's true centreline points with a reconstructed point within ``found_mm``;
    ``radius_mae_<bin>``: mean |radius error| of the reconstructed points within ``matched_mm`` of a true point
    of that bin; ``precision``: share of reconstructed points within ``found_mm`` of the true centreline;
    ``radius_bias_mm``: mean signed radius error of all matched points. None where a bin is empty.
    """
    P, PR = np.asarray(points, float).reshape(-1, 3), np.asarray(radius, float)
    T, R = np.asarray(truth_points, float).reshape(-1, 3), np.asarray(truth_radius, float)
    d_truth = cKDTree(P).query(T)[0] if len(P) else np.full(len(T), np.inf)
    d_pred, j = cKDTree(T).query(P) if len(P) else (np.zeros(0), np.zeros(0, int))
    near = d_pred < matched_mm
    out = {}
    for name, (lo, hi) in RADIUS_BINS_MM.items():
        in_bin = (R >= lo) & (R < hi)
        out[f"recall_{name}"] = float((d_truth[in_bin] < found_mm).mean()) if in_bin.any() else None
        matched = near & (R[j] >= lo) & (R[j] < hi)
        out[f"radius_mae_{name}"] = float(np.abs(PR[matched] - R[j[matched]]).mean()) if matched.any() else None
    out["precision"] = float((d_pred < found_mm).mean()) if len(P) else None
    out["radius_bias_mm"] = float((PR[near] - R[j[near]]).mean()) if near.any() else None
    return out
