"""Ghost-branch dropping (stages.graph.redundancy): a branch that lies on one real vessel's rays in view A
and on another's in view B goes; the real branches, each overlapping the ghost in one view only, stay;
a ghost-free tree is left unchanged. A branch the network did not predict goes when one view explains it
elsewhere, and stays when the network predicted it or no view explains it. A piece floating far from the
tree goes when one view explains it by the tree, and stays when neither does; any piece apart from the tree goes
when a view's image shows it much fainter per mm of radius than the tree's vessels (not contrast-filled); a far
piece goes when it is a stub a few diameters long."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stages.core.geometry import Camera
from stages.graph.optimise import View
from stages.graph.redundancy import (FAR_PIECE_MM, drop_doubly_explained, drop_faint_pieces, drop_far_explained_pieces,
                                     drop_stubs, drop_unsupported_branches)
from stages.graph.synthetic import synthetic_tree, voxelise_prediction
from stages.graph.vascular import VascularGraph

CAMERAS = [Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512), Camera.from_carm(-35, -15, 1100, 750, 0.3, 512, 512)]
VIEWS = [View(c, np.zeros((0, 2))) for c in CAMERAS]  # only the cameras are used


def _along_rays(points: np.ndarray, camera: Camera, shift_mm: float) -> np.ndarray:
    """The points moved ``shift_mm`` along their rays from ``camera``'s source: same projection there."""
    d = points - camera.source
    return points + shift_mm * d / np.linalg.norm(d, axis=1, keepdims=True)


def _with_polylines(graph: VascularGraph, *lines: np.ndarray) -> VascularGraph:
    """``graph`` plus each polyline as its own component (radius 1 mm)."""
    nodes, edges = [graph.nodes], [graph.edges]
    n = len(graph)
    for line in lines:
        nodes.append(line)
        edges.append(np.stack([np.arange(n, n + len(line) - 1), np.arange(n + 1, n + len(line))], 1))
        n += len(line)
    all_nodes = np.vstack(nodes)
    return VascularGraph(all_nodes, np.r_[graph.radius, np.ones(len(all_nodes) - len(graph))], np.vstack(edges))


def _longest_side_branch(tree: VascularGraph) -> np.ndarray:
    deg = tree.degrees()
    return max((s for s in tree.segments() if min(deg[s[0]], deg[s[-1]]) == 1 and max(deg[s[0]], deg[s[-1]]) > 2),
               key=len)


def _present(graph: VascularGraph, points: np.ndarray) -> float:
    """Fraction of ``points`` with a graph node within 0.3 mm."""
    return float(np.mean(cKDTree(graph.nodes).query(points)[0] < 0.3))


def test_ghost_on_two_real_vessels_is_dropped_and_the_vessels_stay():
    tree = synthetic_tree(3)
    side = tree.nodes[_longest_side_branch(tree)]
    ghost = _along_rays(side, CAMERAS[0], 20.0)  # on the side branch's rays in view A, 20 mm deeper
    other = _along_rays(ghost, CAMERAS[1], -20.0)  # a real vessel that the ghost covers in view B
    graph = _with_polylines(tree, ghost, other)
    dropped: list = []
    out = drop_doubly_explained(graph, VIEWS, dropped=dropped)
    assert _present(out, ghost) == 0.0
    assert _present(out, side) == 1.0 and _present(out, other) == 1.0
    assert _present(out, tree.nodes) == 1.0
    assert len(dropped) == 1 and abs(dropped[0] - np.linalg.norm(np.diff(ghost, axis=0), axis=1).sum()) < 1e-6


def test_branch_overlapping_in_one_view_only_stays():
    tree = synthetic_tree(3)
    side = tree.nodes[_longest_side_branch(tree)]
    twin = _along_rays(side, CAMERAS[0], 20.0)  # overlaps the side branch in view A, nothing in view B
    graph = _with_polylines(tree, twin)
    out = drop_doubly_explained(graph, VIEWS)
    assert len(out) == len(graph) and np.array_equal(out.edges, graph.edges)


