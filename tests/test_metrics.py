"""3D/2D metrics on hand-built volumes and point sets with values worked out by hand."""

from __future__ import annotations

import numpy as np
import pytest

from stages.core import metrics as M
from stages.core.errors import UserError
from stages.core.voxels import SparseVoxels


def vox(mask, voxel_size=0.5, origin=(0, 0, 0), offset=(0, 0, 0), occ=None):
    v = SparseVoxels.from_dense(mask, voxel_size, origin, offset)
    v.features["occupancy"] = np.ones(len(v), np.float32) if occ is None else occ
    return v


def box(shape, lo, hi):
    m = np.zeros(shape, bool)
    m[tuple(slice(a, b) for a, b in zip(lo, hi))] = True
    return m


def ball(shape, centre, r):
    g = np.indices(shape).transpose(1, 2, 3, 0)
    return np.linalg.norm(g - np.asarray(centre), axis=-1) <= r


def torus(shape, R, r, centre):
    g = np.indices(shape).transpose(1, 2, 3, 0) - np.asarray(centre, float)
    rho = np.hypot(g[..., 0], g[..., 1])
    return np.hypot(rho - R, g[..., 2]) <= r


# ---------------------------------------------------------------------------- identical / shifted
def test_identical_volumes_are_perfect():
    m = ball((20, 20, 20), (10, 10, 10), 6)
    r = M.metrics_3d(vox(m), vox(m))
    assert r["dice"] == 1.0 and r["cldice"] == 1.0
    assert r["chamfer_mm"] == 0.0 and r["hd95_mm"] == 0.0
    assert r["status"] == "ok" and r["n_pred_voxels"] == m.sum()


def test_one_voxel_shift_of_a_bar():
    # 10×6×6 bar shifted one voxel along its long axis: overlap 9×6×6 → Dice = 2·9/(10+10) = 0.9
    g = box((16, 10, 10), (2, 2, 2), (12, 8, 8))
    p = box((16, 10, 10), (3, 2, 2), (13, 8, 8))
    r = M.metrics_3d(vox(p), vox(g))
    assert r["dice"] == pytest.approx(0.9)


def test_one_voxel_shift_of_a_ball_distances():
    # A sphere shifted by δ = 0.5 mm: a surface point at angle θ to the shift is δ|cosθ| from the
    # other sphere (to first order), |cosθ| is uniform on [0, 1] over the sphere → each directed mean
    # δ/2, so CD = δ = 0.5 mm, and each directed 95th percentile 0.95 δ = 0.475 mm.
    g = ball((40, 40, 40), (20, 20, 20), 12)
    p = ball((40, 40, 40), (21, 20, 20), 12)
    r = M.metrics_3d(vox(p), vox(g))
    assert r["chamfer_mm"] == pytest.approx(0.5, abs=0.08)
    assert r["hd95_mm"] == pytest.approx(0.475, abs=0.08)
    assert r["dice"] == pytest.approx(1 - 3 / (4 * 12), abs=0.02)  # 1 − 3δ/(4R) for a small shift


def test_thin_tube_inside_thick_tube():
    # Coaxial tori (no end caps): tube radius 2 vs 4 voxels (1 vs 2 mm), major radius 14 voxels.
    shape = (44, 44, 14)
    c = (22, 22, 7)
    thin, thick = torus(shape, 14, 2, c), torus(shape, 14, 4, c)
    r = M.metrics_3d(vox(thin), vox(thick))
    # volume ratio of tori = (r1/r2)² → Dice = 2·1/(1+4) = 0.4 (discretised counts: exact below)
    assert r["dice"] == pytest.approx(2 * thin.sum() / (thin.sum() + thick.sum()))
    assert r["dice"] == pytest.approx(0.4, abs=0.05)
    # both skeletons are the core circle: S(thin) ⊂ thick, S(thick) ⊂ thin
    assert r["tprec"] == 1.0
    assert r["tsens"] == pytest.approx(1.0, abs=0.02)
    assert r["cldice"] == pytest.approx(1.0, abs=0.01)
    # the surfaces are 1 mm apart everywhere: each directed mean ≈ 1 → CD ≈ 2 mm, HD95 ≈ 1 mm
    assert r["chamfer_mm"] == pytest.approx(2.0, abs=0.2)
    assert r["hd95_mm"] == pytest.approx(1.0, abs=0.2)


def test_disjoint_shapes():
    g = box((30, 10, 10), (2, 2, 2), (6, 6, 6))
    p = box((30, 10, 10), (20, 2, 2), (24, 6, 6))
    r = M.metrics_3d(vox(p), vox(g))
    assert r["dice"] == 0.0 and r["cldice"] == 0.0 and r["tprec"] == 0.0 and r["tsens"] == 0.0
    # faces 14 voxels (7 mm) apart at least, 22 voxels (11 mm) at most
    assert 2 * 7.0 <= r["chamfer_mm"] <= 2 * 11.0
    assert 7.0 <= r["hd95_mm"] <= 11.0


