"""The reconstruction's own quality checks (stages/quality.py; issue 36, finding 7) on graphs built by hand
and masks drawn from their projections."""

from __future__ import annotations

import numpy as np
import pytest

from stages.core.catheter import near_border
from stages.core.geometry import Camera
from stages.graph.vascular import VascularGraph
from stages.quality import CATHETER_MIN_MM, FAR_PIECE_MM, frame_quality, pieces, summarise


def _polyline(points, step=0.5):
    points = np.asarray(points, float)
    out = [points[0]]
    for a, b in zip(points[:-1], points[1:]):
        n = max(int(np.ceil(np.linalg.norm(b - a) / step)), 1)
        out += [a + (b - a) * t for t in np.arange(1, n + 1) / n]
    return np.asarray(out)


def _graph(*paths, attach=None):
    """Paths as chains of nodes; ``attach[i] = (path j, node k)`` joins path i's first node to that node."""
    nodes, edges, starts = [], [], []
    for path in paths:
        starts.append(len(nodes))
        base = len(nodes)
        nodes += list(path)
        edges += [(base + i, base + i + 1) for i in range(len(path) - 1)]
    for i, (j, k) in (attach or {}).items():
        edges.append((starts[j] + k, starts[i]))
    return VascularGraph(np.asarray(nodes), np.full(len(nodes), 1.0), np.asarray(edges))


def _curve():
    t = np.linspace(0, np.pi, 9)
    return _polyline(np.stack([30 * np.cos(t), 10 * np.sin(2 * t), 30 * np.sin(t) - 15], 1))


@pytest.fixture(scope="module")
def cams():
    return {"a": Camera.from_carm(30.0, 0.0, 1000.0, 750.0, (0.5, 0.5), 512, 512),
            "b": Camera.from_carm(-40.0, 10.0, 1000.0, 750.0, (0.5, 0.5), 512, 512)}


def _masks(graph, cams, shift=(0, 0), width=2):
    from scipy import ndimage

    pts = graph.sample(0.2)[0]
    out = {}
    for v, cam in cams.items():
        m = np.zeros((cam.rows, cam.cols), bool)
        rc = np.rint(cam.project(pts)).astype(int) + np.asarray(shift)
        ok = (rc[:, 0] >= 0) & (rc[:, 0] < cam.rows) & (rc[:, 1] >= 0) & (rc[:, 1] < cam.cols)
        m[rc[ok, 0], rc[ok, 1]] = True
        out[v] = ndimage.binary_dilation(m, iterations=width)
    return out


def test_a_tree_its_masks_agree_with_passes(cams):
    g = _graph(_curve())
    q = frame_quality(g, _masks(g, cams), cams, key="00")
    assert q["passed"], q["problems"]
    assert len(q["pieces"]) == 1 and q["pieces"][0]["length_mm"] == pytest.approx(g.length(), abs=0.1)
    assert q["far_pieces"] == [] and q["branches_outside_masks"] == [] and q["catheter_like"] == []
    assert all(d < 0.5 for d in q["reprojection_mm"].values())
    assert summarise([q])["verdict"] == "quality: passes its own checks on all 1 key frame(s)"


def test_a_floating_ghost_is_a_far_piece_outside_both_masks(cams):
    tree = _graph(_curve())
    ghost_path = _polyline([[0, 40, 30], [4, 43, 30], [6, 45, 33]])
    g = _graph(_curve(), ghost_path)
    q = frame_quality(g, _masks(tree, cams), cams, key="00")  # the masks show the tree only
    assert len(q["pieces"]) == 2
    far = q["far_pieces"]
    assert len(far) == 1 and far[0]["distance_mm"] > FAR_PIECE_MM
    assert far[0]["length_mm"] == pytest.approx(np.linalg.norm(np.diff(ghost_path, axis=0), axis=1).sum(), abs=0.1)
    assert len(q["branches_outside_masks"]) == 1
    assert not q["passed"]
    s = summarise([q])
    assert not s["passed"] and s["failed_frames"] == ["00"] and s["verdict"].startswith("quality: FAILS")
    assert "from the main tree" in s["verdict"]


def test_a_near_piece_is_not_far(cams):
    curve = _curve()
    near = _polyline([curve[0] + [3, 0, 0], curve[0] + [8, 0, 0]])  # 3 mm from the vessel's end
    g = _graph(curve, near)
    q = frame_quality(g, _masks(g, cams), cams)
    assert len(q["pieces"]) == 2 and q["far_pieces"] == [] and q["pieces"][1]["distance_mm"] < FAR_PIECE_MM
    # a piece beyond it, > 10 mm from the largest piece but joined to the tree through the near one: not far
    beyond = _polyline([curve[0] + [16, 0, 0], curve[0] + [18, 0, 0]])
    assert np.linalg.norm(curve[:, None] - beyond[None], axis=-1).min() > FAR_PIECE_MM
    g = _graph(curve, near, beyond)
    q = frame_quality(g, _masks(g, cams), cams)
    assert len(q["pieces"]) == 3 and q["far_pieces"] == []
    assert all(p["distance_mm"] <= FAR_PIECE_MM for p in q["pieces"])


