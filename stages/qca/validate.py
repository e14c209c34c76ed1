"""QCA against known lesions and names: matching, errors, labelling accuracy.

Reads/writes nothing (``benchmarks/bench_qca.py`` and the tests feed it).

* A true lesion is **found** when a reported lesion's MLD point lies within
  ``max(MATCH_MM, length/2)`` of the true lesion's centre (3D, in the frame both are given in); the
  nearest such lesion is its match (each reported lesion matches at most one true lesion).
* A **false lesion** is a reported lesion of %DS ≥ ``false_from`` (50 by default: the clinically
  significant grade) that matches no true lesion of any grade.
* **Labelling accuracy**: of the true centreline of LM, LAD, LCx and RCA (length-weighted), the
  fraction whose nearest analysed vessel point (within ``label_mm``) carries the right name; true
  length with no analysed vessel within ``label_mm`` counts as wrong (a vessel missed is not named).
"""

from __future__ import annotations

import numpy as np

from .truth import CANONICAL

__all__ = ["match_lesions", "label_accuracy", "MATCH_MM"]

MATCH_MM = 5.0


def match_lesions(found: list[dict], truth: list[dict], match_mm: float = MATCH_MM, false_from: float = 50.0):
    """Pairs (true, found or None) per true lesion, and the unmatched reported lesions of %DS ≥ false_from.

    ``found``: dicts with ``point_mm`` (3D), ``ds_percent``…; ``truth``: dicts with ``centre`` and
    ``length_mm`` (:func:`stages.qca.truth.true_lesions`).
    """
    pairs, used = [], set()
    cand = []
    for ti, t in enumerate(truth):
        tol = max(match_mm, t["length_mm"] / 2)
        for fi, f in enumerate(found):
            d = float(np.linalg.norm(np.asarray(f["point_mm"]) - np.asarray(t["centre"])))
            if d <= tol:
                cand.append((d, ti, fi))
    best: dict[int, int] = {}
    for d, ti, fi in sorted(cand):
        if ti in best or fi in used:
            continue
        best[ti] = fi
        used.add(fi)
    for ti, t in enumerate(truth):
        pairs.append((t, found[best[ti]] if ti in best else None))
    false = [f for fi, f in enumerate(found) if fi not in used and f["ds_percent"] >= false_from]
    return pairs, false


def label_accuracy(qca, truth_points, truth_names, label_mm: float = 3.0) -> dict:
    """Length-weighted labelling accuracy (module docstring) of a :class:`~stages.qca.analysis.GraphQCA`.

    ``truth_points`` P×3 (evenly spaced samples of the true tree, in the analysed graph's frame) and
    their branch names. Returns {"accuracy", per-name fractions, "missed"}.
    """
    from scipy.spatial import cKDTree

    pts, names = [], []
    for v in qca.reported():
        pts.append(qca.tree.nodes[v.nodes])
        names += [v.name] * len(v.nodes)
    truth_points = np.asarray(truth_points, float)
    want = np.array([CANONICAL.get(n, "") for n in truth_names])
    sel = want != ""
    if not sel.any():
        return {"accuracy": float("nan"), "by_name": {}, "missed": float("nan")}
    if not pts:
        return {"accuracy": 0.0, "by_name": {n: 0.0 for n in sorted(set(want[sel]))}, "missed": 1.0}
    d, j = cKDTree(np.concatenate(pts)).query(truth_points[sel])
    got = np.asarray(names)[j]
    ok = (got == want[sel]) & (d <= label_mm)
    by = {n: float(ok[want[sel] == n].mean()) for n in sorted(set(want[sel]))}
    near = d <= label_mm
    return {"accuracy": float(ok.mean()), "by_name": by, "missed": float((~near).mean()),
            "accuracy_where_reconstructed": float(ok[near].mean()) if near.any() else float("nan")}
