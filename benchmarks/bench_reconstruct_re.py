"""Benchmark: `autocar reconstruct` end to end on the simulated two-run set (data-re, paper Table 2).

For every case of ``data/re`` (two multi-frame XA DICOMs + the simulator's ``truth.zarr``) the whole
pipeline runs with nothing from the ground truth at inference: our segmentation, our key frames, the 3D
method (SBP network with the shipped weights, or the visual hull), graph optimisation. Scored against
the truth sidecar, per key frame pair (i, j) *that our key-frame stage chose*:

* **coverage / EPE / accuracy** (paper Eqs. 22–24; scoring: :func:`stages.evaluate.score_dynamic_reconstruction`):
  the ground-truth correspondences of that pair are the simulator's centreline nodes at frame i of run A
  and at frame j of run B (the same material point, wherever the heart and breathing moved it), a seeded
  sample of ``--points`` nodes per pair, projected with each run's DICOM camera;
* **3D centreline error** (mm, :func:`stages.metrics.graph_metrics`): the tracked graph of the key frame
  against the truth centreline at the midpoint of the two frames' configurations (the two runs are
  acquired at different times, so no single 3D configuration explains both views exactly);
* **topology**: bifurcations and end points of each key frame's tracked graph; *agreement* = the share
  of key frames whose (bifurcations, end points, components) equal the first key frame's.

Rows: ``--methods`` (default ``sbp,visual-hull``), each ``METHOD`` or ``NAME=METHOD[:WEIGHTS]`` (e.g.
``L7=sbp:stages/weights/sbp_uniform.pt``), with graph optimisation, plus ``<name>-nograph`` scored on
the per-frame predicted voxels (occupancy × centreness weighted) before graph optimisation.

Run:  python benchmarks/bench_reconstruct_re.py [--limit N] [--methods sbp,visual-hull] [--weights F]
Writes docs/benchmarks/reconstruct_re.md and the per-case JSON out/bench_re/<row>.json; reconstructions
are cached under out/bench_re/<name>/<case>/ (keyed by inputs and weights, benchmarks/re_eval.py;
``--fresh`` reruns them). Missing data-re: says so, exits 0.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from re_eval import re_cases_or_say  # noqa: E402

from stages.metrics import COVER_MM, EPSILON_MM  # noqa: E402


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(ROOT / "data" / "re"))
    ap.add_argument("--out", default=str(ROOT / "out" / "bench_re"))
    ap.add_argument("--methods", default="sbp,visual-hull")
    ap.add_argument("--weights", default=None, help="SBP weights (default: the shipped stages/weights/sbp.pt)")
    ap.add_argument("--limit", type=int, default=None)
    ap.add_argument("--points", type=int, default=60, help="ground-truth correspondences per key-frame pair")
    ap.add_argument("--fresh", action="store_true", help="rerun reconstructions even if cached")
    ap.add_argument("--jobs", type=int, default=1, help="cases reconstructed in parallel (processes, 1 thread each)")
    ap.add_argument("--doc", default="reconstruct_re")
    args = ap.parse_args(argv)
    data = Path(args.data)
    cases = re_cases_or_say(data, args.limit)
    if not cases:
        return 0

    from machine import write_section
    from re_eval import PAPER, evaluate_rows, parse_rows, refused_of, results_table

    out = Path(args.out)
    results, refused = evaluate_rows(parse_rows(args.methods, args.weights), cases, out, args.points, args.jobs,
                                     args.fresh, log=lambda m: print(m, flush=True))
    out.mkdir(parents=True, exist_ok=True)
    for name, rows in results.items():
        (out / f"{name}.json").write_text(json.dumps({"rows": rows, "refused": refused_of(refused, name)}, indent=1))

    lines = results_table(results, refused)
    lines.append(f"| paper (AutoCAR, real data) | | {PAPER['coverage']} | {PAPER['epe_mm']} | {PAPER['accuracy']} | | | | | | |")
    weights = args.weights or "stages/weights/sbp.pt (shipped)"
    unique_refusals = {}  # every method refuses the same cases with the same message: name each case once
    for rows in refused.values():
        for r in rows:
            unique_refusals.setdefault(r["case"], r["reason"])
    body = (f"{len(cases)} data-re cases (two 42-frame 512² XA runs each), end to end from DICOM: our U-Net "
            f"segmentation, our key frames (ECG), 3D method, graph optimisation; SBP weights `{weights}`. "
            f"Ground-truth correspondences: {args.points} simulator centreline nodes per chosen key-frame pair "
            f"(covered within {COVER_MM:g} mm in view A, ε = {EPSILON_MM:g} mm for accuracy). `-nograph` rows score "
            f"the per-frame predicted voxels before graph "
            f"optimisation. Per-case JSON: `{out}/<row>.json`. Refused cases (the pipeline's own one-line error, "
            f"e.g. runs < 10° apart) are left out of the means: "
            + ("; ".join(f"{case}: {reason}" for case, reason in unique_refusals.items()) or "none")
            + ".\n\n" + "\n".join(lines) + "\n")
    cmd = "python benchmarks/bench_reconstruct_re.py" + (f" --limit {args.limit}" if args.limit else "") + (
        f" --methods {args.methods}" if args.methods != "sbp,visual-hull" else "") + (
        f" --weights {args.weights}" if args.weights else "")
    write_section(args.doc, "End to end on data-re (Table 2 metrics, 3D centreline error, topology)", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
