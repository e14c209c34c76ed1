"""Graph initialisation, curve segments, Algorithm-1 matching and the deformation graph (no torch needed
except in the deformation-graph consistency test)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from stages.graph import (DeformationGraph, EmptyPredictionError, VascularGraph, init_graph, match_curve_dp,
                          match_curve_greedy)
from stages.graph.synthetic import synthetic_tree, voxelise_prediction
from stages.core.voxels import SparseVoxels


def _centreline_distances(rec: VascularGraph, truth: VascularGraph):
    tp, tr = truth.sample(0.1)
    rp, rr = rec.sample(0.1)
    d_tr = cKDTree(rp).query(tp)[0]
    d_rt, i = cKDTree(tp).query(rp)
    return d_tr, d_rt, rr - tr[i]


# ---------------------------------------------------------------------------------------------- structure
def test_segments_split_at_junctions_and_cover_every_edge_once():
    # a Y (junction at node 2) plus a separate closed loop of 4 nodes
    nodes = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 1, 0], [4, 2, 0], [3, -1, 0],
                      [10, 0, 0], [11, 0, 0], [11, 1, 0], [10, 1, 0]], float)
    edges = [(0, 1), (1, 2), (2, 3), (3, 4), (2, 5), (6, 7), (7, 8), (8, 9), (9, 6)]
    g = VascularGraph(nodes, np.ones(10), edges)
    segs = g.segments()
    assert sorted(len(s) for s in segs) == [2, 3, 3, 5]  # 2→5, 0-1-2, 2-3-4, loop 6-7-8-9-6
    walked = sorted(tuple(sorted(p)) for s in segs for p in zip(s[:-1], s[1:]))
    assert walked == sorted(tuple(sorted(e)) for e in edges)
    assert list(g.bifurcations()) == [2]
    assert g.n_components() == 2
    coarse, kept = g.decimate(2.0)
    assert {0, 2, 4, 5} <= set(kept.tolist()) and coarse.n_components() == 2


def test_position_along_tree_continues_into_detached_pieces():
    # main vessel x = 0…10 (widest at x = 0), a side branch off x = 5, a detached distal piece x = 12…16 and
    # a short wide fragment beside the root: the root stays on the main vessel, the distal piece continues from x = 10
    main = [[x, 0, 0] for x in range(11)]
    branch = [[5, y, 0] for y in range(1, 4)]
    distal = [[x, 0, 0] for x in range(12, 17)]
    fragment = [[0, 4, 0], [0, 5, 0]]
    nodes = np.array(main + branch + distal + fragment, float)
    radius = np.r_[np.linspace(2.0, 1.0, 11), np.full(3, 0.8), np.full(5, 0.7), [3.0, 3.0]]
    edges = ([(i, i + 1) for i in range(10)] + [(5, 11), (11, 12), (12, 13)]
             + [(i, i + 1) for i in range(14, 18)] + [(19, 20)])
    pos = VascularGraph(nodes, radius, edges).position_along_tree()
    total = 16.0  # the distal end: 10 along the main vessel + 2 across the gap + 4 along the piece
    assert np.allclose(pos[:11], np.arange(11) / total)
    assert np.allclose(pos[11:14], (5 + np.arange(1, 4)) / total)
    assert np.allclose(pos[14:19], np.arange(12, 17) / total)
    # the fragment hangs from its nearest placed node (the root, 4 mm away) instead of being a second root
    assert np.allclose(pos[19:], [4 / total, 5 / total])
    assert pos.max() == 1.0 and VascularGraph.empty().position_along_tree().shape == (0,)


# ---------------------------------------------------------------------------------------------- init
@pytest.mark.parametrize("seed,noise", [(0, 0.0), (1, 0.1), (2, 0.1)])
def test_init_graph_recovers_synthetic_tree(seed, noise):
    truth = synthetic_tree(seed)
    pred = voxelise_prediction(truth, noise=noise, seed=seed)
    g = init_graph(pred)
    d_tr, d_rt, dr = _centreline_distances(g, truth)
    # recovered centreline on the truth: sub-voxel (0.5 mm voxels)
    assert d_rt.mean() < 0.2 and np.percentile(d_rt, 95) < 0.5
    # truth covered, except the last ~radius at the tips that thinning always shortens
    assert d_tr.mean() < 0.25 and np.percentile(d_tr, 90) < 0.5
    assert len(g.bifurcations()) == len(truth.bifurcations()) == 4
    assert g.n_components() == 1
    assert abs(dr.mean()) < 0.12 and np.abs(dr).mean() < 0.15  # radius in mm


def test_init_graph_spur_pruning_matters():
    truth = synthetic_tree(1)
    pred = voxelise_prediction(truth)
    pruned = init_graph(pred)
    raw = init_graph(pred, spur_length_mm=0.0, spur_radius_factor=0.0)
    assert len(raw.bifurcations()) > len(pruned.bifurcations()) == len(truth.bifurcations())


def test_init_graph_bridges_sub_threshold_gap():
    truth = synthetic_tree(3)
    pred = voxelise_prediction(truth)
    # a 1.5 mm slab across the main branch with sub-threshold occupancy breaks the thresholded set in two
    p, q = truth.nodes[60], truth.nodes[62]
    t = (q - p) / np.linalg.norm(q - p)
    X = pred.world_points()
    slab = (np.abs((X - p) @ t) < 0.75) & (np.linalg.norm(X - p, axis=1) < 5)
    occ = pred.features["occupancy"].copy()
    occ[slab] *= 0.4  # ≤ 0.4: below the threshold, still well above the bridging floor
    gap = SparseVoxels(pred.coords, pred.voxel_size, pred.origin, {**pred.features, "occupancy": occ})
    unbridged = init_graph(gap, bridge_max_cost=0.0)
    bridged = init_graph(gap)
    assert unbridged.n_components() == 2
    assert bridged.n_components() == 1
    d_tr, d_rt, _ = _centreline_distances(bridged, truth)
    near_gap = np.linalg.norm(truth.sample(0.1)[0] - p, axis=1) < 2
    assert d_tr[near_gap].max() < 0.6  # the bridge runs along the true centreline through the gap
    assert len(bridged.bifurcations()) == 4


def test_init_graph_empty_prediction():
    vox = SparseVoxels(np.array([[0, 0, 0], [1, 0, 0]]), 0.5, np.zeros(3),
                       {"occupancy": np.array([0.2, 0.3], np.float32), "centreness": np.zeros(2, np.float32)})
    with pytest.raises(EmptyPredictionError, match="occupancy ≥ 0.5.*highest is 0.3"):
        init_graph(vox)
    g = init_graph(vox, allow_empty=True)
    assert len(g) == 0 and len(g.edges) == 0


def test_thinning_piece_by_piece_gives_the_skeleton_of_the_whole_volume():
    """Pieces touching only diagonally, pieces in each other's boxes, and a blob: each 26-connected piece thinned in
    its own box gives exactly the thinning of the whole volume, in the same (raster) order."""
    from skimage.morphology import skeletonize

    from stages.graph.init import _thinned_voxels

    rng = np.random.default_rng(3)
    vol = np.zeros((40, 50, 45), bool)
    zz, yy, xx = np.mgrid[:40, :50, :45]
    for _ in range(12):  # random thick segments crossing each other's boxes
        a, b = rng.uniform([2, 2, 2], [38, 48, 43], (2, 3))
        t = np.clip(((np.stack([zz, yy, xx], -1) - a) @ (b - a)) / ((b - a) @ (b - a)), 0, 1)
        d = np.linalg.norm(np.stack([zz, yy, xx], -1) - (a + t[..., None] * (b - a)), axis=-1)
        vol |= d <= rng.uniform(0.8, 2.5)
    vol[0:3, 0:3, 0:3] = True
    vol[3, 3, 3] = True  # touches the corner cube diagonally only: the same 26-connected piece
    expected = np.argwhere(skeletonize(vol))
    np.testing.assert_array_equal(_thinned_voxels(np.argwhere(vol)), expected)
    assert len(_thinned_voxels(np.zeros((0, 3), int))) == 0


# ---------------------------------------------------------------------------------------------- matching
def _parallel_case():
    x = np.arange(0, 60, 0.5)
    A = np.c_[x, np.zeros_like(x), np.zeros_like(x)]
    B = np.c_[x, np.full_like(x, 2.5), np.zeros_like(x)]  # a parallel vessel 2.5 mm away
    xs = np.arange(2, 58, 1.0)
    bump = 1.8 * np.exp(-((xs - 30) / 6) ** 2)  # the curve (vessel A) bulges towards B: nearer to B there
    Q = np.c_[xs + 0.3, bump, 0 * xs]
    truth = np.c_[xs + 0.3, 0 * xs, 0 * xs]
    return np.vstack([A, B]), len(A), Q, truth


def test_dp_beats_greedy_on_parallel_vessels():
    T, nA, Q, truth = _parallel_case()
    dp = match_curve_dp(Q, T)
    greedy = match_curve_greedy(Q, T)
    assert (dp >= nA).sum() == 0  # the DP stays on vessel A
    assert (greedy >= nA).sum() >= 5  # nearest-point matching jumps to the neighbour
    err_dp = np.linalg.norm(T[dp] - truth, axis=1).mean()
    err_gr = np.linalg.norm(T[greedy] - truth, axis=1).mean()
    assert err_dp < 0.35 < err_gr


def test_dp_2d_crossing_keeps_the_right_branch():
    # two vessels crossing in projection at 30°; the curve follows vessel 1 displaced 0.9 px towards vessel 2
    s = np.arange(-30, 30, 0.5)
    v1 = np.c_[s, 0 * s]
    ang = np.radians(30)
    v2 = np.c_[s * np.cos(ang), s * np.sin(ang)]
    T = np.vstack([v1, v2])
    q = np.arange(-25, 25, 1.0)
    Q = np.c_[q, 0.9 * np.sign(q) * np.minimum(np.abs(q) / 3, 1)]
    dp = match_curve_dp(Q, T)
    greedy = match_curve_greedy(Q, T)
    assert (dp >= len(v1)).sum() == 0
    assert (greedy >= len(v1)).sum() >= 2


def test_dp_null_state_leaves_points_beyond_the_target_unmatched():
    x = np.arange(0, 20, 0.5)
    T = np.c_[x, 0 * x, 0 * x]
    xs = np.arange(0, 40, 1.0)
    Q = np.c_[xs, 0.2 + 0 * xs, 0 * xs]  # the curve runs 20 mm past the target's end
    m = match_curve_dp(Q, T, null_cost=3.0)
    assert (m[xs < 19] >= 0).all() and (m[xs > 23] == -1).all()
    m_all = match_curve_dp(Q, T)
    assert (m_all >= 0).all()


# ---------------------------------------------------------------------------------------------- deformation graph
def test_deformation_graph_rigid_parameters_warp_rigidly():
    from stages.graph.deformation import rodrigues
    from stages.graph.optimise import _Warp

    g = synthetic_tree(0)
    dg = DeformationGraph.from_graph(g, spacing_mm=5.0)
    assert 20 < len(dg) < 120
    X = g.nodes
    assert np.allclose(dg.warp(X), X)  # zero parameters: identity
    rvec, t, c = np.array([0.05, -0.1, 0.08]), np.array([1.0, -2.0, 0.5]), X.mean(0)
    R = rodrigues(rvec)[0]
    dg.params = np.hstack([np.tile(rvec, (len(dg), 1)), (dg.nodes - c) @ R.T + c + t - dg.nodes])
    expected = (X - c) @ R.T + c + t
    assert np.abs(dg.warp(X) - expected).max() < 1e-9
    assert dg.regulariser() < 1e-18
    warp = _Warp.of_deformation(X, dg)  # the registration's form of the same warp
    assert np.abs(warp.positions(dg.params, rodrigues(dg.params[:, :3])) - expected).max() < 1e-9
    # a non-rigid perturbation: both forms agree, and the regulariser is positive
    rng = np.random.default_rng(0)
    dg.params = dg.params + rng.normal(0, 0.02, dg.params.shape)
    assert np.abs(warp.positions(dg.params, rodrigues(dg.params[:, :3])) - dg.warp(X)).max() < 1e-9
    assert dg.regulariser() > 0
    reg = _Warp.of_deformation(X, dg, rotation_weight=0.3).regulariser(dg.params, rodrigues(dg.params[:, :3]))[0]
    assert abs(reg * len(dg.edges) - dg.regulariser(rotation_weight=0.3)) < 1e-9
    back = dg.inverse_warp(dg.warp(X))
    assert np.abs(back - X).max() < 1e-3


def test_inverse_warp_converges_where_nodes_twist_strongly():
    """Node rotations of ~100° (a free twist about a vessel's axis) make the fixed-point iteration
    x ← y − u(x) diverge; the damped Newton inverse must still land every point back on its pre-image."""
    x = np.linspace(0, 40, 81)
    dg = DeformationGraph.from_points(np.c_[x, 0 * x, 0 * x], spacing_mm=5.0)
    rng = np.random.default_rng(3)
    dg.params = np.hstack([np.c_[rng.uniform(-1.8, 1.8, len(dg)), np.zeros((len(dg), 2))],  # twist about x
                           rng.normal(0, 1.0, (len(dg), 3))])
    # points off the axis (a side branch 2–4 mm away), where the twist moves them most
    X = np.c_[rng.uniform(2, 38, 200), rng.uniform(-4, 4, 200), rng.uniform(-4, 4, 200)]
    Y = dg.warp(X)
    old = Y.copy()
    for _ in range(10):
        old = Y - (dg.warp(old) - old)
    old_err = np.linalg.norm(dg.warp(old) - Y, axis=1)
    assert (old_err > 0.1).mean() > 0.03 and old_err.max() > 1.0  # the plain iteration does fail here
    back = dg.inverse_warp(Y)
    assert np.linalg.norm(dg.warp(back) - Y, axis=1).max() < 1e-3
    assert np.linalg.norm(back - X, axis=1).max() < 1e-3  # this warp is one-to-one: the true pre-image


def test_rotation_weight_penalises_neighbours_twisting_apart():
    x = np.linspace(0, 40, 81)
    dg = DeformationGraph.from_points(np.c_[x, 0 * x, 0 * x], spacing_mm=5.0)
    twist = np.zeros((len(dg), 6))
    twist[::2, 0] = 1.5  # every other node twisted about the line through all of them
    assert dg.regulariser(twist) < 1e-9  # Eq. 13 alone does not see a twist about the axis
    assert dg.regulariser(twist, rotation_weight=1.0) > 10.0
    assert dg.regulariser(np.zeros_like(twist), rotation_weight=1.0) == 0.0


def test_sample_says_which_edge_each_point_lies_on():
    # a 10 mm and a 2 mm edge at a right angle, sampled every 0.5 mm: 20 + 4 points on them, then the two end nodes
    g = VascularGraph(np.array([[0.0, 0, 0], [10, 0, 0], [10, 2, 0]]), np.ones(3), np.array([[0, 1], [1, 2]]))
    P, r, edge = g.sample(0.5, with_edges=True)
    assert edge.tolist() == [0] * 20 + [1] * 4 + [-1, -1]
    assert np.all(P[edge == 0, 1] == 0) and np.all(P[edge == 1, 0] == 10)
    plain = g.sample(0.5)
    assert np.array_equal(plain[0], P) and np.array_equal(plain[1], r)
