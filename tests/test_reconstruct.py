"""End-to-end `autocar reconstruct`: input checks that must fail fast and cleanly."""

import json

import numpy as np
import pytest

from conftest import assert_one_line_error
from stages.dicom_io import XAGeometry, write_xa


def _run(path, alpha, beta, frames=None, study="1.2.3"):
    frames = np.full((4, 64, 64), 180, np.uint8) if frames is None else frames
    return write_xa(path, frames, XAGeometry(alpha, beta, 1000.0, 750.0, (0.6, 0.6), 64, 64), 66.7, study_uid=study)


def test_nearly_parallel_views_are_refused(cli, tmp_path):
    a = _run(tmp_path / "a.dcm", 30.0, 0.0)
    b = _run(tmp_path / "b.dcm", 34.0, 2.0)
    result = cli("reconstruct", a, b, "-o", tmp_path / "out", "--method", "visual-hull", "--seg-method", "threshold")
    assert_one_line_error(result, "apart", "need ≥ 10°")
    assert not any((tmp_path / "out").glob("*.zarr"))


def test_run_without_contrast_is_refused(cli, tmp_path):
    a = _run(tmp_path / "a.dcm", 30.0, 0.0)
    b = _run(tmp_path / "b.dcm", -30.0, 0.0)
    result = cli("reconstruct", a, b, "-o", tmp_path / "out", "--method", "visual-hull", "--seg-method", "threshold")
    assert_one_line_error(result, "a.dcm", "no vessel found")


def test_geometry_json_missing_fields(cli, tmp_path):
    stack = tmp_path / "frames.npy"
    np.save(stack, np.full((3, 64, 64), 150, np.float32))
    geom = tmp_path / "g.json"
    geom.write_text(json.dumps({"alpha": 10}))
    b = _run(tmp_path / "b.dcm", -30.0, 0.0)
    result = cli("reconstruct", stack, b, "--geometry-a", geom, "-o", tmp_path / "out", "--method", "visual-hull")
    assert_one_line_error(result, "frames.npy", "geometry JSON lacks beta, sid, sod, spacing")


def test_unknown_method(cli, tmp_path):
    a = _run(tmp_path / "a.dcm", 30.0, 0.0)
    b = _run(tmp_path / "b.dcm", -30.0, 0.0)
    assert_one_line_error(cli("reconstruct", a, b, "-o", tmp_path / "o", "--method", "magic"), "unknown --method 'magic'")
