"""Graph optimisation (AutoCAR paper, Methods, "Graph optimization"): from per-key-frame sparse predictions
to vascular graphs with one topology tracked through the cardiac cycle.

Reads: ``autocar.sparse-prediction`` artefacts, one per key frame (+ masks and cameras). Writes, in
``autocar graph-opt`` (:mod:`.stage`): an ``autocar.vascular-graphs`` artefact and a ``.vtp`` / ``.stl`` /
``.json`` per key frame.

Public API (for the ``graph-opt`` stage and the end-to-end ``reconstruct``)::

    from stages.graph import (VascularGraph, init_graph, DeformationGraph, match_curve_dp,
                              register_graph, optimise_frames, View, FrameInput)

    g = init_graph(voxels)                        # SparseVoxels (occupancy, centreness) → VascularGraph
    g = complete_from_views(g, views, voxels)     # + branches both views show and the prediction missed
    g = drop_doubly_explained(g, views)           # − terminal branches both views explain elsewhere (ghosts)
    g = drop_unsupported_branches(g, views, voxels)  # − unpredicted terminal branches one view explains elsewhere
    g.segments()                                  # curve segments between junctions / end points
    dg = DeformationGraph.from_graph(g, spacing_mm=5.0)
    idx = match_curve_dp(curve, target_points)    # Algorithm 1 DP (3D or 2D), −1 = unmatched
    views = [View.from_mask(camera_a, mask_a), View.from_mask(camera_b, mask_b)]
    res = register_graph(g, target_points_3d, views)      # match ↔ L-BFGS; res.graph, res.deformation
    tracked = optimise_frames([FrameInput(key, graph_k, views_k), ...])   # TrackedGraphs

    from stages.graph.io import write_sparse_predictions, read_sparse_predictions, write_vascular_graphs
    from stages.graph.stage import run_graph_opt  # the whole stage, with .vtp/.stl/.json exports

Modules: :mod:`.vascular` (graph type), :mod:`.init` (graph initialisation, Eq. 14 + bridging + spurs +
radii), :mod:`.complete` (branches from the 2D views, epipolar triangulation),
:mod:`.redundancy` (two-view ghosts, unpredicted branches), :mod:`.deformation` (Eqs. 12–13, 15–16),
:mod:`.matching` (Algorithm 1), :mod:`.optimise` (graph updating, key-frame chaining, radius fusion),
:mod:`.io` (artefact layouts: ``autocar.sparse-prediction`` in, ``autocar.vascular-graphs`` out),
:mod:`.stage` (``autocar graph-opt``),
:mod:`.synthetic` (test trees, predictions, warps, masks). Units: mm, world frame LPS.
"""

from .complete import complete_from_views
from .deformation import DeformationGraph
from .init import EmptyPredictionError, init_graph
from .matching import match_curve_dp, match_curve_greedy, match_curves_dp, match_graph
from .optimise import FrameInput, RegistrationResult, TrackedGraphs, View, optimise_frames, register_graph
from .redundancy import drop_doubly_explained, drop_unsupported_branches
from .vascular import VascularGraph

__all__ = [
    "VascularGraph", "init_graph", "complete_from_views", "EmptyPredictionError", "DeformationGraph", "match_curve_dp",
    "match_curves_dp",
    "match_curve_greedy", "match_graph", "register_graph", "optimise_frames", "View", "FrameInput",
    "RegistrationResult", "TrackedGraphs", "drop_doubly_explained", "drop_unsupported_branches",
]