def test_ghost_free_tree_is_unchanged_and_one_view_is_not_enough():
    for seed in (3, 4, 5):
        tree = synthetic_tree(seed)
        out = drop_doubly_explained(tree, VIEWS)
        assert len(out) == len(tree) and np.array_equal(out.edges, tree.edges)
    side = synthetic_tree(3)
    ghost = _along_rays(side.nodes[_longest_side_branch(side)], CAMERAS[0], 20.0)
    graph = _with_polylines(side, ghost, _along_rays(ghost, CAMERAS[1], -20.0))
    assert len(drop_doubly_explained(graph, VIEWS[:1])) == len(graph)


def test_unpredicted_branch_explained_in_one_view_is_dropped():
    tree = synthetic_tree(3)
    twin = _along_rays(tree.nodes[_longest_side_branch(tree)], CAMERAS[0], 20.0)  # hides behind a branch in view A
    graph = _with_polylines(tree, twin)
    dropped: list = []
    out = drop_unsupported_branches(graph, VIEWS, voxelise_prediction(tree), dropped=dropped)
    assert _present(out, twin) == 0.0 and _present(out, tree.nodes) == 1.0
    assert len(dropped) == 1 and abs(dropped[0] - np.linalg.norm(np.diff(twin, axis=0), axis=1).sum()) < 1e-6
    # predicted by the network: stays
    kept = drop_unsupported_branches(graph, VIEWS, voxelise_prediction(graph))
    assert len(kept) == len(graph) and np.array_equal(kept.edges, graph.edges)


def test_unpredicted_branch_no_view_explains_stays():
    tree = synthetic_tree(3)
    far = tree.nodes[_longest_side_branch(tree)] + np.array([0.0, 0.0, 60.0])  # clear of the tree in both views
    graph = _with_polylines(tree, far)
    for cam in CAMERAS:  # its projections are > 10 px from the tree's in both views: nothing explains it
        assert np.linalg.norm(cam.project(far)[:, None] - cam.project(tree.nodes)[None], axis=2).min() > 10
    out = drop_unsupported_branches(graph, VIEWS, voxelise_prediction(tree))
    assert len(out) == len(graph)


def test_far_piece_one_view_explains_goes_and_a_detached_vessel_stays():
    tree = synthetic_tree(3)
    side = tree.nodes[_longest_side_branch(tree)]
    ghost = _along_rays(side, CAMERAS[0], 25.0)  # on the side branch's rays in view A, 25 mm deeper
    # a detached vessel: far from the tree in 3D and off its projection in both views
    x = np.linspace(0, 15, 31)
    detached = tree.nodes.max(0) + np.array([0.0, 0.0, 25.0]) + np.c_[x, 0.5 * x, 0 * x]
    graph = _with_polylines(tree, ghost, detached)
    _, _, gaps, order = graph.pieces(FAR_PIECE_MM)
    assert sum(gaps[c] > FAR_PIECE_MM for c in order) == 2  # both float far from the tree
    for cam in CAMERAS:  # the detached vessel shows in both views away from the tree
        d = cKDTree(cam.project(tree.sample(0.5)[0])).query(cam.project(detached))[0] * cam.isocentre_spacing
        assert np.mean(d <= 1.5) < 0.2
    dropped: list = []
    out = drop_far_explained_pieces(graph, VIEWS, dropped=dropped)
    assert _present(out, ghost) == 0.0 and len(dropped) == 1
    assert _present(out, detached) == 1.0 and _present(out, tree.nodes) == 1.0
    # a ghost next to the tree (gap below FAR_PIECE_MM) is not this function's business
    near = _along_rays(side, CAMERAS[0], 4.0)
    assert _present(drop_far_explained_pieces(_with_polylines(tree, near), VIEWS), near) == 1.0


