"""Time the end of a reconstruction — QCA (qca.json, plots, the .vtp vessel names, qca_sr.dcm) and writing
report.html — on a copy of an existing reconstruction folder, for docs/RECONSTRUCT.md ("What the viewer, the
embedded figures and the SR cost in time"). Prints one JSON line.

Compares two versions of the code when run with each on ``PYTHONPATH`` (e.g. a ``git worktree`` of the
commit before): the report writer's signature tells which one runs. Run it from the folder reconstruct was
run from, so the runs' recorded paths resolve (the SR needs them)::

    .venv/bin/python benchmarks/report_overhead.py out/demo /tmp/overhead_copy
"""

from __future__ import annotations

import argparse
import inspect
import json
import shutil
import time
from pathlib import Path


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recon", type=Path, help="a folder written by `autocar reconstruct` (left as it is)")
    ap.add_argument("work", type=Path, help="scratch folder for the copy (replaced)")
    args = ap.parse_args()
    if not (args.recon / "graphs.zarr").exists():
        raise SystemExit(f"error: {args.recon}: no graphs.zarr (not a reconstruction folder)")
    shutil.rmtree(args.work, ignore_errors=True)
    shutil.copytree(args.recon, args.work)
    (args.work / "qca_sr.dcm").unlink(missing_ok=True)

    import numpy as np
    import pydicom  # noqa: F401  (reconstruct has read the DICOM runs with it already)

    from stages.graph.io import read_sparse_predictions, read_vascular_graphs

    t0 = time.perf_counter()
    from stages.qca import html_section, qca_for_reconstruction

    doc = qca_for_reconstruction(args.work)
    t_qca = time.perf_counter() - t0
    t0 = time.perf_counter()
    from stages import report

    new = "qca" in inspect.signature(report.write_report).parameters
    _, tracked = read_vascular_graphs(args.work / "graphs.zarr")
    _, frames = read_sparse_predictions(args.work / "predictions.zarr")
    model, overlays = [], []
    for key, g, fr in zip(tracked.keys, tracked.graphs, frames):
        if new:
            model.append({"key": key, "nodes": g.nodes, "radius": g.radius, "edges": g.edges, "phase": {},
                          "cameras": {v: report.camera_view(fr.cameras[v], g.nodes.mean(0)) for v in "ab"},
                          "one_view": []})
        else:
            model.append({"key": key, "nodes": np.round(g.nodes, 2).tolist(), "radius": np.round(g.radius, 2).tolist(),
                          "edges": np.asarray(g.edges).tolist(), "pos": np.round(g.position_along_tree(), 3).tolist()})
        overlays.append((key, args.work / f"overlay_{key}.png"))
    report.write_report(args.work / "report.html", title="AutoCAR reconstruction", summary_rows=[], timings=[],
                        frames_model=model, overlays=overlays, warnings=[], sections=html_section(doc),
                        **({"qca": doc} if new else {}))
    t_report = time.perf_counter() - t0
    print(json.dumps({"code": "with the 3D viewer" if new else "before it", "qca_s": round(t_qca, 3),
                      "report_s": round(t_report, 3), "sum_s": round(t_qca + t_report, 3),
                      "sr": (args.work / "qca_sr.dcm").exists(),
                      "report_bytes": (args.work / "report.html").stat().st_size}))


if __name__ == "__main__":
    main()
