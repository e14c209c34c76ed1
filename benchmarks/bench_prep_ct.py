"""Benchmark: speed, memory and accuracy of ``autocar prep-ct`` → docs/benchmarks/prep_ct.md.

1. Full-size case: a 512×512×256 label volume at 0.4 mm holding both procedural trees of one seed,
   saved as NIfTI and prepared by ``autocar prep-ct`` in a fresh process: wall time and peak memory
   (max RSS of the child process), min and median of the repeats.
2. Batch: ``autocar prep-ct --synthetic 20 --jobs 2`` wall time.
3. Accuracy of the 40 trees of that batch against their analytic ground truth (surface distance,
   centreline distance both ways, radius error, bifurcation count).

Run:  python benchmarks/bench_prep_ct.py [--repeats 2] [--cases 20] [--seed 100]
"""

from __future__ import annotations

import argparse
import json
import shutil
import statistics
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.machine import run_child, write_section  # noqa: E402

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

    # ---- 1. full-size volume
    import nibabel as nib

    from stages.anatomy import generate

    anatomy = generate(args.seed)
    vol = anatomy.label_volume(spacing=(0.4, 0.4, 0.4), shape=(512, 512, 256))
    nii = work / "full_512x512x256.nii.gz"
    nib.save(nib.Nifti1Image(vol.data, np.diag([-1.0, -1, 1, 1]) @ vol.affine), str(nii))
    full = []
    for r in range(args.repeats):
        out = work / f"full_{r}"
        full.append(run_child([*AUTOCAR, "prep-ct", str(nii), "-o", str(out)]))
        if full[-1][2] != 0:
            raise SystemExit(f"prep-ct failed on {nii}")
    t_full = [f[0] for f in full]
    m_full = [f[1] for f in full]
    c_full = [f[3] for f in full]

    # ---- 2. batch
    synth = work / "synthetic"
    t_batch, m_batch, rc, cpu_batch = run_child([*AUTOCAR, "prep-ct", "--synthetic", str(args.cases), "--seed", str(args.seed),
                                      "--jobs", "2", "-o", str(synth)])

    # ---- 3. accuracy
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
| 512×512×256 NIfTI label at 0.4 mm, both trees, `autocar prep-ct` wall time (s) | {min(t_full):.1f} | {statistics.median(t_full):.1f} | ≤ 90 s |
| same, CPU time (user + system, s) | {min(c_full):.1f} | {statistics.median(c_full):.1f} | |
| same, peak memory (max RSS, GiB) | {min(m_full):.2f} | {statistics.median(m_full):.2f} | ≤ 4 GB |
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
