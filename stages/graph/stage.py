"""The ``graph-opt`` stage: key-frame sparse predictions → tracked vascular graphs + exports.

Reads one or several ``autocar.sparse-prediction`` artefacts (layout in :mod:`stages.graph.io`), builds
each key frame's graph (:func:`~stages.graph.init.init_graph`), adds the branches both 2D views show and
the prediction missed (:func:`~stages.graph.complete.complete_from_views`; ``complete=False`` skips it),
joins its pieces into one tree by minimal paths through what every view shows as vessel
(:func:`~stages.graph.join.join_pieces_through_views`; ``join=False`` skips it),
drops terminal branches both views explain elsewhere, the two-view ghosts
(:func:`~stages.graph.redundancy.drop_doubly_explained`; ``drop_ghosts=False`` skips it), pieces floating
more than 10 mm from the main tree that one view explains by it
(:func:`~stages.graph.redundancy.drop_far_explained_pieces`, per key frame and again on the tracked
topology, :func:`drop_far_tracked`; ``drop_far=False`` skips both, and then also lets floating pieces first
seen in a later key frame join the tracked topology), pieces apart from the main tree that a view's image shows
much fainter per millimetre of radius than the tree's vessels, i.e. not contrast-filled
(:func:`~stages.graph.redundancy.drop_faint_pieces`,
per key frame, where the predictions carry the X-ray frames; ``drop_far=False`` skips it too), the pieces first
seen in a later key frame that fewer than N key frames' own graphs pass (:func:`drop_unconfirmed_later_pieces`;
``min_support_frames=N``, by default 3 with three or more views and none with two:
:func:`default_min_support_frames`) and, opt-in (``drop_unsupported=True``), terminal branches the network did not
predict that one view explains elsewhere (:func:`~stages.graph.redundancy.drop_unsupported_branches`), and last
the guiding catheter's straight stretch entering the field of view
(:func:`~stages.graph.redundancy.drop_catheter_runs`; ``drop_catheter=False`` keeps it), tracks the reference
frame's topology through all key frames (:func:`~stages.graph.optimise.optimise_frames`, 3D + 2D when masks and
cameras are present), drops, with three or more views, the tracked nodes that project outside a view's image away
from where its vessels leave it (:func:`drop_outside_views_tracked`), drops the stretch lying on the catheter the
runs showed before their contrast arrived (:func:`drop_catheter_tracked`, where the masks mark it; ``drop_catheter=False``
keeps it too), removes the spurs that what was added after
each key frame's own pruning left (:func:`prune_spurs_tracked`), places, with three or more views, the nodes that
another part of the tree overlaps in one view by the views that see them alone (:func:`refit_overlaps_tracked`,
:mod:`stages.graph.refit`; straight catheter-like stretches the moves made are dropped after it,
:func:`drop_catheter_runs_tracked`), and writes an ``autocar.vascular-graphs``
artefact plus, per
key frame, beside it: ``<stem>_<key>.vtp`` (centreline with radius), ``<stem>_<key>.stl`` (lumen surface;
skipped for a graph without edges) and ``<stem>_<key>.json`` (graph, and with cameras its 2D↔2D
correspondences: every node's pixel in both views, :func:`stages.core.export.graph_correspondences`).

Empty predictions: the reference frame must have voxels above the threshold (else a UserError naming
the file and frame); another key frame with an empty prediction is tracked from its 2D masks alone, and
is an error when it has none.
"""

from __future__ import annotations

import logging
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..core.errors import UserError
from ..core.geometry import EXIT_REACH_MM, outside_away_from_exits
from .complete import complete_from_views
from .init import DEFAULT_OCCUPANCY_THRESHOLD, EmptyPredictionError, init_graph, spur_nodes
from .io import read_sparse_predictions, write_vascular_graphs
from .optimise import FrameInput, TrackedGraphs, View, optimise_frames
from .join import join_pieces_through_views
from .refit import refit_overlapped_nodes
from .redundancy import (FAR_PIECE_MM, drop_catheter_runs, drop_doubly_explained, drop_faint_pieces,
                         drop_far_explained_pieces, drop_stubs, drop_unsupported_branches)

__all__ = ["run_graph_opt", "frames_to_inputs", "drop_far_tracked", "drop_outside_views_tracked", "drop_catheter_tracked",
           "refit_overlaps_tracked", "drop_catheter_runs_tracked"]

