"""``autocar prep-ct``: label volumes, meshes or procedural trees → prepared cases (mesh, centreline, labels)."""

from __future__ import annotations

from pathlib import Path
from typing import List, Optional

import typer

from ..common import check_choice, console, progress, set_threads, threads_option, user_errors


def _floats(text: Optional[str], name: str, n: int = 3):
    from stages.core.errors import UserError

    if text is None:
        return None
    try:
        vals = [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise UserError(f"{name} must be comma-separated numbers, got {text!r}") from None
    if len(vals) == 1:
        vals = vals * n
    if len(vals) != n:
        raise UserError(f"{name} needs {n} values (or one for all), got {text!r}")
    return vals


@user_errors
def prep_ct_command(
    inputs: Optional[List[Path]] = typer.Argument(None, help="Label volumes (.nii/.nii.gz/.nrrd/.nhdr/.npy) or surface meshes (.stl/.ply/.obj, world mm LPS)."),
    output: Path = typer.Option(..., "-o", "--output", help="Artefact (*.zarr, one tree) or folder (several cases: <case>_<side>.zarr + .png). A folder must be new or empty unless --force or --resume."),
    synthetic: int = typer.Option(0, "--synthetic", min=0, help="Generate and prepare N procedural cases (two trees each)."),
    seed: int = typer.Option(0, "--seed", help="First seed of --synthetic; case i uses seed + i."),
    jobs: int = typer.Option(1, "--jobs", "-j", min=1, help="Cases prepared in parallel (processes)."),
    spacing: Optional[str] = typer.Option(None, "--spacing", help="Voxel size of .npy inputs, mm: 'sx,sy,sz' or one value."),
    origin: Optional[str] = typer.Option(None, "--origin", help="World position (LPS mm) of voxel (0,0,0) of .npy inputs."),
    side: Optional[str] = typer.Option(None, "--side", metavar="[left|right]", help="The tree of an input holding one tree only."),
    label_voxel: float = typer.Option(0.5, "--label-voxel", min=0.1, help="Sparse label voxel size, mm."),
    band: float = typer.Option(1.0, "--band", min=0.0, help="Band of outside (negative) voxels kept around the lumen, mm."),
    sigma: float = typer.Option(0.2, "--sigma", min=0.0, help="Gaussian filter on the 0.1 mm upsampled mask, mm."),
    no_preview: bool = typer.Option(False, "--no-preview", help="Skip the PNG preview beside each artefact."),
    force: bool = typer.Option(False, "--force", help="Output folder: first remove what prep-ct wrote there (nothing else), then prepare every case."),
    resume: bool = typer.Option(False, "--resume", help="Output folder: keep every case whose inputs and parameters match, prepare the others (add to the folder)."),
    threads: int = threads_option(),
):
    """Prepare coronary trees for training: lumen mesh, centreline graph and sparse labels per tree.

    Each input is split into its left and right trees (label 1 = left, 2 = right; otherwise connected components, the one further to the patient's left (LPS +x) being the left tree), and each tree becomes one prepared case (autocar.prepared-case) with a PNG preview beside it. A case that fails is reported and skipped; the others go on.

    An output folder follows the policy of every autocar output folder: a non-empty one is refused unless --force or --resume; a rerun whose cases are all there and up to date does nothing (exit 0); while the batch runs the folder holds RUNNING, and summary.json replaces it at the end.

    Examples:

      autocar prep-ct mask.nii.gz -o cases/

      autocar prep-ct mask.npy --spacing 0.4,0.4,0.5 -o cases/

      autocar prep-ct --synthetic 20 --seed 0 --jobs 2 -o data/prepared

      autocar prep-ct --synthetic 20 --seed 20 --jobs 2 -o data/prepared --resume
    """
    from rich.table import Table

    from stages.core.errors import UserError
    from stages.prep_ct import PrepParams, run_batch
    from stages.prep_ct.batch import prepare_folder

    if not inputs and synthetic == 0:
        raise UserError("give input files or --synthetic N")
    if inputs and synthetic:
        raise UserError("give input files or --synthetic N, not both")
    check_choice(side, ("left", "right"), "--side")
    set_threads(threads)
    params = PrepParams(label_voxel_mm=label_voxel, band_mm=band, sigma_mm=sigma, preview=not no_preview)
    sp, org = _floats(spacing, "--spacing"), _floats(origin, "--origin")
    n_cases = synthetic or len(inputs)
    if synthetic and output.suffix == ".zarr":
        raise UserError(f"{output}: --synthetic writes two trees per case; give an output folder")
    if n_cases > 1 and output.suffix == ".zarr":
        raise UserError(f"{output}: several cases need an output folder, not one artefact name")
    if force and resume:
        raise UserError("--force and --resume exclude each other: --force starts afresh, --resume reuses")
    if synthetic:
        tasks = [{"kind": "synthetic", "seed": seed + i, "output": str(output), "params": params.to_dict(),
                  "label": f"synthetic seed {seed + i}"} for i in range(synthetic)]
    else:
        for p in inputs:
            if not p.exists():
                raise UserError(f"{p}: no such file")
        tasks = [{"kind": "file", "path": str(p), "output": str(output), "params": params.to_dict(),
                  "spacing": sp, "origin": org, "side": side, "label": str(p)} for p in inputs]

    to_folder = output.suffix != ".zarr"
    failures = []
    written: list[str] = []
    kept: list[str] = []
    with progress() as bar:
        task_id = bar.add_task("prep-ct", total=len(tasks))

        def done(result):
            task, paths, error = result
            if error:
                failures.append((task["label"], error))
                console.print(f"[yellow]skipped[/] {task['label']}: {error}", highlight=False)
            written.extend(paths)
            bar.advance(task_id)

        if to_folder:
            r = prepare_folder(tasks, output, force=force, resume=resume, jobs=jobs, on_done=done)
            kept = r["kept"]
            bar.update(task_id, completed=len(tasks))
        else:  # one artefact: replaced atomically
            run_batch(tasks, jobs=jobs, on_done=done)
    if to_folder and r["skipped"]:
        console.print(f"up to date: {len(kept)} prepared case(s) in {output}, nothing to do", highlight=False)
        return

    if written:
        from stages.core.prepared_case import PreparedCase

        table = Table(title=f"prepared cases ({len(written)})")
        for col in ("artefact", "side", "faces", "nodes", "bifurcations", "lumen voxels", "labels"):
            table.add_column(col, justify="left" if col == "artefact" else "right")
        import numpy as np

        for path in sorted(written)[:40]:
            c = PreparedCase.load(path)
            deg = np.bincount(c.edges.ravel(), minlength=len(c.nodes)) if len(c.edges) else np.zeros(1, int)
            table.add_row(Path(path).name, c.side, str(len(c.faces)), str(len(c.nodes)),
                          str(int(np.maximum(deg - 2, 0).sum())),
                          str(int(c.labels.features["occupancy"].sum())), str(len(c.labels)))
        console.print(table)
        if len(written) > 40:
            console.print(f"… and {len(written) - 40} more")
    console.print(f"wrote {len(written)} prepared case(s) to {output}"
                  + (f"; kept {len(kept)} up-to-date case(s) there" if kept else "")
                  + (f"; {len(failures)} input(s) failed" if failures else ""), highlight=False)
    if failures and not written and not kept:
        raise typer.Exit(code=1)


def register(app: typer.Typer) -> None:
    app.command("prep-ct")(prep_ct_command)