def _angiogram(camera: Camera, pieces) -> np.ndarray:
    """A 512² X-ray frame: background 200, each (graph, attenuation per mm of radius) piece darkened by
    exp(−attenuation × radius) inside its projected tubes (Beer–Lambert: a wider vessel holds more iodine)."""
    img = np.full((camera.rows, camera.cols), 200.0, np.float32)
    rr, cc = np.mgrid[0:camera.rows, 0:camera.cols]
    for graph, attenuation in pieces:
        pts, radius = graph.sample(0.25)
        rc = camera.project(pts)
        r_px = radius / camera.isocentre_spacing
        absorbed = np.zeros(img.shape)
        for (r, c), rad, rad_mm in zip(rc, r_px, radius):
            lo_r, lo_c = int(max(r - rad - 1, 0)), int(max(c - rad - 1, 0))
            win = (slice(lo_r, int(r + rad + 2)), slice(lo_c, int(c + rad + 2)))
            disc = (rr[win] - r) ** 2 + (cc[win] - c) ** 2 <= rad ** 2
            absorbed[win] = np.maximum(absorbed[win], np.where(disc, attenuation * rad_mm, 0.0))
        img *= np.exp(-absorbed).astype(np.float32)
    return img


def _piece(points: np.ndarray, radius_mm: float) -> VascularGraph:
    return VascularGraph(points, np.full(len(points), radius_mm), np.stack([np.arange(len(points) - 1),
                                                                             np.arange(1, len(points))], 1))


def test_piece_the_images_show_faint_goes_and_a_filled_one_stays():
    tree = synthetic_tree(3)
    x = np.linspace(0, 15, 31)
    top = tree.nodes.max(0)
    far = top + np.array([0.0, 0.0, 25.0]) + np.c_[x, 0.5 * x, 0 * x]  # floating far from the tree
    near = top + np.array([5.0, 0.0, 0.0]) + np.c_[0 * x, x, 0.3 * x]  # 5 mm from it
    for radius_mm, attenuation, kept in ((1.0, 0.1, False), (1.0, 0.5, True), (0.5, 0.5, True)):
        # the tree's vessels: 0.5 per mm of radius; a thin piece as filled as the tree is no fainter per mm
        pieces = [_piece(far, radius_mm), _piece(near, radius_mm)]
        graph = _with_polylines(tree, far, near)
        graph = VascularGraph(graph.nodes, np.r_[tree.radius, np.full(2 * len(x), radius_mm)], graph.edges)
        views = [View(c, np.zeros((0, 2)), image=_angiogram(c, [(tree, 0.5)] + [(p, attenuation) for p in pieces]))
                 for c in CAMERAS]
        dropped: list = []
        out = drop_faint_pieces(graph, views, dropped=dropped)
        assert _present(out, far) == _present(out, near) == float(kept)
        assert len(dropped) == (0 if kept else 2)
        assert _present(out, tree.nodes) == 1.0
    # without images nothing is judged
    assert len(drop_faint_pieces(graph, VIEWS)) == len(graph)


def test_tracked_far_ghost_leaves_every_frame_and_the_tree_stays():
    from stages.graph.optimise import FrameInput, TrackedGraphs
    from stages.graph.stage import drop_far_tracked

    tree = synthetic_tree(3)
    side = tree.nodes[_longest_side_branch(tree)]
    graphs = []
    for shift in (0.0, 0.5, 1.0):  # three key frames, the whole scene moving a little
        g = _with_polylines(tree, _along_rays(side, CAMERAS[0], 25.0))
        graphs.append(g.copy(nodes=g.nodes + [shift, 0.0, 0.0]))
    tracked = TrackedGraphs([f"kf{k}" for k in range(3)], graphs, [None] * 3, np.zeros(len(graphs[0]), np.int64))
    out = drop_far_tracked(tracked, [FrameInput(k, g, VIEWS) for k, g in zip(tracked.keys, graphs)])
    assert all(len(g) == len(tree) for g in out.graphs) and len(out.first_frame) == len(tree)
    assert all(np.array_equal(g.edges, out.graphs[0].edges) for g in out.graphs)
    assert _present(out.graphs[0], tree.nodes) == 1.0
    untouched = drop_far_tracked(TrackedGraphs(["kf0"], [tree], [None], np.zeros(len(tree), np.int64)),
                                 [FrameInput("kf0", tree, VIEWS)])
    assert len(untouched.graphs[0]) == len(tree)


