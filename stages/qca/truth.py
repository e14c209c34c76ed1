"""Ground truth for QCA validation: the procedural anatomy's trees as graphs, their lesions, and a
controlled-lesion set.

Reads nothing by itself (callers pass a :class:`stages.core.prepared_case.CaseTruth`, a
:class:`stages.anatomy.Tree` or a seed). Used by the tests and ``benchmarks/bench_qca.py``.

* :func:`truth_graph` — the analytic centrelines (0.25 mm samples with the exact radius) as one
  :class:`~stages.graph.vascular.VascularGraph`: a child branch's first sample coincides with its
  parent's attachment sample, so it is merged into it. Per node it also returns the true branch name.
* :func:`true_lesions` — the anatomy's stenosis records as QCA figures: %DS = the applied diameter
  reduction, MLD = reference × (1 − reduction), length = the raised-cosine profile's full width.
* :func:`add_controlled_lesion` — one more raised-cosine stenosis of a chosen %DS and length on a
  branch, away from branch points and from the tree's own lesions (the same profile the generator
  uses, so the truth is exact); :func:`controlled_case` makes one such seeded case.
"""

from __future__ import annotations

import numpy as np

__all__ = ["truth_graph", "true_lesions", "add_controlled_lesion", "controlled_case", "CANONICAL"]

# the anatomy's branch names → the QCA names of the four main vessels
CANONICAL = {"LM": "LM", "LAD": "LAD", "LCx": "LCX", "RCA": "RCA"}


def _as_truth(obj):
    return obj.truth() if hasattr(obj, "branches") else obj


def truth_graph(truth):
    """(VascularGraph, per-node branch name list, per-node arc position on its branch in mm)."""
    from ..graph.vascular import VascularGraph

    truth = _as_truth(truth)
    polys = truth.polylines()
    nodes, radius, names, arc, edges = [], [], [], [], []
    first = []  # global index of each branch's first kept sample
    offset = 0
    for b, (pts, rad) in enumerate(polys):
        p = int(truth.parent[b])
        s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(pts, axis=0), axis=1))])
        start = 0
        if p >= 0:
            ppts = polys[p][0]
            j = int(np.argmin(np.linalg.norm(ppts - pts[0], axis=1)))
            attach = first[p] + j
            start = 1  # the branch's first sample is the parent's attachment sample
        k = len(pts) - start
        idx = offset + np.arange(k)
        nodes.append(pts[start:])
        radius.append(rad[start:])
        names += [truth.names[b]] * k
        arc.append(s[start:])
        edges.append(np.stack([idx[:-1], idx[1:]], 1))
        if p >= 0 and k:
            edges.append(np.array([[attach, idx[0]]]))
        first.append(offset - start)  # so first[b] + j indexes the branch's j-th sample
        offset += k
    g = VascularGraph(np.concatenate(nodes), np.concatenate(radius), np.concatenate(edges).astype(np.int64))
    return g, names, np.concatenate(arc)


def true_lesions(stenoses) -> list[dict]:
    """QCA figures of the anatomy's stenosis records (diameter_reduction is the applied one)."""
    out = []
    for st in stenoses or []:
        ref = float(st["reference_diameter_mm"])
        red = float(st["diameter_reduction"])
        out.append({"branch": st["branch"], "vessel": CANONICAL.get(st["branch"], st["branch"]),
                    "position_mm": float(st["position_mm"]), "length_mm": float(st["length_mm"]),
                    "centre": [float(v) for v in st["centre"]], "reference_mm": ref, "ds_percent": 100.0 * red,
                    "mld_mm": ref * (1.0 - red)})
    return out


def _arclength(points):
    return np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])


def add_controlled_lesion(tree, rng: np.random.Generator, ds_percent: float, length_mm: float,
                          branches=("LAD", "LCx", "RCA", "LM"), floor_mm: float = 0.15) -> dict | None:
    """Narrow one branch of ``tree`` (an :class:`stages.anatomy.Tree`, changed in place) by a raised-cosine
    stenosis of ``ds_percent`` over ``length_mm``; returns its stenosis record or None if no room.

    The site is ≥ length/2 + 3 mm from every branch point and from the tree's other lesions and ≥ 5 mm
    from the branch's ends. Unlike the generator (whose trees become CTA-like masks that cannot resolve a
    lumen under Ø 1 mm) the residual lumen may go down to Ø ``2 * floor_mm``: a 90 % stenosis of a
    Ø 3.5 mm artery is what the exact-3D check must grade.
    """
    cands = [i for i, b in enumerate(tree.branches) if b.name in branches]
    rng.shuffle(cands)
    red = ds_percent / 100.0
    for i in cands:
        b = tree.branches[i]
        s = _arclength(b.points)
        stops = [s[c.attach] for c in tree.branches if c.parent == i]
        if b.parent < 0 and b.name == "LM":
            stops.append(s[-1])
        others = [(st["position_mm"], st["length_mm"]) for st in tree.stenoses if st["branch"] == b.name]
        lo, hi = 5 + length_mm / 2, s[-1] - 5 - length_mm / 2
        if hi <= lo:
            continue
        for pos in rng.permutation(np.arange(lo, hi, 0.5)):  # every site, in random order
            pos = float(pos)
            k = int(np.argmin(np.abs(s - pos)))
            ref = float(b.radius[k])
            if ref * (1 - red) < floor_mm:
                continue
            if any(abs(pos - q) <= length_mm / 2 + 3 for q in stops):
                continue
            if any(abs(pos - p) <= (length_mm + l) / 2 + 3 for p, l in others):
                continue
            x = (s - pos) / (length_mm / 2)
            bump = np.where(np.abs(x) < 1, 0.5 * (1 + np.cos(np.pi * np.clip(x, -1, 1))), 0.0)
            b.radius = np.maximum(b.radius * (1 - red * bump), floor_mm)
            rec = {"branch": b.name, "position_mm": pos, "length_mm": float(length_mm), "centre": b.points[k].tolist(),
                   "reference_diameter_mm": 2 * ref, "requested_reduction": red, "diameter_reduction": red,
                   "controlled": True}
            tree.stenoses.append(rec)
            return rec
    return None


def controlled_case(seed: int, side: str | None = None):
    """(tree, its new lesion record): the anatomy of ``seed`` with one controlled lesion added, its %DS
    drawn from 20–90 % and its length from 5–25 mm (seeded), or (tree, None) if no branch had room."""
    from ..anatomy import generate

    rng = np.random.default_rng([int(seed), 37])
    anatomy = generate(int(seed))
    side = side or ("left" if seed % 3 != 2 else "right")
    tree = anatomy.tree(side)
    ds = float(rng.uniform(20, 90))
    length = float(rng.uniform(5, 25))
    return tree, add_controlled_lesion(tree, rng, ds, length)
