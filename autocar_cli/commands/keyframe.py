"""``autocar keyframe``: two XA runs → K phase-matched, contrast-filled frame pairs (+ a PNG plot)."""

from __future__ import annotations

from pathlib import Path

import typer

from ..common import (check_choice, choice_option, console, force_option, refuse_existing, require_inputs, set_threads,
                      threads_option, user_errors)
from .segment import SEG_METHODS


@user_errors
def keyframe_command(
    run_a: Path = typer.Argument(..., help="First XA run (DICOM, image folder or .npy/.npz stack)."),
    run_b: Path = typer.Argument(..., help="Second XA run."),
    output: Path = typer.Option(..., "-o", "--output", help="autocar.keyframes artefact to write (*.zarr); a PNG plot goes beside it."),
    masks: list[Path] = typer.Option(None, "--masks", help="autocar.vessel-masks of run A then run B (from `autocar segment`); segmented here if omitted."),
    k: int = typer.Option(7, "-k", "--k", min=1, help="Number of key-frame pairs (phase bins over one cycle)."),
    fill_fraction: float = typer.Option(0.95, "--fill-fraction", min=0.0, max=1.0, help="A chosen frame must reach this fraction of its run's maximal measured contrast filling (0.95 of the measure ≈ 0.9 of the true lumen filling on simulated runs). Where the frames that reach it leave a cardiac phase without a matched pair, it is lowered for that run in 0.05 steps, down to 0.85, with a warning."),
    method: str = choice_option("unet", "--method", choices=SEG_METHODS, help="Segmentation method when masks are not given."),
    force: bool = force_option(),
    threads: int = threads_option(),
):
    """Pick K frame pairs of two runs at matched cardiac phase, all filled with contrast.

    Phase comes from the ECG (DICOM RWaveTimeVector) when present, otherwise from the periodic motion of the vessel masks. Writes the autocar.keyframes artefact and <stem>.png (phase curves, filling, chosen frames).

    Examples:

      autocar keyframe run_a.dcm run_b.dcm -o keyframes.zarr

      autocar keyframe run_a.dcm run_b.dcm --masks masks_a.zarr --masks masks_b.zarr -k 5 -o kf.zarr
    """
    from rich.table import Table

    from stages.core.errors import UserError

    check_choice(method, SEG_METHODS, "--method")
    masks = list(masks or [])
    if len(masks) not in (0, 2):
        raise UserError(f"--masks: give two artefacts (run A then run B), got {len(masks)}")
    for m in masks:
        if not m.exists():
            raise UserError(f"{m}: no such artefact (--masks)")
    require_inputs(run_a, run_b)
    refuse_existing(output, force)
    set_threads(threads)
    from stages.keyframe import keyframe_pairs, plot_keyframes, write_keyframes

    res = keyframe_pairs(run_a, run_b, masks[0] if masks else None, masks[1] if masks else None, k=k,
                         fill_fraction=fill_fraction, method=method)
    write_keyframes(output, res)
    stem = output.name[:-5] if output.name.endswith(".zarr") else output.name
    png = plot_keyframes(output.parent / f"{stem}.png", res)
    table = Table(title=f"{k} key-frame pairs")
    for col in ("#", "frame A", "frame B", "phase", "phase diff"):
        table.add_column(col, justify="right")
    for n, ((i, j), p, e) in enumerate(zip(res["pairs"], res["phase"], res["phase_error"])):
        table.add_row(str(n), str(i), str(j), f"{p:.3f}", f"{e:.3f}")
    console.print(table)
    for key in "ab":
        e = res["estimates"][key]
        console.print(f"run {key}: phase from {e['source']}, period {e['info'].get('period_frames', float('nan')):.1f} "
                      f"frames, {int(e['filled'].sum())}/{len(e['filled'])} frames filled", highlight=False)
    for w in res["warnings"]:
        console.print(f"[yellow]warning:[/] {w}", highlight=False)
    console.print(f"wrote {output} and {png}", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("keyframe")(keyframe_command)
