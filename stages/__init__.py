"""AutoCAR stages: the work behind each ``autocar`` command, plus what the stages share.

One module or package per stage; what the stages share (errors, artefacts, geometry, DICOM I/O,
voxels, sparse tensors, metrics, export, the output-folder policy) is the package :mod:`stages.core`.
"""

__version__ = "0.1.0"