log = logging.getLogger(__name__)

# drop_unconfirmed_later_pieces: a piece first seen in a later key frame stays when at least this many key
# frames' own graphs pass it (data-re, 7 key frames: 2, 3, 4 traded coverage 0.917 → 0.905 / 0.890 / 0.879
# for EPE 4.50 → 4.30 / 4.02 / 3.96 mm; accuracy 0.675 → 0.678 / 0.681 / 0.678); the default with three or more
# views (default_min_support_frames)
MIN_SUPPORT_FRAMES = 3


def frames_to_inputs(frames, source: str = "prediction", occupancy_threshold: float = DEFAULT_OCCUPANCY_THRESHOLD,
                     reference: int = 0, init_kw: dict | None = None, complete: bool = True,
                     complete_kw: dict | None = None, added: list | None = None, drop_ghosts: bool = True,
                     ghost_kw: dict | None = None, ghosts: list | None = None, drop_unsupported: bool = False,
                     unsupported_kw: dict | None = None, unsupported: list | None = None,
                     drop_far: bool = True, workers: int = 1, join: bool = True,
                     joined: list | None = None, drop_catheter: bool = True,
                     catheters: list | None = None) -> list[FrameInput]:
    """PredictionFrames → FrameInputs (graph per frame, views from masks with cameras; with ``complete``,
    each graph gains the branches both views show and the prediction missed, :mod:`.complete`, and
    ``added`` receives per frame the number of branch paths added; with ``drop_ghosts``, terminal branches
    both views explain elsewhere are then removed, :mod:`.redundancy`, and ``ghosts`` receives their
    number per frame (with ``drop_far``, also the far pieces one view explains, removed next); with
    ``drop_unsupported``, terminal branches the network did not predict and one view
    explains elsewhere go too, and ``unsupported`` receives their number per frame; with ``join``, the graph's
    pieces are first joined through the vessels every view shows, :mod:`.join`, and ``joined`` receives the
    number of paths added per frame); with ``drop_catheter``, the catheter-like stretches go last
    (:func:`~stages.graph.redundancy.drop_catheter_runs`), and ``catheters`` receives their number per frame.
    ``workers``: frames
    built at once, in threads (each frame is independent; the result does not depend on it)."""

    def one(i, f):
        views = [View.from_mask(f.cameras[v], m, f.images.get(v)) for v, m in sorted(f.masks.items()) if v in f.cameras]
        blind = sorted(set(f.masks) - set(f.cameras))
        if blind:
            log.warning("%s: key frame %r: mask(s) %s have no camera and are not used", source, f.key, blind)
        try:
            g = init_graph(f.voxels, occupancy_threshold=occupancy_threshold, allow_empty=(i != reference),
                           **(init_kw or {}))
        except EmptyPredictionError as exc:
            raise UserError(f"{source}: key frame {f.key!r} (the reference): {exc}") from None
        if not len(g) and not views:
            raise UserError(f"{source}: key frame {f.key!r}: no voxel reaches occupancy {occupancy_threshold} and "
                            "there are no 2D masks with cameras to track it from")
        paths: list = []
        if complete and len(g):
            g = complete_from_views(g, views, f.voxels, added=paths, **(complete_kw or {}))
        ghost_lengths: list = []
        joins: list = []
        if join and len(g):
            if drop_far:  # a far ghost goes before a path through the vessels could attach it to the tree
                g = drop_far_explained_pieces(g, views, dropped=ghost_lengths)
            g = join_pieces_through_views(g, views, joined=joins)
        if drop_ghosts and len(g):
            g = drop_doubly_explained(g, views, dropped=ghost_lengths, **(ghost_kw or {}))
        if drop_far and len(g):
            g = drop_far_explained_pieces(g, views, dropped=ghost_lengths)
            g = drop_faint_pieces(g, views, dropped=ghost_lengths)
            g = drop_stubs(g, dropped=ghost_lengths)
        unsupported_lengths: list = []
        if drop_unsupported and len(g) and len(views) >= 2:
            g = drop_unsupported_branches(g, views, f.voxels, dropped=unsupported_lengths, **(unsupported_kw or {}))
        catheter_lengths: list = []
        if drop_catheter and len(g):
            g = drop_catheter_runs(g, views, dropped=catheter_lengths)
        return (FrameInput(f.key, g, views), len(paths), len(ghost_lengths), len(unsupported_lengths), len(joins),
                len(catheter_lengths))

    with ThreadPoolExecutor(max(1, min(int(workers), len(frames)))) as pool:
        built = list(pool.map(one, range(len(frames)), frames))
    for b in built:
        for sink, count in zip((added, ghosts, unsupported, joined, catheters), b[1:]):
            if sink is not None:
                sink.append(count)
    return [b[0] for b in built]


