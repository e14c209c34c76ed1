"""``autocar qca``: 3D quantitative coronary analysis of a reconstruction folder (qca.json, qca.csv, plots)."""

from __future__ import annotations

from pathlib import Path

import typer

from ..common import console, set_threads, threads_option, user_errors


@user_errors
def qca_command(
    recon_dir: Path = typer.Argument(..., help="Folder written by `autocar reconstruct` (holds graphs.zarr)."),
    frame: str = typer.Option(None, "--frame", help="Key frame to analyse (a key of graphs.zarr, e.g. 03). Default: the end-diastolic one."),
    min_ds: float = typer.Option(20.0, "--min-ds", min=1.0, max=99.0, help="Report lesions from this % diameter stenosis."),
    smooth: float = typer.Option(1.0, "--smooth", min=0.0, help="Gaussian σ (mm) applied to the radius profile before grading."),
    radius: str = typer.Option("frame", "--radius", metavar="[frame|mean]", help="Radii of the analysed key frame, or each node's mean over the key frames."),
    plots: bool = typer.Option(True, "--plots/--no-plots", help="Write qca_profiles.png, qca_views.png and qca_3d.png."),
    views: bool = typer.Option(True, "--views/--no-views", help="Compute foreshortening/overlap maps and the best view per lesion and segment."),
    threads: int = threads_option(),
):
    """Name the vessels, measure their diameter profiles, grade the stenoses and find the best C-arm views.

    Reads RECON_DIR/graphs.zarr (and keyframes.zarr, predictions.zarr when present); writes qca.json (kind autocar.qca, schema 1; a `vessels` list with `name`, `length_mm` and `lesions`, each with `ds_percent`, `mld_mm`, `reference_mm`, `length_mm`, `position_mm`), qca.csv (one row per lesion) and the plots into RECON_DIR, adds the vessel names to its graphs_<k>.vtp centrelines and, when the runs were DICOM files, writes qca_sr.dcm (the figures as a DICOM Structured Report; run it from the folder reconstruct was run from, so the runs' recorded paths resolve). The end-diastolic key frame is analysed (phase nearest the R wave); the figures' range over all key frames is reported too. A narrowing is reported as a lesion only where the views confirm it (at least one view's own vessel width narrows there, and none keeps its width; a view that sees it over other vessels cannot tell) and the lumen recovers before the vessel ends; the others are listed under each vessel's `unconfirmed_narrowings` with the reason. A reconstruction without a usable tree gives an empty, valid qca.json and a warning. Method and validation: docs/QCA.md.

    Examples:

      autocar qca out/demo

      autocar qca out/demo --frame 03 --min-ds 30 --no-plots
    """
    from dataclasses import replace

    from stages.qca.recon import RECON_PARAMS, qca_for_reconstruction

    set_threads(threads)
    params = replace(RECON_PARAMS, min_ds=float(min_ds), smooth_mm=float(smooth))
    doc = qca_for_reconstruction(recon_dir, frame=frame, params=params, plots=plots, views=views, radius=radius)
    if not doc["message"]:  # (a message was logged as a warning already)
        from rich.table import Table

        table = Table(title=f"{recon_dir} — key frame {doc['frame']}, {doc['side']} tree")
        for col in ("vessel", "segment", "%DS", "MLD mm", "ref mm", "length mm", "best view (α, β)"):
            table.add_column(col)
        for vd in doc["vessels"]:
            for les in vd["lesions"]:
                bv = les.get("best_view")
                table.add_row(vd["name"], les.get("segment") or "", f"{les['ds_percent']:.0f}", f"{les['mld_mm']:.2f}",
                              f"{les['reference_mm']:.2f}", f"{les['length_mm']:.1f}",
                              f"{bv['alpha_deg']:+.0f}°, {bv['beta_deg']:+.0f}°" if bv else "")
        named = ", ".join(f"{vd['name']} {vd['length_mm']:.0f} mm" for vd in doc["vessels"] if vd["name"] != "unlabelled")
        console.print(table)
        unconfirmed = sum(len(vd.get("unconfirmed_narrowings", [])) for vd in doc["vessels"])
        if unconfirmed:
            console.print(f"{unconfirmed} narrowing(s) of the model that the views do not confirm: not reported as "
                          "lesions (qca.json, unconfirmed_narrowings)", highlight=False)
        console.print(f"vessels: {named or 'none named'}", highlight=False)
    console.print(f"wrote {Path(recon_dir) / 'qca.json'} and qca.csv", highlight=False)
    if (doc.get("sr") or {}).get("file"):  # (otherwise the reason was logged as a warning)
        console.print(f"wrote {Path(recon_dir) / doc['sr']['file']} (DICOM Structured Report)", highlight=False)


def register(app: typer.Typer) -> None:
    app.command("qca")(qca_command)
