"""A vascular graph as a rooted tree of vessels: the geometry every QCA step works on.

Reads/writes nothing. :func:`vessel_tree` takes a :class:`stages.graph.vascular.VascularGraph` (or plain
node/radius/edge arrays) and returns a :class:`VesselTree`:

* detached pieces whose end comes within ``join_gap_mm`` of the main piece are bridged to it first;
* the **root** (ostium), by one of two rules (:mod:`stages.qca.analysis` tries both and keeps the
  better-named tree): ``ostium="widest"`` takes the free end of the widest part of each component (
  :func:`_ostium`: the nodes within 70 % of the widest lumen, radii averaged along the tree over ~2 mm,
  connected to it): lumens narrow downstream. It need not be an
  end point: a catheter or a ghost grown out of the ostium becomes a vessel of its own leaving the root.
  ``ostium="end"`` takes instead the end point maximising its mean radius
  over the first 10 mm (relative to the widest end's) + 0.5 × its relative height (z);
* the graph is turned into a tree by its shortest-path tree from the root (a reconstruction's small
  loops are cut where they are longest from the root); other components of at least ``min_piece_mm``
  become trees of their own, rooted the same way;
* **segments** run between junctions and ends; at every junction one child *continues* the parent
  vessel and the others start side branches. The continuation is the child with the largest downstream
  size ``Σ r²·l`` (lumen volume / π) times a turning-angle factor ``((1 + cos θ)/2)⁴`` (θ: the turn
  from the parent's last 5 mm to the child's first 6 mm; a child leaving at a right angle must be 16×
  larger to count as the continuation), so a vessel stays on its trunk past side branches even
  where the trunk has become thinner than its last branch but is still the longer one;
* a **vessel** is the path from where it leaves its parent (or the root) along the continuations to a
  distal end; it knows its parent vessel, the arc position where it leaves it, and the junctions along
  it with the size of each side branch (which the reference-diameter fit uses for Murray's law).

Where a trunk reaches a junction that has only a stub besides the continuation, and the continuation's
median radius over its first 1–15 mm is under half the trunk's just before (a right coronary ending in
its last marginal), the trunk ends there and the thin vessel is a branch of its own.

Spurs shorter than ``min_branch_mm`` (a reconstruction's stubs, a 1-voxel bump of the skeleton) are
kept in the tree but never start a vessel of their own; they do not count as junctions either.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Vessel", "VesselTree", "vessel_tree"]

TURN_EXPONENT = 4.0  # continuation score = volume × ((1 + cos turn) / 2) ** TURN_EXPONENT
OSTIUM_HEIGHT_WEIGHT = 0.5  # ostium="end": score = mean radius over 10 mm / the widest end's + 0.5 × relative height
TRUNK_END_RATIO = 0.5  # a stub junction after which the lumen is < half the trunk's ends the trunk
PLATEAU = 0.7  # the proximal trunk: nodes within 70 % of the widest (smoothed) lumen
STUB_DROP_MM = 8.0  # a trunk end this far below the widest node is a hanging stub, not the ostium


@dataclass
class Vessel:
    """One vessel: node indices proximal → distal, arc length ``s`` (mm) from its own origin."""

    index: int
    nodes: np.ndarray  # node indices into the tree's arrays, proximal → distal
    s: np.ndarray  # arc length from the vessel's origin, mm
    parent: int  # index of the parent vessel, −1 for a root vessel
    parent_s: float  # arc position on the parent where this vessel leaves it (mm); 0 for roots
    component: int  # which tree (0 = the main one)
    junctions: list = field(default_factory=list)  # [(s on this vessel, child vessel index, child radius)]
    spurs: list = field(default_factory=list)  # s of junctions with only stubs shorter than min_branch_mm
    name: str = "unlabelled"
    ostium_s: float = 0.0  # arc length of this vessel's origin from the tree's ostium (mm)

    @property
    def length(self) -> float:
        return float(self.s[-1]) if len(self.s) else 0.0


@dataclass
class VesselTree:
    nodes: np.ndarray  # N×3 mm
    radius: np.ndarray  # N mm
    parent: np.ndarray  # N parent node in the rooted tree (−1 at the roots and at nodes left out)
    roots: list  # root node of each component kept (the main one first)
    vessels: list  # Vessel, parents before children
    side: str = "unknown"  # "left" | "right" | "unknown" (set by stages.qca.labels)

    def vessel(self, name: str):
        for v in self.vessels:
            if v.name == name:
                return v
        return None

    def subtree_length(self, vessel: Vessel) -> float:
        """Length of a vessel plus everything that branches off it (recursively)."""
        total = vessel.length
        for c in self.vessels:
            if c.parent == vessel.index:
                total += self.subtree_length(c)
        return total

    def main_vessels(self):
        return [v for v in self.vessels if v.component == 0]


def _ostium(nodes, radius, edges, A, members, sigma_mm: float = 2.0, plateau: float = PLATEAU) -> int:
    """The ostium of one component: the free end of the widest part of the tree.

    Lumens narrow downstream (taper, Murray's law at every branch), so the lumen is widest at the
    ostium. Radii are averaged along the tree over ~``sigma_mm`` first; the nodes within ``plateau``
    (70 %) of the widest one that connect to it form the proximal trunk, and the ostium is the highest
    (largest z: the ostia sit at the aortic root, above the heart) of that trunk's free end points, or
    the widest node itself when that end lies more than 8 mm below it (a stub hanging from the trunk).
    Noise moves the single widest node anywhere along a nearly untapered proximal RCA or LM; the end of
    the plateau does not move. A thinner vessel grown out of the ostium (a Ø 2 mm catheter, a ghost) is
    not part of the plateau and becomes a vessel of its own leaving the root.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order

    n = len(nodes)
    B = coo_matrix((np.ones(2 * len(edges)), (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])),
                   shape=(n, n)).tocsr()
    deg = np.asarray(B.sum(1)).ravel()
    spacing = float(np.median(_edge_lengths(nodes, edges))) if len(edges) else 1.0
    steps = int(min(400, max(1, round(1.5 * (sigma_mm / max(spacing, 1e-3)) ** 2))))
    r = np.asarray(radius, float).copy()
    for _ in range(steps):  # each step: the mean of a node and its neighbours (≈ Gaussian along the tree)
        r = (B @ r + r) / (deg + 1)
    best = int(members[np.argmax(r[members])])
    keep = r >= plateau * r[best]
    sub = B.multiply(keep[:, None]).multiply(keep[None, :]).tocsr()
    sub.eliminate_zeros()  # the traversal follows stored entries, zero or not
    trunk = breadth_first_order(sub, best, directed=False, return_predecessors=False)
    ends = trunk[deg[trunk] == 1]
    if len(ends) == 0:
        return best
    top = int(ends[np.argmax(nodes[ends, 2])])  # the ostia sit at the aortic root, above the heart
    # a trunk end well below the widest node is a stub hanging from the trunk, not the ostium
    return best if nodes[best, 2] > nodes[top, 2] + STUB_DROP_MM else top


