"""Epipolar geometry of two X-ray views: plane angles, candidate correspondences and triangulation.

Reads and writes nothing (pure geometry on :class:`stages.geometry.Camera` and :class:`Centreline2D`).

Every plane through both sources (the baseline) is an epipolar plane; we label it by its angle θ about the
baseline, with θ = 0 the plane through the isocentre. A point of view A and a point of view B can be the
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

from .centreline2d import Centreline2D

__all__ = ["EpipolarFrame", "Candidates", "candidates", "triangulate"]


@dataclass
class EpipolarFrame:
    """Baseline frame of a camera pair: θ of any ray, for either view."""

    source_a: np.ndarray
    source_b: np.ndarray
    u: np.ndarray  # unit baseline direction (A → B)
    e1: np.ndarray  # ⊥ u, towards the isocentre
    e2: np.ndarray

    @classmethod
    def of(cls, cam_a, cam_b) -> "EpipolarFrame":
        sa, sb = np.asarray(cam_a.source, float), np.asarray(cam_b.source, float)
        u = sb - sa
        norm = np.linalg.norm(u)
        if norm < 1e-6:
            raise ValueError("the two views share their source position: no baseline")
        u = u / norm
        to_iso = -sa
        e1 = to_iso - (to_iso @ u) * u
        if np.linalg.norm(e1) < 1e-6:  # isocentre on the baseline: any perpendicular will do
            e1 = np.cross(u, [0.0, 0.0, 1.0] if abs(u[2]) < 0.9 else [1.0, 0.0, 0.0])
        e1 /= np.linalg.norm(e1)
        return cls(sa, sb, u, e1, np.cross(u, e1))

    def theta_of_dirs(self, dirs: np.ndarray) -> np.ndarray:
        return np.arctan2(dirs @ self.e2, dirs @ self.e1)

    def theta(self, cam, rc: np.ndarray) -> np.ndarray:
        """θ of the rays through (row, col) pixels of ``cam`` (rays from either source give the same θ)."""
        _, dirs = cam.rays(np.asarray(rc, float).reshape(-1, 2))
        return self.theta_of_dirs(dirs)

    def theta_gradient(self, cam, rc: np.ndarray, h: float = 0.5) -> np.ndarray:
        """|∂θ/∂pixel| (rad per px) at each pixel: converts a tolerance in pixels to one in θ."""
        rc = np.asarray(rc, float).reshape(-1, 2)
        g_r = (self.theta(cam, rc + [h, 0]) - self.theta(cam, rc - [h, 0])) / (2 * h)
        g_c = (self.theta(cam, rc + [0, h]) - self.theta(cam, rc - [0, h])) / (2 * h)
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


def candidates(frame: EpipolarFrame, cl_a: Centreline2D, cam_a, cl_b: Centreline2D, cam_b, *,
               tol_px: float = 3.0, run_step_px: float = 3.0, chunk: int = 512) -> Candidates:
    """Candidates in B of every point of A (see the module docstring)."""
    empty = Candidates(np.zeros(0, int), np.zeros((0, 2)), np.zeros(0, int), np.zeros(0), np.zeros(0))
    if len(cl_a) == 0 or len(cl_b) < 2:
        return empty
    th_a = frame.theta(cam_a, cl_a.points)
    th_b = frame.theta(cam_b, cl_b.points)
    g_b = np.maximum(frame.theta_gradient(cam_b, cl_b.points), 1e-12)
    # segments k → k+1 inside a branch
    seg = np.flatnonzero(cl_b.branch[:-1] == cl_b.branch[1:])
    t0, t1 = th_b[seg], th_b[seg + 1]
    g = 0.5 * (g_b[seg] + g_b[seg + 1])
    lo = np.minimum(t0, t1) - tol_px * g
    hi = np.maximum(t0, t1) + tol_px * g
    out = {k: [] for k in ("query", "b_pos", "b_index", "miss_px", "run_px")}
    for c0 in range(0, len(th_a), chunk):
        ta = th_a[c0:c0 + chunk]
        hit = (ta[:, None] >= lo[None, :]) & (ta[:, None] <= hi[None, :])
        qi, si = np.nonzero(hit)
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
        # the best (smallest miss) segment of each run, plus extra samples along long runs
        order = np.lexsort((miss, run_id))
        first = order[np.r_[True, run_id[order][1:] != run_id[order][:-1]]]
        pick = [first]
        long_runs = np.flatnonzero(run_len > 2 * run_step_px)
        if len(long_runs):
            pos_in_run = np.arange(len(qi)) - np.flatnonzero(new_run)[run_id]
            extra = np.flatnonzero(np.isin(run_id, long_runs) & (pos_in_run % int(run_step_px) == 0))
            pick.append(extra)
        sel = np.unique(np.concatenate(pick))
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
