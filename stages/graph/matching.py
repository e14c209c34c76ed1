"""Graph matching (paper, Algorithm 1): each curve segment of a graph is matched to a target point set by a
dynamic programme over candidate points.

For a curve q_1..q_n and, per curve point, candidates c (its ``k`` nearest target points), the programme
chooses one candidate per point minimising

    Σ_i ‖q_i − c_i‖  +  λ Σ_i | ‖c_{i+1} − c_i‖ − ‖q_{i+1} − q_i‖ |

(unary distance + pairwise term keeping the spacing, hence the order, of the curve). This is the
recurrence Algorithm 1 intends (its printed listing has index errors): Viterbi over the candidates,
vectorised with NumPy across candidates *and* across all curves of a graph at once (curves padded to the
longest). An optional "no match" state with a fixed cost ``null_cost`` lets a point stay unmatched
(a segment absent from the target) instead of being dragged to a wrong vessel.

Works in any dimension: 3D (a curve against the next frame's predicted centreline points) and 2D (a
projected curve against a view's vessel centreline pixels). Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np

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


def match_curves_dp(curves: list[np.ndarray], targets, k: int = 8, lam: float = 2.0, max_dist: float | None = None,
                    null_cost: float | None = None) -> list[np.ndarray]:
    """Match several curves at once. Returns, per curve, the chosen target index per point (−1: no match)."""
    T = _as_targets(targets)
    curves = [np.asarray(c, float) for c in curves]
    out = [np.full(len(c), -1, np.int64) for c in curves]
    if not curves or not len(T):
        return out
    k = int(min(k, len(T)))
    S = len(curves)
    lengths = np.array([len(c) for c in curves])
    Lmax = int(lengths.max())
    D = curves[0].shape[1]
    Q = np.zeros((S, Lmax, D))
    valid = np.arange(Lmax)[None, :] < lengths[:, None]
    Q[valid] = np.concatenate(curves)
    dist, idx = T.tree.query(Q[valid], k)
    dist, idx = dist.reshape(-1, k), idx.reshape(-1, k)
    U = np.full((S, Lmax, k), _BIG)
    C = np.zeros((S, Lmax, k), np.int64)
    U[valid], C[valid] = dist, idx
    if max_dist is not None:
        U[U > max_dist] = _BIG
    null = null_cost is not None
    if null:
        U = np.concatenate([U, np.full((S, Lmax, 1), float(null_cost))], 2)
    ks = U.shape[2]
    P = T.points[C]  # S×L×k×D candidate positions
    step = np.linalg.norm(np.diff(Q, axis=1), axis=2)  # S×(L−1) curve spacing
    cost = U[:, 0].copy()
    back = np.zeros((S, Lmax, ks), np.int64)
    for i in range(1, Lmax):
        gap = np.linalg.norm(P[:, i, None, :, :] - P[:, i - 1, :, None, :], axis=3)  # S×k(prev)×k(cur)
        pair = lam * np.abs(gap - step[:, i - 1, None, None])
        if null:  # to/from the no-match state costs nothing beyond its unary
            pair = np.pad(pair, ((0, 0), (0, 1), (0, 1)))
        total = cost[:, :, None] + pair
        best = total.argmin(1)  # S×ks
        new = np.take_along_axis(total, best[:, None, :], 1)[:, 0] + U[:, i]
        live = valid[:, i]
        back[:, i] = np.where(live[:, None], best, np.arange(ks)[None, :])
        cost = np.where(live[:, None], new, cost)
    state = cost.argmin(1)
    for s in range(S):
        n = lengths[s]
        st = int(state[s])
        path = np.empty(n, np.int64)
        for i in range(n - 1, -1, -1):
            path[i] = st
            st = int(back[s, i, st])
        m = np.where(path < k, C[s, np.arange(n), np.minimum(path, k - 1)], -1)
        m[np.where(path < k, U[s, np.arange(n), np.minimum(path, k - 1)], 0) >= _BIG] = -1
        out[s] = m
    return out


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
