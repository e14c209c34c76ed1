"""Stage ``render``: the synthetic X-ray engine.

Reads prepared cases (``autocar.prepared-case``) and a pose model (``autocar.pose-model``); writes
training-pair shards (``autocar.render-pairs``), simulated two-run XA acquisitions (multi-frame XA
DICOM + ``autocar.xa-truth`` sidecar) and the project's data products (``examples/``, ``data/se``,
``data/re``). Modules:

* :mod:`.raster`   exact triangle raster of lumen silhouettes and path lengths; Möller–Trumbore reference
* :mod:`.augment`  temporal-misalignment augmentation (TPS warps of one view)
* :mod:`.motion`   dynamic heart model (contraction, shortening, twist, respiration, RR variability)
* :mod:`.xa`       XA image formation (iodine line integrals, bolus, thorax anatomy, noise, blur, collimator)
* :mod:`.pairs`    online training pairs (:func:`render_pair`) and pair shards
* :mod:`.acquire`  simulated acquisitions with ground truth and 2D↔2D correspondences
* :mod:`.products` the seeded data sets and the bundled example
* :mod:`.realism`  image statistics for comparing simulated and real runs
* :mod:`.phantom`  a small tube tree built directly as a prepared case (tests, benchmarks)

Seed ranges (never reused by training): training cases 0–999 999; data-se 1 000 000+; data-re
2 000 000+; examples 3 000 000+ (see :mod:`.products`).
"""

from .augment import Warp2D, random_warp
from .motion import HeartMotion, sample_motion
from .pairs import render_pair
from .raster import boundary_disagreement, rasterise_mask, rasterise_path_length, raycast_mask

__all__ = ["Warp2D", "random_warp", "HeartMotion", "sample_motion", "render_pair", "rasterise_mask",
           "rasterise_path_length", "raycast_mask", "boundary_disagreement"]
