"""``autocar graph-opt``: key-frame sparse predictions → tracked vascular graphs (+ .vtp/.stl/.json)."""

from __future__ import annotations

from pathlib import Path

import typer

from ..common import Steps, console, force_option, refuse_existing, set_threads, threads_option, user_errors

# = stages.graph.init.DEFAULT_OCCUPANCY_THRESHOLD (tests/test_cli_help.py checks): importing that module here
# would pull scipy into `autocar --help`
DEFAULT_OCCUPANCY_THRESHOLD = 0.2


@user_errors
def graph_opt_command(
    predictions: list[Path] = typer.Argument(..., help="autocar.sparse-prediction artefact(s) (*.zarr), key frames in cardiac order."),
    output: Path = typer.Option(..., "-o", "--output", help="autocar.vascular-graphs artefact to write (*.zarr); exports go beside it."),
    threshold: float = typer.Option(DEFAULT_OCCUPANCY_THRESHOLD, "--threshold", min=0.0, max=1.0, help="Occupancy threshold for the graph initialisation."),
    reference: int = typer.Option(0, "--reference", min=0, help="Index of the key frame whose topology is tracked."),
    spacing: float = typer.Option(5.0, "--spacing", min=0.5, help="Deformation-graph node spacing in mm."),
    complete: bool = typer.Option(True, "--complete/--no-complete", help="Add the branches both 2D views show and the 3D prediction missed, triangulated along epipolar lines (needs masks and cameras in the predictions)."),
    join: bool = typer.Option(True, "--join/--no-join", help="Join the graph's pieces into one tree by minimal paths through the vessels every 2D view shows (needs masks and cameras in the predictions)."),
    drop_ghosts: bool = typer.Option(True, "--drop-ghosts/--keep-ghosts", help="Remove terminal branches that both 2D views already explain with other parts of the graph (two-view ghosts)."),
    drop_unsupported: bool = typer.Option(False, "--drop-unsupported/--keep-unsupported", help="Opt-in: also remove terminal branches the network hardly predicted (< 10 % of their length near a voxel of occupancy ≥ 0.5) that one 2D view explains with other parts of the graph (helped on the tuning cases, not on data-re: docs/benchmarks/graph_completion_re.md)."),
    drop_far: bool = typer.Option(True, "--drop-far/--keep-far", help="Remove pieces apart from the main tree that the X-ray images show much fainter per mm of radius than the tree's vessels (not contrast-filled), pieces floating more than 10 mm from the main tree that one 2D view already explains with the tree (ghosts; docs/benchmarks/far_pieces.md), pieces apart from the main tree shorter than four lumen diameters, and keep floating pieces first seen in a later key frame out of the tracked topology."),
    drop_catheter: bool = typer.Option(True, "--drop-catheter/--keep-catheter", help="Remove the guiding catheter, which every view shows but which is not a coronary: long straight stretches from a free end of the tree that enter the field of view climbing towards the head (≥ 20 mm, chord/arc ≥ 0.99, free end within 10 % of an image edge), and the stretch on the pixels the masks mark as catheter (seen before the contrast arrived)."),
    min_support_frames: int | None = typer.Option(None, "--min-support-frames", min=0, show_default="3 with three or more runs, 0 with two", help="Drop the pieces first seen in a later key frame that fewer than N key frames' own graphs pass (chance matches of one frame; fewer ghosts, lower coverage: on data-re with two runs N=3 took the tracked graphs' distance to the truth from 4.3 to 3.2 mm and coverage from 0.917 to 0.890, with a third run EPE from 2.16 to 1.94 mm and coverage from 0.966 to 0.954; docs/TWOVIEW.md). 0: keep them all."),
    no_exports: bool = typer.Option(False, "--no-exports", help="Write only the artefact (no .vtp/.stl/.json)."),
    force: bool = force_option(),
    threads: int = threads_option(),
):
    """Build and track the vascular graph through the key frames (paper: graph optimisation).

    Per key frame: threshold + thin the predicted volume, minimum spanning tree, bridge gaps through the prediction, prune spurs, add the branches both views show and the prediction missed (epipolar triangulation backed by the network's sub-threshold occupancy), join the pieces into one tree along the vessels every view shows (minimal paths through the views' vessel hull), drop ghost branches (terminal branches both views explain elsewhere, pieces floating far from the tree that one view explains with it, pieces apart from the tree that the X-ray images (when the predictions carry them, as reconstruct's do) show much fainter per mm of radius than the tree's vessels, i.e. not contrast-filled; with --drop-unsupported also terminal branches the network did not predict that one view explains elsewhere), drop the catheter's straight stretch entering the field of view; then a deformation graph carries the reference frame's graph to every other key frame (Algorithm-1 matching in 3D and, with masks and cameras, in 2D; L-BFGS). Writes the autocar.vascular-graphs artefact and, beside it, per key frame <stem>_<key>.vtp (centreline with radius), .stl (lumen) and .json (graph).

    Examples:

      autocar graph-opt case7_pred.zarr -o case7_graphs.zarr

      autocar graph-opt kf0.zarr kf1.zarr kf2.zarr -o graphs.zarr --no-exports
    """
    from rich.table import Table

    from stages.core.errors import UserError

    for p in predictions:
        if not p.exists():
            raise UserError(f"{p}: no such artefact")
    refuse_existing(output, force)
    set_threads(threads)
    from stages.graph.stage import run_graph_opt

    with Steps() as steps:
        summary = run_graph_opt(predictions, output, exports=not no_exports, occupancy_threshold=threshold,
                                reference=reference, spacing_mm=spacing, complete=complete, join=join,
                                drop_ghosts=drop_ghosts, drop_unsupported=drop_unsupported, drop_far=drop_far,
                                drop_catheter=drop_catheter, min_support_frames=min_support_frames, workers=threads,
                                progress=lambda done, total: steps("tracking, key frames", done, total))
    table = Table(title=f"{summary['case_id']}: vascular graphs ({summary['seconds_total']:.1f} s)")
    for col in ("key frame", "nodes", "edges", "bifurcations", "length mm", "own graph nodes", "branches from 2D",
                "pieces joined", "ghosts dropped", "unpredicted dropped", "catheter dropped", "views"):
        table.add_column(col, justify="right")
    for f in summary["frames"]:
        table.add_row(f["key"], str(f["nodes"]), str(f["edges"]), str(f["bifurcations"]), f"{f['length_mm']:.0f}",
                      str(f["own_graph_nodes"]), str(f["branches_from_views"]), str(f["pieces_joined"]),
                      str(f["ghost_branches_dropped"]), str(f["unsupported_branches_dropped"]),
                      str(f["catheter_stretches_dropped"]), str(f["views"]))
    console.print(table)
    console.print(f"wrote {len(summary['written'])} file(s): {output}" + ("" if no_exports else " and exports beside it"),
                  highlight=False)


def register(app: typer.Typer) -> None:
    app.command("graph-opt")(graph_opt_command)
