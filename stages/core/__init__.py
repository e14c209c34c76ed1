"""The shared core of the stages: what several stages use and none of them owns. No command of its own.

* :mod:`~stages.core.errors` — :class:`UserError`, the one error the CLI prints as a line, not a traceback;
* :mod:`~stages.core.artefacts` — the artefact store (zarr v3 / NPZ, atomic writes, kind + schema checks);
* :mod:`~stages.core.geometry` — C-arm cameras: DICOM angles or a 3×4 matrix, projection, rays;
* :mod:`~stages.core.dicom_io` — XA DICOM runs read and written (frames, geometry, timing, ECG);
* :mod:`~stages.core.runs` — a run as every stage reads it: DICOM, a frame folder or stack + geometry JSON;
* :mod:`~stages.core.voxels` — sparse voxel sets on disk and in NumPy (:class:`SparseVoxels`);
* :mod:`~stages.core.sparse` — sparse 3D tensors and layers in PyTorch (what the networks run on);
* :mod:`~stages.core.prepared_case` — the prepared-case artefact (``autocar.prepared-case``) that
  ``prep-ct`` writes and ``render``, ``train`` and ``evaluate`` read;
* :mod:`~stages.core.metrics` — the paper's 3D/2D metrics and graph errors, in memory;
* :mod:`~stages.core.export` — ``.vtp`` / ``.stl`` / ``.json`` exports of vascular graphs;
* :mod:`~stages.core.outputs` — the output-folder policy of every command that writes a folder.
* :mod:`~stages.core.threads` — how many CPU threads torch, the numpy pools and numba compute with.

Nothing here imports a stage: the core sits below every stage module and package of :mod:`stages`.
This package imports none of its modules itself, so ``import stages.core`` stays cheap.
"""