def test_point_set_distances_by_hand():
    P = np.array([[0.0, 0, 0], [1.0, 0, 0]])
    G = np.array([[0.0, 0, 0]])
    r = M.chamfer_hd95(P, G)
    # P→G: [0, 1] mean 0.5; G→P: [0] mean 0 → CD 0.5; 95th percentile of [0, 1] (linear) = 0.95
    assert r["chamfer_mm"] == pytest.approx(0.5)
    assert r["hd95_mm"] == pytest.approx(0.95)
    P2 = np.array([[0.0, 0, 0], [3.0, 4.0, 0]])
    G2 = np.array([[0.0, 0, 0], [0.0, 4.0, 0]])
    r2 = M.chamfer_hd95(P2, G2)
    # P→G: [0, 3] mean 1.5; G→P: [0, 3] mean 1.5 → CD 3.0; HD95 = 0.95·3 = 2.85
    assert r2["chamfer_mm"] == pytest.approx(3.0)
    assert r2["hd95_mm"] == pytest.approx(2.85)


# ---------------------------------------------------------------------------- empty inputs
def test_empty_prediction_is_defined():
    g = ball((12, 12, 12), (6, 6, 6), 3)
    empty = SparseVoxels(np.zeros((0, 3)), 0.5, np.zeros(3), {"occupancy": np.zeros(0, np.float32)})
    r = M.metrics_3d(empty, vox(g))
    assert r["dice"] == 0.0 and r["cldice"] == 0.0
    assert np.isnan(r["chamfer_mm"]) and np.isnan(r["hd95_mm"])
    assert r["status"] == "empty-prediction"


def test_all_background_prediction_counts_as_empty():
    g = ball((12, 12, 12), (6, 6, 6), 3)
    p = vox(g, occ=np.full(int(g.sum()), 0.2, np.float32))  # voxels listed, none with p ≥ 0.5
    r = M.metrics_3d(p, vox(g))
    assert r["dice"] == 0.0 and r["status"] == "empty-prediction" and r["n_pred_voxels"] == 0


def test_both_empty():
    e = SparseVoxels(np.zeros((0, 3)), 0.5, np.zeros(3), {"occupancy": np.zeros(0, np.float32)})
    r = M.metrics_3d(e, e)
    assert (r["dice"], r["cldice"], r["chamfer_mm"], r["hd95_mm"], r["status"]) == (1.0, 1.0, 0.0, 0.0, "both-empty")


# ---------------------------------------------------------------------------- grids
def test_coarser_prediction_is_resampled_linearly():
    # 1 mm voxels with centres 0..9 mm. Trilinear occupancy on the 0.5 mm grid (origin −0.5 mm, so
    # centres −0.5..9.5, 21 per axis): 1 inside [0, 9]; 0.5 on a face half a voxel out (kept, ≥ 0.5);
    # 0.25 on edges and 0.125 at corners (dropped). Kept: the 19³ interior + 6 faces of 19² = 9025.
    pred = SparseVoxels.from_dense(np.ones((10, 10, 10), bool), 1.0, (0, 0, 0))
    pred.features["occupancy"] = np.ones(len(pred), np.float32)
    truth = vox(np.ones((21, 21, 21), bool), 0.5, (-0.5, -0.5, -0.5))
    r = M.metrics_3d(pred, truth)
    assert r["n_pred_voxels"] == 19 ** 3 + 6 * 19 ** 2
    assert r["dice"] == pytest.approx(2 * 9025 / (9025 + 21 ** 3))
    assert "prediction resampled" in r["notes"]


def test_shifted_origins_on_the_same_lattice_are_not_resampled():
    m = ball((16, 16, 16), (8, 8, 8), 5)
    a = vox(m, 0.5, (0, 0, 0))
    b = vox(m, 0.5, (10.0, 0, 0), offset=(-20, 0, 0))  # same world voxels, other origin
    r = M.metrics_3d(a, b)
    assert r["dice"] == 1.0 and r["notes"] == ""


def test_half_voxel_offset_grid_is_resampled():
    # a 0.5 mm prediction whose lattice is offset by 0.25 mm: resampled, a block stays nearly itself
    m = box((30, 30, 30), (5, 5, 5), (25, 25, 25))
    truth = vox(m)
    pred = vox(m, 0.5, (0.25, 0.25, 0.25))
    r = M.metrics_3d(pred, truth)
    assert "prediction resampled" in r["notes"]
    assert r["dice"] > 0.85