def _join_pieces(nodes, edges, gap_mm: float) -> np.ndarray:
    """Edges plus one bridge per detached piece whose end lies within ``gap_mm`` of the largest piece
    (pieces joined largest first, each to the grown main piece): a reconstruction often breaks a vessel
    for a few mm where the two views disagree."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    n = len(nodes)
    w = np.maximum(_edge_lengths(nodes, edges), 1e-6)
    A = coo_matrix((np.r_[w, w], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n))
    ncomp, label = connected_components(A.tocsr(), directed=False)
    if ncomp < 2:
        return edges
    length = np.bincount(label[edges[:, 0]], w, minlength=ncomp)
    order = list(np.argsort(-length, kind="stable"))
    deg = np.bincount(edges.ravel(), minlength=n)
    main = label == order[0]
    bridges = []
    for c in order[1:]:
        ends = np.flatnonzero((label == c) & (deg <= 1))
        if len(ends) == 0 or not main.any():
            continue
        idx = np.flatnonzero(main)
        d, j = cKDTree(nodes[idx]).query(nodes[ends])
        k = int(np.argmin(d))
        if d[k] <= gap_mm:
            bridges.append((int(ends[k]), int(idx[j[k]])))
            main |= label == c
    return np.concatenate([edges, np.asarray(bridges, np.int64).reshape(-1, 2)]) if bridges else edges


def _edge_lengths(nodes, edges):
    return np.linalg.norm(nodes[edges[:, 0]] - nodes[edges[:, 1]], axis=1) if len(edges) else np.zeros(0)


def vessel_tree(graph=None, *, nodes=None, radius=None, edges=None, min_branch_mm: float = 4.0,
                min_piece_mm: float = 20.0, root=None, join_gap_mm: float = 0.0, ostium: str = "widest") -> VesselTree:
    """Rooted vessel tree of a graph (see the module docstring). ``root``: force the ostium node."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, dijkstra

    if graph is not None:
        nodes, radius, edges = graph.nodes, graph.radius, graph.edges
    nodes = np.asarray(nodes, float).reshape(-1, 3)
    radius = np.asarray(radius, float).reshape(-1)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    edges = edges[edges[:, 0] != edges[:, 1]]
    n = len(nodes)
    parent = np.full(n, -1, np.int64)
    if n == 0 or len(edges) == 0:
        return VesselTree(nodes, radius, parent, [], [])
    if join_gap_mm > 0:
        edges = _join_pieces(nodes, edges, join_gap_mm)
    w = np.maximum(_edge_lengths(nodes, edges), 1e-6)
    A = coo_matrix((np.r_[w, w], (np.r_[edges[:, 0], edges[:, 1]], np.r_[edges[:, 1], edges[:, 0]])), shape=(n, n)).tocsr()
    ncomp, label = connected_components(A, directed=False)
    comp_len = np.bincount(label[edges[:, 0]], w, minlength=ncomp)
    order = np.argsort(-comp_len, kind="stable")
    deg = np.bincount(edges.ravel(), minlength=n)
    roots, vessels = [], []
    for ci, comp in enumerate(c for c in order if comp_len[c] >= (min_piece_mm if c != order[0] else 0.0)):
        members = np.flatnonzero(label == comp)
        if root is not None and ci == 0 and label[int(root)] == comp:
            r0 = int(root)
        elif ostium == "widest":
            r0 = _ostium(nodes, radius, edges, A, members)
        else:
            ends = members[deg[members] == 1]
            if len(ends) == 0:
                ends = members
            near = dijkstra(A, indices=ends, limit=10.0)[:, members]
            reach = np.isfinite(near)
            mean_r = (reach * radius[members][None, :]).sum(1) / np.maximum(reach.sum(1), 1)
            z = nodes[ends, 2]
            height = (z - z.min()) / max(float(np.ptp(z)), 1e-9)
            r0 = int(ends[np.argmax(mean_r / max(mean_r.max(), 1e-9) + OSTIUM_HEIGHT_WEIGHT * height)])
        dist, pred = dijkstra(A, indices=r0, return_predecessors=True)
        parent[members] = np.where(pred[members] >= 0, pred[members], -1)
        parent[r0] = -1
        roots.append(r0)
        vessels += _decompose(nodes, radius, parent, members, r0, dist, ci, len(vessels), min_branch_mm)
    return VesselTree(nodes, radius, parent, roots, vessels)


