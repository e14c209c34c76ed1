"""Vessels that overlap in one view, placed by the views that see them apart.

Where two vessels overlap in one view's projection, that view's mask holds one band and its skeleton runs through it
once. The 3D step triangulates both vessels from that skeleton and graph-opt's registration pulls both onto it, so in
that view the two project onto the same line, whichever of them the image shows there. With three or more views the
others usually see the two apart, and they alone fix where each vessel lies.

:func:`refit_overlapped_nodes` moves, in one key frame's graph, the nodes that another part of the tree (more than
:data:`SEPARATION_MM` away along it) overlaps in some view — projects within :data:`OVERLAP_MM` of — and that at least
two views see alone: each such node is fitted to the centrelines of the views that see it alone (its distance across
the nearest centreline pixel's line, Huber loss), its displacement kept close to its neighbours' (the rest of the tree
is held where it is). With two views no node qualifies: one view alone cannot fix a depth.

Measured on data-re with a third run (20 cases, Table 2's protocol; docs/benchmarks/re_errors.md has the census): of
the queries lost, the largest share were overlaps in view A where the model held the right vessel but another of its
vessels projected nearer the query — both on view A's skeleton (0.17 and 0.19 mm from it) while the true tree's other
vessel lay about 1 mm away. Refitting took accuracy 0.883 → 0.890 and EPE 1.53 → 1.46 mm (docs/TWOVIEW.md).

Reads/writes nothing.
"""

from __future__ import annotations

import numpy as np

from .optimise import _huber, _lbfgs, _project, _project_backward
from .redundancy import _far_partners, _overlapping_pairs
from .vascular import VascularGraph

__all__ = ["overlapped_nodes", "refit_overlapped_nodes", "OVERLAP_MM", "SEPARATION_MM"]

OVERLAP_MM = 1.5  # another part of the tree projecting this close (isocentre mm) overlaps a node in that view ...
SEPARATION_MM = 15.0  # ... when it lies this far away along the tree (a node's own vessel and side branches do not count)
REACH_PX = 5.0  # a view's centreline pixel further than this from a node's projection is not its vessel
HUBER_MM = 0.5
SMOOTHNESS = 1.0  # weight of the neighbours' displacement differences (mm², per edge) against the views (mm, per term)
ANCHOR = 0.01  # weight of each moved node's displacement (mm², per node): keeps a node no view holds where it was


def overlapped_nodes(graph: VascularGraph, camera) -> np.ndarray:
    """Per node: does another part of ``graph`` (more than :data:`SEPARATION_MM` away along it) project within
    :data:`OVERLAP_MM` of it in ``camera``'s view?"""
    pairs = _overlapping_pairs(graph.nodes, camera, OVERLAP_MM)
    partners = _far_partners(graph, np.arange(len(graph)), pairs, SEPARATION_MM)
    return np.asarray(partners.sum(1)).ravel() > 0


def refit_overlapped_nodes(graph: VascularGraph, views, rounds: int = 3, iterations: int = 30) -> tuple[VascularGraph, int]:
    """``graph`` with its nodes that some view sees overlapped by another part of the tree, and at least two views see
    alone, fitted to those views' centrelines (module docstring); and the number of nodes moved. ``views``:
    :class:`~stages.graph.optimise.View` s with centrelines (fewer than three: nothing can qualify). Each of the
    ``rounds`` finds every moved node's nearest centreline pixel per view again, then runs L-BFGS."""
    if len(views) < 3 or len(graph) < 2 or not len(graph.edges):
        return graph, 0
    overlapped = np.array([overlapped_nodes(graph, v.camera) for v in views])  # views × nodes
    free = overlapped.any(0) & ((~overlapped).sum(0) >= 2)
    if not free.any():
        return graph, 0
    X0 = np.asarray(graph.nodes, float)
    moved = np.flatnonzero(free)
    slot = np.full(len(graph), -1)
    slot[moved] = np.arange(len(moved))
    edges = graph.edges[free[graph.edges].any(1)]  # the edges a moved node touches
    delta = np.zeros((len(moved), 3))

    def displacement(d):
        D = np.zeros_like(X0)
        D[moved] = d
        return D

    for _ in range(rounds):
        X = X0 + displacement(delta)
        terms = []
        for v, hidden in zip(views, overlapped):
            sel = moved[~hidden[moved]]
            if not len(sel):
                continue
            tree, normals = v.centreline_lines
            rc = v.camera.project(X[sel])
            ok = np.isfinite(rc).all(1)
            dist, nearest = tree.query(np.where(ok[:, None], rc, 0.0))
            ok &= dist <= REACH_PX
            if ok.any():
                terms.append((v.camera, slot[sel[ok]], tree.data[nearest[ok]], normals[nearest[ok]],
                              float(v.camera.isocentre_spacing)))
        if not terms:
            break
        n_terms = sum(len(t[1]) for t in terms)

        def energy(d):
            D = displacement(d)
            diff = D[edges[:, 0]] - D[edges[:, 1]]
            value = SMOOTHNESS * float((diff * diff).sum()) / len(edges) + ANCHOR * float((d * d).sum()) / len(d)
            grad_D = np.zeros_like(X0)
            np.add.at(grad_D, edges[:, 0], SMOOTHNESS * 2 * diff / len(edges))
            np.add.at(grad_D, edges[:, 1], -SMOOTHNESS * 2 * diff / len(edges))
            grad = grad_D[moved] + ANCHOR * 2 * d / len(d)
            for camera, idx, target, normal, mm_per_px in terms:
                rc, h, KR = _project(camera, X0[moved[idx]] + d[idx])
                across = ((rc - target) * normal).sum(1) * mm_per_px
                rho, drho = _huber(np.abs(across), HUBER_MM)
                value += float(rho.sum()) / n_terms
                g_rc = (drho * np.sign(across) * mm_per_px / n_terms)[:, None] * normal
                np.add.at(grad, idx, _project_backward(g_rc, h, KR))
            return value, grad

        delta = _lbfgs(energy, delta, iterations)
    return graph.copy(nodes=X0 + displacement(delta)), len(moved)
