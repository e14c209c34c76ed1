"""Benchmark: speed, memory and accuracy of ``autocar prep-ct`` → docs/benchmarks/prep_ct.md.

A 512×512×256 NIfTI label volume at 0.4 mm (both trees of one seed) in a fresh process; a ``--synthetic``
batch with 2 jobs; the batch's trees against their analytic truth (stages/prep_ct/accuracy.py).
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import min_median, run_child, write_section  # noqa: E402

AUTOCAR = [sys.executable, "-m", "autocar_cli.main"]


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=2)
    ap.add_argument("--cases", type=int, default=20)
    ap.add_argument("--seed", type=int, default=100)
    ap.add_argument("--work", default=str(ROOT / "out" / "bench_prep_ct"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)

    import nibabel as nib

    from stages.anatomy import generate

    anatomy = generate(args.seed)
    vol = anatomy.label_volume(spacing=(0.4, 0.4, 0.4), shape=(512, 512, 256))
    nii = work / "full_512x512x256.nii.gz"
    nib.save(nib.Nifti1Image(vol.data, np.diag([-1.0, -1, 1, 1]) @ vol.affine), str(nii))
    full = [run_child([*AUTOCAR, "prep-ct", str(nii), "-o", str(work / f"full_{r}")]) for r in range(args.repeats)]
    if any(f[2] != 0 for f in full):
        raise SystemExit(f"prep-ct failed on {nii}")
    t_full, m_full, _, c_full = zip(*full)

    synth = work / "synthetic"
    t_batch, m_batch, _, cpu_batch = run_child([*AUTOCAR, "prep-ct", "--synthetic", str(args.cases), "--seed",
                                                str(args.seed), "--jobs", "2", "-o", str(synth)])

    from stages.prep_ct.accuracy import evaluate_case
    from stages.core.prepared_case import PreparedCase, find_cases

    rows = [evaluate_case(PreparedCase.load(p)) for p in find_cases(synth)]
    keys = ["surface_mean", "surface_p95", "cl_pred_to_truth_mean", "cl_pred_to_truth_p95",
            "cl_truth_to_pred_mean", "cl_truth_to_pred_p95", "radius_mae"]
    agg = {k: (float(np.mean([r[k] for r in rows])), float(np.max([r[k] for r in rows]))) for k in keys}
    bif_ok = sum(r["bifurcations"] == r["bifurcations_truth"] for r in rows)
    (work / "accuracy.json").write_text(json.dumps(rows, indent=1))

    fmt = lambda k: f"{agg[k][0]:.3f} | {agg[k][1]:.3f}"  # noqa: E731
    body = f"""
Machine shared with other engineers' jobs: timings are noisy (min and median of repeats).

| what | min | median | target |
|---|---|---|---|
| 512×512×256 NIfTI label at 0.4 mm, both trees, `autocar prep-ct` wall time (s) | {min_median(t_full, '{:.1f}')} | ≤ 90 s |
| same, CPU time (user + system, s) | {min_median(c_full, '{:.1f}')} | |
| same, peak memory (max RSS, GiB) | {min_median(m_full)} | ≤ 4 GB |
| `autocar prep-ct --synthetic {args.cases} --jobs 2` wall time (s, one run) | {t_batch:.0f} | | ≤ 600 s |
| same, CPU time of all workers (s); CPU s / 2 cores ≈ wall on an idle machine | {cpu_batch:.0f} | {cpu_batch / 2:.0f} | |
| same, peak memory of one worker (GiB) | {m_batch:.2f} | | |

Accuracy of the {len(rows)} prepared trees of that batch (seeds {args.seed}–{args.seed + args.cases - 1}, both trees)
against the analytic ground truth (`stages/prep_ct/accuracy.py`), mean over trees | worst tree:

| figure (mm) | mean | worst tree | target |
|---|---|---|---|
| mesh vertex → analytic surface, mean | {fmt('surface_mean')} | ≤ 0.10 |
| mesh vertex → analytic surface, 95th pct | {fmt('surface_p95')} | ≤ 0.25 |
| centreline → truth, mean | {fmt('cl_pred_to_truth_mean')} | ≤ 0.20 |
| centreline → truth, 95th pct | {fmt('cl_pred_to_truth_p95')} | ≤ 0.50 |
| truth → centreline, mean | {fmt('cl_truth_to_pred_mean')} | ≤ 0.20 |
| truth → centreline, 95th pct | {fmt('cl_truth_to_pred_p95')} | ≤ 0.50 |
| radius mean absolute error | {fmt('radius_mae')} | ≤ 0.15 |

Bifurcation count equal to the truth: {bif_ok}/{len(rows)} trees ({100 * bif_ok / max(len(rows), 1):.0f} %, target ≥ 95 %).
Per-tree figures: `{work / 'accuracy.json'}`.
"""
    cmd = f"python benchmarks/bench_prep_ct.py --repeats {args.repeats} --cases {args.cases} --seed {args.seed}"
    path = write_section("prep_ct", "prep-ct: speed, memory and accuracy", cmd, body)
    print(path.read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
