"""Two-view correspondence (stages/twoview) on data-se: accuracy, recall and radius by vessel size, speed → docs/benchmarks/twoview_se.md.

Table 1's protocol (:mod:`stages.evaluate.synthetic_pairs`), optionally with segmenter-style mask noise;
per pair the four metrics, :func:`stages.core.metrics.centreline_by_radius` against the analytic truth,
the 3D step's wall time on one thread and the process's peak memory.

Run:  python benchmarks/bench_twoview_se.py [--limit N] [--mask-noise] [--doc FILE]. Missing data-se: exits 0.
"""

from __future__ import annotations

import argparse
import datetime as dt
import resource
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

BIN_NAMES = ("< 0.9 mm", "0.9–1.5 mm", "> 1.5 mm")  # stages.core.metrics.RADIUS_BINS_MM


def _mean(rows, key):
    vals = [r[key] for r in rows if r.get(key) is not None]
    return float(np.mean(vals)) if vals else None


def main(argv=None) -> int:
    from stages.evaluate.synthetic_pairs import se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=None)
    ap.add_argument("--limit", type=int, default=20, help="first N pairs (0: all)")
    ap.add_argument("--mask-noise", action="store_true", help="also score with segmenter-style mask noise")
    ap.add_argument("--doc", default=str(ROOT / "docs" / "benchmarks" / "twoview_se.md"))
    args = ap.parse_args(argv)
    data = se_or_say(args.data)
    if data is None:
        return 0
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    from machine import machine_description
    from stages.evaluate.synthetic_pairs import se_pairs
    from stages.core.metrics import centreline_by_radius, metrics_3d
    from stages.twoview import match_views, tubes_to_voxels

    load0 = os.getloadavg()
    tables = {}
    for noise in ((False, True) if args.mask_noise else (False,)):
        rows = []
        for p in se_pairs(data, args.limit or None, 2.0, mask_noise=noise):
            t0 = time.perf_counter()
            m = match_views(p.mask_a, p.mask_b, p.cam_a, p.cam_b)
            pred = tubes_to_voxels(m.polylines)
            seconds = time.perf_counter() - t0
            r = {"case_id": p.case.case_id, "seconds": seconds}
            r.update(metrics_3d(pred, p.truth, workers=1))
            P = np.concatenate([pl.points for pl in m.polylines]) if m.polylines else np.zeros((0, 3))
            PR = np.concatenate([pl.radius for pl in m.polylines]) if m.polylines else np.zeros(0)
            r.update(centreline_by_radius(P, PR, p.case.truth.points, p.case.truth.radius))
            rows.append(r)
            print(f"{'noisy ' if noise else ''}pair {p.index}: Dice {r['dice']:.3f} clDice {r['cldice']:.3f} "
                  f"CD {r['chamfer_mm']:.2f} ({seconds:.2f} s)", flush=True)
        tables["with segmenter-style mask noise" if noise else "exact silhouettes"] = rows
    load1 = os.getloadavg()
    peak_gb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1e6
    lines = ["## Two-view correspondence on data-se (stages/twoview)", "",
             f"- command: `python benchmarks/bench_twoview_se.py --limit {args.limit}"
             f"{' --mask-noise' if args.mask_noise else ''}`",
             f"- machine: {machine_description()}; load average {load0[0]:.1f} at the start, {load1[0]:.1f} at the end",
             f"- date: {dt.date.today().isoformat()}", "",
             "| masks | pairs | Dice | clDice | CD (mm) | HD95 (mm) | precision (1 mm) | recall " + " | recall ".join(BIN_NAMES)
             + " | radius MAE " + " | radius MAE ".join(BIN_NAMES) + " | radius bias (mm) | s per pair (median) |",
             "|---" * 14 + "|"]
    fmt = lambda v, f="{:.3f}": "n/a" if v is None else f.format(v)  # noqa: E731
    for name, rows in tables.items():
        lines.append(f"| {name} | {len(rows)} | " + " | ".join(fmt(_mean(rows, k)) for k in ("dice", "cldice")) + " | "
                     + " | ".join(fmt(_mean(rows, k), "{:.2f}") for k in ("chamfer_mm", "hd95_mm")) + " | "
                     + " | ".join(fmt(_mean(rows, k)) for k in ("precision", "recall_small", "recall_medium", "recall_large"))
                     + " | " + " | ".join(fmt(_mean(rows, k)) for k in ("radius_mae_small", "radius_mae_medium", "radius_mae_large"))
                     + f" | {fmt(_mean(rows, 'radius_bias_mm'))} | {np.median([r['seconds'] for r in rows]):.2f} |")
    lines += ["", f"Peak memory of the whole process (data loading and metrics included): {peak_gb:.2f} GB.", ""]
    Path(args.doc).parent.mkdir(parents=True, exist_ok=True)
    Path(args.doc).write_text("\n".join(lines))
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
