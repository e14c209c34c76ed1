"""Vessel names on a rooted vessel tree: side (left/right) found from the tree itself, then LM, LAD,
LCX, RCA, the largest diagonal (D), obtuse marginal (OM) and acute marginal (AM); "unlabelled"
otherwise — a name is given only where the rule below is unambiguous.

Reads/writes nothing; :func:`label_tree` changes the :class:`~stages.qca.tree.VesselTree` in place.

Rules (patient frame LPS, +y posterior; the thresholds come from the anatomy described in
stages/anatomy.py and were checked on 80 procedural trees, see docs/QCA.md):

* **Side.** A left tree divides early: its root vessel (from the ostium) has, within
  ``LM_MAX_MM`` (25 mm) of the ostium, a junction whose side vessel carries ≥ 30 mm of tree and is at
  least 0.55× as wide as the trunk just after it (the left-main bifurcation). A right coronary gives
  off only small branches there (conus ≤ Ø 1.7 mm, ≤ 30 mm). No such split → right tree. A vessel whose
  mean heading over its 10–40 mm climbs (z component > 0.4: a catheter up the aorta, a ghost) is never
  the split's branch nor LAD/LCX (on 40 procedural left trees the LAD's heading z ≤ −0.31, the LCX's ≤ 0.17).
* **LM** = the root vessel up to that split (none if the split is within 1 mm of the ostium: a
  reconstruction that lost the LM). Of the vessels leaving the split (the trunk's continuation
  and the side vessel(s) leaving within 3 mm of it), the one heading most anteriorly over its 10–40 mm
  (most negative y of its mean direction from the split) is the **LAD**, the most posterior one the
  **LCX**; a third one (ramus intermedius) stays unlabelled.
* **RCA** = the root vessel of a right tree.
* **D** = the LAD's side vessel of largest lumen volume among those ≥ 20 mm long (septal twigs are
  shorter); **OM** likewise on the LCX; **AM** on the RCA, attached between 15 mm and 75 % of its
  length (the conus is proximal, the PDA/PLB distal).
* Segments: proximal / mid / distal thirds of a named vessel's length.
"""

from __future__ import annotations

import numpy as np

from .tree import Vessel, VesselTree

__all__ = ["label_tree", "segment_of", "LM_MAX_MM"]

LM_MAX_MM = 25.0
LM_MIN_MM = 1.0  # a split closer to the ostium than this: no LM in the tree
MAX_HEADING_UP = 0.4  # coronaries leave the ostium and the LM split downwards or sideways; a catheter climbs
SPLIT_MIN_SUBTREE_MM = 30.0
SPLIT_MIN_WIDTH_RATIO = 0.55
SIDE_BRANCH_MIN_MM = 20.0


def _median_radius(tree: VesselTree, v: Vessel, lo: float, hi: float) -> float:
    sel = (v.s >= lo) & (v.s <= hi)
    return float(np.median(tree.radius[v.nodes[sel]])) if sel.any() else float(np.median(tree.radius[v.nodes]))


def _volume(tree: VesselTree, v: Vessel) -> float:
    r = tree.radius[v.nodes]
    return float(np.sum(np.diff(v.s) * 0.5 * (r[1:] ** 2 + r[:-1] ** 2)))


def _split_vessel(tree: VesselTree, v: Vessel, at_s: float) -> Vessel:
    """Cut ``v`` at arc ``at_s`` (a node of it): ``v`` keeps the proximal part; returns the distal part,
    a new vessel whose parent is ``v``; side vessels beyond the cut move to it."""
    k = int(np.argmin(np.abs(v.s - at_s)))
    new = Vessel(len(tree.vessels), v.nodes[k:].copy(), v.s[k:] - v.s[k], v.index, float(v.s[k]), v.component)
    new.ostium_s = v.ostium_s + float(v.s[k])
    cut = float(v.s[k])
    moved = [j for j in v.junctions if j[0] > cut + 1e-6]
    v.junctions = [j for j in v.junctions if j[0] <= cut + 1e-6] + [(cut, new.index, float(np.median(tree.radius[new.nodes[:8]])))]
    new.junctions = [(sj - cut, ci, rb) for sj, ci, rb in moved]
    for sj, ci, _ in moved:
        child = tree.vessels[ci]
        child.parent, child.parent_s = new.index, sj - cut
    v.nodes, v.s = v.nodes[: k + 1].copy(), v.s[: k + 1].copy()
    tree.vessels.append(new)
    return new


