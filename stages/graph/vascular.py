"""The vascular graph: centreline nodes (mm, LPS) with a lumen radius each, an undirected edge list and a
node identity that survives tracking through the key frames.

Reads/writes nothing by itself (see :mod:`stages.graph.io` and :mod:`stages.core.export`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["VascularGraph"]


@dataclass
class VascularGraph:
    """Undirected graph of centreline nodes.

    ``nodes`` N×3 float (world mm), ``radius`` N float (mm), ``edges`` E×2 int (node indices),
    ``node_id`` N int64: a stable identity; tracked graphs of different key frames share it.
    """

    nodes: np.ndarray
    radius: np.ndarray
    edges: np.ndarray
    node_id: np.ndarray | None = field(default=None)

    def __post_init__(self):
        self.nodes = np.asarray(self.nodes, dtype=float).reshape(-1, 3)
        self.radius = np.asarray(self.radius, dtype=float).reshape(-1)
        self.edges = np.asarray(self.edges, dtype=np.int64).reshape(-1, 2)
        n = len(self.nodes)
        if len(self.radius) != n:
            raise ValueError(f"radius has {len(self.radius)} entries for {n} nodes")
        if len(self.edges) and (self.edges.min() < 0 or self.edges.max() >= n):
            raise ValueError("edge refers to a node that does not exist")
        self.node_id = np.arange(n, dtype=np.int64) if self.node_id is None else np.asarray(self.node_id, np.int64)
        if len(self.node_id) != n:
            raise ValueError(f"node_id has {len(self.node_id)} entries for {n} nodes")

    # ---------------------------------------------------------------- basics
    def __len__(self) -> int:
        return len(self.nodes)

    @classmethod
    def empty(cls) -> "VascularGraph":
        return cls(np.zeros((0, 3)), np.zeros(0), np.zeros((0, 2), np.int64))

    def copy(self, nodes=None, radius=None) -> "VascularGraph":
        return VascularGraph(self.nodes.copy() if nodes is None else nodes,
                             self.radius.copy() if radius is None else radius,
                             self.edges.copy(), self.node_id.copy())

    def degrees(self) -> np.ndarray:
        return np.bincount(self.edges.ravel(), minlength=len(self)) if len(self.edges) else np.zeros(len(self), int)

    def adjacency(self):
        """Symmetric CSR adjacency with Euclidean edge lengths as weights."""
        from scipy.sparse import coo_matrix

        n = len(self)
        e = self.edges
        w = np.linalg.norm(self.nodes[e[:, 0]] - self.nodes[e[:, 1]], axis=1) if len(e) else np.zeros(0)
        w = np.maximum(w, 1e-9)  # csgraph treats explicit zeros as missing edges
        A = coo_matrix((np.r_[w, w], (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n))
        return A.tocsr()

    def bifurcations(self) -> np.ndarray:
        """Indices of junction nodes (degree ≥ 3)."""
        return np.flatnonzero(self.degrees() >= 3)

    def endpoints(self) -> np.ndarray:
        return np.flatnonzero(self.degrees() == 1)

    def n_components(self) -> int:
        from scipy.sparse.csgraph import connected_components

        return int(connected_components(self.adjacency(), directed=False)[0]) if len(self) else 0

    def pieces(self, far_mm: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
        """Connected pieces and their gap to the main tree: (label per node, length per piece in mm, gap per
        piece in mm, pieces largest first). The main tree is the longest piece grown by every piece within
        ``far_mm`` of it, transitively (a vessel broken into pieces stays one tree), gap 0 for the longest;
        a piece no such chain reaches keeps its distance to the grown tree (> ``far_mm``)."""
        from scipy.sparse.csgraph import connected_components
        from scipy.spatial import cKDTree

        if not len(self):
            return np.zeros(0, np.int64), np.zeros(0), np.zeros(0), []
        _, label = connected_components(self.adjacency(), directed=False)
        e = self.edges
        lengths = np.zeros(label.max() + 1)
        if len(e):
            np.add.at(lengths, label[e[:, 0]], np.linalg.norm(self.nodes[e[:, 0]] - self.nodes[e[:, 1]], axis=1))
        order = [int(c) for c in np.argsort(-lengths, kind="stable")]
        gaps = np.zeros(len(lengths))
        rest = set(order[1:])
        main_pts = self.nodes[label == order[0]]
        while rest:  # grow the main tree by the nearest piece while it is within far_mm
            main = cKDTree(main_pts)
            dist = {c: float(main.query(self.nodes[label == c])[0].min()) for c in rest}
            c = min(dist, key=dist.get)
            if dist[c] > far_mm:
                for k, v in dist.items():
                    gaps[k] = v
                break
            gaps[c] = dist[c]
            rest.discard(c)
            main_pts = np.vstack([main_pts, self.nodes[label == c]])
        return label, lengths, gaps, order

    def position_along_tree(self) -> np.ndarray:
        """Per node, its geodesic distance from the root along the tree, over the largest such distance (0…1).

        The root is the widest end point of the longest connected component (mean radius over its first
        10 mm). A piece not connected to it (a vessel the reconstruction left detached) continues from the
        point of the rooted part nearest to it: its nearest node starts at that point's distance plus the
        gap, so distal pieces are coloured as distal rather than as a second root.
        """
        from scipy.sparse.csgraph import connected_components, dijkstra
        from scipy.spatial import cKDTree

        n = len(self)
        if n == 0:
            return np.zeros(0)
        A = self.adjacency()
        _, label = connected_components(A, directed=False)
        e = self.edges
        seg = np.linalg.norm(self.nodes[e[:, 0]] - self.nodes[e[:, 1]], axis=1) if len(e) else np.zeros(0)
        comp_length = np.bincount(label[e[:, 0]], seg, minlength=label.max() + 1) if len(e) else np.zeros(1)
        # ties in length go to the component with the most nodes, then the lowest label: deterministic
        sizes = np.bincount(label)
        main = int(np.lexsort((-np.arange(len(sizes)), sizes, comp_length))[-1])
        members = np.flatnonzero(label == main)
        deg = self.degrees()[members]
        ends = members[deg <= 1] if np.any(deg <= 1) else members
        # the widest start: the end point whose first 10 mm have the largest mean radius (one node's radius
        # is noisy; a truncated distal end can be locally wide)
        near = dijkstra(A, indices=ends, limit=10.0) <= 10.0
        root = int(ends[np.argmax((near * self.radius).sum(1) / near.sum(1))])
        dist = np.full(n, np.inf)
        dist[members] = dijkstra(A, indices=root)[members]
        placed = label == main
        while not placed.all():  # attach the detached piece nearest to the placed part, then the next
            tree = cKDTree(self.nodes[placed])
            idx_placed = np.flatnonzero(placed)
            rest = np.flatnonzero(~placed)
            gap, j = tree.query(self.nodes[rest])
            k = int(np.argmin(gap))
            start, anchor = int(rest[k]), int(idx_placed[j[k]])
            piece = np.flatnonzero(label == label[start])
            dist[piece] = dist[anchor] + gap[k] + dijkstra(A, indices=start)[piece]
            placed[piece] = True
        return dist / max(float(dist.max()), 1e-6)

    def length(self) -> float:
        """Total centreline length in mm."""
        e = self.edges
        return float(np.linalg.norm(self.nodes[e[:, 0]] - self.nodes[e[:, 1]], axis=1).sum()) if len(e) else 0.0

    def to_networkx(self):
        import networkx as nx

        g = nx.Graph()
        for i in range(len(self)):
            g.add_node(i, pos=self.nodes[i], radius=float(self.radius[i]), node_id=int(self.node_id[i]))
        g.add_edges_from(self.edges.tolist())
        return g

    def subgraph(self, keep) -> "VascularGraph":
        """The graph induced by a boolean mask (or index array) of nodes; edges re-indexed."""
        keep = np.asarray(keep)
        mask = np.zeros(len(self), bool)
        mask[keep] = True
        new_index = np.cumsum(mask) - 1
        e = self.edges[mask[self.edges].all(axis=1)] if len(self.edges) else self.edges
        return VascularGraph(self.nodes[mask], self.radius[mask], new_index[e], self.node_id[mask])

    # ---------------------------------------------------------------- curve segments
    def segments(self) -> list[np.ndarray]:
        """Curve segments: node-index paths between nodes of degree ≠ 2 (junctions, end points).

        Every edge belongs to exactly one segment. A closed loop of degree-2 nodes becomes one segment
        starting and ending at the same node. Isolated nodes are left out.
        """
        n = len(self)
        if not len(self.edges):
            return []
        deg = self.degrees()
        # CSR-style adjacency listing each edge's identity, to mark edges as walked (built by sorting,
        # not by a sparse matrix, which would merge duplicate edges)
        e = self.edges
        src = np.r_[e[:, 0], e[:, 1]]
        dst = np.r_[e[:, 1], e[:, 0]]
        ids = np.r_[np.arange(len(e)), np.arange(len(e))]
        order = np.lexsort((dst, src))
        indices = dst[order]
        edge_of = ids[order].astype(np.int64)
        indptr = np.searchsorted(src[order], np.arange(n + 1))
        used = np.zeros(len(e), bool)
        segs: list[np.ndarray] = []

        def walk(start, slot):
            path = [start]
            prev, k = start, slot
            while True:
                used[edge_of[k]] = True
                cur = int(indices[k])
                path.append(cur)
                if deg[cur] != 2 or cur == start:
                    return path
                a, b = indptr[cur], indptr[cur + 1]
                nxt = [s for s in range(a, b) if not used[edge_of[s]]]
                if not nxt:
                    return path
                prev, k = cur, nxt[0]

        for u in np.flatnonzero(deg != 2):
            for k in range(indptr[u], indptr[u + 1]):
                if not used[edge_of[k]]:
                    segs.append(np.asarray(walk(int(u), k), np.int64))
        for k0 in np.flatnonzero(~used):  # pure cycles
            if used[k0]:
                continue
            u = int(e[k0, 0])
            slot = next(s for s in range(indptr[u], indptr[u + 1]) if edge_of[s] == k0)
            segs.append(np.asarray(walk(u, slot), np.int64))
        return segs

    def decimate(self, step_mm: float) -> tuple["VascularGraph", np.ndarray]:
        """A coarser graph keeping junctions, end points and about one node every ``step_mm`` along each
        segment (consecutive kept nodes joined). Returns (graph, indices of the kept nodes in ``self``)."""
        keep = self.degrees() == 0  # isolated nodes stay
        pairs = []
        for seg in self.segments():
            cum = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(self.nodes[seg], axis=0), axis=1))]
            bins = np.floor(cum / step_mm).astype(np.int64)
            sel = np.r_[True, bins[1:] != bins[:-1]]
            sel[-1] = True
            kept = seg[sel]
            keep[kept] = True
            pairs.append(np.stack([kept[:-1], kept[1:]], 1))
        idx = np.flatnonzero(keep)
        new = -np.ones(len(self), np.int64)
        new[idx] = np.arange(len(idx))
        e = new[np.concatenate(pairs)] if pairs else np.zeros((0, 2), np.int64)
        e = e[e[:, 0] != e[:, 1]]
        return VascularGraph(self.nodes[idx], self.radius[idx], e, self.node_id[idx]), idx

    # ---------------------------------------------------------------- sampling
    def sample(self, step: float = 0.25, with_edges: bool = False):
        """Points every ≤ ``step`` mm along every edge with interpolated radii: (P×3, P); ``with_edges``: also the
        edge each point was sampled on (P; −1 for the end nodes appended last, and for every point of a graph
        without edges)."""
        if not len(self.edges):
            out = self.nodes.copy(), self.radius.copy()
            return (*out, -np.ones(len(self.nodes), np.int64)) if with_edges else out
        a, b = self.nodes[self.edges[:, 0]], self.nodes[self.edges[:, 1]]
        ra, rb = self.radius[self.edges[:, 0]], self.radius[self.edges[:, 1]]
        L = np.linalg.norm(b - a, axis=1)
        k = np.maximum(np.ceil(L / step).astype(int), 1)
        owner = np.repeat(np.arange(len(L)), k)
        start = np.cumsum(k) - k
        t = (np.arange(k.sum()) - start[owner]) / k[owner]
        pts = a[owner] + t[:, None] * (b - a)[owner]
        rad = ra[owner] + t * (rb - ra)[owner]
        deg = self.degrees()
        ends = np.flatnonzero(deg <= 1)  # the far ends of terminal edges are not reached by t < 1
        out = np.vstack([pts, self.nodes[ends]]), np.r_[rad, self.radius[ends]]
        return (*out, np.r_[owner, -np.ones(len(ends), np.int64)]) if with_edges else out

    # ---------------------------------------------------------------- serialisation
    def to_dict(self) -> dict:
        return {"units": "mm", "frame": "LPS", "nodes": np.round(self.nodes, 4).tolist(),
                "radius": np.round(self.radius, 4).tolist(), "edges": self.edges.tolist(),
                "node_id": self.node_id.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "VascularGraph":
        return cls(np.asarray(d["nodes"], float).reshape(-1, 3), np.asarray(d["radius"], float),
                   np.asarray(d["edges"], np.int64).reshape(-1, 2), d.get("node_id"))
