"""The ``autocar`` command line: a thin Typer layer over the stage functions in :mod:`stages`."""
