"""Exact minimum-cost labelling of chains (Viterbi), compiled: the one home of the chain dynamic programme.

Reads and writes nothing. Two stages choose one state per point along chains of points:

* the two-view correspondence method (:mod:`stages.twoview.select`): per 2D centreline point, one epipolar
  candidate in the other view or "no partner";
* graph matching (:mod:`stages.graph.matching`, the paper's Algorithm 1): per curve point, one of its nearest
  target points or "no match".

Both are the same problem. Points come grouped in chains; point ``i`` has ``K_i`` candidate states with unary
costs, plus optionally a *null* state (no partner) with its own unary cost; each step ``i − 1 → i`` inside a
chain has a ``K_{i−1} × K_i`` block of pairwise costs; entering or leaving the null state costs
``switch_cost`` and staying in it nothing. The programme is sequential along a chain, which is why it is
compiled (numba) rather than written as a NumPy loop: the Python version spent most of ``make demo``'s
graph-opt and half of the 3D step in per-point interpreter overhead.

Ties go to the first state, the null state last (as ``numpy.argmin`` over the candidates then null would).
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["label_chains"]


@njit(cache=True, nogil=True)
def _label_chains(chain_bounds, state_start, unary, null_unary, pair, pair_start, has_null, switch_cost, chosen):
    n_states_max = 0
    for i in range(len(state_start) - 1):
        n_states_max = max(n_states_max, state_start[i + 1] - state_start[i])
    width = n_states_max + 1
    for c in range(len(chain_bounds) - 1):
        p0, p1 = chain_bounds[c], chain_bounds[c + 1]
        if p1 <= p0:
            continue
        back = np.empty((p1 - p0, width), np.int64)
        cost = np.empty(width)
        new = np.empty(width)
        k0 = state_start[p0 + 1] - state_start[p0]
        for s in range(k0):
            cost[s] = unary[state_start[p0] + s]
        cost[k0] = null_unary[p0] if has_null else np.inf
        for i in range(p0 + 1, p1):
            k1 = state_start[i + 1] - state_start[i]
            base = pair_start[i]
            for s in range(k1):
                best, arg = np.inf, 0
                for r in range(k0):
                    t = cost[r] + pair[base + r * k1 + s]
                    if t < best:
                        best, arg = t, r
                if has_null:
                    t = cost[k0] + switch_cost
                    if t < best:
                        best, arg = t, k0
                new[s] = best + unary[state_start[i] + s]
                back[i - p0, s] = arg
            if has_null:
                best, arg = np.inf, 0
                for r in range(k0):
                    t = cost[r] + switch_cost
                    if t < best:
                        best, arg = t, r
                t = cost[k0] + 0.0
                if t < best:
                    best, arg = t, k0
                new[k1] = best + null_unary[i]
                back[i - p0, k1] = arg
            else:
                new[k1] = np.inf
            for s in range(k1 + 1):
                cost[s] = new[s]
            k0 = k1
        best, state = np.inf, 0
        for s in range(k0 + 1):
            if cost[s] < best:
                best, state = cost[s], s
        for i in range(p1 - 1, p0 - 1, -1):
            k = state_start[i + 1] - state_start[i]
            chosen[i] = state if state < k else -1
            if i > p0:
                state = back[i - p0, state]


def label_chains(chain_bounds, state_start, unary, pair, pair_start, *, null_unary=None,
                 switch_cost: float = 0.0) -> np.ndarray:
    """Optimal state per point (the module docstring); −1 where the null state is chosen.

    ``chain_bounds`` (C+1): point ``i`` belongs to chain ``c`` when ``chain_bounds[c] <= i < chain_bounds[c+1]``.
    ``state_start`` (N+1): point ``i``'s candidate states are ``unary[state_start[i]:state_start[i+1]]``.
    ``pair`` / ``pair_start`` (N): the step into point ``i`` (not a chain's first point) costs
    ``pair[pair_start[i] + r * K_i + s]`` from state ``r`` of point ``i − 1`` to state ``s`` of point ``i``.
    ``null_unary`` (N, or None for no null state): the cost of point ``i`` having no partner.
    Returns, per point, the index of its chosen state among its own candidates (0 … K_i − 1) or −1.
    """
    state_start = np.ascontiguousarray(state_start, np.int64)
    n = len(state_start) - 1
    chosen = np.full(n, -1, np.int64)
    if n <= 0:
        return chosen
    has_null = null_unary is not None
    null = np.ascontiguousarray(null_unary if has_null else np.zeros(n), np.float64)
    _label_chains(np.ascontiguousarray(chain_bounds, np.int64), state_start, np.ascontiguousarray(unary, np.float64),
                  null, np.ascontiguousarray(pair, np.float64), np.ascontiguousarray(pair_start, np.int64), has_null,
                  float(switch_cost), chosen)
    return chosen