def _mask_views(frame: FrameInput) -> list:
    """The key frame's views that carry a vessel mask (three or more: the further runs are evidence of their own)."""
    return [v for v in frame.views if v.mask is not None]


def _without_nodes(tracked: TrackedGraphs, drop: np.ndarray) -> TrackedGraphs:
    """The tracked graphs without the nodes flagged in ``drop`` (the same in every key frame: one topology)."""
    if not drop.any():
        return tracked
    return replace(tracked, graphs=[g.subgraph(~drop) for g in tracked.graphs], first_frame=tracked.first_frame[~drop])


def _dropped_in_most_frames(tracked: TrackedGraphs, frames: list[FrameInput], rule) -> TrackedGraphs:
    """The tracked topology without the nodes that ``rule(graph, frame)`` (a key frame's graph → what it keeps) removes
    in more than half of the key frames."""
    votes = np.zeros(len(tracked.graphs[0]))
    for g, f in zip(tracked.graphs, frames):
        votes += ~np.isin(g.node_id, rule(g, f).node_id)
    return _without_nodes(tracked, votes > len(tracked.graphs) / 2)


def drop_far_tracked(tracked: TrackedGraphs, frames: list[FrameInput]) -> TrackedGraphs:
    """The tracked topology without the far pieces that one view explains by the tree
    (:func:`~stages.graph.redundancy.drop_far_explained_pieces`) and the pieces apart from the tree that are stubs
    a few diameters long (:func:`~stages.graph.redundancy.drop_stubs`) in more than half of the key frames.

    The per-frame rule runs on each frame's own graph before tracking; registration then pulls the tracked
    graph onto the 2D centrelines, where a ghost's projection lands on the tree's and is caught. On data-re
    (L8, 20 cases) this took the far ghosts left in the tracked graphs from 38 to 13 and no true far piece
    (docs/benchmarks/far_pieces.md)."""
    return _dropped_in_most_frames(tracked, frames, lambda g, f: drop_stubs(drop_far_explained_pieces(g, f.views)))


def drop_outside_views_tracked(tracked: TrackedGraphs, frames: list[FrameInput],
                               exit_reach_mm: float = EXIT_REACH_MM) -> TrackedGraphs:
    """The tracked topology without the nodes that project outside a view's image away from where that view's
    vessels leave it (:func:`~stages.core.geometry.outside_away_from_exits`) in more than half of the key frames
    that have three or more views.

    Why: the 3D step drops such points of each key frame's own prediction, but the tracked graph gathers what
    every key frame adds, warped into the others. A ghost at the wrong depth can project outside a further run's
    image, where that run cannot refute it, while the tree's vessels leave an image only through its border. With
    two views every node was built inside both images. On data-re with a third run (20 cases) this took the
    tracked graphs' recon → truth distance from 2.53 to 2.35 mm after the 3D step's own cut (docs/TWOVIEW.md)."""
    votes = np.zeros(len(tracked.graphs[0]), np.int64)
    judged = 0
    for g, f in zip(tracked.graphs, frames):
        views = _mask_views(f)
        if len(views) < 3 or not len(g):
            continue
        judged += 1
        outside = np.zeros(len(g), bool)
        for v in views:
            outside |= outside_away_from_exits(v.camera, v.mask, v.camera.project(g.nodes), exit_reach_mm)
        votes += outside
    drop = votes > judged / 2
    return _without_nodes(tracked, drop)


# drop_catheter_tracked: a node on the catheter in a view's mask (within this many pixels) ...
CATHETER_REACH_PX = 2.0
# ... is catheter where every view that shows a catheter says so; with one such view only on a stretch from a free end
# this long (a vessel crossing the catheter in that view goes on beyond it)
ONE_VIEW_CATHETER_MM = 5.0


