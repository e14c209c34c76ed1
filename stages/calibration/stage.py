"""The ``calibrate`` stage: XA runs in, an ``autocar.calibration`` JSON artefact out.

Reads: two or more runs (DICOM files, or frame folders / ``.npy``/``.npz`` stacks with a geometry JSON;
:func:`stages.core.runs.load_run`). Each run is reduced to a full-contrast frame (median of its later
half, :func:`stages.segment.vesselness.contrast_frame`) and segmented (Frangi vesselness by default).
Writes: one JSON file (atomic) with the standard artefact header (kind ``autocar.calibration``, schema 1)
and ``runs`` (per run: path, header camera, corrected camera, correction), ``report``
(:func:`stages.calibration.runs.calibrate_runs`), ``summary_lines`` (what the CLI prints last). The header
cameras are first placed in the first run's patient frame where the table moved between runs
(:func:`stages.core.runs.place_on_one_table`).
:func:`load_calibration` reads it back into cameras by run name.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..core.artefacts import read_json
from ..core.errors import UserError
from ..core.geometry import Camera

__all__ = ["KIND", "SCHEMA_VERSION", "run_calibration", "summary_lines", "write_calibration", "load_calibration",
           "masks_of_runs"]

KIND = "autocar.calibration"
SCHEMA_VERSION = 1


def masks_of_runs(paths, geometries=None, seg_method: str = "vesselness"):
    """(names, cameras, masks, fovs, table offsets) of the runs: contrast frame → vessel mask; the cameras placed
    on the first run's table, ``{name: offset mm}`` for the runs that moved (:func:`stages.core.runs.place_on_one_table`)."""
    from ..evaluate.heldout import contrast_mask
    from ..core.runs import load_run, place_on_one_table

    geometries = list(geometries or [])
    names, runs, masks, fovs = [], [], [], []
    for k, p in enumerate(paths):
        run = load_run(p, geometries[k] if k < len(geometries) else None)
        if run.camera is None:
            raise UserError(f"{p}: no C-arm geometry (give a geometry JSON with --geometry)")
        mask, fov = contrast_mask(run.frames, seg_method)
        name = Path(p).stem if Path(p).suffix else Path(p).name
        if name in names:
            name = f"{name}_{k + 1}"
        names.append(name)
        runs.append(run)
        masks.append(mask)
        fovs.append(fov)
    table = place_on_one_table(runs, names)  # the header cameras in one patient frame where the table moved
    return names, [r.camera for r in runs], masks, fovs, table


def summary_lines(report: dict) -> list[str]:
    """Human-readable last lines: per run its correction and residual before → after."""
    lines = [f"calibration ({report.get('method')}), reference run {report.get('reference_run')}: "
             f"{'applied' if report.get('applied') else 'not applied (header geometry kept)'}"]
    before, after = report.get("residual_before", {}), report.get("residual_after", {})
    for name, c in report.get("corrections", {}).items():
        if name == report.get("reference_run"):
            continue
        line = (f"  {name}: shift {c.get('shift_mm_norm', 0.0):.2f} mm ({c['shift_row_px']:+.1f}, {c['shift_col_px']:+.1f} px), "
                f"in-plane {c['inplane_deg']:+.2f}°, dα {c['dalpha_deg']:+.2f}°, dβ {c['dbeta_deg']:+.2f}°, "
                f"dSID {c['dsid_mm']:+.1f} mm")
        b = before.get(name, before) if isinstance(before.get(name, None), dict) else before
        a = after.get(name, after) if isinstance(after.get(name, None), dict) else after
        if "chamfer_px" in b and b["chamfer_px"] is not None:
            line += (f"; residual {b['chamfer_px']:.2f} px / {b['chamfer_mm']:.2f} mm → "
                     f"{a['chamfer_px']:.2f} px / {a['chamfer_mm']:.2f} mm")
        elif "epipolar_px" in b:
            line += (f"; residual {b['epipolar_px']:.2f} px / {b['epipolar_mm']:.2f} mm → "
                     f"{a['epipolar_px']:.2f} px / {a['epipolar_mm']:.2f} mm")
        elif "profile_overlap" in b:
            line += f"; crossing-profile overlap {b['profile_overlap']:.3f} → {a['profile_overlap']:.3f}"
        lines.append(line)
    for w in report.get("warnings", []):
        lines.append(f"  warning: {w}")
    return lines


def run_calibration(paths, geometries=None, *, static: bool = False, reference: int = 0,
                    seg_method: str = "vesselness", bounds: dict | None = None) -> dict:
    """Calibrate the runs; returns the artefact content (without header) as a dict."""
    from .runs import calibrate_runs

    paths = [Path(p) for p in paths]
    if len(paths) < 2:
        raise UserError("calibrate needs two or more runs")
    if not 0 <= reference < len(paths):
        raise UserError(f"--reference {reference}: must be 0…{len(paths) - 1} (index of a run)")
    names, cams, masks, fovs, table = masks_of_runs(paths, geometries, seg_method)
    new, report = calibrate_runs(masks, cams, names, static=static, reference=reference, bounds=bounds, fovs=fovs)
    runs = [{"name": n, "path": str(p), "header_camera": c.to_dict(), "camera": nc.to_dict(),
             "table_offset_mm": table.get(n), "correction": report["corrections"].get(n)}
            for n, p, c, nc in zip(names, paths, cams, new)]
    lines = [f"{n}: the table stood ({d[0]:+.1f}, {d[1]:+.1f}, {d[2]:+.1f}) mm (x, y, z) from {names[0]}'s; its camera "
             "was placed accordingly before calibrating" for n, d in table.items()]
    return {"runs": runs, "report": report, "summary_lines": lines + summary_lines(report)}


def write_calibration(path, result: dict, inputs=(), parameters=None) -> Path:
    from ..core.artefacts import root_attributes, write_json

    doc = dict(root_attributes(KIND, SCHEMA_VERSION, "calibrate", inputs=inputs, parameters=parameters), **result)
    return write_json(path, doc)


def load_calibration(path) -> dict[str, Camera]:
    """Corrected cameras by run name from an ``autocar.calibration`` file."""
    path = Path(path)
    doc = read_json(path, "calibration file")
    if not isinstance(doc, dict) or doc.get("kind") != KIND:
        raise UserError(f"{path}: not an {KIND} file (kind {doc.get('kind') if isinstance(doc, dict) else None!r})")
    if doc.get("schema_version") != SCHEMA_VERSION:
        raise UserError(f"{path}: {KIND} schema version {doc.get('schema_version')!r}, expected {SCHEMA_VERSION}")
    out = {}
    for r in doc.get("runs", []):
        cam = Camera.from_dict(r["camera"])
        if not np.all(np.isfinite(cam.matrix)):
            raise UserError(f"{path}: run {r.get('name')!r} has a non-finite camera")
        out[r["name"]] = cam
    return out