def _heading(tree: VesselTree, v: Vessel, origin: np.ndarray) -> np.ndarray:
    sel = (v.s >= 10.0) & (v.s <= 40.0)
    if not sel.any():
        sel = v.s >= 0.5 * v.s[-1]
    d = tree.nodes[v.nodes[sel]].mean(0) - origin
    return d / max(np.linalg.norm(d), 1e-9)


def _largest_side(tree: VesselTree, v: Vessel, lo: float = 0.0, hi: float = np.inf):
    best, best_vol = None, 0.0
    for sj, ci, _ in v.junctions:
        c = tree.vessels[ci]
        if not (lo <= sj <= hi) or c.length < SIDE_BRANCH_MIN_MM or c.name != "unlabelled":
            continue
        vol = _volume(tree, c)
        if vol > best_vol:
            best, best_vol = c, vol
    return best


def find_lm_split(tree: VesselTree, root: Vessel):
    """Arc position of the left-main bifurcation on ``root`` (module docstring), or None."""
    for sj, ci, rb in root.junctions:
        if sj > LM_MAX_MM:
            break

        child = tree.vessels[ci]
        if _heading(tree, child, tree.nodes[child.nodes[0]])[2] > MAX_HEADING_UP:
            continue  # climbs towards the aorta: a catheter or a ghost, not a coronary branch
        trunk = _median_radius(tree, root, sj + 1.0, sj + 6.0)
        if tree.subtree_length(child) >= SPLIT_MIN_SUBTREE_MM and rb >= SPLIT_MIN_WIDTH_RATIO * trunk \
                and root.length - sj >= SPLIT_MIN_SUBTREE_MM:
            return float(sj)
    return None


def label_tree(tree: VesselTree) -> str:
    """Name the vessels of ``tree`` (module docstring); returns and records the side."""
    for v in tree.vessels:
        v.name = "unlabelled"
    roots = [v for v in tree.vessels if v.parent < 0 and v.component == 0]
    if not roots:
        tree.side = "unknown"
        return tree.side
    root = roots[0]
    split = find_lm_split(tree, root)
    if split is None:
        tree.side = "right"
        root.name = "RCA"
        am = _largest_side(tree, root, 15.0, 0.75 * root.length)
        if am is not None:
            am.name = "AM"
        return tree.side
    tree.side = "left"
    if split >= LM_MIN_MM:
        cont = _split_vessel(tree, root, split)
        root.name = "LM"
        origin = tree.nodes[root.nodes[-1]]
    else:  # the reconstruction has no left main: LAD and LCX leave from the ostium itself
        cont, origin = root, tree.nodes[root.nodes[0]]
    at_split = [cont] + [tree.vessels[ci] for sj, ci, _ in root.junctions
                         if abs(sj - split) <= 3.0 and tree.vessels[ci] is not cont]
    at_split = [v for v in at_split if v.length >= 10.0 and _heading(tree, v, origin)[2] <= MAX_HEADING_UP]
    if not at_split:  # nothing at the split long enough and heading down (a truncated or odd reconstruction)
        return tree.side
    ys = [float(_heading(tree, v, origin)[1]) for v in at_split]
    order = np.argsort(ys)
    lad = at_split[int(order[0])]
    lad.name = "LAD"
    if len(at_split) >= 2:
        at_split[int(order[-1])].name = "LCX"
    d = _largest_side(tree, lad, 3.0)
    if d is not None:
        d.name = "D"
    lcx = tree.vessel("LCX")
    if lcx is not None:
        om = _largest_side(tree, lcx, 3.0)
        if om is not None:
            om.name = "OM"
    return tree.side


def segment_of(vessel: Vessel, s: float) -> str:
    """"proximal LAD", "mid RCA", …; "" for unlabelled vessels."""
    if vessel.name == "unlabelled":
        return ""
    third = min(int(3 * s / max(vessel.length, 1e-9)), 2)
    return f"{('proximal', 'mid', 'distal')[third]} {vessel.name}"
