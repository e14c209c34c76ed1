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
                "profile": {"s_mm": np.round(prof.s[::every], 2).tolist(),
                            "diameter_mm": np.round(prof.diameter[::every], 3).tolist(),
                            "reference_mm": np.round(prof.reference[::every], 3).tolist()},
            })
        return {"side": self.side, "vessels": vessels}


def analyse_graph(graph, params: QCAParams | None = None, root=None) -> GraphQCA:
    """Tree, names, profiles and lesions of one graph (a VascularGraph)."""
    from ..graph.vascular import VascularGraph

    p = params or QCAParams()
    bad = ~np.isfinite(graph.radius) | (graph.radius <= 0)
    if bad.any():  # a node without a usable radius takes the median of the others (none: 1 mm)
        good = graph.radius[~bad]
        graph = VascularGraph(graph.nodes, np.where(bad, float(np.median(good)) if len(good) else 1.0, graph.radius),
                              graph.edges, graph.node_id)
    tree = vessel_tree(graph, min_branch_mm=p.min_branch_mm, root=root, join_gap_mm=p.join_gap_mm)
    label_tree(tree)
    out = GraphQCA(tree, {}, p)
    for v in tree.vessels:
        if v.length < p.min_vessel_mm and v.name == "unlabelled":
            continue
        r = tree.radius[v.nodes]
        junctions = [(sj, rb) for sj, _, rb in v.junctions]
        leaf = len(v.nodes) and not any(c.parent == v.index for c in tree.vessels if abs(c.parent_s - v.length) < 0.5)
        prof = vessel_profile(v.s, r, junctions, spurs=v.spurs, step_mm=p.step_mm, smooth_mm=p.smooth_mm, min_ds=p.min_ds,
                              skip_start_mm=p.skip_start_mm if v.parent >= 0 else 0.0,
                              skip_end_mm=p.skip_end_mm if leaf else 0.0, murray_weight=p.murray_weight)
        prof.lesions = [les for les in prof.lesions if les["reference_mm"] >= p.min_reference_mm]
        out.profiles[v.index] = prof
    return out
