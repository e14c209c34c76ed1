"""Graph matching (paper, Algorithm 1): each curve segment of a graph is matched to a target point set by a
dynamic programme over candidate points.

For a curve q_1..q_n and, per curve point, candidates c (its ``k`` nearest target points), the programme
chooses one candidate per point minimising

    Σ_i ‖q_i − c_i‖  +  λ Σ_i | ‖c_{i+1} − c_i‖ − ‖q_{i+1} − q_i‖ |

(unary distance + pairwise term keeping the spacing, hence the order, of the curve). This is the
recurrence Algorithm 1 intends (its printed listing has index errors): Viterbi over the candidates, all
curves of a graph in one compiled pass (:mod:`stages.core.chain_dp`), its spacing costs compiled too. An optional "no match" state with a fixed cost ``null_cost`` lets a point stay unmatched
(a segment absent from the target) instead of being dragged to a wrong vessel.

Works in any dimension: 3D (a curve against the next frame's predicted centreline points) and 2D (a
projected curve against a view's vessel centreline pixels). Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from ..core.chain_dp import label_chains

__all__ = ["match_curve_dp", "match_curves_dp", "match_curve_greedy", "match_graph", "Targets"]

_BIG = 1e6


class Targets:
    """A target point set with its KD-tree (built once, queried at every match)."""

    def __init__(self, points: np.ndarray):
        from scipy.spatial import cKDTree

        self.points = np.asarray(points, float)
        self.tree = cKDTree(self.points)

    def __len__(self) -> int:
        return len(self.points)


def _as_targets(targets) -> Targets:
    return targets if isinstance(targets, Targets) else Targets(targets)


@njit(cache=True, nogil=True)
def _spacing_costs(Q, P, step_i, lam):
    """λ |‖c_i − c_{i−1}‖ − ‖q_i − q_{i−1}‖| for every (previous, current) candidate pair of every step
    ``step_i`` (flat, steps × k(previous) × k(current)); compiled because the NumPy version's temporaries
    (steps × k × k × D) cost more than the programme itself."""
    k, dim = P.shape[1], P.shape[2]
    out = np.empty(len(step_i) * k * k)
    for e in range(len(step_i)):
        i = step_i[e]
        step = 0.0
        for d in range(dim):
            step += (Q[i, d] - Q[i - 1, d]) ** 2
        step = np.sqrt(step)
        for r in range(k):
            for s in range(k):
                g = 0.0
                for d in range(dim):
                    g += (P[i, s, d] - P[i - 1, r, d]) ** 2
                out[(e * k + r) * k + s] = lam * abs(np.sqrt(g) - step)
    return out


def match_curves_dp(curves: list[np.ndarray], targets, k: int = 8, lam: float = 2.0, max_dist: float | None = None,
                    null_cost: float | None = None) -> list[np.ndarray]:
    """Match several curves at once. Returns, per curve, the chosen target index per point (−1: no match)."""
    T = _as_targets(targets)
    curves = [np.asarray(c, float) for c in curves]
    out = [np.full(len(c), -1, np.int64) for c in curves]
    if not curves or not len(T):
        return out
    k = int(min(k, len(T)))
    lengths = np.array([len(c) for c in curves])
    bounds = np.r_[0, np.cumsum(lengths)]
    Q = np.concatenate(curves)
    if not len(Q):
        return out
    dist, idx = T.tree.query(Q, k)
    U, C = dist.reshape(-1, k), idx.reshape(-1, k)
    if max_dist is not None:
        U = np.where(U > max_dist, _BIG, U)
    P = T.points[C]  # N×k×D candidate positions
    # steps i−1 → i inside a curve: λ |‖c_i − c_{i−1}‖ − ‖q_i − q_{i−1}‖| for every (previous, current) pair
    step_i = np.setdiff1d(np.arange(1, len(Q)), bounds[1:-1])
    pair = _spacing_costs(np.ascontiguousarray(Q), np.ascontiguousarray(P), step_i.astype(np.int64), float(lam))
    pair_start = np.zeros(len(Q), np.int64)
    pair_start[step_i] = np.arange(len(step_i)) * k * k
    chosen = label_chains(bounds, np.arange(0, len(Q) * k + 1, k), U.ravel(), pair, pair_start,
                          null_unary=None if null_cost is None else np.full(len(Q), float(null_cost)))
    has = chosen >= 0
    m = np.full(len(Q), -1, np.int64)
    m[has] = C[has, chosen[has]]
    m[has & (U[np.arange(len(Q)), np.maximum(chosen, 0)] >= _BIG)] = -1
    return [m[bounds[s]:bounds[s + 1]] for s in range(len(curves))]


def match_curve_dp(curve: np.ndarray, targets, k: int = 8, lam: float = 2.0, max_dist: float | None = None,
                   null_cost: float | None = None) -> np.ndarray:
    """Target index per curve point (−1: unmatched) by the Algorithm-1 dynamic programme."""
    return match_curves_dp([curve], targets, k, lam, max_dist, null_cost)[0]


def match_curve_greedy(curve: np.ndarray, targets, max_dist: float | None = None) -> np.ndarray:
    """Baseline: nearest target point of every curve point independently."""
    T = _as_targets(targets)
    d, i = T.tree.query(np.asarray(curve, float))
    if max_dist is not None:
        i = np.where(d <= max_dist, i, -1)
    return i.astype(np.int64)


def match_graph(points: np.ndarray, segments: list[np.ndarray], targets, **kw) -> np.ndarray:
    """Matched target position per graph node (N×D, NaN when unmatched), matching every segment by the DP.

    A node shared by several segments (a junction) gets the mean of its matches.
    """
    T = _as_targets(targets)
    pts = np.asarray(points, float)
    acc = np.zeros_like(pts)
    cnt = np.zeros(len(pts))
    if segments:
        matches = match_curves_dp([pts[s] for s in segments], T, **kw)
        for seg, m in zip(segments, matches):
            ok = m >= 0
            np.add.at(acc, seg[ok], T.points[m[ok]])
            np.add.at(cnt, seg[ok], 1)
    out = np.full_like(pts, np.nan)
    hit = cnt > 0
    out[hit] = acc[hit] / cnt[hit, None]
    return out