def _catheter_stretches(g, on: np.ndarray) -> np.ndarray:
    """``on`` (per node) kept only on the stretches that run from a free end of the graph through flagged nodes up to
    the first junction or unflagged node (a catheter hangs off the tree at its tip) and are at least
    :data:`ONE_VIEW_CATHETER_MM` long."""
    keep = np.zeros(len(g), bool)
    degree = g.degrees()
    neighbours = [[] for _ in range(len(g))]
    for a, b in g.edges:
        neighbours[a].append(b)
        neighbours[b].append(a)
    for end in np.flatnonzero(on & (degree == 1)):
        path, previous = [int(end)], -1
        while True:
            following = [m for m in neighbours[path[-1]] if m != previous]
            if len(following) != 1 or not on[following[0]] or degree[following[0]] > 2:
                break
            previous = path[-1]
            path.append(int(following[0]))
        if np.linalg.norm(np.diff(g.nodes[path], axis=0), axis=1).sum() >= ONE_VIEW_CATHETER_MM:
            keep[path] = True
    return keep


def drop_catheter_tracked(tracked: TrackedGraphs, frames: list[FrameInput]) -> TrackedGraphs:
    """The tracked topology without the stretch that lies on the catheter the runs showed before their contrast
    arrived (the views' ``catheter`` pixels, :mod:`stages.core.catheter`), in more than half of the key frames
    that have such a view. Why here and not in the masks: the catheter is one 3D object in every view, so the
    3D step and the alignment of the runs use it as evidence like a vessel; only the tree must not keep it. A node
    is on it where every view that shows a catheter has it within :data:`CATHETER_REACH_PX` of its pixels: in two
    views a vessel crossing the catheter in one lies elsewhere in the other. With one such view only stretches from a
    free end count (:func:`_catheter_stretches`)."""
    votes = np.zeros(len(tracked.graphs[0]), np.int64)
    judged = 0
    for g, f in zip(tracked.graphs, frames):
        views = [v for v in f.views if v.catheter is not None]
        if not views or not len(g):
            continue
        judged += 1
        on = np.ones(len(g), bool)
        for v in views:
            rc = np.rint(v.camera.project(g.nodes)).astype(np.int64)
            inside = (rc >= 0).all(1) & (rc[:, 0] < v.catheter.shape[0]) & (rc[:, 1] < v.catheter.shape[1])
            near = np.zeros(len(g), bool)
            near[inside] = v.catheter_distance[rc[inside, 0], rc[inside, 1]] <= CATHETER_REACH_PX
            on &= near
        votes += _catheter_stretches(g, on) if len(views) == 1 else on
    if not judged:
        return tracked
    return _without_nodes(tracked, votes > judged / 2)


def prune_spurs_tracked(tracked: TrackedGraphs, reference: int = 0, passes: int = 4) -> TrackedGraphs:
    """The tracked topology without its spurs (:func:`~stages.graph.init.spur_nodes`, judged on the reference key
    frame; again where removing one leaves another). Why: each key frame's graph is pruned when it is extracted, but
    the branches that completion and joining add, the pieces tracking carries in from other key frames and the drops
    after them leave stubs of their own: on the phantom's 28 pairs 26 end points per tree, 21 without them (its
    tree has about 11 branches); on data-re 18 → 15 (two runs) and 13 → 12 (three). The scores barely move (held-out
    distance 1.76 → 1.75 mm on the phantom's pairs; EPE and accuracy within 0.05 mm and 0.002 on data-re)."""
    for _ in range(passes):
        drop = spur_nodes(tracked.graphs[reference])
        if not drop.any():
            break
        tracked = _without_nodes(tracked, drop)
    return tracked


def refit_overlaps_tracked(tracked: TrackedGraphs, frames: list[FrameInput]) -> tuple[TrackedGraphs, list[int]]:
    """Each key frame's tracked graph with the nodes that overlap another part of the tree in one view placed by the
    views that see them alone (:func:`~stages.graph.refit.refit_overlapped_nodes`; key frames with three or more views
    with masks); and the number of nodes moved per key frame. The topology stays."""
    graphs, moved = [], []
    for g, f in zip(tracked.graphs, frames):
        refitted, n = refit_overlapped_nodes(g, _mask_views(f))
        graphs.append(refitted)
        moved.append(n)
    return replace(tracked, graphs=graphs), moved


