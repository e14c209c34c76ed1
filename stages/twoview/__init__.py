"""Explicit two-view correspondence: the default 3D method of ``autocar reconstruct`` (``--method correspondence``).

Two vessel masks (and optionally the segmenter's probabilities) with their cameras in; matched 3D centreline
points with lumen radii, and their tubes on the sparse 0.5 mm grid, out. Geometric and local: 2D centrelines
(:mod:`.centreline2d`), epipolar candidates (:mod:`.epipolar`), a chain labelling per 2D branch both ways
(:mod:`.select`), their combination and rasterisation (:mod:`.method`). Reads and writes no files.
"""

from .centreline2d import Centreline2D, extract_centreline
from .method import Polyline3D, TwoViewMatch, correspondence_prediction, match_views, tubes_to_voxels, voxel_prior
from .select import SelectionParams

__all__ = ["Centreline2D", "extract_centreline", "Polyline3D", "TwoViewMatch", "correspondence_prediction",
           "match_views", "tubes_to_voxels", "voxel_prior", "SelectionParams"]
