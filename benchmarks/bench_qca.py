"""Benchmark: 3D QCA against known lesions and names → docs/benchmarks/qca_exact.md and docs/benchmarks/qca_re.md.

Two runs (issue 37; method in docs/QCA.md; the runs themselves: stages/qca/validate.py):

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
import sys
import time
from pathlib import Path

os.environ.setdefault("OMP_NUM_THREADS", "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import write_section  # noqa: E402

SE_CASES = ROOT / "data" / "se" / "cases"
RE_DIR = ROOT / "data" / "re"
CENTRELINE_SMOOTH_MM = float(os.environ.get("QCA_CENTRELINE_SMOOTH", "0.5"))


def run_exact(limit: int, source: str = "truth", perturbed: bool = False) -> dict:
    from stages.qca.validate import exact_cases, validate_exact

    return validate_exact(exact_cases(SE_CASES, limit, source), source, perturbed, CENTRELINE_SMOOTH_MM)


def _recon_dir(case: str, row: str) -> Path | None:
    for d in (ROOT / "out" / "table2" / row / case, ROOT / "out" / "qca_re" / case):
        if (d / "graphs.zarr").exists():
            return d
    return None


def _reconstruct(case_dir: Path, out: Path) -> None:
    import subprocess

    out.parent.mkdir(parents=True, exist_ok=True)
    done = subprocess.run([str(ROOT / ".venv" / "bin" / "autocar"), "reconstruct", str(case_dir / "run_a.dcm"),
                           str(case_dir / "run_b.dcm"), "-o", str(out), "--force"],
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    if done.returncode == 2:  # refused with a one-line error (e.g. runs < 10° apart): the case is left out
        print(f"{case_dir.name}: reconstruct refused the case; left out", flush=True)
    elif done.returncode != 0:
        raise RuntimeError(f"{case_dir.name}: autocar reconstruct failed (exit {done.returncode})")


def run_re(row: str = "L8", reconstruct: bool = False, limit: int | None = None, extra_cases=(), recon_dirs=None,
           radius: str = "frame") -> dict:
    """The full validation; ``extra_cases`` (folders with run_a/run_b/truth.zarr) go first, and
    ``recon_dirs`` maps a case folder's name to its reconstruction (else :func:`_recon_dir`)."""
    from stages.qca.validate import validate_reconstructions

    cases = sorted(p for p in RE_DIR.glob("case_*") if (p / "truth.zarr").exists())[:limit]
    if extra_cases:
        cases = list(extra_cases) + cases

    def recon_of(case_dir: Path) -> Path | None:
        recon = (recon_dirs or {}).get(case_dir.name) or _recon_dir(case_dir.name, row)
        if recon is None and reconstruct:
            _reconstruct(case_dir, ROOT / "out" / "qca_re" / case_dir.name)
            recon = _recon_dir(case_dir.name, row)
        return recon

    return validate_reconstructions(cases, recon_of, RE_DIR, row, radius)


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
    ap.add_argument("--json", type=Path, default=None, help="default: out/qca_exact.json (--exact), out/qca_re.json")
    ap.add_argument("--doc", action="store_true", help="write the docs/benchmarks page")
    args = ap.parse_args(argv)
    args.json = args.json or ROOT / "out" / ("qca_exact.json" if args.exact else "qca_re.json")
    t0 = time.perf_counter()
    if args.exact:
        res = run_exact(args.limit or 90, args.source, args.perturb)
    else:
        extra = [ROOT / "examples"] if args.example else []
        res = run_re(args.row, args.reconstruct, args.limit, extra, {"examples": args.example} if args.example else None,
                     args.radius)
    res["seconds"] = time.perf_counter() - t0
    args.json.parent.mkdir(parents=True, exist_ok=True)
    from stages.core.artefacts import write_json

    write_json(args.json, res)
    short = {k: v for k, v in res.items() if k != "per_lesion"}
    print(json.dumps(short, indent=1))
    if args.doc:
        cmd = "python benchmarks/bench_qca.py " + " ".join(a for a in (argv or sys.argv[1:]))
        print("wrote", write_doc(res, args.exact, cmd))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
