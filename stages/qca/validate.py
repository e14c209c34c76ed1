"""QCA against known lesions and names: matching, errors, labelling accuracy, and the validation runs.

:func:`match_lesions` and :func:`label_accuracy` read and write nothing (the tests feed them). The runs
of ``benchmarks/bench_qca.py`` (which writes their docs) read the truth: :func:`validate_exact` the
prepared data-se cases (:func:`exact_cases`), :func:`validate_reconstructions` reconstruction folders
(``graphs.zarr``, ``summary.json``; ``qca_for_reconstruction`` writes its qca.json there) and the
cases' ``truth.zarr``.

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

import json
import statistics
import time
from pathlib import Path

import numpy as np

from .truth import CANONICAL

__all__ = ["match_lesions", "label_accuracy", "MATCH_MM", "exact_cases", "perturb", "validate_exact",
           "validate_reconstructions"]

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


# ---------------------------------------------------------------------- validation runs
def read_case_truth(path: Path):
    """(CaseTruth, stenoses, side, seed, centreline graph) of a prepared case without loading its mesh/labels."""
    from ..core.artefacts import read_zarr
    from ..graph.vascular import VascularGraph
    from ..core.prepared_case import CaseTruth

    g = read_zarr(path, kind="autocar.prepared-case", schema_version=1)
    attrs = dict(g.attrs)
    tg = g["truth"]
    truth = CaseTruth(tg["points"][...], tg["radius"][...], tg["branch"][...], tg["parent"][...],
                      list(dict(tg.attrs).get("names", [])))
    cl = VascularGraph(g["centreline/nodes"][...], g["centreline/radius"][...], g["centreline/edges"][...])
    seed = (attrs.get("source") or {}).get("seed")
    return truth, list(attrs.get("stenoses") or []), attrs["side"], seed, cl


def exact_cases(folder: Path, limit: int, source: str = "truth"):
    """Yield (case name, graph, true lesions, side, truth graph, truth names) for the first ``limit``
    prepared cases in ``folder`` (the same trees regenerated from the data-se seeds when it is not
    there), then their controlled-lesion twins (:func:`stages.qca.truth.controlled_case`)."""
    from ..anatomy import generate
    from ..render.products import SEED_SE
    from .truth import controlled_case, true_lesions, truth_graph

    paths = sorted(folder.glob("case_*.zarr"))[:limit] if folder.is_dir() else []
    items = []
    if paths:
        for p in paths:
            truth, stenoses, side, seed, cl = read_case_truth(p)
            items.append((p.stem, truth, stenoses, side, seed, cl))
    else:
        for i in range(limit):
            seed = SEED_SE + i
            side = "left" if seed % 3 != 2 else "right"
            tree = generate(seed).tree(side)
            items.append((f"seed_{seed}_{side}", tree.truth(), tree.stenoses, side, seed, None))
    for name, truth, stenoses, side, seed, cl in items:
        g, names, _ = truth_graph(truth)
        graph = g if source == "truth" or cl is None else cl
        yield name, graph, true_lesions(stenoses), side, g, names
    for name, truth, stenoses, side, seed, cl in items:
        if seed is None or source != "truth":  # the controlled twins were never voxelised: no centreline
            continue
        tree, rec = controlled_case(int(seed), side)
        if rec is None:
            continue
        g, names, _ = truth_graph(tree)
        yield f"{name}+controlled", g, true_lesions([rec]), side, g, names


def _smooth_on_graph(graph, values, sigma_mm: float, step_mm: float = 0.25):
    """``values`` per node blurred along the graph by repeated neighbour averaging (≈ Gaussian σ)."""
    from scipy.sparse import coo_matrix, diags

    n = len(graph)
    e = graph.edges
    A = coo_matrix((np.ones(2 * len(e)), (np.r_[e[:, 0], e[:, 1]], np.r_[e[:, 1], e[:, 0]])), shape=(n, n)).tocsr()
    deg = np.asarray(A.sum(1)).ravel()
    W = diags(1 / (1 + deg)) @ (A + diags(np.ones(n)))  # each step: mean of the node and its neighbours
    steps = int(round(1.5 * (sigma_mm / step_mm) ** 2))  # a step adds ~2/3 sample² of variance on a chain
    v = np.asarray(values, float)
    for _ in range(steps):
        v = W @ v
    return v


def perturb(graph, seed: int, blur_mm: float = 1.0, noise: float = 0.08, corr_mm: float = 1.0, bias: float = 1.3):
    """A reconstruction-like copy of an exact graph: radius blurred along the tree (σ ``blur_mm``), scaled by
    ``bias`` and multiplied by correlated noise (``noise`` relative SD, correlation ``corr_mm``). Positions kept."""
    from ..graph.vascular import VascularGraph

    rng = np.random.default_rng([seed, 7])
    eps = _smooth_on_graph(graph, rng.normal(0, 1, len(graph)), corr_mm)
    eps = eps / max(float(eps.std()), 1e-9) * noise
    r = _smooth_on_graph(graph, graph.radius, blur_mm) * bias * (1 + eps)
    return VascularGraph(graph.nodes, np.maximum(r, 0.1), graph.edges)


def validate_exact(cases, source: str = "truth", perturbed: bool = False, centreline_smooth_mm: float = 0.5) -> dict:
    """The analysis alone on exact trees: ``cases`` as :func:`exact_cases` yields them (``perturbed``:
    :func:`perturb`-ed radii and the reconstruction parameters). Summary dict (:func:`summary`)."""
    from .analysis import QCAParams, analyse_graph

    params = QCAParams() if source == "truth" else QCAParams(smooth_mm=centreline_smooth_mm)
    if perturbed:
        from .recon import RECON_PARAMS

        params = RECON_PARAMS
    rows, false, sides, labels, times, trees = [], 0, 0, [], [], 0
    for name, graph, truth, side, tgraph, tnames in cases:
        if perturbed:
            graph = perturb(graph, len(times))
        t = time.process_time()
        q = analyse_graph(graph, params)
        found = [les for v in q.to_dict()["vessels"] for les in v["lesions"]]
        times.append(time.process_time() - t)
        trees += 1
        sides += q.side == side
        pairs, fl = match_lesions(found, truth)
        is_ctrl = name.endswith("+controlled")
        if not is_ctrl:  # the controlled twin repeats the tree's own lesions: count its new lesion only
            false += len(fl)
            labels.append(label_accuracy(q, tgraph.nodes, tnames)["accuracy"])
        for tr, f in pairs:
            rows.append({"case": name, "vessel": tr["vessel"], "true_ds": tr["ds_percent"], "true_mld": tr["mld_mm"],
                         "true_length": tr["length_mm"], "true_ref": tr["reference_mm"], "controlled": is_ctrl,
                         "found": f is not None, **({"ds": f["ds_percent"], "mld": f["mld_mm"], "length": f["length_mm"],
                                                    "ref": f["reference_mm"], "segment": f["segment"]} if f else {})})
    n_trees = trees - sum(1 for r in rows if r["controlled"])
    return summary(rows, false, n_trees, labels, sides / max(trees, 1), times,
                   extra={"source": source + (" perturbed" if perturbed else "")})


def summary(rows, false, n_trees, labels, side_acc, times, extra=None) -> dict:
    """Errors of the found lesions, sensitivity, false lesions per tree, labelling, analysis time; ``per_lesion``."""
    hit = [r for r in rows if r["found"]]
    sig = [r for r in rows if r["true_ds"] >= 50]
    out = {"lesions": len(hit), "true_lesions": len(rows),
           "ds_mae_pp": float(np.mean([abs(r["ds"] - r["true_ds"]) for r in hit])) if hit else None,
           "mld_mae_mm": float(np.mean([abs(r["mld"] - r["true_mld"]) for r in hit])) if hit else None,
           "length_mae_mm": float(np.mean([abs(r["length"] - r["true_length"]) for r in hit])) if hit else None,
           "sensitivity_all": len(hit) / max(len(rows), 1),
           "sensitivity_50": (sum(r["found"] for r in sig) / len(sig)) if sig else None,
           "false_per_tree": false / max(n_trees, 1), "trees": n_trees,
           "label_accuracy": float(np.mean(labels)) if labels else None, "side_accuracy": side_acc,
           "seconds_per_tree_min": float(min(times)) if times else None,
           "seconds_per_tree_median": float(statistics.median(times)) if times else None,
           "per_lesion": rows}
    out.update(extra or {})
    return out


def validate_reconstructions(cases, recon_of, re_dir: Path, row: str = "L8", radius: str = "frame") -> dict:
    """QCA of two-view reconstructions against the simulator's truth moved to the analysed key frame.

    ``cases``: data-re case folders (run_a/run_b/truth.zarr); ``recon_of(case_dir)``: its reconstruction
    folder or None (the case is skipped); ``re_dir``: where a truth sidecar's relative case path points;
    ``row``: recorded as is. Times ``qca_for_reconstruction`` with its plots, after one warm-up call."""
    from ..graph.io import read_vascular_graphs
    from ..graph.vascular import VascularGraph
    from ..render.acquire import load_truth
    from .analysis import QCAParams, analyse_graph
    from .recon import RECON_PARAMS, qca_for_reconstruction
    from .truth import true_lesions, truth_graph
    from .views import foreshortening, view_directions, view_grid

    rows, false, labels, times, sides, fs_err, n_trees, skipped = [], 0, [], [], [], [], 0, []
    labels_near, fs_seg, fs_seg_rows, done = [], [], [], []
    alphas, betas = view_grid(5.0)
    dirs, _, _ = view_directions(alphas, betas)
    for case_dir in cases:
        recon = recon_of(case_dir)
        if recon is None:
            skipped.append(case_dir.name)
            continue
        if not done:  # warm-up: the first call pays the imports (matplotlib, zarr codecs), not the analysis
            qca_for_reconstruction(recon, plots=True, radius=radius)
        done.append(case_dir.name)
        t = time.process_time()
        doc = qca_for_reconstruction(recon, plots=True, radius=radius)
        times.append(time.process_time() - t)
        tr = load_truth(case_dir / "truth.zarr")
        case_path = Path(tr["attrs"]["case"])
        if not case_path.is_absolute():
            case_path = re_dir / case_path
        if not case_path.exists():
            case_path = re_dir / "cases" / case_path.name
        if case_path.exists():
            truth, stenoses, side, _, _ = read_case_truth(case_path)
        else:  # the bundled example's case was prepared in a temporary folder: regenerate its tree
            from ..anatomy import generate

            side = "right" if case_path.stem.endswith("_right") else "left"
            tree = generate(int(tr["attrs"]["seed"])).tree(side)
            truth, stenoses = tree.truth(), tree.stenoses
        n_trees += 1
        sides.append(doc["side"] == side)
        summary_json = json.loads((recon / "summary.json").read_text())
        keys = doc["frame"]
        k = [str(x) for x in _graph_keys(recon)].index(str(keys)) if keys is not None else 0
        ia = int(summary_json["pairs"][k][0])
        motion = tr["motion"]
        phase, resp = float(tr["a"]["phase"][ia]), float(tr["a"]["resp"][ia])
        tg, tnames, tarc = truth_graph(truth)
        moved = motion.apply(tg.nodes, phase, resp)
        tl = true_lesions(stenoses)
        for les in tl:
            les["centre"] = motion.apply(np.asarray(les["centre"])[None], phase, resp)[0].tolist()
        found = [dict(les, vessel=vd["name"]) for vd in doc["vessels"] for les in vd["lesions"]]
        pairs, fl = match_lesions(found, tl)
        false += len(fl)
        # labelling, on the reconstruction's analysed frame (same parameters as qca_for_reconstruction)
        _, tracked = read_vascular_graphs(recon / "graphs.zarr")
        q = analyse_graph(tracked.graphs[k], RECON_PARAMS)  # names and geometry do not depend on the radius source
        la = label_accuracy(q, moved, tnames)
        labels.append(la["accuracy"])
        labels_near.append(la["accuracy_where_reconstructed"])
        by_id = {q.vessel_id(v): v for v in q.reported()}
        names = np.asarray(tnames)
        # foreshortening of the named vessels' thirds: reconstruction vs the moved true tree, same names
        qt = analyse_graph(VascularGraph(moved, tg.radius, tg.edges), QCAParams())
        for name in ("LM", "LAD", "LCX", "RCA"):
            vr, vt = q.tree.vessel(name), qt.tree.vessel(name)
            if vr is None or vt is None:
                continue
            for third in range(3):
                segs = []
                for v in (vr, vt):
                    sel = (v.s >= v.length * third / 3) & (v.s <= v.length * (third + 1) / 3)
                    segs.append((q if v is vr else qt).tree.nodes[v.nodes[sel]])
                if min(len(x) for x in segs) >= 2:
                    err = float(np.abs(foreshortening(segs[0], dirs) - foreshortening(segs[1], dirs)).mean())
                    fs_seg.append(err)
                    fs_seg_rows.append({"case": case_dir.name, "segment": f"{('proximal', 'mid', 'distal')[third]} {name}",
                                        "fs_mae_pp": err})
        for t_les, f in pairs:
            row_ = {"case": case_dir.name, "vessel": t_les["vessel"], "true_ds": t_les["ds_percent"],
                    "true_mld": t_les["mld_mm"], "true_length": t_les["length_mm"], "true_ref": t_les["reference_mm"],
                    "found": f is not None, "controlled": False}
            if f is not None:
                row_.update({"ds": f["ds_percent"], "mld": f["mld_mm"], "length": f["length_mm"], "ref": f["reference_mm"],
                             "segment": f.get("segment", ""), "named": f.get("vessel")})
                # foreshortening of lesion ± max(5 mm, half its length): reconstruction vs the moved truth
                v = by_id.get(f["id"].split(".")[0])
                half = max(5.0, 0.5 * f["length_mm"])
                if v is not None:
                    sel = (v.s >= f["position_mm"] - half) & (v.s <= f["position_mm"] + half)
                    on = np.flatnonzero(names == t_les["branch"])
                    tsel = on[np.abs(tarc[on] - t_les["position_mm"]) <= max(5.0, 0.5 * t_les["length_mm"])]
                    if sel.sum() >= 2 and len(tsel) >= 2:
                        e = np.abs(foreshortening(q.tree.nodes[v.nodes[sel]], dirs) - foreshortening(moved[tsel], dirs))
                        row_["fs_mae_pp"] = float(e.mean())
                        fs_err.append(float(e.mean()))
            rows.append(row_)
    return summary(rows, false, n_trees, labels, float(np.mean(sides)) if sides else None, times,
                   extra={"row": row, "skipped_cases": skipped, "radius_source": radius, "cases": done,
                          "label_accuracy_where_reconstructed": float(np.nanmean(labels_near)) if labels_near else None,
                          "foreshortening_mae_pp": float(np.mean(fs_err)) if fs_err else None,
                          "foreshortening_segments_mae_pp": float(np.mean(fs_seg)) if fs_seg else None,
                          "foreshortening_segments": len(fs_seg), "foreshortening_per_segment": fs_seg_rows})


def _graph_keys(recon: Path):
    from ..core.artefacts import read_zarr

    return read_zarr(recon / "graphs.zarr", kind="autocar.vascular-graphs", schema_version=1).attrs["frame_keys"]
