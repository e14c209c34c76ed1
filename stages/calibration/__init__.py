"""Self-calibration of C-arm geometry from the vessels.

Reads: two or more XA runs (their vessel masks, or matched centreline points, and their cameras).
Writes: corrected cameras (a correction per run) in memory; ``autocar calibrate`` (:mod:`.stage`) writes
them as an ``autocar.calibration`` JSON artefact.

* :mod:`.model` — the per-run correction (detector shift, in-plane rotation, dα, dβ, dSID) and
  gauge-free measures of two-view geometry;
* :mod:`.pair` — :func:`calibrate_pair`: two runs, from matched centreline points;
* :mod:`.masks` — :func:`calibrate_masks`: two runs, from their vessel masks;
* :mod:`.runs` — :func:`calibrate_runs`: two or more runs (jointly for a static scene);
* :mod:`.views` — a view's 6-DoF pose fitted to a fixed 3D model by chamfer (held-out check);
* :mod:`.synthetic` — synthetic trees and injected C-arm errors for tests and the benchmark;
* :mod:`.validate` — the benchmark's accuracy runs: injected errors, and pair against joint calibration on the phantom.
"""

from .model import DOF, Correction, apply_correction, relative_geometry_error, triangulate
from .masks import calibrate_masks
from .pair import PairCalibration, calibrate_pair, epipolar_residuals, pair_residual
from .runs import calibrate_runs
from .views import Pose6, apply_pose, fit_view_correction, fit_view_pose

__all__ = ["DOF", "Correction", "apply_correction", "relative_geometry_error", "triangulate",
           "PairCalibration", "calibrate_pair", "epipolar_residuals", "pair_residual",
           "calibrate_masks", "calibrate_runs", "Pose6", "apply_pose", "fit_view_pose", "fit_view_correction"]
