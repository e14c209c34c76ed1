"""``autocar info``: what is in a DICOM run or an artefact (geometry, timing, header, arrays)."""

from __future__ import annotations

from pathlib import Path

import typer

from ..common import console, user_errors


@user_errors
def info_command(
    paths: list[Path] = typer.Argument(..., help="XA DICOM files and/or autocar artefacts (*.zarr, *.npz)."),
):
    """Show the C-arm geometry and timing of XA runs, or the header and arrays of artefacts.

    A DICOM file's header claims (frames, rows, columns, bits) are checked against the pixel data it holds; a truncated or lying file is one error line.

    Examples:

      autocar info examples/run_a.dcm examples/run_b.dcm

      autocar info out/masks_a.zarr out/graphs.zarr
    """
    from rich.table import Table

    from stages.core.artefacts import artefact_attributes
    from stages.core.dicom_io import read_xa

    for path in paths:
        if path.suffix in (".zarr", ".npz"):
            attrs = artefact_attributes(path)
            table = Table(title=f"{path}", show_header=False)
            for key in ("kind", "schema_version", "writer", "inputs", "parameters", "created"):
                table.add_row(key, str(attrs.get(key)))
            console.print(table)
            continue
        run = read_xa(path, load_pixels=False)
        g, cam = run.geometry, run.geometry.camera()
        table = Table(title=f"{path} ({run.metadata.get('Manufacturer') or 'unknown maker'})", show_header=False)
        rows = [
            ("primary angle α (LAO+)", f"{g.alpha:.1f}°"), ("secondary angle β (CRA+)", f"{g.beta:.1f}°"),
            ("SID / SOD", f"{g.sid:.0f} / {g.sod:.0f} mm"),
            ("detector spacing", f"{g.spacing[0]:.4f} × {g.spacing[1]:.4f} mm (from {g.spacing_source})"),
            ("isocentre spacing", f"{cam.isocentre_spacing:.4f} mm/px"),
            ("image", f"{g.rows} × {g.cols}, {run.n_frames} frame(s), {run.bits_stored} bit"),
            ("frame time", f"{(run.frame_times_ms[1] - run.frame_times_ms[0]) if run.n_frames > 1 else 0:.1f} ms"),
            ("source position (LPS mm)", "(" + ", ".join(f"{v:.1f}" for v in cam.source) + ")"),
            ("viewing direction", "(" + ", ".join(f"{v:.3f}" for v in cam.view_dir) + ")"),
            ("ECG / phase", ecg_text(run.ecg)),
        ]
        for k, v in rows:
            table.add_row(k, v)
        console.print(table)


def ecg_text(ecg: dict | None) -> str:
    """ECG information in words: heart rate and R-wave times, rounded (not a raw dict)."""
    if not ecg:
        return "none"
    parts = []
    if ecg.get("heart_rate_bpm"):
        parts.append(f"heart rate {float(ecg['heart_rate_bpm']):.0f} bpm")
    rw = ecg.get("r_wave_time_vector_ms")
    if rw:
        times = ", ".join(f"{float(t):.0f}" for t in rw[:8]) + (f", … ({len(rw)} in all)" if len(rw) > 8 else "")
        parts.append(f"R waves at {times} ms")
    for key, value in ecg.items():
        if key not in ("heart_rate_bpm", "r_wave_time_vector_ms"):
            parts.append(f"{key} {value}")
    return "; ".join(parts)


def register(app: typer.Typer) -> None:
    app.command("info")(info_command)
