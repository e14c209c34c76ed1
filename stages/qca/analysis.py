"""3D QCA of one vascular graph: vessels named, profiled and graded.

Reads/writes nothing; :func:`analyse_graph` returns a :class:`GraphQCA` (the tree, the profiles, and
:meth:`GraphQCA.to_dict`, the ``vessels`` part of qca.json).

Which vessels are reported: every named vessel, and every unlabelled one at least ``min_vessel_mm``
long. Lesions are graded where the reference lumen is at least ``min_reference_mm`` wide
(QCA is not done on vessels under ~1.5 mm; the synthetic engine puts stenoses only on vessels of
Ø ≥ 2 mm) and not within ``skip_start_mm`` of a side branch's origin (its first samples carry the
parent's lumen) nor ``skip_end_mm`` of a free distal end.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .labels import label_tree, segment_of
from .profile import Profile, vessel_profile
from .tree import VesselTree, vessel_tree

__all__ = ["GraphQCA", "analyse_graph", "QCAParams"]


@dataclass
class QCAParams:
    smooth_mm: float = 0.0  # Gaussian σ of the radius profile (mm)
    min_ds: float = 20.0  # lesions reported from this %DS
    min_reference_mm: float = 1.2  # graded only where the reference diameter is at least this
    min_vessel_mm: float = 10.0  # vessels reported from this length
    skip_start_mm: float = 1.5
    skip_end_mm: float = 2.0
    step_mm: float = 0.25
    murray_weight: float = 20.0
    min_branch_mm: float = 4.0
    join_gap_mm: float = 5.0  # bridge detached pieces whose end is this close to the main tree
    ostium: str = "best"  # "end", "widest" (stages.qca.tree.vessel_tree) or "best" of both (_labelled_tree)

    def to_dict(self) -> dict:
        return dict(self.__dict__)


@dataclass
class GraphQCA:
    tree: VesselTree
    profiles: dict = field(default_factory=dict)  # vessel index → Profile
    params: QCAParams = field(default_factory=QCAParams)

    @property
    def side(self) -> str:
        return self.tree.side

    def reported(self):
        return [v for v in self.tree.vessels if v.index in self.profiles]

    def lesions(self):
        """[(vessel, lesion dict)] over all reported vessels."""
        return [(v, les) for v in self.reported() for les in self.profiles[v.index].lesions]

    def lesion_points(self, vessel, lesion) -> np.ndarray:
        """3D point of a lesion's MLD."""
        pts = self.tree.nodes[vessel.nodes]
        return np.array([np.interp(lesion["position_mm"], vessel.s, pts[:, k]) for k in range(3)])

    def vessel_id(self, v) -> str:
        return f"v{v.index}"

    def to_dict(self, profile_step_mm: float = 0.5) -> dict:
        vessels = []
        for v in self.reported():
            prof: Profile = self.profiles[v.index]
            every = max(int(round(profile_step_mm / max(prof.s[1] - prof.s[0], 1e-9))), 1) if len(prof.s) > 1 else 1
            parent = self.tree.vessels[v.parent] if v.parent >= 0 else None
            lesions = []
            for k, les in enumerate(prof.lesions):
                p = self.lesion_points(v, les)
                lesions.append({"id": f"{self.vessel_id(v)}.l{k}", **{key: round(float(val), 3) for key, val in les.items()},
                                "segment": segment_of(v, les["position_mm"]),
                                "ostium_distance_mm": round(v.ostium_s + les["position_mm"], 2),
                                "point_mm": [round(float(c), 2) for c in p],
                                "significant": bool(les["ds_percent"] >= 50.0)})
            vessels.append({
                "id": self.vessel_id(v), "name": v.name, "length_mm": round(v.length, 2),
                "parent": self.vessel_id(parent) if parent is not None else None,
                "parent_name": parent.name if parent is not None else None,
                "origin_on_parent_mm": round(v.parent_s, 2) if parent is not None else None,
                "ostium_distance_mm": round(v.ostium_s, 2), "component": int(v.component),
                "proximal_diameter_mm": round(float(np.median(prof.diameter[(prof.s >= 2) & (prof.s <= 7)]))
                                              if np.any((prof.s >= 2) & (prof.s <= 7)) else float(prof.diameter[0]), 3),
                "min_diameter_mm": round(float(prof.diameter[prof.valid].min()) if prof.valid.any() else float(prof.diameter.min()), 3),
                "lesions": lesions,
                # graph node indices from the origin on: the key frames share them (exports name the nodes)
                "nodes": [int(i) for i in v.nodes],
                "profile": {"s_mm": np.round(prof.s[::every], 2).tolist(),
                            "diameter_mm": np.round(prof.diameter[::every], 3).tolist(),
                            "reference_mm": np.round(prof.reference[::every], 3).tolist()},
            })
        return {"side": self.side, "vessels": vessels}


MAIN_NAMES = ("LM", "LAD", "LCX", "RCA")


