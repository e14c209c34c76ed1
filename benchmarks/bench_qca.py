"""Benchmark: 3D QCA against known lesions and names → docs/benchmarks/qca_exact.md and docs/benchmarks/qca_re.md.

Two runs (issue 37; method in docs/QCA.md):

* ``--exact [--limit N]`` — the analysis alone, on the true 3D trees: the analytic centreline and
  radius of each data-se tree (``data/se/cases``; the same trees regenerated from their seeds when the
  set is not there), with the generator's own stenoses, plus a controlled-lesion set (one more
  raised-cosine lesion per tree, 20–90 % DS, 5–25 mm, seeded by the tree's seed; stages/qca/truth.py).
  Targets: %DS MAE ≤ 3 pp, MLD MAE ≤ 0.15 mm, length MAE ≤ 1.5 mm. ``--source centreline`` runs it on
  the prepared case's voxel-derived centreline graph instead (radii from the 0.4 mm CTA-like mask).
* without ``--exact`` — the full validation on data-re two-view reconstructions: reused from
  ``out/table2/<row>/<case>/`` (``--row``, default L8) when there, else from ``out/qca_re/<case>/``,
  made with ``autocar reconstruct`` only with ``--reconstruct`` (~1 min per case). The truth is moved
  to the analysed key frame's run-A frame with the case's heart motion. Targets: sensitivity ≥ 0.90
  for lesions ≥ 50 % DS at ≤ 0.3 false lesions (≥ 50 % DS, matching no true lesion) per tree, %DS MAE
  ≤ 7 pp, length MAE ≤ 3 mm, ≥ 90 % of the true LM/LAD/LCX/RCA length named right, foreshortening
  within 5 pp of the true tree's, ``autocar qca`` ≤ 2 s per case.

Writes ``--json FILE``: {"lesions", "ds_mae_pp", "mld_mae_mm", "length_mae_mm", …} (+ "sensitivity_50",
"false_per_tree", "label_accuracy" for the full run) and, with ``--doc``, the Markdown page with the
per-lesion table.

Run:  python benchmarks/bench_qca.py --exact --limit 90 --json out/qca_exact.json --doc
      python benchmarks/bench_qca.py --json out/qca_re.json --doc
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import write_section  # noqa: E402

SE_CASES = ROOT / "data" / "se" / "cases"
RE_DIR = ROOT / "data" / "re"
CENTRELINE_SMOOTH_MM = float(os.environ.get("QCA_CENTRELINE_SMOOTH", "0.5"))


# ---------------------------------------------------------------------------------------------- cases
def _read_case_truth(path: Path):
    """(CaseTruth, stenoses, side, seed, centreline graph) of a prepared case without loading its mesh/labels."""
    from stages.artefacts import read_zarr
    from stages.graph.vascular import VascularGraph
    from stages.prepared_case import CaseTruth

    g = read_zarr(path, kind="autocar.prepared-case", schema_version=1)
    attrs = dict(g.attrs)
    tg = g["truth"]
    truth = CaseTruth(tg["points"][...], tg["radius"][...], tg["branch"][...], tg["parent"][...],
                      list(dict(tg.attrs).get("names", [])))
    cl = VascularGraph(g["centreline/nodes"][...], g["centreline/radius"][...], g["centreline/edges"][...])
    seed = (attrs.get("source") or {}).get("seed")
    return truth, list(attrs.get("stenoses") or []), attrs["side"], seed, cl


def exact_cases(limit: int, source: str = "truth"):
    """Yield (case name, graph, truth names per node, true lesions, side, truth graph, truth names) for the first
    ``limit`` data-se trees, then their controlled-lesion twins."""
    from stages.anatomy import generate
    from stages.render.products import SEED_SE
    from stages.qca.truth import controlled_case, true_lesions, truth_graph

    paths = sorted(SE_CASES.glob("case_*.zarr"))[:limit] if SE_CASES.is_dir() else []
    items = []
    if paths:
        for p in paths:
            truth, stenoses, side, seed, cl = _read_case_truth(p)
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
    from stages.graph.vascular import VascularGraph

    rng = np.random.default_rng([seed, 7])
    eps = _smooth_on_graph(graph, rng.normal(0, 1, len(graph)), corr_mm)
    eps = eps / max(float(eps.std()), 1e-9) * noise
    r = _smooth_on_graph(graph, graph.radius, blur_mm) * bias * (1 + eps)
    return VascularGraph(graph.nodes, np.maximum(r, 0.1), graph.edges)


def run_exact(limit: int, source: str = "truth", perturbed: bool = False) -> dict:
    from stages.qca.analysis import QCAParams, analyse_graph
    from stages.qca.validate import label_accuracy, match_lesions

    params = QCAParams() if source == "truth" else QCAParams(smooth_mm=CENTRELINE_SMOOTH_MM)
    if perturbed:
        from stages.qca.recon import RECON_PARAMS

        params = RECON_PARAMS
    rows, false, sides, labels, times, trees, controlled = [], 0, 0, [], [], 0, []
    for name, graph, truth, side, tgraph, tnames in exact_cases(limit, source):
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
    return _summary(rows, false, n_trees, labels, sides / max(trees, 1), times,
                    extra={"source": source + (" perturbed" if perturbed else "")})


def _summary(rows, false, n_trees, labels, side_acc, times, extra=None) -> dict:
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


# ---------------------------------------------------------------------------------------------- data-re
def _recon_dir(case: str, row: str) -> Path | None:
    for d in (ROOT / "out" / "table2" / row / case, ROOT / "out" / "qca_re" / case):
        if (d / "graphs.zarr").exists():
            return d
    return None


def _reconstruct(case_dir: Path, out: Path) -> None:
    import subprocess

    out.parent.mkdir(parents=True, exist_ok=True)
    subprocess.run([str(ROOT / ".venv" / "bin" / "autocar"), "reconstruct", str(case_dir / "run_a.dcm"),
                    str(case_dir / "run_b.dcm"), "-o", str(out), "--force"], check=True,
                   env={**os.environ, "OMP_NUM_THREADS": "1"})


def run_re(row: str = "L8", reconstruct: bool = False, limit: int | None = None, extra_cases=(), recon_dirs=None,
           radius: str = "frame") -> dict:
    """The full validation; ``extra_cases`` (folders with run_a/run_b/truth.zarr) go first, and
    ``recon_dirs`` maps a case folder's name to its reconstruction (else :func:`_recon_dir`)."""
    from stages.qca.analysis import analyse_graph
    from stages.qca.recon import RECON_PARAMS, qca_for_reconstruction
    from stages.qca.truth import truth_graph, true_lesions
    from stages.qca.validate import label_accuracy, match_lesions
    from stages.qca.views import foreshortening, view_directions, view_grid
    from stages.render.acquire import load_truth

    cases = sorted(p for p in RE_DIR.glob("case_*") if (p / "truth.zarr").exists())[:limit]
    if extra_cases:
        cases = list(extra_cases) + cases
    rows, false, labels, times, sides, fs_err, n_trees, skipped = [], 0, [], [], [], [], 0, []
    labels_near, fs_seg, fs_seg_rows, done = [], [], [], []
    alphas, betas = view_grid(5.0)
    dirs, _, _ = view_directions(alphas, betas)
    for case_dir in cases:
        recon = (recon_dirs or {}).get(case_dir.name) or _recon_dir(case_dir.name, row)
        if recon is None and reconstruct:
            _reconstruct(case_dir, ROOT / "out" / "qca_re" / case_dir.name)
            recon = _recon_dir(case_dir.name, row)
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
            case_path = RE_DIR / case_path
        if not case_path.exists():
            case_path = RE_DIR / "cases" / case_path.name
        if case_path.exists():
            truth, stenoses, side, _, _ = _read_case_truth(case_path)
        else:  # the bundled example's case was prepared in a temporary folder: regenerate its tree
            from stages.anatomy import generate

            side = "right" if case_path.stem.endswith("_right") else "left"
            tree = generate(int(tr["attrs"]["seed"])).tree(side)
            truth, stenoses = tree.truth(), tree.stenoses
        n_trees += 1
        sides.append(doc["side"] == side)
        summary = json.loads((recon / "summary.json").read_text())
        keys = doc["frame"]
        k = [str(x) for x in _graph_keys(recon)].index(str(keys)) if keys is not None else 0
        ia = int(summary["pairs"][k][0])
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
        from stages.graph.io import read_vascular_graphs

        _, tracked = read_vascular_graphs(recon / "graphs.zarr")
        q = analyse_graph(tracked.graphs[k], RECON_PARAMS)  # names and geometry do not depend on the radius source
        la = label_accuracy(q, moved, tnames)
        labels.append(la["accuracy"])
        labels_near.append(la["accuracy_where_reconstructed"])
        by_id = {q.vessel_id(v): v for v in q.reported()}
        names = np.asarray(tnames)
        # foreshortening of the named vessels' thirds: reconstruction vs the moved true tree, same names
        from stages.graph.vascular import VascularGraph
        from stages.qca.analysis import QCAParams

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
    out = _summary(rows, false, n_trees, labels, float(np.mean(sides)) if sides else None, times,
                   extra={"row": row, "skipped_cases": skipped, "radius_source": radius, "cases": done,
                          "label_accuracy_where_reconstructed": float(np.nanmean(labels_near)) if labels_near else None,
                          "foreshortening_mae_pp": float(np.mean(fs_err)) if fs_err else None,
                          "foreshortening_segments_mae_pp": float(np.mean(fs_seg)) if fs_seg else None,
                          "foreshortening_segments": len(fs_seg), "foreshortening_per_segment": fs_seg_rows})
    return out


