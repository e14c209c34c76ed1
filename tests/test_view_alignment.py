"""Inter-run motion correction (stages/view_alignment.py): view B's image shift from two vessel masks."""

import numpy as np
import pytest

from stages.core.geometry import Camera, epipolar_angles, epipolar_frame
from stages.graph.synthetic import render_mask, synthetic_tree
from stages.view_alignment import (REFINE_PX, _across_direction, estimate_run_shifts,
                                   estimate_view_b_shift, mismatch_curve)

CAM_A = Camera.from_carm(30, 20, 1100, 750, 0.3, 512, 512)
CAM_B = Camera.from_carm(-35, -15, 1100, 750, 0.3, 512, 512)


def _tree(seed=3):
    return synthetic_tree(seed, n_side=6, main_length=110.0, centre=(0.0, 0.0, 0.0))


def _across(px):
    u, _ = _across_direction(CAM_B, epipolar_frame(CAM_A, CAM_B))
    return px * u


def test_one_point_has_the_same_epipolar_angle_in_both_views():
    pts = np.random.default_rng(0).normal(scale=30.0, size=(20, 3))
    frame = epipolar_frame(CAM_A, CAM_B)
    ta = epipolar_angles(CAM_A, CAM_A.project(pts), frame)
    tb = epipolar_angles(CAM_B, CAM_B.project(pts), frame)
    np.testing.assert_allclose(ta, tb, atol=1e-9)
    # and a shift across view B's epipolar lines changes the angle, one along them does not
    u, rate = _across_direction(CAM_B, frame)
    centre = np.array([[256.0, 256.0]])
    along = np.array([-u[1], u[0]])
    assert abs(epipolar_angles(CAM_B, centre + 5 * u, frame) - epipolar_angles(CAM_B, centre, frame))[0] == pytest.approx(5 * rate, rel=0.02)
    assert abs(epipolar_angles(CAM_B, centre + 5 * along, frame) - epipolar_angles(CAM_B, centre, frame))[0] < 0.05 * 5 * rate


@pytest.mark.parametrize("shift_px", [0.0, 6.0, -9.0])
def test_recovers_a_known_shift_of_view_b(shift_px):
    tree = _tree()
    mask_a = render_mask(tree, CAM_A)
    # the tree as view B saw it after the heart moved: the same as a camera whose image is shifted
    mask_b = render_mask(tree, CAM_B.shifted(*_across(shift_px)))
    est = estimate_view_b_shift(mask_a, mask_b, CAM_A, CAM_B)
    assert est.across_px == pytest.approx(shift_px, abs=1.0)
    assert est.mismatch <= est.mismatch_header + 0.01


def test_joint_fit_overrides_one_misleading_pair():
    tree = _tree()
    mask_a = render_mask(tree, CAM_A)
    truth = [4.0, 4.5, 5.0, 5.5, 6.0]
    curves = [mismatch_curve(mask_a, render_mask(tree, CAM_B.shifted(*_across(s))), CAM_A, CAM_B) for s in truth]
    # one pair's profiles match best at −20 px (e.g. a vessel missing from one mask): a false minimum
    bad = curves[2]
    bad.mismatch = 0.5 - 0.45 * np.exp(-0.5 * ((bad.steps_px + 20.0) / 3.0) ** 2)
    assert estimate_run_shifts([bad], [0], [0])[0].across_px == pytest.approx(-20.0, abs=0.5)
    frames_a, frames_b = [10, 12, 14, 16, 18], [20, 21, 22, 23, 24]
    fitted = estimate_run_shifts(curves, frames_a, frames_b, min_gain=0.0)
    for i, (est, s) in enumerate(zip(fitted, truth)):
        if i == 2:  # the misleading pair is not pulled to its false minimum: kept at the header or near the line
            assert est.across_px == 0.0 or est.across_px == pytest.approx(s, abs=REFINE_PX + 0.5)
        else:
            assert est.across_px == pytest.approx(s, abs=1.5)
    # a pair whose shift barely improves its match keeps the header geometry
    gains = [c.at_header - c.at(e.across_px) for c, e in zip(curves, fitted)]
    gated = estimate_run_shifts(curves, frames_a, frames_b, min_gain=float(np.median(gains)))
    assert sum(e.applied for e in gated) < len(gated)
    assert all(e.applied == (g >= np.median(gains)) for e, g in zip(gated, gains) if e.applied)
    assert estimate_view_b_shift(mask_a, np.zeros_like(mask_a), CAM_A, CAM_B).applied is False


