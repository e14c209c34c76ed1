"""``autocar reconstruct``: two XA runs → time-resolved 3D coronary model, end to end."""

from __future__ import annotations

import math
from pathlib import Path
from typing import List, Optional

import typer

from ..common import (Steps, check_choice, choice_option, console, module_constants, set_threads, threads_option,
                      user_errors)

METHODS, DEFAULT_METHOD = module_constants("stages.methods3d", "METHODS", "DEFAULT_METHOD")  # without numpy

SEG_METHODS = ("unet", "vesselness", "threshold")  # = stages.reconstruct.SEG_METHODS (that module is heavy)
SIDES = ("left", "right")


@user_errors
def reconstruct_command(
    run_a: Path = typer.Argument(..., help="First run: XA DICOM file (or frame folder/stack with --geometry-a)."),
    run_b: Path = typer.Argument(..., help="Second run, from another C-arm angle (≥ 10° apart)."),
    more_runs: Optional[List[Path]] = typer.Argument(
        None, help="Further runs of the same study (same injection, other angles): their frames at each key frame's "
                   "cardiac phase add depth evidence to the 3D step (--method correspondence)."),
    output: Path = typer.Option(Path("autocar-out"), "-o", "--output",
                                help="Output folder (artefacts of every stage, exports, report.html). Must be new or "
                                     "empty unless --force or --resume."),
    method: str = choice_option(DEFAULT_METHOD, "--method", choices=METHODS,
                                help="3D prediction: 'sbp' (the shipped network), 'correspondence' (two-view centreline matching), "
                                     "'visual-hull' (geometric baseline) or 'dense' (L2-style dense back-projection)."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="Weights of the learned --method (default: the shipped file)."),
    seg_method: str = choice_option("unet", "--seg-method", choices=SEG_METHODS,
                                    help="Vessel segmentation: the shipped network, Frangi vesselness or top-hat threshold."),
    keyframes: int = typer.Option(7, "--keyframes", "-k", min=1, help="Number of phase-matched key-frame pairs."),
    geometry_a: Optional[Path] = typer.Option(None, "--geometry-a", help="Geometry JSON for run A (when it is not DICOM)."),
    geometry_b: Optional[Path] = typer.Option(None, "--geometry-b", help="Geometry JSON for run B."),
    geometry_more: Optional[List[Path]] = typer.Option(
        None, "--geometry-more", help="Geometry JSON of a further run (repeat once per further run, in order)."),
    side: str = choice_option("left", "--side", choices=SIDES,
                              help="Tree side the SBP network is conditioned on."),
    align_views: bool = typer.Option(True, "--align-views/--no-align-views",
                                     help="Per key frame, shift run B's image to be epipolar-consistent with run A "
                                          "(corrects the heart's motion between the two acquisitions)."),
    calibrate: bool = typer.Option(False, "--calibrate/--no-calibrate",
                                   help="Refine run B's C-arm geometry from the vessels of both runs before the 3D "
                                        "step (the shift across the epipolar lines; reported with the residual before "
                                        "and after). Off by default: on a beating heart it cannot tell a header offset from "
                                        "motion between the runs, which view alignment follows per key frame; use it on "
                                        "static scenes (docs/CALIBRATION.md)."),
    qca: bool = typer.Option(True, "--qca/--no-qca",
                             help="Quantitative coronary analysis of the result (named vessels, diameter profiles, "
                                  "stenoses, best viewing angles): qca.json, qca.csv, plots and a report section."),
    force: bool = typer.Option(False, "--force", help="Reuse a non-empty output folder: first remove what autocar wrote there (nothing else)."),
    resume: bool = typer.Option(False, "--resume", help="Continue in a non-empty output folder: keep every stage whose inputs and parameters match, recompute the rest."),
    threads: int = threads_option(),
):
    """Reconstruct the coronary tree from two (or more) cine runs: segment → key frames → 3D prediction → graph optimisation → .vtp/.stl/.json per key frame, overlays and report.html.

    Run A is the reference frame and run A + B give the key-frame pairs; every further run of the same study adds its frame of the same cardiac phase as evidence (a third view rejects most of the ghosts two views cannot tell from vessels). A run is refused if given twice.

    With --threads N, up to N key frames are predicted (the correspondence method) and graphed at once; the results do not depend on N.

    Every input and option is checked before anything is written. While the run works the output folder holds a file named RUNNING; summary.json replaces it at the end. The last lines say how good the result is by its own checks (pieces, ghosts, catheter-like branches, reprojection distance).

    Examples:

      autocar reconstruct run_a.dcm run_b.dcm -o out

      autocar reconstruct run_a.dcm run_b.dcm -o out --method visual-hull --seg-method vesselness

      autocar reconstruct run_a.dcm run_b.dcm -o out --resume -k 5

      autocar reconstruct run_a.dcm run_b.dcm run_c.dcm -o out

      autocar reconstruct frames_a/ frames_b/ --geometry-a a.json --geometry-b b.json -o out
    """
    from rich.table import Table

    from stages.core.errors import UserError

    check_choice(method, METHODS, "--method")
    check_choice(seg_method, SEG_METHODS, "--seg-method")
    check_choice(side, SIDES, "--side")
    if force and resume:
        raise UserError("--force and --resume exclude each other: --force starts afresh, --resume reuses")
    existing = "force" if force else "resume" if resume else "refuse"
    set_threads(threads)
    from stages.reconstruct import reconstruct

    with Steps() as steps:
        summary = reconstruct(run_a, run_b, output, geometry_a=geometry_a, geometry_b=geometry_b, method=method,
                              weights=weights, seg_method=seg_method, k=keyframes, side=side,
                              align_views=align_views, qca=qca, calibrate=calibrate, more_runs=more_runs or (),
                              more_geometries=geometry_more or (),
                              existing=existing, workers=threads,
                              progress=lambda msg: console.print(f"[cyan]•[/] {msg}", highlight=False), step=steps)
    table = Table(title="stage timings")
    table.add_column("stage")
    table.add_column("seconds", justify="right")
    for name, seconds in summary["timings"]:
        table.add_row(name, f"{seconds:.2f}")
    table.add_row("[bold]total[/]", f"[bold]{summary['total_seconds']:.2f}[/]")
    console.print(table)
    shifts = [s for s in summary.get("view_b_shifts") or [] if s]
    aligned = [s for s in shifts if "across_mm" in s]
    if aligned:
        moved = [s["across_mm"] for s in aligned if s["shift_px"] != [0.0, 0.0]]
        console.print(f"run B aligned to run A on {len(moved)} of {len(aligned)} key frame(s)"
                      + (f" (shift across the epipolar lines {min(moved):+.2f} … {max(moved):+.2f} mm)" if moved else
                         ": the header geometry already matched"), highlight=False)
    by_further = [math.hypot(*s["further_runs_px"]) for s in shifts if "further_runs_px" in s]
    if by_further:
        console.print(f"run B placed where the further runs see the tree (breathing between the runs) on "
                      f"{len(by_further)} key frame(s): {min(by_further):.1f} … {max(by_further):.1f} px", highlight=False)
    if summary.get("reused"):
        console.print(f"reused from the earlier run: {', '.join(summary['reused'])}", highlight=False)
    for name, d in (summary.get("table_offsets_mm") or {}).items():
        console.print(f"{name}: the table moved ({d[0]:+.1f}, {d[1]:+.1f}, {d[2]:+.1f}) mm (x, y, z) from run A's; "
                      "its camera was placed accordingly", highlight=False)
    for row in (summary.get("runs") or [])[2:]:
        used = sum(f is not None for f in row["frames"])
        shares = [c for c in row.get("consistency") or [] if c is not None]
        moved = [s for s in row.get("shift_px") or [] if s and any(s)]
        agree = (f" ({100 * min(shares):.0f}–{100 * max(shares):.0f} % of runs A and B's model on its vessels)"
                 if shares else "")
        shift = (f", its image shifted {max(abs(v) for s in moved for v in s)} px at most to meet them" if moved else "")
        console.print(f"{row['run']} ({Path(row['path']).name}): evidence in {used} of {len(row['frames'])} key "
                      f"frame(s){agree}{shift}", highlight=False)
    if summary.get("calibration"):
        from stages.calibration.stage import summary_lines

        for line in summary_lines(summary["calibration"]):
            console.print(line, highlight=False)
    _print_qca(summary.get("qca"))
    _print_quality(summary["quality"])
    console.print(f"wrote {output}/report.html and the artefacts of every stage in {output}", highlight=False)


