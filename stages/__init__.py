"""AutoCAR stages: the work behind each ``autocar`` command, plus what the stages share.

Shared modules: ``errors`` (user errors), ``artefacts`` (zarr/NPZ store), ``geometry`` (C-arm
cameras), ``dicom_io`` (XA DICOM read/write). One module or package per stage besides.
"""

__version__ = "0.1.0"