def _named_length(tree) -> float:
    return sum(v.length for v in tree.vessels if v.name in MAIN_NAMES)


def _labelled_tree(graph, p: QCAParams, root=None):
    """The named vessel tree. With ``ostium="best"`` both ostium rules of :func:`vessel_tree` are tried
    ("end": the widest, highest free end; "widest": the free end of the widest trunk, or an inner node
    when the ostium is not a free end) and the tree whose LM/LAD/LCX/RCA are the longest is kept: each
    rule fails where the other does not (a catheter or a lost left main make the ostium an inner node;
    a reconstruction's radius noise can make a mid-vessel point the widest). An "end" root whose first
    10 mm are under 70 % as wide as the "widest" root's is never kept (a catheter's far end)."""
    rules = ("end", "widest") if p.ostium == "best" and root is None else (p.ostium if p.ostium != "best" else "end",)
    trees = []
    for rule in rules:
        tree = vessel_tree(graph, min_branch_mm=p.min_branch_mm, root=root, join_gap_mm=p.join_gap_mm, ostium=rule)
        label_tree(tree)
        trees.append(tree)
    if len(trees) == 1 or not trees[0].roots or trees[0].roots[:1] == trees[1].roots[:1]:
        return trees[0]
    end, widest = trees
    # the ostium is the widest lumen: an end root far thinner than the widest trunk is a catheter or a twig
    if _root_radius(end) < THIN_ROOT * _root_radius(widest):
        return widest
    return widest if _named_length(widest) > _named_length(end) + 1.0 else end


THIN_ROOT = 0.7


def _root_radius(tree, within_mm: float = 10.0) -> float:
    """Mean radius of the main tree's nodes within ``within_mm`` of its root, along the tree."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import dijkstra

    n = len(tree.nodes)
    child = np.flatnonzero(tree.parent >= 0)
    par = tree.parent[child]
    w = np.maximum(np.linalg.norm(tree.nodes[child] - tree.nodes[par], axis=1), 1e-6)
    A = coo_matrix((np.r_[w, w], (np.r_[child, par], np.r_[par, child])), shape=(n, n)).tocsr()
    d = dijkstra(A, indices=tree.roots[0], limit=within_mm)
    return float(tree.radius[np.isfinite(d)].mean())


def within_parent_mm(tree: VesselTree, v, margin_mm: float = 0.5) -> float:
    """How far (mm along ``v``) a side branch runs inside its parent's lumen: its first nodes lie within the
    parent's radius (plus ``margin_mm``) of the parent's centreline, so the radius measured there is the
    parent's, not the branch's. An oblique branch stays inside longer than the parent's radius."""
    parent = tree.vessels[v.parent]
    pts, ppts = tree.nodes[v.nodes], tree.nodes[parent.nodes]
    if len(pts) < 2 or len(ppts) < 1:
        return 0.0
    d = np.linalg.norm(pts[:, None, :] - ppts[None, :, :], axis=2)
    nearest = d.argmin(1)
    inside = d[np.arange(len(pts)), nearest] <= tree.radius[parent.nodes][nearest] + margin_mm
    first_out = int(np.argmin(inside)) if not inside.all() else len(pts) - 1
    return float(v.s[first_out])


def analyse_graph(graph, params: QCAParams | None = None, root=None) -> GraphQCA:
    """Tree, names, profiles and lesions of one graph (a VascularGraph)."""
    from ..graph.vascular import VascularGraph

    p = params or QCAParams()
    bad = ~np.isfinite(graph.radius) | (graph.radius <= 0)
    if bad.any():  # a node without a usable radius takes the median of the others (none: 1 mm)
        good = graph.radius[~bad]
        graph = VascularGraph(graph.nodes, np.where(bad, float(np.median(good)) if len(good) else 1.0, graph.radius),
                              graph.edges, graph.node_id)
    tree = _labelled_tree(graph, p, root)
    out = GraphQCA(tree, {}, p)
    for v in tree.vessels:
        if v.length < p.min_vessel_mm and v.name == "unlabelled":
            continue
        r = tree.radius[v.nodes]
        junctions = [(sj, rb) for sj, _, rb in v.junctions]
        leaf = len(v.nodes) and not any(c.parent == v.index for c in tree.vessels if abs(c.parent_s - v.length) < 0.5)
        skip_start = max(p.skip_start_mm, within_parent_mm(tree, v)) if v.parent >= 0 else 0.0
        prof = vessel_profile(v.s, r, junctions, spurs=v.spurs, step_mm=p.step_mm, smooth_mm=p.smooth_mm, min_ds=p.min_ds,
                              skip_start_mm=skip_start,
                              skip_end_mm=p.skip_end_mm if leaf else 0.0, murray_weight=p.murray_weight)
        prof.lesions = [les for les in prof.lesions if les["reference_mm"] >= p.min_reference_mm]
        out.profiles[v.index] = prof
    return out