def test_a_long_straight_branch_entering_the_image_is_catheter_like(cams):
    curve = _curve()
    k = len(curve) // 3  # a side branch off the middle of the vessel, running out of the field of view
    rod = _polyline([curve[k] + [0, 0, 1], curve[k] + [0, 0, 100]])
    g = _graph(curve, rod, attach={1: (0, k)})
    q = frame_quality(g, _masks(g, cams), cams)
    assert len(q["catheter_like"]) == 1
    assert q["catheter_like"][0]["length_mm"] >= CATHETER_MIN_MM and q["catheter_like"][0]["straightness"] > 0.99
    assert not q["passed"] and any("catheter" in p for p in q["problems"])
    # as long and as straight, but ending inside the image (a straight stretch of vessel): not flagged
    inside = _graph(curve, _polyline([curve[k] + [0, 0, 1], curve[k] + [0, 0, CATHETER_MIN_MM + 5]]), attach={1: (0, k)})
    assert frame_quality(inside, _masks(inside, cams), cams)["catheter_like"] == []
    short = _graph(curve, _polyline([curve[k] + [0, 0, 1], curve[k] + [0, 0, 8]]), attach={1: (0, k)})
    assert frame_quality(short, _masks(short, cams), cams)["catheter_like"] == []
    # as long and as straight, leaving the image downwards (a vessel heading for the apex): not flagged
    down = _graph(curve, _polyline([curve[k] - [0, 0, 1], curve[k] - [0, 0, 100]]), attach={1: (0, k)})
    assert any(near_border(cam, curve[k] - [0, 0, 100]) for cam in cams.values())
    assert frame_quality(down, _masks(down, cams), cams)["catheter_like"] == []
    # a catheter entering the tree at the ostium (the vessel's free end): one segment, straight at its far end
    inlet = _polyline([curve[0] + [0, 0, 100], curve[0] + [0, 0, 1]])
    joined = _graph(inlet, curve, attach={1: (0, len(inlet) - 1)})
    q = frame_quality(joined, _masks(joined, cams), cams)
    assert len(q["catheter_like"]) == 1 and q["catheter_like"][0]["length_mm"] >= CATHETER_MIN_MM


def test_graph_opt_drops_the_catheter_like_stretches_and_keeps_the_vessels(cams):
    """graph-opt removes what the check would flag: the rod entering the image and the inlet at the ostium go,
    the vessel they join and a straight stretch ending inside the image stay; the check then passes."""
    from stages.graph.optimise import View
    from stages.graph.redundancy import drop_catheter_runs

    curve = _curve()
    k = len(curve) // 3
    rod = _polyline([curve[k] + [0, 0, 1], curve[k] + [0, 0, 100]])
    inlet = _polyline([curve[0] + [0, 0, 100], curve[0] + [0, 0, 1]])
    stub = _polyline([curve[2 * k] + [0, 0, 1], curve[2 * k] + [0, 0, CATHETER_MIN_MM + 5]])
    g = _graph(inlet, curve, rod, stub, attach={1: (0, len(inlet) - 1), 2: (1, k), 3: (1, 2 * k)})
    masks = _masks(g, cams)
    views = [View.from_mask(cams[v], masks[v]) for v in sorted(cams)]
    dropped = []
    kept = drop_catheter_runs(g, views, dropped=dropped)
    assert len(dropped) == 2 and min(dropped) > 90
    assert len(curve) + len(stub) - 3 <= len(kept) <= len(curve) + len(stub)  # the inlet's run may take a node of the vessel
    q = frame_quality(kept, masks, cams)
    assert q["catheter_like"] == [] and len(q["pieces"]) == 1
    # the same rule on the tracked topology (after nodes were moved): the key frames' majority decides
    from stages.graph.optimise import FrameInput, TrackedGraphs
    from stages.graph.stage import drop_catheter_runs_tracked

    tracked = TrackedGraphs(["00", "01", "02"], [g] * 3, [None] * 3, np.zeros(len(g), np.int64))
    out = drop_catheter_runs_tracked(tracked, [FrameInput(k, g, views) for k in tracked.keys])
    assert all(np.array_equal(h.node_id, kept.node_id) for h in out.graphs) and len(out.first_frame) == len(kept)
    straight_in_one = [FrameInput("00", g, views)] + [FrameInput(k, g, []) for k in ("01", "02")]  # no views: no cut
    assert len(drop_catheter_runs_tracked(tracked, straight_in_one).graphs[0]) == len(g)


def test_reprojection_distance_is_in_mm_at_the_isocentre(cams):
    # a vessel along the patient's axis projects onto an image column (β = 0 in view a); masks moved 6 columns
    g = _graph(_polyline([[0, 0, -20], [0, 0, 20]]))
    q = frame_quality(g, _masks(g, {"a": cams["a"]}, shift=(0, 6), width=1), {"a": cams["a"]})
    assert q["reprojection_mm"]["a"] == pytest.approx(6 * cams["a"].isocentre_spacing, rel=0.1)
    aligned = frame_quality(g, _masks(g, {"a": cams["a"]}, width=1), {"a": cams["a"]})
    assert aligned["reprojection_mm"]["a"] < 0.2 * q["reprojection_mm"]["a"]


def test_pieces_of_an_empty_graph():
    assert pieces(VascularGraph.empty()) == []
