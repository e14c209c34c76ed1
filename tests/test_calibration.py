"""Self-calibration of C-arm geometry (stages/calibration) on synthetic geometry with known errors."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from stages.calibration import Correction, apply_correction, calibrate_pair, relative_geometry_error
from stages.calibration.model import carm_angles, triangulate
from stages.calibration.pair import _across_direction
from stages.calibration.synthetic import random_error, synthetic_matches, synthetic_tree, true_camera
from stages.calibration.views import apply_pose, centreline_distance_map, fit_view_pose
from stages.core.errors import UserError
from stages.core.geometry import Camera


def _pair():
    # phantom runs IM1 and IM3 (α, β, SID), SOD 720 mm, 0.39 mm detector pixels, 512²
    return (Camera.from_carm(31.3, 0.1, 860, 720, 0.390625, 512, 512),
            Camera.from_carm(-0.8, -23.2, 891, 720, 0.390625, 512, 512))


@pytest.fixture(scope="module")
def tree():
    return synthetic_tree(seed=3, step_mm=0.4)


def test_correction_matches_the_carm_parameters():
    _, hb = _pair()
    c = apply_correction(hb, Correction(0.0, 0.0, 0.0, 1.5, -2.0, 12.0))
    ref = Camera.from_carm(-0.8 + 1.5, -23.2 - 2.0, 891 + 12.0, 720, 0.390625, 512, 512)
    assert np.abs(c.matrix - ref.matrix).max() < 1e-8 * np.abs(ref.matrix).max()
    assert carm_angles(c) == pytest.approx((0.7, -25.2))
    assert c.carm["sid"] == pytest.approx(903.0)
    s = apply_correction(hb, Correction(3.0, -2.0))
    np.testing.assert_allclose(s.matrix, hb.shifted(3.0, -2.0).matrix)
    np.testing.assert_allclose(apply_correction(hb, Correction()).matrix, hb.matrix)
    # in-plane rotation turns the image about the principal point: the isocentre stays put
    r = apply_correction(hb, Correction(inplane_deg=2.0))
    np.testing.assert_allclose(r.project(np.zeros((1, 3))), hb.project(np.zeros((1, 3))), atol=1e-9)


def test_triangulation_is_exact_on_true_projections(tree):
    ha, hb = _pair()
    X = triangulate(ha, hb, ha.project(tree), hb.project(tree))
    assert np.abs(X - tree).max() < 1e-6


def test_exact_recovery_noise_free(tree):
    """Run A true, run B off in every observable degree of freedom: recovered to numerical precision."""
    ha, hb = _pair()
    u = _across_direction(ha, hb)
    inject = Correction(7.0 * u[0], 7.0 * u[1], 1.2, -2.0, 1.5, 15.0)  # 7 px across, 1.2°, −2°, 1.5°, +15 mm
    tb = apply_correction(hb, inject)
    pa, pb = synthetic_matches(tree, ha, tb)
    res = calibrate_pair(pa, pb, ha, hb, prior_weight=0.0)
    assert res.applied
    np.testing.assert_allclose(res.correction_b.vector(), inject.vector(), atol=2e-3)
    assert res.report["residual_after"]["epipolar_px"] < 1e-3
    assert res.report["residual_before"]["epipolar_px"] > 3.0
    err = relative_geometry_error(res.cam_a, res.cam_b, ha, tb)
    assert err["rms_mm"] < 1e-3 and err["rotation_deg"] < 1e-3


def test_injected_errors_in_both_runs_are_recovered_up_to_the_gauge(tree):
    """Both runs off (isocentre shift, angles, in-plane, SID; half the benchmark's maximum), no noise."""
    ha, hb = _pair()
    rng = np.random.default_rng(5)
    kw = dict(shift_mm=5.0, angle_deg=1.5, inplane_deg=1.0, sid_mm=10.0)
    ta, tb = true_camera(ha, random_error(rng, **kw)), true_camera(hb, random_error(rng, **kw))
    pa, pb = synthetic_matches(tree, ta, tb)
    res = calibrate_pair(pa, pb, ha, hb)
    before = relative_geometry_error(ha, hb, ta, tb)
    after = relative_geometry_error(res.cam_a, res.cam_b, ta, tb)
    assert res.applied
    assert before["rms_mm"] > 2.0  # measured 5.5 mm
    assert after["rms_mm"] < 0.5  # measured 0.17 mm
    # the report: run A is the fixed reference, B carries the correction, residuals in px and mm
    rep = res.report
    assert rep["corrections"]["A"]["shift_mm_norm"] == 0.0
    assert rep["residual_after"]["epipolar_mm"] < rep["residual_before"]["epipolar_mm"]
    assert any("along its epipolar lines" in s for s in rep["fixed_dofs"])


def test_outlier_matches_do_not_break_it(tree):
    ha, hb = _pair()
    u = _across_direction(ha, hb)
    inject = Correction(10.0 * u[0], 10.0 * u[1], 0.0, 1.0, 0.0, 0.0)
    tb = apply_correction(hb, inject)
    pa, pb = synthetic_matches(tree, ha, tb, noise_px=0.3, outliers=0.15, seed=2)
    res = calibrate_pair(pa, pb, ha, hb)
    assert res.applied
    assert relative_geometry_error(res.cam_a, res.cam_b, ha, tb)["rms_mm"] < 1.0


def test_views_too_close_are_refused(tree):
    ha = Camera.from_carm(30.0, 0.0, 900, 720, 0.39, 512, 512)
    hb = Camera.from_carm(36.0, 3.0, 900, 720, 0.39, 512, 512)
    pa, pb = synthetic_matches(tree, ha, hb)
    with pytest.raises(UserError, match=r"only 6\.7° apart"):
        calibrate_pair(pa, pb, ha, hb)


def test_too_few_points_are_refused(tree):
    ha, hb = _pair()
    pa, pb = synthetic_matches(tree[:12], ha, hb)
    with pytest.raises(UserError, match="too few to calibrate"):
        calibrate_pair(pa, pb, ha, hb)
    with pytest.raises(UserError, match="equal size"):
        calibrate_pair(pa, pb[:5], ha, hb)


def test_a_correction_beyond_the_bounds_is_refused_with_a_warning(tree, caplog):
    ha, hb = _pair()
    u = _across_direction(ha, hb)
    shift_px = 12.0 / hb.isocentre_spacing  # 12 mm across, bound 5 mm
    tb = apply_correction(hb, Correction(shift_px * u[0], shift_px * u[1]))
    pa, pb = synthetic_matches(tree, ha, tb)
    with caplog.at_level(logging.WARNING):
        res = calibrate_pair(pa, pb, ha, hb, bounds={"shift_mm": 5.0})
    assert not res.applied and res.correction_b.is_zero()
    np.testing.assert_allclose(res.cam_b.matrix, hb.matrix)
    w = res.report["warnings"][0]
    assert w.startswith("calibration of B refused: across_px") and "shift ±5 mm" in w
    assert "header geometry kept" in caplog.text
    # the proposal stayed inside the bounds
    prop = res.report["proposed_correction"]
    assert prop["shift_mm_norm"] <= 5.0 + 1e-6
    assert res.report["residual_after"] == res.report["residual_before"]


def test_pose_fit_recovers_a_held_out_view(tree):
    """A view 6 mm / 1° off: the fitted pose puts the model back on its centreline."""
    _, hb = _pair()
    truth = apply_pose(hb, [0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    rc = np.rint(truth.project(tree)).astype(int)
    cl = np.zeros((truth.rows, truth.cols), bool)
    ok = truth.in_image(rc)
    cl[rc[ok, 0], rc[ok, 1]] = True
    header = apply_pose(hb, [1.0, -0.5, 0.5, 6.0, -4.0, 0.0])
    dmap = centreline_distance_map(cl)
    cam, pose, rep = fit_view_pose(tree, header, dmap)
    assert rep["cost_before_px"] > 5.0
    assert rep["cost_after_px"] < 0.6  # the rounding of the rasterised centreline
    assert rep["applied"]
    d = np.linalg.norm(cam.project(tree) - truth.project(tree), axis=1)
    assert np.median(d) < 1.0
