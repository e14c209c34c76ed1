"""Benchmark: 3D QCA against known lesions and names → docs/benchmarks/qca_exact.md and docs/benchmarks/qca_re.md.

The runs are stages/qca/validate.py's (docs/QCA.md). ``--exact``: the analysis alone on the true data-se
trees with a controlled lesion each; without it: data-re reconstructions (from out/table2/ or out/qca_re/,
made with ``--reconstruct``). Run: ``python benchmarks/bench_qca.py [--exact --limit 90] --json F --doc``
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import write_section  # noqa: E402

SE_CASES = ROOT / "data" / "se" / "cases"
RE_DIR = ROOT / "data" / "re"


def _recon_dir(case: str, row: str) -> Path | None:
    return next((d for d in (ROOT / "out" / "table2" / row / case, ROOT / "out" / "qca_re" / case)
                 if (d / "graphs.zarr").exists()), None)


def run_re(row: str = "L8", reconstruct: bool = False, limit: int | None = None, example: Path | None = None,
           radius: str = "frame", data: Path = RE_DIR) -> dict:
    """The full validation; with ``example`` (its reconstruction folder) the bundled example goes first.
    ``data``: the data-re set (data/re, or data/re3, whose runs A and B are data-re's)."""
    import subprocess

    from stages.qca.validate import validate_reconstructions

    cases = sorted(p for p in Path(data).glob("case_*") if (p / "truth.zarr").exists())[:limit]
    cases = [ROOT / "examples", *cases] if example else cases

    def recon_of(case: Path) -> Path | None:
        if case.name == "examples" and example:
            return example
        if _recon_dir(case.name, row) is None and reconstruct:
            out = ROOT / "out" / "qca_re" / case.name
            out.parent.mkdir(parents=True, exist_ok=True)
            rc = subprocess.run([str(ROOT / ".venv" / "bin" / "autocar"), "reconstruct", str(case / "run_a.dcm"),
                                 str(case / "run_b.dcm"), "-o", str(out), "--force"],
                                env={**os.environ, "OMP_NUM_THREADS": "1"}).returncode
            if rc == 2:  # refused with a one-line error (e.g. runs < 10° apart): the case is left out
                print(f"{case.name}: reconstruct refused the case; left out", flush=True)
            elif rc != 0:
                raise RuntimeError(f"{case.name}: autocar reconstruct failed (exit {rc})")
        return _recon_dir(case.name, row)

    return validate_reconstructions(cases, recon_of, Path(data), row, radius)


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
    per_lesion = f"\n### Per lesion\n\n{_table(res['per_lesion'])}\n"
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
"""
        return write_section("qca_exact", "3D QCA on the true trees (exact 3D)", command, body + per_lesion)
    body = f"""
Two-view reconstructions (radius source: {res['radius_source']}): {res['trees']} tree(s) — {', '.join(res['cases']) or 'none'}{'; data-re cases without a reconstruction (skipped): ' + ', '.join(res['skipped_cases']) if res['skipped_cases'] else ''}.
Reconstructions are reused from out/table2/{res['row']}/<case>/ or out/qca_re/<case>/ (`autocar reconstruct` defaults).
The truth is the generator's tree moved to the analysed key frame (run A's frame) by the case's heart motion.

| lesions found / true | sensitivity (≥ 50 % DS) | false lesions (≥ 50 %) per tree | %DS MAE pp | MLD MAE mm | length MAE mm | labelling (where reconstructed) | side right | foreshortening MAE pp: lesions / main-vessel thirds | `qca` s per case with plots (min / median, CPU, in-process) |
|---|---|---|---|---|---|---|---|---|---|
| {res['lesions']} / {res['true_lesions']} | {_fmt(res['sensitivity_50'])} | {_fmt(res['false_per_tree'])} | {_fmt(res['ds_mae_pp'])} | {_fmt(res['mld_mae_mm'], '{:.3f}')} | {_fmt(res['length_mae_mm'])} | {_fmt(res['label_accuracy'], '{:.3f}')} ({_fmt(res['label_accuracy_where_reconstructed'], '{:.3f}')}) | {_fmt(res['side_accuracy'])} | {_fmt(res['foreshortening_mae_pp'])} / {_fmt(res['foreshortening_segments_mae_pp'])} ({res['foreshortening_segments']}) | {_fmt(res['seconds_per_tree_min'])} / {_fmt(res['seconds_per_tree_median'])} |

Targets (issue 37): sensitivity ≥ 0.90 at ≤ 0.3 false lesions per tree, %DS MAE ≤ 7 pp, length MAE ≤ 3 mm,
labelling ≥ 0.90, foreshortening within 5 pp, ≤ 2 s per case.
"""
    return write_section("qca_re", "3D QCA on data-re reconstructions", command, body + per_lesion)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--exact", action="store_true", help="analysis on the true 3D trees only")
    ap.add_argument("--limit", type=int, default=None, help="number of cases (default: all)")
    ap.add_argument("--source", choices=["truth", "centreline"], default="truth", help="--exact: which true graph")
    ap.add_argument("--perturb", action="store_true", help="--exact: reconstruction-like radii (blurred σ 1 mm, ×1.3, "
                    "8 %% correlated noise), reconstruction parameters")
    ap.add_argument("--row", default="L8", help="full run: the out/table2 row whose reconstructions to reuse")
    ap.add_argument("--reconstruct", action="store_true", help="full run: reconstruct cases that have no reconstruction")
    ap.add_argument("--example", type=Path, help="full run: also the bundled example, reconstructed in this folder")
    ap.add_argument("--radius", choices=["frame", "mean"], default="frame",
                    help="full run: the analysed frame's radii or the mean over the key frames")
    ap.add_argument("--data", type=Path, default=RE_DIR, help="full run: the data-re set (data/re3 works too)")
    ap.add_argument("--json", type=Path, help="default: out/qca_exact.json (--exact), out/qca_re.json")
    ap.add_argument("--doc", action="store_true", help="write the docs/benchmarks page")
    args = ap.parse_args(argv)
    args.json = args.json or ROOT / "out" / ("qca_exact.json" if args.exact else "qca_re.json")
    t0 = time.perf_counter()
    if args.exact:
        from stages.qca.validate import exact_cases, validate_exact

        res = validate_exact(exact_cases(SE_CASES, args.limit or 90, args.source), args.source, args.perturb)
    else:
        res = run_re(args.row, args.reconstruct, args.limit, args.example, args.radius, args.data)
    res["seconds"] = time.perf_counter() - t0
    args.json.parent.mkdir(parents=True, exist_ok=True)
    from stages.core.artefacts import write_json

    write_json(args.json, res)
    print(json.dumps({k: v for k, v in res.items() if k != "per_lesion"}, indent=1))
    if args.doc:
        cmd = "python benchmarks/bench_qca.py " + " ".join(a for a in (argv or sys.argv[1:]))
        print("wrote", write_doc(res, args.exact, cmd))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
