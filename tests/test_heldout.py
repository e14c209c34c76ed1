"""Held-out-view check on the real phantom runs (skipped when ../shared/data/phantom_xa is absent)."""

from __future__ import annotations

import numpy as np
import pytest

from stages.evaluate import heldout as H
from stages.core.geometry import Camera


@pytest.fixture(scope="module")
def three_views(phantom_dir, tmp_path_factory):
    folder = tmp_path_factory.mktemp("phantom3")
    for name in ("IM1.dcm", "IM2.dcm", "IM3.dcm"):
        (folder / name).symlink_to(phantom_dir / name)  # links, never copies of the data
    return H.load_views(folder)


def test_segmentation_finds_the_phantom_vessels(three_views):
    for v in three_views:
        frac = v.mask[v.fov].mean()
        assert 0.01 < frac < 0.08, (v.name, frac)  # thin vessels: a few % of the field of view
        assert v.centreline.sum() > 1000  # measured 1377–1749 px (≈ 450–570 mm at the isocentre)


def test_heldout_rows_nominal_beats_a_wrong_pose(three_views):
    rows = H.heldout_rows(three_views, (0, 1))
    assert len(rows) == 1 and rows[0]["heldout"] == "IM3" and rows[0]["pair"] == "IM1+IM2"
    r = rows[0]
    assert r["hull_voxels"] > 10_000
    assert 0.7 < r["coverage"] <= 1.0  # measured 0.92
    assert 1.0 < r["distance_mm"] < 8.0  # measured 4.4 mm
    # the same check with the held-out view's pose rotated by 15° (α) must score clearly worse
    # (measured: coverage 0.92 → 0.70, distance 4.36 → 5.06 mm)
    v3 = three_views[2]
    c = v3.camera.carm
    wrong = Camera.from_carm(c["alpha"] + 15.0, c["beta"], c["sid"], c["sod"], c["spacing"], v3.camera.rows, v3.camera.cols)
    bad_view = H.View(v3.name, wrong, v3.mask, v3.fov, v3.centreline)
    bad = H.heldout_rows([three_views[0], three_views[1], bad_view], (0, 1))[0]
    assert bad["coverage"] < r["coverage"] - 0.1
    assert bad["distance_mm"] > r["distance_mm"] + 0.4


def test_summary_and_table(three_views):
    rows = []
    for pair in ((0, 1), (0, 2), (1, 2)):
        rows += H.heldout_rows(three_views, pair)
    res = {"views": [v.name for v in three_views], "epsilon_mm": 3.0, "rows": rows, "summary": H.summarise(rows)}
    s = res["summary"]["nominal"]
    assert s["n"] == 3 and s["coverage"]["n"] == 3
    assert s["coverage"]["mean"] == pytest.approx(np.mean([r["coverage"] for r in rows]))
    md = H.markdown_table(res)
    assert "IM1+IM2" in md and "IM2+IM3" in md and "coverage@3mm" in md


def test_too_few_runs_is_a_clear_error(tmp_path):
    from stages.core.errors import UserError

    with pytest.raises(UserError, match="at least 3"):
        H.load_views(tmp_path)


def test_fitted_pose_rows_and_own_views(three_views):
    """The held-out view's pose fitted to the reconstruction scores at least as well as its header pose;
    the pair's own calibration uses its two runs only and is reported."""
    own, calib = [], {}
    rows = H.heldout_rows(three_views, (0, 1), calibrate=True, fit_pose=True, own=own, calibration=calib)
    assert [r["pose"] for r in rows] == ["nominal", "fitted"]
    nom, fit = rows
    for r in rows:
        assert {"coverage", "distance_mm", "distance_median_mm"} <= set(r) and r["heldout"] == "IM3"
    assert fit["distance_mm"] < nom["distance_mm"]  # measured 4.36 → 3.8 mm (visual hull, ghosts included)
    assert fit["distance_median_mm"] < nom["distance_median_mm"]
    assert fit["pose_fit"]["cost_after_px"] < fit["pose_fit"]["cost_before_px"]
    assert set(calib) == {"IM1+IM2"} and calib["IM1+IM2"]["runs"] == ["IM1", "IM2"]
    assert [o["view"] for o in own] == ["IM1", "IM2"]
    assert all(o["distance_mm"] < 0.5 for o in own)  # a hull reprojects onto its own views (measured 0.30)


def test_default_method_resolves_to_what_reconstruct_uses():
    from stages.methods3d import DEFAULT_METHOD

    assert H.resolve_method("default") == DEFAULT_METHOD
    assert H.resolve_method("visual-hull") == "visual-hull"


def test_projected_distances_per_point_and_outside_the_field_of_view():
    """Each 3D point's distance (mm at the isocentre) from its projection to the view's centreline, NaN where it
    projects outside the field of view; the check's mean distance is their mean."""
    cam = Camera.from_carm(0.0, 0.0, 1000.0, 750.0, 0.3, 128, 128)
    centreline = np.zeros((128, 128), bool)
    centreline[64, :] = True  # one horizontal line through the image centre
    fov = np.zeros((128, 128), bool)
    fov[:, :100] = True
    view = H.View("synthetic", cam, centreline.copy(), fov, centreline)
    target = np.array([[64.0, 30.0], [74.0, 30.0], [54.0, 50.0], [64.0, 120.0]])  # (row, col); the last outside the fov
    origins, dirs = cam.rays(target)
    points = origins + 750.0 * dirs  # about at the isocentre's depth
    d = H.projected_distances(points, view, cam)
    rc = cam.project(points)
    px = cam.isocentre_spacing
    assert np.isnan(d[3])
    np.testing.assert_allclose(d[:3], np.abs(rc[:3, 0] - 64.0) * px, atol=0.02 * px)
    mean, n = H._project_distance(points, view, cam)
    assert n == 3 and mean == pytest.approx(np.nanmean(d))


def test_a_reconstruction_on_another_runs_table_is_moved_into_the_views_frame():
    """`reconstruct` puts its output in its first run's patient frame; when that run's table stood elsewhere than the
    first file's, the held-out views (placed on the first file's table) see the points only once moved by that run's
    table offset: every point then projects in run B's view where run B's own header camera projects it."""
    header_b = Camera.from_carm(30.0, 10.0, 1000.0, 750.0, 0.3, 128, 128)
    offset = [1.5, -28.9, -33.7]
    blank = np.zeros((128, 128), bool)
    views = [H.View("A", Camera.from_carm(0.0, 0.0, 1000.0, 750.0, 0.3, 128, 128), blank, blank, blank),
             H.View("B", header_b.on_table_moved_by(offset), blank, blank, blank, table_offset_mm=offset)]
    points = np.random.default_rng(0).normal(0.0, 20.0, (50, 3))  # a reconstruction from run B, in B's frame
    moved = H.in_views_frame(points, views, "B")
    np.testing.assert_allclose(views[1].camera.project(moved), header_b.project(points), atol=1e-9)
    np.testing.assert_allclose(moved - points, -np.asarray([offset] * 50))
    np.testing.assert_array_equal(H.in_views_frame(points, views, "A"), points)  # the reference table: unchanged