def _graph_keys(recon: Path):
    from stages.artefacts import read_zarr

    return read_zarr(recon / "graphs.zarr", kind="autocar.vascular-graphs", schema_version=1).attrs["frame_keys"]


# ---------------------------------------------------------------------------------------------- docs
def _fmt(v, f="{:.2f}"):
    return "–" if v is None else f.format(v)


def _table(rows) -> str:
    lines = ["| case | vessel | true %DS | %DS | true MLD mm | MLD mm | true length mm | length mm | segment |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['case']} | {r['vessel']} | {r['true_ds']:.1f} | {_fmt(r.get('ds'), '{:.1f}')} | "
                     f"{r['true_mld']:.2f} | {_fmt(r.get('mld'))} | {r['true_length']:.1f} | {_fmt(r.get('length'), '{:.1f}')} | "
                     f"{r.get('segment', 'missed') if r['found'] else '**missed**'} |")
    return "\n".join(lines)


def write_doc(res: dict, exact: bool, command: str) -> Path:
    if exact:
        body = f"""
On the true 3D trees ({res['source']}: {'the analytic centrelines, 0.25 mm samples with the exact radius' if res['source'] == 'truth' else "the prepared cases' voxel-derived centreline graphs"}),
{res['trees']} data-se trees with the generator's own stenoses plus one controlled lesion per tree (20–90 % DS, 5–25 mm).
Targets (issue 37): %DS MAE ≤ 3 pp, MLD MAE ≤ 0.15 mm, length MAE ≤ 1.5 mm.

| lesions found / true | %DS MAE pp | MLD MAE mm | length MAE mm | false lesions (≥ 50 %) per tree | side right | LM/LAD/LCX/RCA length named right | analysis s per tree (min / median, CPU) |
|---|---|---|---|---|---|---|---|
| {res['lesions']} / {res['true_lesions']} | {_fmt(res['ds_mae_pp'])} | {_fmt(res['mld_mae_mm'], '{:.3f}')} | {_fmt(res['length_mae_mm'])} | {_fmt(res['false_per_tree'])} | {_fmt(res['side_accuracy'])} | {_fmt(res['label_accuracy'], '{:.3f}')} | {_fmt(res['seconds_per_tree_min'], '{:.3f}')} / {_fmt(res['seconds_per_tree_median'], '{:.3f}')} |

Lesion length is the raised-cosine-equivalent length, 2 × the full width at half the maximal narrowing
(docs/QCA.md); the truth is the generator's full profile width.

### Per lesion

{_table(res['per_lesion'])}
"""
        return write_section("qca_exact", "3D QCA on the true trees (exact 3D)", command, body)
    body = f"""
Two-view reconstructions (radius source: {res['radius_source']}): {res['trees']} tree(s) — {', '.join(res['cases']) or 'none'}{'; data-re cases without a reconstruction (skipped): ' + ', '.join(res['skipped_cases']) if res['skipped_cases'] else ''}.
Reconstructions are reused from out/table2/{res['row']}/<case>/ or out/qca_re/<case>/ (`autocar reconstruct` defaults).
The truth is the generator's tree moved to the analysed key frame (run A's frame) by the case's heart motion.

| lesions found / true | sensitivity (≥ 50 % DS) | false lesions (≥ 50 %) per tree | %DS MAE pp | MLD MAE mm | length MAE mm | labelling (where reconstructed) | side right | foreshortening MAE pp: lesions / main-vessel thirds | `qca` s per case with plots (min / median, CPU, in-process) |
|---|---|---|---|---|---|---|---|---|---|
| {res['lesions']} / {res['true_lesions']} | {_fmt(res['sensitivity_50'])} | {_fmt(res['false_per_tree'])} | {_fmt(res['ds_mae_pp'])} | {_fmt(res['mld_mae_mm'], '{:.3f}')} | {_fmt(res['length_mae_mm'])} | {_fmt(res['label_accuracy'], '{:.3f}')} ({_fmt(res['label_accuracy_where_reconstructed'], '{:.3f}')}) | {_fmt(res['side_accuracy'])} | {_fmt(res['foreshortening_mae_pp'])} / {_fmt(res['foreshortening_segments_mae_pp'])} ({res['foreshortening_segments']}) | {_fmt(res['seconds_per_tree_min'])} / {_fmt(res['seconds_per_tree_median'])} |

Targets (issue 37): sensitivity ≥ 0.90 at ≤ 0.3 false lesions per tree, %DS MAE ≤ 7 pp, length MAE ≤ 3 mm,
labelling ≥ 0.90, foreshortening within 5 pp, ≤ 2 s per case.

### Per lesion

{_table(res['per_lesion'])}
"""
    return write_section("qca_re", "3D QCA on data-re reconstructions", command, body)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exact", action="store_true", help="analysis on the true 3D trees only")
    ap.add_argument("--limit", type=int, default=None, help="number of cases (default: all)")
    ap.add_argument("--source", choices=["truth", "centreline"], default="truth", help="--exact: which true graph")
    ap.add_argument("--perturb", action="store_true",
                    help="--exact: reconstruction-like radii (blurred σ 1 mm, ×1.3, 8 %% correlated noise), reconstruction parameters")
    ap.add_argument("--row", default="L8", help="full run: the out/table2 row whose reconstructions to reuse")
    ap.add_argument("--reconstruct", action="store_true", help="full run: reconstruct cases that have no reconstruction")
    ap.add_argument("--example", type=Path, default=None,
                    help="full run: also validate the bundled example (examples/) with this reconstruction folder of it")
    ap.add_argument("--radius", choices=["frame", "mean"], default="frame",
                    help="full run: the analysed frame's radii or the mean over the key frames")
    ap.add_argument("--json", type=Path, required=True)
    ap.add_argument("--doc", action="store_true", help="write the docs/benchmarks page")
    args = ap.parse_args(argv)
    t0 = time.perf_counter()
    if args.exact:
        res = run_exact(args.limit or 90, args.source, args.perturb)
    else:
        extra = [ROOT / "examples"] if args.example else []
        res = run_re(args.row, args.reconstruct, args.limit, extra, {"examples": args.example} if args.example else None,
                     args.radius)
    res["seconds"] = time.perf_counter() - t0
    args.json.parent.mkdir(parents=True, exist_ok=True)
    from stages.artefacts import write_json

    write_json(args.json, res)
    short = {k: v for k, v in res.items() if k != "per_lesion"}
    print(json.dumps(short, indent=1))
    if args.doc:
        cmd = "python benchmarks/bench_qca.py " + " ".join(a for a in (argv or sys.argv[1:]))
        print("wrote", write_doc(res, args.exact, cmd))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
