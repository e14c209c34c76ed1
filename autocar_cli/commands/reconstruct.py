"""``autocar reconstruct``: two XA runs → time-resolved 3D coronary model, end to end."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..common import console, user_errors


@user_errors
def reconstruct_command(
    run_a: Path = typer.Argument(..., help="First run: XA DICOM file (or frame folder/stack with --geometry-a)."),
    run_b: Path = typer.Argument(..., help="Second run, from another C-arm angle (≥ 10° apart)."),
    output: Path = typer.Option(Path("autocar-out"), "-o", "--output", help="Output folder (artefacts of every stage, exports, report.html)."),
    method: str = typer.Option("sbp", "--method", help="3D prediction: 'sbp' (the shipped network), 'visual-hull' or 'dense' (the L2-style dense back-projection baseline)."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="Weights of the learned --method (default: the shipped file)."),
    seg_method: str = typer.Option("unet", "--seg-method", help="Vessel segmentation: unet | vesselness | threshold."),
    keyframes: int = typer.Option(7, "--keyframes", "-k", min=1, help="Number of phase-matched key-frame pairs."),
    geometry_a: Optional[Path] = typer.Option(None, "--geometry-a", help="Geometry JSON for run A (when it is not DICOM)."),
    geometry_b: Optional[Path] = typer.Option(None, "--geometry-b", help="Geometry JSON for run B."),
    side: str = typer.Option("left", "--side", help="Tree side the SBP network is conditioned on: left | right."),
    align_views: bool = typer.Option(True, "--align-views/--no-align-views",
                                     help="Per key frame, shift run B's image to be epipolar-consistent with run A "
                                          "(corrects the heart's motion between the two acquisitions)."),
):
    """Reconstruct the coronary tree from two cine runs: segment → key frames → 3D prediction →
    graph optimisation → .vtp/.stl/.json per key frame, overlays and report.html. Prints stage timings."""
    from rich.table import Table

    from stages.reconstruct import reconstruct

    summary = reconstruct(run_a, run_b, output, geometry_a=geometry_a, geometry_b=geometry_b, method=method,
                          weights=weights, seg_method=seg_method, k=keyframes, side=side,
                          align_views=align_views,
                          progress=lambda msg: console.print(f"[cyan]•[/] {msg}"))
    table = Table(title="stage timings")
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    for name, seconds in summary["timings"]:
        table.add_row(name, f"{seconds:.2f}")
    table.add_row("[bold]total[/]", f"[bold]{summary['total_seconds']:.2f}[/]")
    console.print(table)
    shifts = [s for s in summary.get("view_b_shifts") or [] if s]
    if shifts:
        moved = [s["across_mm"] for s in shifts if s["shift_px"] != [0.0, 0.0]]
        console.print(f"run B aligned to run A on {len(moved)} of {len(shifts)} key frame(s)"
                      + (f" (shift across the epipolar lines {min(moved):+.2f} … {max(moved):+.2f} mm)" if moved else
                         ": the header geometry already matched"))
    console.print(f"wrote {output}/report.html and the artefacts of every stage in {output}")


def register(app: typer.Typer) -> None:
    app.command("reconstruct")(reconstruct_command)
