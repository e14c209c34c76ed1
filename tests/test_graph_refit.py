"""Vessels that overlap in one view (stages.graph.refit): two parallel vessels a millimetre apart in view A, one band
in its mask, are placed back where views B and C see them after starting on A's skeleton between them; with two
views nothing moves; a tree without overlaps stays where it is."""

from __future__ import annotations

import numpy as np
from scipy.ndimage import binary_dilation
from scipy.spatial import cKDTree

from stages.core.geometry import Camera
from stages.graph.optimise import View
from stages.graph.refit import overlapped_nodes, refit_overlapped_nodes
from stages.graph.vascular import VascularGraph

CAMERAS = [Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512), Camera.from_carm(-35, -15, 1100, 750, 0.3, 512, 512),
           Camera.from_carm(75, -25, 1100, 750, 0.3, 512, 512)]


def _lines(*polylines: np.ndarray) -> VascularGraph:
    """One component per polyline (radius 1 mm)."""
    nodes, edges, n = [], [], 0
    for line in polylines:
        nodes.append(line)
        edges.append(np.stack([np.arange(n, n + len(line) - 1), np.arange(n + 1, n + len(line))], 1))
        n += len(line)
    return VascularGraph(np.vstack(nodes), np.ones(n), np.vstack(edges))


def _view(camera: Camera, graph: VascularGraph) -> View:
    """The view of ``graph``'s vessels: its 0.25 mm samples projected, dilated by 2 px, thinned."""
    mask = np.zeros((camera.rows, camera.cols), bool)
    rc = np.rint(camera.project(graph.sample(0.25)[0])).astype(int)
    ok = camera.in_image(rc)
    mask[rc[ok, 0], rc[ok, 1]] = True
    return View.from_mask(camera, binary_dilation(mask, iterations=2).astype(np.uint8))


def _scene():
    """Two straight vessels 40 mm long: the second 12 mm deeper along view A's rays and 1 mm aside, so A shows one
    band; B and C show them apart."""
    a = CAMERAS[0]
    depth = a.view_dir
    along = np.cross(depth, [0.0, 0.0, 1.0])
    along /= np.linalg.norm(along)
    aside = np.cross(depth, along)
    t = np.linspace(-20, 20, 81)[:, None]
    first = t * along + 0.15 * t * aside
    second = first + 12.0 * depth + 1.0 * aside
    return first, second, aside


def test_vessels_overlapping_in_one_view_go_back_where_the_other_two_see_them():
    first, second, aside = _scene()
    truth = _lines(first, second)
    views = [_view(c, truth) for c in CAMERAS]
    assert overlapped_nodes(truth, CAMERAS[0]).mean() > 0.8  # one band in view A ...
    assert not overlapped_nodes(truth, CAMERAS[1]).any() and not overlapped_nodes(truth, CAMERAS[2]).any()  # ... apart
    # as the 3D step leaves them: both moved half a millimetre towards each other, onto A's skeleton between them
    start = _lines(first + 0.5 * aside, second - 0.5 * aside)
    refitted, moved = refit_overlapped_nodes(start, views)
    assert moved > 0.8 * len(start)
    assert np.array_equal(refitted.edges, start.edges) and np.array_equal(refitted.node_id, start.node_id)
    before = np.linalg.norm(start.nodes - truth.nodes, axis=1)
    after = np.linalg.norm(refitted.nodes - truth.nodes, axis=1)
    assert np.median(before) > 0.45 and np.median(after) < 0.25
    # a point on the first vessel's line in view A is now nearest the first vessel, not the second
    qa = CAMERAS[0].project(refitted.nodes)
    queries = CAMERAS[0].project(first[10:-10])
    _, nearest = cKDTree(qa).query(queries)
    assert np.mean(nearest < len(first)) > 0.9


def test_two_views_move_nothing_and_a_tree_without_overlaps_stays():
    first, second, aside = _scene()
    start = _lines(first + 0.5 * aside, second - 0.5 * aside)
    views = [_view(c, _lines(first, second)) for c in CAMERAS]
    same, moved = refit_overlapped_nodes(start, views[:2])
    assert moved == 0 and same is start
    alone = _lines(first)
    same, moved = refit_overlapped_nodes(alone, [_view(c, alone) for c in CAMERAS])
    assert moved == 0 and np.array_equal(same.nodes, alone.nodes)
