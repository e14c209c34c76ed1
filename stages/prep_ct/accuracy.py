"""Accuracy of a prepared case against the analytic ground truth of a procedural tree (``case.truth``).

Used by the tests and ``benchmarks/bench_prep_ct.py`` for the acceptance figures:

* surface: |signed distance| of every mesh vertex to the analytic tube surface (union of balls along
  the truth centreline, sampled every 0.05 mm);
* centreline: distance from prepared centreline points (edges densified every 0.1 mm) to the truth
  polylines and back, both directions; radius error at every prepared node against the radius of
  the nearest truth point;
* bifurcations: Σ (degree − 2) of the prepared graph against the truth tree's count.
"""

from __future__ import annotations

import numpy as np

from .labels import densify_polyline


def truth_samples(truth, step: float = 0.05):
    """Truth centreline points and radii resampled every ``step`` mm, plus the segment list per branch."""
    from ..anatomy import resample

    pts, rad = [], []
    for p, r in truth.polylines():
        if len(p) < 2:
            continue
        q, s = resample(p, r, step)
        pts.append(q)
        rad.append(s)
    return np.concatenate(pts), np.concatenate(rad)


def truth_sdf(truth, x, step: float = 0.05) -> np.ndarray:
    """Signed distance (negative inside) to the union of balls of the truth centreline."""
    from scipy.spatial import cKDTree

    pts, rad = truth_samples(truth, step)
    tree = cKDTree(pts)
    x = np.asarray(x, float).reshape(-1, 3)
    rmax, rmin = float(rad.max()), float(rad.min())
    d0, _ = tree.query(x)
    out = np.empty(len(x))
    # the minimising ball lies within d0 + (rmax − rmin) of x; process in chunks with a ball query
    for s in range(0, len(x), 20000):
        xs = x[s:s + 20000]
        lists = tree.query_ball_point(xs, d0[s:s + 20000] + (rmax - rmin) + 1e-6)
        lens = np.fromiter((len(l) for l in lists), int, len(lists))
        flat = np.fromiter((i for l in lists for i in l), int, int(lens.sum()))
        owner = np.repeat(np.arange(len(xs)), lens)
        val = np.linalg.norm(pts[flat] - xs[owner], axis=1) - rad[flat]
        res = np.full(len(xs), np.inf)
        np.minimum.at(res, owner, val)
        out[s:s + 20000] = res
    return out


def truth_bifurcations(truth) -> int:
    """Σ (degree − 2) of the truth tree (children off a parent's last point split it, others add 1)."""
    count, ends = 0, {}
    last = {}
    for b in range(len(truth.parent)):
        idx = np.nonzero(truth.branch == b)[0]
        last[b] = truth.points[idx[-1]] if len(idx) else None
    for b, par in enumerate(truth.parent):
        if par < 0:
            continue
        first = truth.points[truth.branch == b][0]
        if last[par] is not None and np.linalg.norm(first - last[par]) < 1e-3:
            ends[par] = ends.get(par, 0) + 1
        else:
            count += 1
    return count + sum(n - 1 for n in ends.values())


def evaluate_case(case) -> dict:
    """Acceptance figures of one prepared synthetic case (needs ``case.truth``)."""
    from scipy.spatial import cKDTree

    from .centreline import bifurcation_count

    t = case.truth
    sd = truth_sdf(t, case.vertices)
    surf = np.abs(sd)
    tp, tr = truth_samples(t, 0.05)
    pred = densify_polyline(case.nodes, case.edges, 0.1)
    d_pt = cKDTree(tp).query(pred)[0]
    d_tp = cKDTree(pred).query(tp)[0]
    _, near = cKDTree(tp).query(case.nodes)
    rad_err = np.abs(case.radius - tr[near])
    return {
        "surface_mean": float(surf.mean()), "surface_p95": float(np.percentile(surf, 95)),
        "surface_signed_mean": float(sd.mean()),
        "cl_pred_to_truth_mean": float(d_pt.mean()), "cl_pred_to_truth_p95": float(np.percentile(d_pt, 95)),
        "cl_truth_to_pred_mean": float(d_tp.mean()), "cl_truth_to_pred_p95": float(np.percentile(d_tp, 95)),
        "radius_mae": float(rad_err.mean()),
        "bifurcations": bifurcation_count(case.nodes, case.edges), "bifurcations_truth": truth_bifurcations(t),
    }
