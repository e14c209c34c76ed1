"""``autocar calibrate``: refine the C-arm geometry of two or more runs from their vessels."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..common import check_choice, choice_option, console, force_option, refuse_existing, set_threads, threads_option, user_errors

SEG_METHODS = ("vesselness", "unet", "threshold")


@user_errors
def calibrate_command(
    runs: List[Path] = typer.Argument(..., help="Two or more XA runs: DICOM files, frame folders or .npy/.npz stacks."),
    output: Path = typer.Option(..., "-o", "--output", help="autocar.calibration JSON file to write."),
    geometry: Optional[List[Path]] = typer.Option(
        None, "--geometry", help="Geometry JSON per run, in the order of the runs (frame folders / stacks; see docs/CALIBRATION.md)."),
    static: bool = typer.Option(False, "--static", help="The scene does not move between runs (a phantom): calibrate "
                                "more than two runs jointly."),
    reference: int = typer.Option(0, "--reference", help="Index of the run held fixed (0 = the first)."),
    seg: str = choice_option("vesselness", "--seg", choices=SEG_METHODS, help="Segmentation of each run's contrast frame."),
    max_shift_mm: float = typer.Option(40.0, "--max-shift-mm", min=0.5, help="Bound of the detector shift (mm at the isocentre)."),
    max_angle_deg: float = typer.Option(8.0, "--max-angle-deg", min=0.1, help="Bound of the primary/secondary angle corrections."),
    force: bool = force_option(),
    threads: int = threads_option(),
):
    """Self-calibrate the runs' geometry from the vessels.

    Runs whose table moved (the header's table position, or TablePosition in a geometry JSON) are first placed on the first run's table. Per run (all but the reference): detector shift, in-plane rotation, primary/secondary angle corrections and SID, bounded and robust; what two views cannot observe is held fixed (docs/CALIBRATION.md). Writes the autocar.calibration JSON; the last lines give every correction and the residual before → after. A correction that does not lower the residual or ends at a bound is refused with a warning.

    Examples:

      autocar calibrate run_a.dcm run_b.dcm -o calib.json

      autocar calibrate ../shared/data/phantom_xa/IM*.dcm --static -o phantom_calib.json
    """
    check_choice(seg, SEG_METHODS, "--seg")
    refuse_existing(output, force)
    set_threads(threads)
    from stages.calibration.model import DEFAULT_BOUNDS
    from stages.calibration.stage import run_calibration, write_calibration

    bounds = dict(DEFAULT_BOUNDS, shift_mm=max_shift_mm, angle_deg=max_angle_deg)
    result = run_calibration(runs, geometry, static=static, reference=reference, seg_method=seg, bounds=bounds)
    write_calibration(output, result, inputs=[str(r) for r in runs],
                      parameters={"static": static, "reference": reference, "seg": seg, "bounds": bounds})
    for line in result["summary_lines"]:
        console.print(line, highlight=False, soft_wrap=True)
    console.print(f"wrote {output} ({result['report'].get('seconds', 0):.1f} s)", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("calibrate")(calibrate_command)
