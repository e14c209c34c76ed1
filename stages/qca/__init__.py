"""3D quantitative coronary analysis (QCA) of reconstructed or true vessel trees (docs/QCA.md).

Reads: a reconstruction folder's ``graphs.zarr`` (+ ``keyframes.zarr``, ``predictions.zarr``, optional).
Writes there (:mod:`.recon`): ``qca.json``, ``qca.csv`` and the QCA plots.

Modules: :mod:`.tree` (graph → rooted vessels), :mod:`.labels` (side and names), :mod:`.profile`
(diameter profile, reference, lesions), :mod:`.analysis` (one graph), :mod:`.views` (foreshortening,
overlap, best view), :mod:`.recon` (a reconstruction folder → qca.json/csv/plots), :mod:`.report`
(CSV, PNGs, the report.html section), :mod:`.truth` and :mod:`.validate` (ground truth; matching and the validation runs).
"""

from __future__ import annotations


def qca_for_reconstruction(recon_dir, **kwargs) -> dict:
    """Analyse a reconstruction folder and write qca.json, qca.csv and the plots there (see :mod:`.recon`)."""
    from .recon import qca_for_reconstruction as run

    return run(recon_dir, **kwargs)


def html_section(source) -> str:
    """The report.html section (HTML fragment) for a folder's qca.json or its content (see :mod:`.report`)."""
    from .report import html_section as section

    return section(source)


__all__ = ["qca_for_reconstruction", "html_section"]
