"""The non-DICOM path: frame folders (PNG/TIFF) + geometry JSON, checked against the DICOM path on the
real phantom runs, and malformed geometry JSON refused naming the key."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.core.errors import UserError
from stages.core.geometry import camera_from_geometry_dict, load_geometry_json
from stages.core.runs import export_frames, load_run

GOOD = {"PositionerPrimaryAngle": 31.3, "PositionerSecondaryAngle": 0.1, "DistanceSourceToDetector": 860,
        "DistanceSourceToPatient": 720, "ImagerPixelSpacing": [0.390625, 0.390625], "Rows": 512, "Columns": 512}


@pytest.fixture(scope="module")
def exported(phantom_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("frames")
    return {n: export_frames(phantom_dir / f"{n}.dcm", out / n) for n in ("IM1", "IM6")}


def test_frame_folder_equals_the_dicom_run(phantom_dir, exported):
    for name, folder in exported.items():
        d = load_run(phantom_dir / f"{name}.dcm")
        f = load_run(folder)
        np.testing.assert_array_equal(f.frames, d.frames)
        np.testing.assert_allclose(f.frame_times_ms, d.frame_times_ms, atol=1e-6)
        np.testing.assert_allclose(f.camera.matrix, d.camera.matrix, rtol=1e-12)
        assert f.camera.carm == d.camera.carm
        assert json.loads((folder / "geometry.json").read_text())["units"] == {"angle": "deg", "length": "mm"}


def test_calibration_on_frames_equals_the_dicom_path(phantom_dir, exported):
    from stages.calibration.stage import run_calibration

    a = run_calibration([phantom_dir / "IM1.dcm", phantom_dir / "IM6.dcm"])
    b = run_calibration([exported["IM1"], exported["IM6"]])
    assert a["report"]["applied"] == b["report"]["applied"]
    ca, cb = a["report"]["corrections"]["IM6"], b["report"]["corrections"]["IM6"]
    assert ca == cb  # same frames, same geometry: the same correction to the digit
    np.testing.assert_allclose(a["runs"][1]["camera"]["matrix"], b["runs"][1]["camera"]["matrix"])


@pytest.mark.parametrize("change, fragment", [
    ({"DistanceSourceToPatient": None}, "missing geometry field(s) DistanceSourceToPatient"),
    ({"PositionerPrimaryAngle": float("nan")}, "PositionerPrimaryAngle is nan"),
    ({"DistanceSourceToDetector": 0.86}, "DistanceSourceToDetector = 0.86 is outside the plausible range 300…3000 mm "
                                         "(it looks like metres or centimetres"),
    ({"ImagerPixelSpacing": 390.625}, "ImagerPixelSpacing = 390.625 is outside the plausible range 0.01…5 mm "
                                      "(it looks like micrometres"),
    ({"PositionerSecondaryAngle": "23 deg"}, "PositionerSecondaryAngle must be a number"),
    ({"units": {"angle": "rad"}}, "units.angle is 'rad'"),
    ({"Rows": 256}, "Rows = 256 but the frames have 512"),
    ({"DistanceSourceToPatient": 900}, "SOD (DistanceSourceToPatient = 900 mm) must be smaller than SID"),
])
def test_malformed_geometry_json_is_refused_naming_the_key(tmp_path, change, fragment):
    d = dict(GOOD)
    for k, v in change.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    p = tmp_path / "geometry.json"
    p.write_text(json.dumps(d))  # NaN is written as the JSON extension NaN, as Python and many tools do
    with pytest.raises(UserError) as exc:
        load_geometry_json(p, rows=512, cols=512)
    assert fragment in str(exc.value) and str(p) in str(exc.value)


def test_frames_with_a_bad_geometry_json_fail_in_load_run(tmp_path):
    from PIL import Image

    folder = tmp_path / "run"
    folder.mkdir()
    for i in range(2):
        Image.fromarray(np.full((512, 512), 1000 + i, np.uint16)).save(folder / f"f{i}.png")
    d = dict(GOOD, frame_rate_fps=15.0, r_wave_times_ms=[100.0, 900.0])
    (folder / "geometry.json").write_text(json.dumps(d))
    r = load_run(folder)
    assert r.frames.dtype == np.float32 and r.frames[1, 0, 0] == 1001.0  # 16-bit values kept
    np.testing.assert_allclose(r.frame_times_ms, [0.0, 1000.0 / 15])
    assert r.ecg == {"r_wave_time_vector_ms": [100.0, 900.0]}
    (folder / "geometry.json").write_text(json.dumps(dict(d, r_wave_times_ms=[900.0, 100.0])))
    with pytest.raises(UserError, match="r_wave_times_ms must be finite and increasing"):
        load_run(folder)
    (folder / "geometry.json").write_text(json.dumps(dict(d, frame_time_ms=40.0)))
    with pytest.raises(UserError, match="frame_time_ms .* and frame_rate_fps .* disagree"):
        load_run(folder)
    (folder / "geometry.json").write_text(json.dumps(dict(GOOD, DistanceSourceToDetector=float("inf"))))
    with pytest.raises(UserError, match="DistanceSourceToDetector is inf"):
        load_run(folder)


def test_matrix_form_still_works():
    from stages.core.geometry import Camera

    ref = Camera.from_carm(10, 5, 1000, 750, 0.3, 64, 64)
    cam = camera_from_geometry_dict({"matrix": ref.matrix.tolist()}, rows=64, cols=64)
    np.testing.assert_allclose(cam.project(np.zeros((1, 3))), ref.project(np.zeros((1, 3))), atol=1e-6)