def test_far_apart_sets_refuse_clearly():
    a = vox(np.ones((2, 2, 2), bool), 0.5, (0, 0, 0))
    b = vox(np.ones((2, 2, 2), bool), 0.5, (5000.0, 5000.0, 5000.0))
    with pytest.raises(UserError, match="same world frame"):
        M.metrics_3d(a, b)


# ---------------------------------------------------------------------------- skeleton behaviour
def test_skeleton_of_thin_structures():
    line = np.zeros((5, 20, 5), bool)
    line[2, 2:18, 2] = True
    assert np.array_equal(M.skeleton(line), line)  # 1-voxel line is its own skeleton
    for w in ((2, 3), (3, 3), (2, 2), (4, 4)):  # skimage alone returns nothing for 2×2 and 4×4
        bar = np.zeros((8, 20, 8), bool)
        bar[2:2 + w[0], 2:18, 2:2 + w[1]] = True
        sk = M.skeleton(bar)
        assert np.all(bar[sk])  # inside the bar
        # one voxel per cross-section along the bar, ends shortened by about half the width
        assert np.all(sk.sum(axis=(0, 2))[5:15] == 1), w
    dot = np.zeros((3, 3, 3), bool)
    dot[1, 1, 1] = True
    assert M.skeleton(dot).sum() == 1


# ---------------------------------------------------------------------------- independent cross-check
def _random_shape(rng, shape):
    from scipy import ndimage

    noise = ndimage.gaussian_filter(rng.normal(size=shape), 2.0)
    return noise > np.percentile(noise, 85)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_dice_and_cldice_match_an_independent_formulation(seed):
    from skimage.morphology import skeletonize

    rng = np.random.default_rng(seed)
    shape = (28, 30, 26)
    pm, gm = _random_shape(rng, shape), _random_shape(rng, shape)
    off_p, off_g = rng.integers(-5, 5, 3), rng.integers(-5, 5, 3)
    origin = np.array([1.5, -2.0, 0.5])
    pred = vox(pm, 0.5, origin, offset=off_p)
    truth = vox(gm, 0.5, origin, offset=off_g)
    r = M.metrics_3d(pred, truth)
    # independent: sets of integer world indices, skeletons on a big zero-padded canvas
    P = {tuple(c) for c in pred.coords.tolist()}
    G = {tuple(c) for c in truth.coords.tolist()}
    assert r["dice"] == pytest.approx(2 * len(P & G) / (len(P) + len(G)))
    canvas_lo = np.minimum(pred.coords.min(0), truth.coords.min(0)) - 3
    size = tuple((np.maximum(pred.coords.max(0), truth.coords.max(0)) - canvas_lo + 4).tolist())

    def skel_set(coords):
        c = np.zeros(size, bool)
        idx = coords - canvas_lo
        c[tuple(idx.T)] = True
        plain = {tuple(x) for x in (np.argwhere(skeletonize(c)) + canvas_lo).tolist()}
        ours = {tuple(x) for x in (np.argwhere(M.skeleton(c)) + canvas_lo).tolist()}
        # our skeleton = skimage's plus stand-ins only for components skimage deleted entirely
        assert plain <= ours and ours <= {tuple(x) for x in coords.tolist()}
        return ours

    SP, SG = skel_set(pred.coords), skel_set(truth.coords)
    tprec, tsens = len(SP & G) / len(SP), len(SG & P) / len(SG)
    assert r["tprec"] == pytest.approx(tprec)
    assert r["tsens"] == pytest.approx(tsens)
    assert r["cldice"] == pytest.approx(2 * tprec * tsens / (tprec + tsens))


# ---------------------------------------------------------------------------- graphs
def test_graph_metrics_parallel_segments():
    # two parallel 10 mm segments 1 mm apart: every sample is exactly 1 mm from the other → 1.0;
    # radii 1.0 and 1.5 everywhere → radius error 0.5
    a = (np.array([[0, 0, 0], [10, 0, 0]], float), np.array([1.0, 1.0]), np.array([[0, 1]]))
    b = (np.array([[0, 1, 0], [10, 1, 0]], float), np.array([1.5, 1.5]), np.array([[0, 1]]))
    r = M.graph_metrics(a, b)
    assert r["centreline_error_mm"] == pytest.approx(1.0)
    assert r["radius_error_mm"] == pytest.approx(0.5)