def test_stubs_apart_from_the_tree_go_and_a_vessel_stays():
    tree = synthetic_tree(3)
    corner = tree.nodes.max(0) + np.array([0.0, 0.0, 25.0])
    stub = corner + np.c_[np.linspace(0, 5, 11), np.zeros(11), np.zeros(11)]  # 5 mm of a 2 mm-wide lumen: 2.5 diameters
    vessel = corner + [0.0, 20.0, 0.0] + np.c_[np.linspace(0, 15, 31), np.zeros(31), np.zeros(31)]  # 7.5 diameters
    graph = _with_polylines(tree, stub, vessel)  # radius 1 mm
    dropped: list = []
    out = drop_stubs(graph, dropped=dropped)
    assert _present(out, stub) == 0.0 and np.allclose(dropped, [5.0])
    assert _present(out, vessel) == 1.0 and _present(out, tree.nodes) == 1.0
    # a stub near the tree goes as well: the joining, which runs first, did not attach it
    end = tree.nodes[np.argmax(tree.nodes[:, 0])]
    near = end + [3.0, 0.0, 0.0] + np.c_[np.linspace(0, 5, 11), np.zeros(11), np.zeros(11)]
    assert _present(drop_stubs(_with_polylines(tree, near)), near) == 0.0
    assert drop_stubs(tree) is tree


def _mask_of(camera: Camera, *graphs: VascularGraph) -> np.ndarray:
    """A vessel mask of ``graphs`` in ``camera``: their 0.25 mm samples projected and dilated by 2 px."""
    from scipy.ndimage import binary_dilation

    mask = np.zeros((camera.rows, camera.cols), bool)
    for g in graphs:
        rc = np.rint(camera.project(g.sample(0.25)[0])).astype(int)
        ok = camera.in_image(rc)
        mask[rc[ok, 0], rc[ok, 1]] = True
    return binary_dilation(mask, iterations=2)


def test_tracked_node_outside_a_third_view_goes_unless_that_view_shows_a_vessel_leaving_there():
    from stages.graph.optimise import FrameInput, TrackedGraphs
    from stages.graph.stage import drop_outside_views_tracked

    tree = synthetic_tree(3)
    line = np.c_[np.linspace(0, 20, 41), np.zeros(41), np.zeros(41)]
    ghost = VascularGraph(np.array([0.0, -40.0, 40.0]) + line, np.ones(41),
                          np.stack([np.arange(40), np.arange(1, 41)], 1))
    graph = _with_polylines(tree, ghost.nodes)
    third = Camera.from_carm(45, -30, 1100, 750, 0.3, 352, 352)  # a tighter field: the tree inside, the ghost not
    assert third.in_image(third.project(tree.nodes), margin=8).all()
    assert not third.in_image(third.project(ghost.nodes)).any()
    views = [View(c, np.zeros((0, 2)), _mask_of(c, tree, ghost)) for c in CAMERAS]  # built on A and B
    tracked = TrackedGraphs(["kf0", "kf1"], [graph, graph], [None] * 2, np.zeros(len(graph), np.int64))
    # where the ghost would enter the third view's image, a vessel of that view meeting the border
    leaving = _mask_of(third, tree)
    rc = np.rint(np.clip(third.project(ghost.nodes), 0, 351)).astype(int)
    leaving[rc[:, 0], rc[:, 1]] = True

    def kept(*third_masks, n_views=3):
        frames = [FrameInput(k, graph, (views + [View(third, np.zeros((0, 2)), m)])[:n_views])
                  for k, m in zip(tracked.keys, third_masks)]
        out = drop_outside_views_tracked(tracked, frames)
        assert all(np.array_equal(g.edges, out.graphs[0].edges) for g in out.graphs)
        assert _present(out.graphs[0], tree.nodes) == 1.0 and len(out.first_frame) == len(out.graphs[0])
        return len(out.graphs[0])

    tree_only = _mask_of(third, tree)
    assert kept(tree_only, tree_only) == len(tree)
    # two views judge nothing; nor does a third that shows no vessel leaving in one key frame of two
    assert kept(tree_only, tree_only, n_views=2) == len(graph)
    assert kept(tree_only, leaving) == len(graph)
    # the third view's vessel meets the border where the ghost would enter: it may be a vessel continuing outside
    assert kept(leaving, leaving) == len(graph)