def _print_qca(qca: dict | None) -> None:
    """One line: the named vessels and their lesions (details in qca.json and the report)."""
    if qca is None:
        return
    if not qca["vessels"]:
        console.print(f"QCA: no vessel analysed ({qca.get('message') or 'no usable tree'})", highlight=False)
        return
    console.print("QCA: " + ", ".join(f"{v['name']} {v['length_mm']:.0f} mm"
                                      + (f" ({v['lesions']} lesion{'s' if v['lesions'] > 1 else ''})" if v["lesions"] else "")
                                      for v in qca["vessels"]) + " (qca.json, qca.csv)", highlight=False)
    unconfirmed = sum(v.get("unconfirmed_narrowings", 0) for v in qca["vessels"])
    if unconfirmed:
        console.print(f"QCA: {unconfirmed} narrowing(s) of the model that the views do not confirm, not reported as "
                      "lesions (qca.json: unconfirmed_narrowings)", highlight=False)


def _print_quality(quality: dict) -> None:
    """Per key frame one line of the result's own checks, then the verdict line."""
    for f in quality["frames"]:
        pieces = f["pieces"]
        rep = ", ".join(f"{v} {'n/a' if d is None else f'{d:.2f}'} mm" for v, d in f["reprojection_mm"].items())
        sizes = ", ".join(("%.0f mm" % p["length_mm"]) + ("" if i == 0 else " at %.0f mm" % p["distance_mm"])
                          for i, p in enumerate(pieces))
        line = f"key frame {f['key']}: {len(pieces)} piece(s) ({sizes}); reprojection {rep or 'n/a'}"
        if f["problems"]:
            line += " — " + "; ".join(f["problems"])
        console.print(line, highlight=False)
    style = "green" if quality["passed"] else "bold yellow"
    console.print(f"[{style}]{_markup_escape(quality['verdict'])}[/]")


def _markup_escape(text: str) -> str:
    from rich.markup import escape

    return escape(text)


def register(app: typer.Typer) -> None:
    app.command("reconstruct")(reconstruct_command)
