"""Graph completion from the views (stages.graph.complete): a side branch the 3D graph lacks is
triangulated along epipolar lines and joins the graph at the right place; a path the network gave no
occupancy at all is not added; nothing is added when the graph already explains both views."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from stages.core.geometry import Camera
from stages.graph.complete import complete_from_views
from stages.graph.optimise import View
from stages.graph.synthetic import render_mask, synthetic_tree, voxelise_prediction

CAMERAS = [Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512), Camera.from_carm(-35, -15, 1100, 750, 0.3, 512, 512)]


def _without_a_side_branch(tree):
    """The tree minus its longest terminal segment (a side branch), and that segment's node indices."""
    deg = tree.degrees()
    terminal = [s for s in tree.segments() if deg[s[0]] == 1 or deg[s[-1]] == 1]
    side = max((s for s in terminal if deg[s[0]] > 2 or deg[s[-1]] > 2), key=len)
    inner = [int(n) for n in side if deg[n] <= 2]  # keep the bifurcation node in the graph
    keep = np.setdiff1d(np.arange(len(tree)), inner)
    return tree.subgraph(keep), np.asarray(inner)


def _weak_prediction(tree, scale):
    """A network-like prediction that is under-confident everywhere (occupancy × ``scale``)."""
    vox = voxelise_prediction(tree)
    vox.features["occupancy"] = vox.features["occupancy"] * scale
    return vox


def test_missing_side_branch_is_triangulated_and_attached():
    tree = synthetic_tree(3)
    views = [View.from_mask(c, render_mask(tree, c)) for c in CAMERAS]
    partial, missing = _without_a_side_branch(tree)
    branch = tree.nodes[missing]
    assert cKDTree(partial.nodes).query(branch)[0].max() > 10.0  # a real gap: the branch is ≥ 10 mm long
    added: list = []
    # the network saw the branch, but under the graph threshold (occupancy ≤ 0.15)
    done = complete_from_views(partial, views, _weak_prediction(tree, 0.15), added=added)
    assert len(done) > len(partial) and added
    new = done.nodes[len(partial):]
    # the branch is now covered, and what was added lies on the true tree (not a ghost along the ray)
    assert np.percentile(cKDTree(done.nodes).query(branch)[0], 90) < 1.0
    assert np.median(cKDTree(tree.sample(0.2)[0]).query(new)[0]) < 0.6
    # attached to the old graph, not left as a floating piece; old nodes and their ids untouched
    assert done.n_components() == partial.n_components()
    assert np.array_equal(done.nodes[:len(partial)], partial.nodes)
    assert np.array_equal(done.node_id[:len(partial)], partial.node_id)
    assert len(np.unique(done.node_id)) == len(done)


def test_a_further_view_keeps_the_branch_it_shows_and_vetoes_the_one_it_does_not():
    """With a third run, a completed branch must lie on its vessels too: where that view shows the branch it is added
    as with two views; where it shows no vessel there, nothing is added."""
    tree = synthetic_tree(3)
    third = Camera.from_carm(0, -35, 1050, 740, 0.3, 512, 512)
    views = [View.from_mask(c, render_mask(tree, c)) for c in CAMERAS]
    partial, missing = _without_a_side_branch(tree)
    weak = _weak_prediction(tree, 0.15)
    shown = complete_from_views(partial, views + [View.from_mask(third, render_mask(tree, third))], weak)
    assert np.percentile(cKDTree(shown.nodes).query(tree.nodes[missing])[0], 90) < 1.0
    hidden = complete_from_views(partial, views + [View.from_mask(third, render_mask(partial, third))], weak)
    assert len(hidden) == len(partial)


def test_complete_graph_is_left_unchanged_and_one_view_is_not_enough():
    tree = synthetic_tree(4)
    views = [View.from_mask(c, render_mask(tree, c)) for c in CAMERAS]
    done = complete_from_views(tree, views)
    assert len(done) == len(tree) and np.array_equal(done.edges, tree.edges)
    partial, _ = _without_a_side_branch(tree)
    assert len(complete_from_views(partial, views[:1])) == len(partial)


def test_paths_the_network_did_not_see_are_not_added():
    tree = synthetic_tree(3)
    views = [View.from_mask(c, render_mask(tree, c)) for c in CAMERAS]
    partial, _ = _without_a_side_branch(tree)
    # occupancy 0 along the missing branch (only the partial graph's lumen is predicted)
    done = complete_from_views(partial, views, voxelise_prediction(partial))
    assert len(done) == len(partial)
    # the same call with the gate off adds the branch: the gate, not the matching, held it back
    assert len(complete_from_views(partial, views, voxelise_prediction(partial), min_occupancy=0.0)) > len(partial)


def test_tubes_of_one_occupancy_level_do_not_veto_a_branch():
    """A geometric method's prediction is tubes around the points it matched (occupancy 1 only): it says
    nothing about a branch it did not match, so the branch both views show is added."""
    tree = synthetic_tree(3)
    views = [View.from_mask(c, render_mask(tree, c)) for c in CAMERAS]
    partial, missing = _without_a_side_branch(tree)
    tubes = voxelise_prediction(partial)
    tubes.features["occupancy"] = np.ones(len(tubes), np.float32)
    # even a gate that would take nine tenths of the path inside the tubes does not apply
    done = complete_from_views(partial, views, tubes, min_occupancy=0.9)
    assert np.percentile(cKDTree(done.nodes).query(tree.nodes[missing])[0], 90) < 1.0
    # a graded prediction of the same voxels does veto it
    tubes.features["occupancy"][0] = 0.5
    assert len(complete_from_views(partial, views, tubes, min_occupancy=0.9)) == len(partial)


def test_a_guide_wire_crossing_the_missing_branch_in_one_view_is_not_walked():
    """A straight wire entering view A's image crosses the missing branch there: the branch is added as
    without the wire, and nothing is triangulated along the wire."""
    from scipy import ndimage

    tree = synthetic_tree(3)
    partial, missing = _without_a_side_branch(tree)
    masks = [render_mask(tree, c) for c in CAMERAS]
    # the wire: from the top edge of view A through the middle of the missing branch's projection
    mid = CAMERAS[0].project(tree.nodes[missing[len(missing) // 2]][None])[0]
    rows = np.arange(0, 512)
    cols = np.rint(mid[1] + (rows - mid[0]) * 0.15).astype(int)
    ok = (cols >= 0) & (cols < 512)
    wire = np.zeros_like(masks[0], bool)
    wire[rows[ok], cols[ok]] = True
    masks[0] = masks[0] | ndimage.binary_dilation(wire, iterations=1)
    views = [View.from_mask(c, m) for c, m in zip(CAMERAS, masks)]
    done = complete_from_views(partial, views)
    assert np.percentile(cKDTree(done.nodes).query(tree.nodes[missing])[0], 90) < 1.0
    # every added point lies on the true tree: none on a ghost of the wire
    new = done.nodes[len(partial):]
    assert len(new) and np.percentile(cKDTree(tree.sample(0.2)[0]).query(new)[0], 95) < 1.5