def test_graph_metrics_directed_means_separate_straying_from_missing():
    # prediction = the first 10 mm of a 20 mm truth segment, shifted 1 mm: every predicted sample is
    # 1 mm from the truth; the truth's far half is missed (mean distance over it 1 + ... grows to ~10 mm)
    truth = (np.array([[0, 0, 0], [20, 0, 0]], float), None, np.array([[0, 1]]))
    pred = (np.array([[0, 1, 0], [10, 1, 0]], float), None, np.array([[0, 1]]))
    r = M.graph_metrics(pred, truth)
    assert r["centreline_pred_to_truth_mm"] == pytest.approx(1.0)
    far = np.linspace(10, 20, 41)  # truth samples beyond the prediction's end, 0.25 mm apart
    expected_missing = (np.sum(np.hypot(far - 10, 1.0)) + 40 * 1.0) / 81
    assert r["centreline_truth_to_pred_mm"] == pytest.approx(expected_missing, rel=1e-6)
    assert r["centreline_error_mm"] == pytest.approx(0.5 * (1.0 + expected_missing))


def test_sample_graph_interpolates_radius():
    pts, rad = M.sample_graph([[0, 0, 0], [1, 0, 0]], [1.0, 2.0], [[0, 1]], step=0.25)
    order = np.argsort(pts[:, 0])
    assert np.allclose(pts[order, 0], [0, 0.25, 0.5, 0.75, 1.0])
    assert np.allclose(rad[order], [1, 1.25, 1.5, 1.75, 2.0])


# ---------------------------------------------------------------------------- 2D correspondences
def test_correspondence_metrics_by_hand():
    truth_b = np.array([[10.0, 10], [20, 20], [30, 30], [40, 40]])
    partners = np.array([[10.0, 10], [20, 24], [30, 45], [np.nan, np.nan]])  # exact, 4 px, 15 px, uncovered
    r = M.correspondence_metrics(partners, truth_b, spacing_b_mm=0.3)
    assert r["coverage"] == pytest.approx(0.75)
    assert r["epe_mm"] == pytest.approx((0 + 1.2 + 4.5) / 3)
    assert r["accuracy"] == pytest.approx(2 / 4)  # errors 0 and 1.2 mm are < 3 mm
    assert r["accuracy_covered"] == pytest.approx(2 / 3)


def test_no_covered_query_and_no_pairs():
    r = M.correspondence_metrics(np.full((2, 2), np.nan), np.zeros((2, 2)), 0.3)
    assert r["coverage"] == 0 and r["accuracy"] == 0 and np.isnan(r["epe_mm"]) and r["status"] == "no-covered-query"
    with pytest.raises(UserError, match="no annotated"):
        M.correspondence_metrics(np.zeros((0, 2)), np.zeros((0, 2)), 0.3)


def test_match_partners_queries_view_a():
    # two predicted pairs; the query sits on pair 0's A-point, though pair 1's B-point lies nearer the
    # annotated partner: the partner must come from view A's match (pair 0)
    pred_a = np.array([[5.0, 5.0], [50.0, 50.0]])
    pred_b = np.array([[100.0, 100.0], [10.0, 10.0]])
    out = M.match_partners(pred_a, pred_b, [[5.2, 5.0], [200.0, 200.0]], cover_px=2.0)
    assert np.allclose(out[0], [100, 100])
    assert np.all(np.isnan(out[1]))  # nothing within 2 px of the second query → uncovered


def test_match_partners_tie_goes_to_heavier_weight():
    pred_a = np.array([[5.0, 5.0], [5.0, 5.0]])  # same A pixel (points on one ray)
    pred_b = np.array([[1.0, 1.0], [9.0, 9.0]])
    out = M.match_partners(pred_a, pred_b, [[5.0, 5.0]], cover_px=1.0, weights=[0.2, 0.9])
    assert np.allclose(out[0], [9, 9])


def test_centreline_by_radius_bins_recall_and_radius_error():
    from stages.core.metrics import centreline_by_radius

    t = np.stack([np.linspace(0, 20, 41), np.zeros(41), np.zeros(41)], 1)  # 0.5 mm spacing
    r = np.where(t[:, 0] < 10, 0.6, 2.0)  # a thin half (< 0.9 mm) and a thick half (> 1.5 mm)
    found = t[t[:, 0] >= 10] + [0, 0.2, 0]  # only the thick half, 0.2 mm off, radius 0.3 mm too large
    s = centreline_by_radius(found, np.full(len(found), 2.3), t, r)
    assert s["recall_small"] < 0.1 and s["recall_large"] == 1.0 and s["recall_medium"] is None
    assert s["radius_mae_large"] == pytest.approx(0.3) and s["radius_mae_small"] is None
    assert s["precision"] == 1.0 and s["radius_bias_mm"] == pytest.approx(0.3)
    empty = centreline_by_radius(np.zeros((0, 3)), np.zeros(0), t, r)
    assert empty["recall_large"] == 0.0 and empty["precision"] is None
