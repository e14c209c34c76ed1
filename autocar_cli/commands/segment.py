"""``autocar segment``: XA run → per-frame vessel probability and mask (+ overlay PNGs and a GIF)."""

from __future__ import annotations

from pathlib import Path

import typer

from ..common import (check_choice, choice_option, console, force_option, refuse_existing, require_inputs, set_threads,
                      threads_option, user_errors)

SEG_METHODS = ("unet", "vesselness", "threshold")  # = stages.segment.infer.METHODS (tests/test_cli_help.py checks)


@user_errors
def segment_command(
    run: Path = typer.Argument(..., help="XA run: DICOM file, folder of frame images, or .npy/.npz stack (T×H×W)."),
    output: Path = typer.Option(..., "-o", "--output", help="autocar.vessel-masks artefact to write (*.zarr)."),
    method: str = choice_option("unet", "--method", choices=SEG_METHODS,
                                help="The shipped network (unet), Frangi vesselness, or top-hat + Otsu threshold."),
    geometry: Path = typer.Option(None, "--geometry", help="Geometry JSON for image folders / stacks (alpha, beta, sid, sod, spacing, frame_time_ms)."),
    threshold: float = typer.Option(None, "--threshold", help="Override the method's threshold (unet: probability, default 0.5)."),
    weights: Path = typer.Option(None, "--weights", help="Other network weights (default: the shipped stages/weights/seg.pt)."),
    no_fov: bool = typer.Option(False, "--no-fov", help="Do not estimate and apply the field of view (collimator)."),
    no_overlays: bool = typer.Option(False, "--no-overlays", help="Write only the artefact (no PNG/GIF)."),
    force: bool = force_option(),
    threads: int = threads_option(),
):
    """Segment the vessels of every frame of an XA run.

    Writes the autocar.vessel-masks artefact (prob T×H×W float16, mask T×H×W uint8, fov H×W) and, beside it, <stem>_fNNN.png overlays and <stem>.gif (an animated preview).

    Examples:

      autocar segment run_a.dcm -o masks_a.zarr

      autocar segment frames/ --geometry frames/geometry.json -o masks.zarr --method vesselness
    """
    import time

    check_choice(method, SEG_METHODS, "--method")
    require_inputs(run, geometry, weights)
    refuse_existing(output, force)
    set_threads(threads)
    from stages.segment import save_overlays, segment_run, write_masks

    t0 = time.time()
    res = segment_run(run, method=method, geometry=geometry, threshold=threshold, weights=weights, fov=not no_fov)
    dt = time.time() - t0
    write_masks(output, res)
    files = [output]
    if not no_overlays:
        stem = output.name[:-5] if output.name.endswith(".zarr") else output.name
        files += save_overlays(res["run"].frames, res["mask"], output.parent / stem, fov=res["fov"])
    T = res["mask"].shape[0]
    area = res["mask"].reshape(T, -1).mean(1)
    console.print(f"{run}: {T} frame(s) {res['mask'].shape[1]}×{res['mask'].shape[2]}, method {method}, "
                  f"{dt:.1f} s ({T / max(dt, 1e-9):.1f} frames/s); vessel fraction per frame "
                  f"min {area.min():.3f} / max {area.max():.3f}; field of view {res['fov'].mean():.0%} of the image",
                  highlight=False)
    console.print(f"wrote {len(files)} file(s): {output} and overlays beside it", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("segment")(segment_command)
