"""prep-ct: mesh and sparse-volume preparation of coronary trees (the paper's training material).

Reads: a label volume (NIfTI ``.nii/.nii.gz``, NRRD ``.nrrd/.nhdr``, or ``.npy`` + spacing), a surface
mesh (``.stl/.ply/.obj``, world mm LPS), or nothing (``--synthetic``: procedural trees from
:mod:`stages.anatomy`, turned into a CTA-like label volume first so they take the same path as a real
mask).
Writes: one ``autocar.prepared-case`` zarr artefact per tree (:mod:`stages.core.prepared_case`) and a PNG
preview beside it (three orthogonal maximum projections of the labels with the centreline drawn).

Per input, the label is split into trees (:func:`pipeline.split_trees`): label values 1 (left) and
2 (right) when both are present; otherwise connected components (26-connectivity), the two largest
being the trees and the one whose centroid lies further to the patient's left (larger LPS x) the
left tree; smaller components are attached to the nearer tree (a vessel broken by a stenosis) or
dropped when under 0.5 % of the foreground (logged). Each tree then gets

* a lumen mesh (:mod:`.mesh`: 0.1 mm block-wise upsampling, Gaussian, marching cubes),
* a centreline graph with radii (:mod:`.centreline`: skeleton refined onto the ridge of φ, Eq. 1),
* sparse labels at 0.5 mm (:mod:`.labels`: occupancy Eq. 4, centreness Eq. 3).
"""

from .pipeline import (  # noqa: F401
    PrepParams,
    prepare_file,
    prepare_mask,
    prepare_synthetic,
    run_batch,
    split_trees,
)