def _decompose(nodes, radius, parent, members, root, dist, component, first_index, min_branch_mm):
    """Vessels of one rooted component (see the module docstring)."""
    children: dict[int, list[int]] = {int(m): [] for m in members}
    for m in members:
        p = int(parent[m])
        if p >= 0:
            children[p].append(int(m))
    # post-order: downstream length and volume of every node's subtree (the edge to the node included)
    order = sorted(members.tolist(), key=lambda m: -dist[m])
    down_len = {m: 0.0 for m in children}
    down_vol = {m: 0.0 for m in children}
    for m in order:
        p = int(parent[m])
        if p < 0:
            continue
        l = float(np.linalg.norm(nodes[m] - nodes[p]))
        r2 = 0.5 * (radius[m] ** 2 + radius[p] ** 2)
        down_len[p] += down_len[m] + l
        down_vol[p] += down_vol[m] + l * r2

    def direction(a, b, span=6.0):
        """Unit direction from node a along the path starting with child b, over ``span`` mm."""
        cur, travelled = b, float(np.linalg.norm(nodes[b] - nodes[a]))
        while travelled < span and children[cur]:
            nxt = max(children[cur], key=lambda c: down_vol[c])
            travelled += float(np.linalg.norm(nodes[nxt] - nodes[cur]))
            cur = nxt
        d = nodes[cur] - nodes[a]
        return d / max(np.linalg.norm(d), 1e-9)

    def mean_radius_along(start, first, lo, hi):
        """Median radius of the path leaving ``start`` through ``first`` (main continuation) between lo and hi mm."""
        vals, cur, prev, travelled = [], first, start, 0.0
        while True:
            travelled += float(np.linalg.norm(nodes[cur] - nodes[prev]))
            if travelled > hi:
                break
            if travelled >= lo:
                vals.append(radius[cur])
            if not children[cur]:
                break
            prev, cur = cur, max(children[cur], key=lambda c: down_vol[c])
        return float(np.median(vals)) if vals else float(radius[first])

    def _trunk_ends(junction, nxt, path):
        back = [radius[m] for m in path[-25:-4]] or [radius[junction]]
        r_before = float(np.median(back))
        return down_len[nxt] >= 15.0 and mean_radius_along(junction, nxt, 1.0, 15.0) < TRUNK_END_RATIO * r_before

    vessels = []
    stack = [(root, -1, 0.0)]  # (start node, parent vessel, s on parent)
    while stack:
        start, pv, ps = stack.pop()
        path = [start]
        if pv >= 0:  # a side branch: its path starts at the junction node on the parent
            path = [int(parent[start]), start]
        cur = start
        junctions, spurs = [], []
        while children[cur]:
            kids = children[cur]
            big = [c for c in kids if down_len[c] + np.linalg.norm(nodes[c] - nodes[cur]) >= min_branch_mm]
            if len(kids) == 1:
                nxt = kids[0]
            else:
                incoming = None
                if len(path) >= 2:  # the parent's direction over its last ~5 mm
                    back, k = 0.0, len(path) - 1
                    while k > 0 and back < 5.0:
                        back += float(np.linalg.norm(nodes[path[k]] - nodes[path[k - 1]]))
                        k -= 1
                    incoming = nodes[cur] - nodes[path[k]]
                    incoming = incoming / max(np.linalg.norm(incoming), 1e-9)

                def score(c):
                    vol = down_vol[c] + 1e-9
                    if incoming is None:
                        return vol
                    cos = float(direction(cur, c) @ incoming)
                    return vol * (0.5 + 0.5 * max(cos, 0.0)) ** TURN_EXPONENT

                nxt = max(kids, key=score)
                for c in big:
                    if c != nxt:
                        junctions.append((cur, c))
                if any(c != nxt and c not in big for c in kids):
                    spurs.append(cur)
                    if len(big) <= 1 and _trunk_ends(cur, nxt, path):
                        # the trunk ends in a stub here and what follows is a much thinner vessel: that
                        # vessel is a branch of its own (its lumen does not continue the trunk's)
                        junctions.append((cur, nxt))
                        spurs.pop()
                        break
            path.append(nxt)
            cur = nxt
        path = np.asarray(path, np.int64)
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(nodes[path], axis=0), axis=1))])
        idx = first_index + len(vessels)
        pos = {int(m): k for k, m in enumerate(path)}
        v = Vessel(idx, path, s, pv, ps, component, [])
        v.ostium_s = float(dist[path[0]])
        v.spurs = [float(s[pos[m]]) for m in spurs]
        vessels.append(v)
        for jn, c in reversed(junctions):
            stack.append((c, idx, float(s[pos[jn]])))
    # every junction of a parent with the child vessel it starts and the child's proximal radius (its
    # median over 0.5–4 mm from the junction: the junction node itself carries the parent's radius)
    for v in vessels:
        if v.parent < 0:
            continue
        sel = (v.s > 0.5) & (v.s <= 4.0)
        r_child = float(np.median(radius[v.nodes[sel]])) if sel.any() else float(radius[v.nodes[-1]])
        vessels[v.parent - first_index].junctions.append((v.parent_s, v.index, r_child))
    for v in vessels:
        v.junctions.sort(key=lambda j: j[0])
    return vessels
