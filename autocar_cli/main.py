"""Entry point of ``autocar``: builds the Typer app from one module per command.

Each module in ``autocar_cli.commands`` exposes ``register(app)``; add new ones to ``COMMAND_MODULES``
in pipeline order (that is the order ``autocar --help`` lists them). Heavy libraries (torch, zarr...)
are imported inside the command functions so ``--help`` stays fast.
"""

from __future__ import annotations

import importlib

import typer

from stages import __version__

COMMAND_MODULES = [
    "info",
    "prep_ct",
    "fit_poses",
    "render",
    "train",
    "segment",
    "keyframe",
    "calibrate",
    "reconstruct",
    "batch",
    "graph_opt",
    "qca",
    "evaluate",
]

app = typer.Typer(
    name="autocar",
    help=(
        "AutoCAR: time-resolved 3D coronary models from two X-ray angiography runs.\n\n"
        "Each stage is its own command reading and writing zarr/NPZ artefacts, so any stage can be "
        "rerun or swapped. Lengths in mm, angles in degrees, world frame DICOM LPS at the isocentre."
    ),
    no_args_is_help=True,
    add_completion=False,
    rich_markup_mode="rich",
    pretty_exceptions_enable=False,
)


def _version(value: bool):
    if value:
        typer.echo(f"autocar {__version__}")
        raise typer.Exit()


@app.callback()
def _root(version: bool = typer.Option(False, "--version", callback=_version, is_eager=True, help="Show the version and exit.")):
    pass


for _name in COMMAND_MODULES:
    importlib.import_module(f"autocar_cli.commands.{_name}").register(app)


def main() -> None:
    app()


if __name__ == "__main__":
    main()
