"""Stage ``batch``: ``reconstruct`` over a cohort of studies, on Dask distributed (a local cluster or a real one).

Reads: a folder of study folders (each holding the XA runs of one study: DICOM files, a DICOMDIR, ``.npy``/
``.npz`` stacks or frame folders with their geometry JSON) or a CSV manifest (``study, run_a, run_b`` +
optional ``geometry_a, geometry_b`` + any extra columns) — :mod:`stages.batch.plan`.
Writes, in the output folder:

* ``<study>/`` (or ``<study>/<pair>/`` when a study has several pairs) — exactly the folder
  ``autocar reconstruct -o`` writes for that pair (:mod:`stages.batch.study`, on a Dask worker);
* ``studies.csv``, ``vessels.csv``, ``lesions.csv`` and ``index.html`` — the cohort, rewritten atomically as
  each study finishes (:mod:`stages.batch.cohort`).

A study whose folder is complete and up to date is skipped without a task; the others run one task per
pair (:mod:`stages.batch.engine`: :func:`~stages.batch.engine.run_batch`; the plan:
:func:`stages.batch.plan.plan_batch`).

Nothing is imported here, so the CLI can read the submodules' constants without numpy or Dask.
"""