def test_no_centreline_gives_no_shift():
    tree = _tree()
    empty = np.zeros((512, 512), np.uint8)
    curve = mismatch_curve(render_mask(tree, CAM_A), empty, CAM_A, CAM_B)
    assert np.isnan(curve.mismatch).all()
    (est,) = estimate_run_shifts([curve], [0], [0])
    assert not est.applied


def test_a_fit_at_the_edge_of_the_search_range_is_not_applied():
    tree = _tree()
    mask_a = render_mask(tree, CAM_A)
    curve = mismatch_curve(mask_a, render_mask(tree, CAM_B), CAM_A, CAM_B)
    # profiles that only get better towards the limit: no minimum inside the range
    curve.mismatch = 1.0 - (curve.steps_px - curve.steps_px[0]) / (curve.steps_px[-1] - curve.steps_px[0])
    curve.at_header = 1.0  # so the gain alone would let it through
    assert estimate_run_shifts([curve], [0], [0], min_gain=-np.inf)[0].applied is False
    (est,) = estimate_run_shifts([curve], [0], [0])
    assert not est.applied


def test_the_prior_prefers_the_smaller_of_two_near_equal_minima():
    tree = _tree()
    curve = mismatch_curve(render_mask(tree, CAM_A), render_mask(tree, CAM_B), CAM_A, CAM_B)
    s = curve.steps_px
    # two minima, the far one (25 px, e.g. a catheter lined up with a vessel) a little deeper than the near one
    curve.mismatch = 0.5 - 0.12 * np.exp(-0.5 * ((s - 3.0) / 2.0) ** 2) - 0.14 * np.exp(-0.5 * ((s - 25.0) / 2.0) ** 2)
    curve.at_header = float(curve.at(0.0))
    curves = [curve, curve]
    without = estimate_run_shifts(curves, [0, 1], [0, 1], min_gain=0.0, prior_per_px=0.0)
    assert [e.across_px for e in without] == pytest.approx([25.0, 25.0], abs=0.5)
    # 0.002 per px charges the far minimum 0.044 more than the near one: more than its 0.02 advantage
    with_prior = estimate_run_shifts(curves, [0, 1], [0, 1], min_gain=0.0, prior_per_px=0.002)
    assert [e.across_px for e in with_prior] == pytest.approx([3.0, 3.0], abs=0.5)
    # the reported mismatch is the curve's own, not the penalised cost
    assert with_prior[0].mismatch == pytest.approx(float(curve.at(with_prior[0].across_px)))


def test_a_wrong_shift_loses_confident_voxels_which_is_how_reconstruct_checks_a_shift():
    from stages.methods3d import hull_prediction
    from stages.methods3d import confident_voxels

    tree = _tree()
    mask_a, mask_b = render_mask(tree, CAM_A), render_mask(tree, CAM_B)
    counts = [confident_voxels(hull_prediction(mask_a, mask_b, CAM_A, CAM_B.shifted(*_across(s))))
              for s in (0.0, 3.0, 6.0, -6.0)]
    # the more view B is shifted off the truth, the fewer rays of the two views meet (a hull keeps its
    # ghosts, so it loses only a few per cent; the SBP network's confident voxels drop faster)
    assert counts[0] > counts[1] > counts[2] > 0 and counts[3] < counts[0]


@pytest.mark.parametrize("method", ["visual-hull", "correspondence"])
def test_reconstruct_keeps_a_right_shift_and_rejects_a_wrong_one(method):
    # the hull is checked by its confident voxels, the correspondence method by its matched points
    from stages.methods3d import load_evidence_predictor
    from stages.reconstruct import predict_with_checked_shift
    from stages.view_alignment import ViewShift

    hull = load_evidence_predictor(method)

    tree = _tree()
    mask_a = render_mask(tree, CAM_A)
    moved_b = render_mask(tree, CAM_B.shifted(*_across(6.0)))  # run B's image moved by 6 px
    right = ViewShift(tuple(_across(6.0)), 6.0, 0.1, 0.3)
    _, cam, kept = predict_with_checked_shift(hull, mask_a, moved_b, CAM_A, CAM_B, right)
    assert kept and np.allclose(cam.K, CAM_B.shifted(*_across(6.0)).K)
    wrong = ViewShift(tuple(_across(-6.0)), -6.0, 0.1, 0.3)
    _, cam, kept = predict_with_checked_shift(hull, mask_a, render_mask(tree, CAM_B), CAM_A, CAM_B, wrong)
    assert not kept and cam is CAM_B
