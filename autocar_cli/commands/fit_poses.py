"""``autocar fit-poses``: pose statistics of a DICOM archive (or the built-in default model)."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..common import console, user_errors


@user_errors
def fit_poses_command(
    dicom_dir: Optional[Path] = typer.Argument(None, help="Folder of XA DICOM runs, searched recursively."),
    output: Path = typer.Option(..., "-o", "--output", help="Pose-model artefact to write (*.zarr); a PNG figure is written beside it."),
    clusters: int = typer.Option(9, "--clusters", "-k", min=2, help="Number of K-means clusters on (α, β)."),
    default: bool = typer.Option(False, "--default", help="Write the built-in clinical model (nine standard projections) instead of fitting a folder."),
    uniform: bool = typer.Option(False, "--uniform", help="Write the uniform-sphere ablation model (paper L7) instead."),
    seed: int = typer.Option(0, "--seed", help="Random seed (K-means initialisation, default-model draws)."),
):
    """Fit the C-arm pose model used for pose-domain adaptation.

    Reads every run's (α, β, SID, SOD, pixel spacing, size), clusters (α, β) with K-means and keeps every pose with its cluster. Training draws pairs from two distinct clusters, one recorded pose each.

    Examples:

      autocar fit-poses /data/xa_archive -o poses.zarr

      autocar fit-poses --default -o poses.zarr
    """
    from rich.table import Table

    from stages.core.errors import UserError
    from stages.poses import PoseModel, fit_poses

    if sum([dicom_dir is not None, default, uniform]) != 1:
        raise UserError("give exactly one of DICOM_DIR, --default or --uniform")
    skipped = []
    if default:
        model, inputs = PoseModel.default(seed=seed), ["built-in default"]
    elif uniform:
        model, inputs = PoseModel.uniform_sphere(seed=seed), ["built-in uniform sphere"]
    else:
        model, skipped = fit_poses(dicom_dir, n_clusters=clusters, seed=seed)
        inputs = [str(dicom_dir)]
    params = {"clusters": model.n_clusters, "seed": seed, "default": default, "uniform": uniform}
    model.save(output, inputs=inputs, parameters=params)
    figure = model.save_figure(Path(output).with_suffix(".png"))

    table = Table(title=f"pose model {output}: {len(model)} poses")
    for col in ("cluster", "name", "α °", "β °", "poses", "SID mm", "SOD mm", "spacing mm"):
        table.add_column(col, justify="right" if col not in ("name",) else "left")
    for row in model.cluster_summary():
        table.add_row(str(row["cluster"]), row["name"], f"{row['alpha']:.1f}", f"{row['beta']:.1f}", str(row["count"]),
                      f"{row['sid']:.0f}", f"{row['sod']:.0f}", f"{row['spacing']:.3f}")
    console.print(table)
    if skipped:
        console.print(f"[yellow]skipped {len(skipped)} file(s)[/]:")
        for path, reason in skipped:
            console.print(f"  {path}: {reason}", highlight=False)
    console.print(f"wrote {output} and {figure}")


def register(app: typer.Typer) -> None:
    app.command("fit-poses")(fit_poses_command)