def drop_catheter_runs_tracked(tracked: TrackedGraphs, frames: list[FrameInput]) -> TrackedGraphs:
    """The tracked topology without the straight catheter-like stretches (:func:`~stages.graph.redundancy.
    drop_catheter_runs`, the rule each key frame's own graph met first) in more than half of the key frames. Why again:
    moving nodes after that first cut can straighten a stretch into the rule, which the quality check then flags (a
    phantom feed tube in one set of three runs once :func:`refit_overlaps_tracked` had moved its nodes)."""
    return _dropped_in_most_frames(tracked, frames, lambda g, f: drop_catheter_runs(g, f.views))


def default_min_support_frames(frames: list[FrameInput]) -> int:
    """:data:`MIN_SUPPORT_FRAMES` when a key frame has three or more views with masks, else 0 (keep every piece).

    Why only then: with two runs the pieces first seen in a later key frame hold much of what the reference frame
    missed, and dropping the unconfirmed ones costs coverage (data-re, two runs: 0.917 → 0.890); with three the
    key frames' own graphs carry fewer ghosts and miss less, and on data-re with a third run (20 cases) requiring
    three key frames took EPE from 2.16 to 1.94 mm and the 3D error from 1.95 to 1.86 mm, coverage 0.966 → 0.954
    (docs/TWOVIEW.md)."""
    return MIN_SUPPORT_FRAMES if any(len(_mask_views(f)) >= 3 for f in frames) else 0


def frame_support(tracked: TrackedGraphs, frames: list[FrameInput], join_dist_mm: float = 2.0) -> np.ndarray:
    """Per tracked node, the number of key frames whose own graph passes it: within ``join_dist_mm`` or
    1.5 × its radius of its tracked position in that frame (the rule :func:`optimise_frames` joins by)."""
    support = np.zeros(len(tracked.graphs[0]), np.int64)
    for g, f in zip(tracked.graphs, frames):
        if len(f.graph) and len(g):
            d, _ = cKDTree(f.graph.sample(0.5)[0]).query(g.nodes)
            support += d <= np.maximum(join_dist_mm, 1.5 * g.radius)
    return support


def drop_unconfirmed_later_pieces(tracked: TrackedGraphs, frames: list[FrameInput],
                                  min_frames: int = MIN_SUPPORT_FRAMES) -> TrackedGraphs:
    """The tracked topology without the pieces first seen in a later key frame that fewer than ``min_frames``
    key frames' own graphs pass (median over the piece's nodes, :func:`frame_support`).

    Why: every key frame's 3D prediction carries its own ghosts (chance two-view matches of that frame's
    masks), and each later frame may add pieces to the topology, so the tracked graph gathers the ghosts of
    all frames. A vessel the reference frame missed is seen again in other frames where the warp carries
    it; a chance match is not. On data-re (CO, 20 cases) 3566 mm of the tracked graphs' ghost segments (more
    than 2 mm from the truth) but 256 mm of true ones were first seen in a later frame (docs/TWOVIEW.md)."""
    later = np.flatnonzero(tracked.first_frame != tracked.first_frame.min()) if len(tracked.graphs[0]) else []
    if not len(later):
        return tracked
    support = frame_support(tracked, frames)
    g0 = tracked.graphs[0]
    is_later = np.zeros(len(g0), bool)
    is_later[later] = True
    e = g0.edges[is_later[g0.edges].all(axis=1)] if len(g0.edges) else np.zeros((0, 2), np.int64)
    n = len(g0)
    _, label = connected_components(coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n)), directed=False)
    drop = np.zeros(n, bool)
    for c in np.unique(label[is_later]):
        members = np.flatnonzero(is_later & (label == c))
        if np.median(support[members]) < min_frames:
            drop[members] = True
    return _without_nodes(tracked, drop)


