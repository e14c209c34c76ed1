"""Epipolar geometry of two X-ray views: plane angles, candidate correspondences and triangulation.

Reads and writes nothing (pure geometry on :class:`stages.core.geometry.Camera` and :class:`Centreline2D`).

Every plane through both sources (the baseline) is an epipolar plane, labelled by its angle θ about the
baseline (:func:`stages.core.geometry.epipolar_angles`, near 0 for the plane through the isocentre). A point of view A and a point of view B can be the
same 3D point only if their rays lie in the same plane, i.e. have the same θ. So the candidates of a view-A
centreline point are where view B's centreline branches cross its θ — found per branch segment, with a
tolerance band of ``tol_px`` pixels (measured across the epipolar lines in view B) for misaligned views
(temporal misalignment, header error). A segment that only comes within the band gives its closest point;
a run of consecutive segments in the band (a vessel along the epipolar line) gives candidates every
``run_step_px`` so the selection can choose among them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..core.geometry import epipolar_angles
from .centreline2d import Centreline2D

__all__ = ["angle_gradient", "Candidates", "candidates", "triangulate"]


def angle_gradient(cam, rc: np.ndarray, frame, h: float = 0.5) -> np.ndarray:
    """|∂θ/∂pixel| (rad per px) of the epipolar-plane angle at each pixel: converts a tolerance in pixels
    to one in θ."""
    rc = np.asarray(rc, float).reshape(-1, 2)
    g_r = (epipolar_angles(cam, rc + [h, 0], frame) - epipolar_angles(cam, rc - [h, 0], frame)) / (2 * h)
    g_c = (epipolar_angles(cam, rc + [0, h], frame) - epipolar_angles(cam, rc - [0, h], frame)) / (2 * h)
    return np.hypot(g_r, g_c)


def triangulate(cam_a, rc_a: np.ndarray, cam_b, rc_b: np.ndarray):
    """Midpoints of the closest approach of matched rays. Returns (points N×3, gap N mm between the rays)."""
    oa, da = cam_a.rays(np.asarray(rc_a, float).reshape(-1, 2))
    ob, db = cam_b.rays(np.asarray(rc_b, float).reshape(-1, 2))
    w = oa - ob
    b = np.einsum("ij,ij->i", da, db)
    d = np.einsum("ij,ij->i", da, w)
    e = np.einsum("ij,ij->i", db, w)
    denom = np.maximum(1.0 - b * b, 1e-9)
    s = (b * e - d) / denom
    t = (e - b * d) / denom
    pa, pb = oa + s[:, None] * da, ob + t[:, None] * db
    return 0.5 * (pa + pb), np.linalg.norm(pa - pb, axis=1)


@dataclass
class Candidates:
    """Candidate partners in view B of view-A centreline points (flat arrays, grouped by ``query``)."""

    query: np.ndarray  # M int index into the view-A centreline
    b_pos: np.ndarray  # M×2 (row, col) in view B, sub-pixel
    b_index: np.ndarray  # M int nearest view-B centreline point
    miss_px: np.ndarray  # M distance across the epipolar line in view B (0 for a true crossing)
    run_px: np.ndarray  # M length of the band run the candidate came from (long: vessel along the line)

    def __len__(self) -> int:
        return len(self.query)


def candidates(frame, cl_a: Centreline2D, cam_a, cl_b: Centreline2D, cam_b, *,
               tol_px: float = 3.0, run_step_px: float = 3.0, chunk: int = 512) -> Candidates:
    """Candidates in B of every point of A (see the module docstring); ``frame``:
    :func:`stages.core.geometry.epipolar_frame` of the two cameras."""
    empty = Candidates(np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), np.zeros(0))
    if len(cl_a) == 0 or len(cl_b) < 2:
        return empty
    th_a = epipolar_angles(cam_a, cl_a.points, frame)
    th_b = epipolar_angles(cam_b, cl_b.points, frame)
    g_b = np.maximum(angle_gradient(cam_b, cl_b.points, frame), 1e-12)
    # segments k → k+1 inside a branch
    seg = np.flatnonzero(cl_b.branch[:-1] == cl_b.branch[1:])
    t0, t1 = th_b[seg], th_b[seg + 1]
    g = 0.5 * (g_b[seg] + g_b[seg + 1])
    lo = np.minimum(t0, t1) - tol_px * g
    hi = np.maximum(t0, t1) + tol_px * g
    out = {k: [] for k in ("query", "b_pos", "b_index", "miss_px", "run_px")}
    # the segments whose band holds a query's θ: among those whose band starts within the widest band below it
    by_lo = np.argsort(lo, kind="stable")
    lo_sorted = lo[by_lo]
    widest = float(np.max(hi - lo)) if len(lo) else 0.0
    for c0 in range(0, len(th_a), chunk):
        ta = th_a[c0:c0 + chunk]
        first = np.searchsorted(lo_sorted, ta - widest, side="left")
        last = np.searchsorted(lo_sorted, ta, side="right")
        counts = last - first
        qi = np.repeat(np.arange(len(ta)), counts)
        si = by_lo[np.arange(counts.sum()) - np.repeat(np.cumsum(counts) - counts, counts) + np.repeat(first, counts)]
        inside = hi[si] >= ta[qi]
        qi, si = qi[inside], si[inside]
        order = np.argsort(qi * len(seg) + si, kind="stable")  # by query, then along view B's centreline
        qi, si = qi[order], si[order]
        if len(qi) == 0:
            continue
        k = seg[si]
        dt = t1[si] - t0[si]
        with np.errstate(divide="ignore", invalid="ignore"):
            frac = np.where(np.abs(dt) > 1e-15, (ta[qi] - t0[si]) / dt, 0.5)
        frac = np.clip(frac, 0.0, 1.0)
        pos = cl_b.points[k] + frac[:, None] * (cl_b.points[k + 1] - cl_b.points[k])
        th_pos = t0[si] + frac * dt
        miss = np.abs(ta[qi] - th_pos) / g[si]
        # runs: consecutive segments of the same query and the same branch
        new_run = np.r_[True, (qi[1:] != qi[:-1]) | (k[1:] != k[:-1] + 1)]
        run_id = np.cumsum(new_run) - 1
        run_len = np.bincount(run_id)
        # the best (smallest miss, the first of equals) segment of each run, plus extra samples along long runs
        run_start = np.flatnonzero(new_run)
        best = np.flatnonzero(miss == np.minimum.reduceat(miss, run_start)[run_id])
        sel = best[np.r_[True, run_id[best][1:] != run_id[best][:-1]]]
        in_long_run = run_len[run_id] > 2 * run_step_px
        if in_long_run.any():
            pos_in_run = np.arange(len(qi)) - run_start[run_id]
            picked = in_long_run & (pos_in_run % int(run_step_px) == 0)
            picked[sel] = True
            sel = np.flatnonzero(picked)
        out["query"].append(qi[sel] + c0)
        out["b_pos"].append(pos[sel])
        out["b_index"].append(np.where(frac[sel] < 0.5, k[sel], k[sel] + 1))
        out["miss_px"].append(miss[sel])
        out["run_px"].append(run_len[run_id[sel]].astype(float))
    if not out["query"]:
        return empty
    cat = {k: np.concatenate(v) for k, v in out.items()}
    order = np.argsort(cat["query"], kind="stable")
    return Candidates(**{k: v[order] for k, v in cat.items()})
