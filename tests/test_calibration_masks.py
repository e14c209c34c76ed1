"""Calibration from vessel masks (no matches): the crossing-profile route, the joint static calibration,
the calibrate command and its artefact — on synthetic masks with a known offset."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy import ndimage

from stages.calibration import Correction, apply_correction, calibrate_masks, calibrate_runs
from stages.calibration.pair import _across_direction
from stages.calibration.synthetic import synthetic_tree
from stages.core.errors import UserError
from stages.core.geometry import Camera

ANGLES = [(31.3, 0.1, 860), (-0.8, -23.2, 891), (-27.3, -0.1, 865), (24.0, -18.8, 939)]


def _cam(k):
    a, b, sid = ANGLES[k]
    return Camera.from_carm(a, b, sid, 720, 0.390625, 512, 512)


def _mask(cam, pts, radius_px=2):
    rc = np.rint(cam.project(pts)).astype(int)
    ok = cam.in_image(rc)
    m = np.zeros((cam.rows, cam.cols), bool)
    m[rc[ok, 0], rc[ok, 1]] = True
    return ndimage.binary_dilation(m, iterations=radius_px)


@pytest.fixture(scope="module")
def tree():
    return synthetic_tree(seed=11, step_mm=0.2)


def test_profile_route_recovers_a_shift_across_the_epipolar_lines(tree):
    ha, hb = _cam(0), _cam(1)
    u = _across_direction(ha, hb)
    shift_px = 8.0 / hb.isocentre_spacing  # 8 mm at the isocentre
    tb = apply_correction(hb, Correction(shift_px * u[0], shift_px * u[1]))
    cal = calibrate_masks(_mask(ha, tree), _mask(tb, tree), ha, hb)
    assert cal.applied and cal.report["method"] == "crossing-profile"
    got = np.array([cal.correction_b.shift_row_px, cal.correction_b.shift_col_px])
    across = float(got @ u) * hb.isocentre_spacing
    assert across == pytest.approx(8.0, abs=1.0)  # measured 8.1 mm
    rep = cal.report
    assert rep["residual_after"]["profile_overlap"] > rep["residual_before"]["profile_overlap"]
    assert any("along its epipolar lines" in s for s in rep["fixed_dofs"])
    # the header pair already consistent: nothing to gain, nothing applied
    same = calibrate_masks(_mask(ha, tree), _mask(hb, tree), ha, hb)
    assert abs(same.correction_b.shift_row_px) + abs(same.correction_b.shift_col_px) < 1.5


def test_masks_route_refuses_degenerate_pairs(tree):
    ha = _cam(0)
    near = Camera.from_carm(34.0, 4.0, 860, 720, 0.390625, 512, 512)
    with pytest.raises(UserError, match="apart"):
        calibrate_masks(_mask(ha, tree), _mask(near, tree), ha, near)
    empty = np.zeros((512, 512), bool)
    with pytest.raises(UserError, match="too little vessel centreline"):
        calibrate_masks(_mask(ha, tree), empty, ha, _cam(1))


def test_joint_static_calibration_finds_the_offset_run(tree):
    """Four runs of a static tree; run 3's header is 6 mm off: the joint fit puts it back."""
    heads = [_cam(k) for k in range(4)]
    off = Correction(-6.0 / heads[3].isocentre_spacing, 4.0 / heads[3].isocentre_spacing)
    trues = list(heads)
    trues[3] = apply_correction(heads[3], off)
    masks = [_mask(c, tree) for c in trues]
    cams, rep = calibrate_runs(masks, heads, ["R1", "R2", "R3", "R4"], static=True)
    assert rep["method"].startswith("joint")
    d_before = np.median(np.linalg.norm(heads[3].project(tree) - trues[3].project(tree), axis=1))
    d_after = np.median(np.linalg.norm(cams[3].project(tree) - trues[3].project(tree), axis=1))
    assert d_before > 20.0  # px (7.2 mm at the isocentre)
    assert d_after < 3.0  # px: within the model's own gauge slack
    assert rep["residual_after"]["R4"]["chamfer_px"] < rep["residual_before"]["R4"]["chamfer_px"]
    assert rep["corrections"]["R1"]["shift_mm_norm"] == 0.0  # the reference run is held fixed


def _write_run(folder, cam, tree):
    folder.mkdir()
    mask = _mask(cam, tree)
    img = np.where(ndimage.gaussian_filter(mask.astype(float), 1.0) > 0.3, 400.0, 1000.0)
    np.save(folder / "frames.npy", np.stack([img] * 4).astype(np.float32))
    (folder / "frames.json").write_text(json.dumps({
        "alpha": cam.carm["alpha"], "beta": cam.carm["beta"], "sid": cam.carm["sid"], "sod": 720,
        "spacing": 0.390625, "frame_time_ms": 66.7}))
    return folder / "frames.npy"


def test_calibrate_command_writes_the_artefact(tmp_path, tree):
    from typer.testing import CliRunner

    from autocar_cli.main import app
    from stages.calibration.stage import KIND, load_calibration

    a = _write_run(tmp_path / "a", _cam(0), tree)
    b = _write_run(tmp_path / "b", _cam(1), tree)
    out = tmp_path / "calib.json"
    res = CliRunner().invoke(app, ["calibrate", str(a), str(b), "-o", str(out)])
    assert res.exit_code == 0, res.output
    doc = json.loads(out.read_text())
    assert doc["kind"] == KIND and doc["schema_version"] == 1 and len(doc["runs"]) == 2
    assert "reference run" in doc["summary_lines"][0]
    cams = load_calibration(out)
    assert set(cams) == {"frames", "frames_2"}
    # a run against itself: refused with one error line, exit 2
    res = CliRunner().invoke(app, ["calibrate", str(a), str(a), "-o", str(tmp_path / "x.json")])
    assert res.exit_code == 2 and "0.0° apart" in res.output
    # an existing output without --force
    res = CliRunner().invoke(app, ["calibrate", str(a), str(b), "-o", str(out)])
    assert res.exit_code == 2 and "already exists" in res.output


def test_load_calibration_checks_the_kind(tmp_path):
    from stages.calibration.stage import load_calibration

    p = tmp_path / "c.json"
    p.write_text(json.dumps({"kind": "autocar.metrics", "schema_version": 1, "runs": []}))
    with pytest.raises(UserError, match="not an autocar.calibration file"):
        load_calibration(p)
    p.write_text(json.dumps({"kind": "autocar.calibration", "schema_version": 7, "runs": []}))
    with pytest.raises(UserError, match="schema version 7, expected 1"):
        load_calibration(p)
    with pytest.raises(UserError, match="no such calibration file"):
        load_calibration(tmp_path / "missing.json")