def test_spurs_left_after_tracking_are_pruned_in_every_key_frame():
    """A 2 mm stub on a 1.5 mm-radius vessel (what a completion path or a drop leaves) goes from every key frame's
    graph, the vessel and a 20 mm branch stay."""
    from stages.graph.optimise import TrackedGraphs
    from stages.graph.stage import prune_spurs_tracked

    main = [[0.0, 0.0, z] for z in np.arange(0.0, 41.0, 1.0)]  # nodes 0–40 along z
    branch = [[x, 0.0, 20.0] for x in np.arange(1.0, 21.0, 1.0)]  # nodes 41–60 from node 20
    stub = [[0.0, y, 30.0] for y in (1.0, 2.0)]  # nodes 61–62 from node 30
    nodes = np.array(main + branch + stub)
    edges = ([[i, i + 1] for i in range(40)] + [[20, 41]] + [[i, i + 1] for i in range(41, 60)]
             + [[30, 61], [61, 62]])
    g = VascularGraph(nodes, np.full(len(nodes), 1.5), np.array(edges))
    frames = [g, g.copy(nodes=g.nodes + [0.5, 0.0, 0.0])]
    out = prune_spurs_tracked(TrackedGraphs(["kf0", "kf1"], frames, [None] * 2, np.zeros(len(g), np.int64)))
    assert all(len(h) == len(g) - 2 for h in out.graphs) and len(out.first_frame) == len(g) - 2
    assert len(out.graphs[0].endpoints()) == 2 + 1  # the vessel's two ends and the branch's
    assert np.allclose(out.graphs[1].nodes, out.graphs[0].nodes + [0.5, 0.0, 0.0])


def test_tree_stretch_on_the_catheter_seen_before_the_contrast_goes_and_the_tree_stays():
    """A 25 mm catheter hanging off the tree's root goes when both views mark it as catheter; with one such view it
    goes too, while a vessel stretch that view also marks (a vessel crossing the catheter there) stays: it goes on
    into the tree at both ends."""
    from stages.graph.optimise import FrameInput, TrackedGraphs
    from stages.graph.stage import drop_catheter_tracked

    tree = synthetic_tree(3)
    root = 0
    assert tree.degrees()[root] == 1
    line = tree.nodes[root] + np.array([0.0, -1.0, 0.0]) * np.arange(1.0, 26.0)[:, None]
    assert all(c.in_image(c.project(line), margin=20).all() for c in CAMERAS)
    n, k = len(tree), len(line)
    graph = VascularGraph(np.vstack([tree.nodes, line]), np.r_[tree.radius, np.ones(k)],
                          np.vstack([tree.edges, [[root, n]], np.c_[np.arange(n, n + k - 1), np.arange(n + 1, n + k)]]))
    cath = VascularGraph(line, np.ones(k), np.c_[np.arange(k - 1), np.arange(1, k)])
    inner = max(tree.segments(), key=len)[10:-10]  # the middle of the longest segment: tree on both sides
    crossed = tree.subgraph(np.isin(np.arange(n), inner))
    tracked = TrackedGraphs(["kf0", "kf1"], [graph, graph], [None] * 2, np.zeros(len(graph), np.int64))
    far_from_line = cKDTree(line).query(tree.nodes)[0] > 2.0

    def kept(catheters):
        views = [View(c, np.zeros((0, 2)), _mask_of(c, graph), None, m) for c, m in zip(CAMERAS, catheters)]
        out = drop_catheter_tracked(tracked, [FrameInput(k, graph, views) for k in tracked.keys])
        assert len(out.first_frame) == len(out.graphs[0])
        return out.graphs[0]

    both = kept([_mask_of(c, cath) for c in CAMERAS])
    assert _present(both, line[2:]) == 0.0 and _present(both, tree.nodes[far_from_line]) == 1.0
    one = kept([_mask_of(CAMERAS[0], cath, crossed), None])
    assert _present(one, line[2:]) == 0.0 and _present(one, tree.nodes[far_from_line]) == 1.0
    assert len(kept([None, None])) == len(graph)
