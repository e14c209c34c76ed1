"""``autocar evaluate``: metric tables for predictions, or the held-out-view check on real runs."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..common import console, set_threads, threads_option, user_errors


@user_errors
def evaluate_command(
    predictions: Optional[List[Path]] = typer.Argument(
        None, help="autocar.sparse-prediction artefacts (*.zarr), or folders holding them."),
    truth: Optional[List[Path]] = typer.Option(
        None, "-t", "--truth", help="Ground truth: prepared cases (*.zarr), sparse predictions or meshes "
        "(.stl/.ply/.obj), or folders of them; matched to predictions by case_id."),
    annotations: Optional[List[Path]] = typer.Option(
        None, "-a", "--annotations", help="Correspondence-annotation JSON files (or folders) for the 2D metrics."),
    output: Path = typer.Option(..., "-o", "--output", help="Output base name: writes BASE.zarr, .json, .csv and .md."),
    grid: float = typer.Option(0.5, "--grid", min=0.05, help="Voxel size (mm) of the common grid for the 3D metrics."),
    epsilon: float = typer.Option(3.0, "--epsilon", min=0.0, help="Accuracy / coverage threshold ε in mm."),
    heldout: Optional[Path] = typer.Option(
        None, "--heldout", help="Instead: held-out-view check on a folder of XA DICOM runs of a static scene "
        "(every pair, or every --views N runs, reconstructs; the other runs score)."),
    heldout_method: str = typer.Option("visual-hull", "--heldout-method",
                                       help="Reconstruction for --heldout: default (what reconstruct uses) | "
                                       "correspondence | visual-hull | sbp | dense."),
    heldout_calibrate: bool = typer.Option(True, "--heldout-calibrate/--no-heldout-calibrate",
                                           help="--heldout: self-calibrate each pair (or subset) from its own runs "
                                           "first."),
    heldout_fit_pose: bool = typer.Option(True, "--heldout-fit-pose/--no-heldout-fit-pose",
                                          help="--heldout: also score each held-out view after fitting its 6-DoF "
                                          "pose to the reconstruction (pose: fitted rows)."),
    heldout_views: int = typer.Option(2, "--views", min=2,
                                      help="--heldout: reconstruct from every subset of this many runs (2: every "
                                      "pair) and score on the runs left out."),
    heldout_max_subsets: Optional[int] = typer.Option(None, "--max-subsets", min=1,
                                                      help="--heldout: at most this many subsets, drawn with a fixed "
                                                      "seed (default: all of them)."),
    heldout_seg: str = typer.Option("vesselness", "--heldout-seg", help="Segmentation for --heldout: vesselness | unet | threshold."),
    weights: Optional[Path] = typer.Option(None, "--weights", help="Weights for a learned --heldout-method (default: the shipped file)."),
    threads: int = threads_option(),
):
    """Score predictions against ground truth (paper Eqs. 17–24) and tabulate them.

    3D: Dice, clDice, Chamfer, HD95 on a common 0.5 mm grid (+ centreline and radius error when both
    sides have graphs). 2D: coverage, EPE and accuracy (ε = 3 mm) on annotated correspondences.
    Prints a table and writes BASE.zarr (autocar.metrics), BASE.json, BASE.csv, BASE.md with the
    per-case rows and mean ± sd, median over cases.

    Examples:

      autocar evaluate preds/ -t cases/ -o out/metrics

      autocar evaluate hull.zarr -t case_0001_left.zarr -a case_0001.json -o out/case1

      autocar evaluate --heldout ../shared/data/phantom_xa -o out/heldout --heldout-method default

      autocar evaluate --heldout ../shared/data/phantom_xa -o out/heldout3 --heldout-method default --views 3
    """
    from rich.table import Table

    from stages.core.errors import UserError

    set_threads(threads)
    if heldout is not None:
        if predictions:
            raise UserError("--heldout runs on DICOM runs alone; give no prediction artefacts with it")
        return _heldout(heldout, output, epsilon, heldout_method, heldout_seg, weights, heldout_calibrate,
                        heldout_fit_pose, heldout_views, heldout_max_subsets)
    if not predictions:
        raise UserError("give prediction artefacts (or --heldout FOLDER)")

    from stages.evaluate import aggregate, evaluate_paths, write_metrics

    from ..common import progress

    with progress() as bar:
        task = bar.add_task("evaluating", total=None)
        rows = evaluate_paths(predictions, truth or (), annotations or (), voxel_size=grid, epsilon_mm=epsilon,
                              progress=lambda n, total: bar.update(task, completed=n, total=total))
    agg = aggregate(rows)
    paths = write_metrics(output, rows, agg, inputs=[str(p) for p in predictions] + [str(p) for p in truth or []]
                          + [str(p) for p in annotations or []], parameters={"grid_mm": grid, "epsilon_mm": epsilon})

    cols = list(agg)
    table = Table(title=f"{len(rows)} case(s)")
    table.add_column("case")
    for c in cols:
        table.add_column(c, justify="right")
    table.add_column("status")

    def fmt(v, c):
        if v is None or v != v:
            return "n/a"
        return f"{v:.2f}" if c.endswith("_mm") else f"{v:.3f}"

    for r in rows:
        status = ", ".join(r[k] for k in ("status", "graph_status", "correspondence_status") if r.get(k, "ok") != "ok") or "ok"
        table.add_row(r["case_id"], *[fmt(r.get(c), c) if c in r else "–" for c in cols], status)
    if len(rows) > 1:
        table.add_section()
        table.add_row("mean", *[fmt(agg[c]["mean"], c) for c in cols], "")
        table.add_row("sd", *[fmt(agg[c]["sd"], c) for c in cols], "")
        table.add_row("median", *[fmt(agg[c]["median"], c) for c in cols], "")
    console.print(table)
    console.print("wrote " + ", ".join(str(p) for p in paths.values()), highlight=False)


def _heldout(folder: Path, output: Path, epsilon: float, method: str = "visual-hull", seg_method: str = "vesselness",
             weights: Optional[Path] = None, calibrate: bool = True, fit_pose: bool = True, views: int = 2,
             max_subsets: Optional[int] = None):
    from rich.table import Table

    from stages.evaluate.heldout import run_heldout, write_heldout_report

    from ..common import progress

    with progress() as bar:
        task = bar.add_task("run pairs" if views == 2 else f"subsets of {views} runs", total=None)
        result = run_heldout(folder, epsilon_mm=epsilon, method=method, weights=weights, seg_method=seg_method,
                             calibrate=calibrate, fit_pose=fit_pose, views_per_subset=views, max_subsets=max_subsets,
                             progress=lambda n, total: bar.update(task, completed=n, total=total))
    base = output.with_suffix("") if output.suffix in (".json", ".md") else output
    json_path, md_path = base.with_name(base.name + ".json"), base.with_name(base.name + ".md")
    write_heldout_report(result, json_path, md_path)
    method = result["method"]
    table = Table(title=f"held-out-view check, {method} from {views} views on {seg_method} masks, "
                        f"{len(result['subsets'])} subsets of {len(result['views'])} runs, ε = {epsilon:g} mm")
    for c in ("pose", "rows", "coverage mean ± sd", "median", "distance mm mean ± sd", "median"):
        table.add_column(c, justify="right")
    for lab, s in result["summary"].items():
        c, d = s["coverage"], s["distance_mm"]
        table.add_row(lab, str(s["n"]), f"{c['mean']:.3f} ± {c['sd'] or 0:.3f}", f"{c['median']:.3f}",
                      f"{d['mean']:.2f} ± {d['sd'] or 0:.2f}", f"{d['median']:.2f}")
    console.print(table)
    own = result.get("own_summary") or {}
    if own.get("n"):
        console.print(f"own {'two' if views == 2 else views} views: mean reprojection distance {own['distance_mm_mean']:.2f} mm "
                      f"(median {own['distance_mm_median']:.2f}) over {own['n']} views", highlight=False)
    moved = result.get("table_offsets_mm") or {}
    if moved:
        console.print(f"runs placed on {result['views'][0]}'s table (header table positions; x, y, z mm): "
                      + ", ".join(f"{n} ({d[0]:+.1f}, {d[1]:+.1f}, {d[2]:+.1f})" for n, d in moved.items()),
                      highlight=False)
    cal = result.get("calibration") or {}
    if cal:
        console.print(f"self-calibration applied in {sum(bool(v.get('applied')) for v in cal.values())} of "
                      f"{len(cal)} {'pairs' if views == 2 else 'subsets'}", highlight=False)
    console.print(f"wrote {json_path}, {md_path}", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("evaluate")(evaluate_command)