def run_graph_opt(inputs, output, *, exports: bool = True, occupancy_threshold: float = DEFAULT_OCCUPANCY_THRESHOLD,
                  reference: int = 0, spacing_mm: float = 5.0, surface_voxel_mm: float = 0.4, complete: bool = True,
                  complete_kw: dict | None = None, drop_ghosts: bool = True, ghost_kw: dict | None = None,
                  drop_unsupported: bool = False, unsupported_kw: dict | None = None, drop_far: bool = True,
                  min_support_frames: int | None = None, progress=None, workers: int = 1, join: bool = True,
                  drop_catheter: bool = True) -> dict:
    """Run the stage; returns a summary dict (per frame: nodes, edges, bifurcations, length, seconds).
    ``workers``: key frames built and exported at once, in threads (the outputs do not depend on it)."""
    from ..core.export import write_graph_json, write_lumen_surface, write_vtp

    inputs = [Path(p) for p in ([inputs] if isinstance(inputs, (str, Path)) else inputs)]
    output = Path(output)
    source = ", ".join(map(str, inputs))
    t0 = time.perf_counter()
    case_id, frames = read_sparse_predictions(inputs)
    if not 0 <= reference < len(frames):
        raise UserError(f"{source}: reference frame index {reference} is outside 0..{len(frames) - 1}")
    added: list[int] = []
    ghosts: list[int] = []
    unsupported: list[int] = []
    joined: list[int] = []
    catheters: list[int] = []
    fin = frames_to_inputs(frames, source, occupancy_threshold, reference, complete=complete, complete_kw=complete_kw,
                           added=added, drop_ghosts=drop_ghosts, ghost_kw=ghost_kw, ghosts=ghosts,
                           drop_unsupported=drop_unsupported, unsupported_kw=unsupported_kw, unsupported=unsupported,
                           drop_far=drop_far, workers=workers, join=join, joined=joined, drop_catheter=drop_catheter,
                           catheters=catheters)
    t_init = time.perf_counter() - t0
    tracked = optimise_frames(fin, reference=reference, progress=progress, spacing_mm=spacing_mm,
                              max_float_mm=FAR_PIECE_MM if drop_far else float("inf"))
    tracked = drop_outside_views_tracked(tracked, fin)
    if drop_far:
        tracked = drop_far_tracked(tracked, fin)
    if min_support_frames is None:
        min_support_frames = default_min_support_frames(fin)
    if min_support_frames:
        tracked = drop_unconfirmed_later_pieces(tracked, fin, min_support_frames)
    if drop_catheter:
        tracked = drop_catheter_tracked(tracked, fin)
    tracked = prune_spurs_tracked(tracked, reference)
    tracked, refitted = refit_overlaps_tracked(tracked, fin)
    if drop_catheter and any(refitted):
        tracked = drop_catheter_runs_tracked(tracked, fin)
    t_opt = time.perf_counter() - t0 - t_init
    params = {"occupancy_threshold": occupancy_threshold, "reference": reference, "spacing_mm": spacing_mm,
              "complete": complete, "join": join, "drop_ghosts": drop_ghosts, "drop_unsupported": drop_unsupported, "drop_far": drop_far,
              "drop_catheter": drop_catheter,
              "min_support_frames": int(min_support_frames)}
    write_vascular_graphs(output, tracked, case_id=case_id, reference=reference, inputs=[str(p) for p in inputs],
                          parameters=params)
    written = [output]
    if exports:
        stem = output.name[:-5] if output.name.endswith(".zarr") else output.stem

        def export(key, g, frame):
            base = output.parent / f"{stem}_{key}"
            files = [write_vtp(base.with_suffix(".vtp"), g)]
            if len(g.edges):  # a single-node graph has no lumen surface to mesh
                files.append(write_lumen_surface(base.with_suffix(".stl"), g, surface_voxel_mm))
            files.append(write_graph_json(base.with_suffix(".json"), g, frame.cameras, frame.source_frames,
                                          case_id=case_id, key_frame=key))
            return files

        with ThreadPoolExecutor(max(1, min(int(workers), len(frames)))) as pool:
            for files in pool.map(export, tracked.keys, tracked.graphs, frames):
                written.extend(files)
    frames_summary = []
    per_frame = zip(tracked.keys, tracked.graphs, fin, added, ghosts, unsupported, joined, catheters, refitted)
    for key, g, f, n_added, n_ghosts, n_unsupported, n_joined, n_catheters, n_refitted in per_frame:
        frames_summary.append({"key": key, "nodes": len(g), "edges": len(g.edges), "bifurcations": len(g.bifurcations()),
                               "length_mm": g.length(), "own_graph_nodes": len(f.graph), "views": len(f.views),
                               "branches_from_views": n_added, "pieces_joined": n_joined,
                               "ghost_branches_dropped": n_ghosts, "unsupported_branches_dropped": n_unsupported,
                               "catheter_stretches_dropped": n_catheters, "overlap_nodes_refitted": n_refitted})
    return {"case_id": case_id, "frames": frames_summary, "written": [str(p) for p in written],
            "seconds_init": t_init, "seconds_optimise": t_opt, "seconds_total": time.perf_counter() - t0}
