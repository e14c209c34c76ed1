"""End-to-end `autocar reconstruct`: input checks that must fail fast and cleanly."""

import json
from pathlib import Path

import numpy as np
import pytest

from conftest import assert_one_line_error
from stages.core.dicom_io import XAGeometry, write_xa


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
    # the file at fault is the geometry JSON; the message names every missing key (stages.core.geometry)
    assert_one_line_error(result, "g.json", "geometry JSON lacks PositionerSecondaryAngle, DistanceSourceToDetector")


def test_unknown_method(cli, tmp_path):
    a = _run(tmp_path / "a.dcm", 30.0, 0.0)
    b = _run(tmp_path / "b.dcm", -30.0, 0.0)
    assert_one_line_error(cli("reconstruct", a, b, "-o", tmp_path / "o", "--method", "magic"), "unknown --method 'magic'")


def test_bundled_example_end_to_end_with_the_default_method(tmp_path):
    """`make demo`'s run: the default 3D method + U-Net on the bundled example, scored against its
    simulator truth.

    Measured 2026-12-04 with the correspondence method (the default): coverage 0.886, accuracy 0.757
    (ε = 1.5 mm), EPE 2.04 mm (view B's shift checked by the matched points; 0.876 / 0.736 / 2.13 before), truth → reconstruction centreline distance 2.17 mm, 7 key frames with one
    tracked topology (SBP, 2026-11-24: 0.87 / 0.70 / 1.26 mm).
    """
    from pathlib import Path

    vtk = pytest.importorskip("vtk")
    root = Path(__file__).resolve().parents[1]

    from stages.evaluate import score_dynamic_reconstruction
    from stages.reconstruct import reconstruct
    from stages.render.acquire import load_truth
    from stages.core.runs import load_run

    ex = root / "examples"
    # two threads (`--threads 2`): key frames predicted and graphed concurrently, results in key-frame order
    summary = reconstruct(ex / "run_a.dcm", ex / "run_b.dcm", tmp_path / "demo", workers=2)
    from stages.methods3d import DEFAULT_METHOD

    assert summary["method"] == DEFAULT_METHOD and len(summary["pairs"]) == 7 and not summary["warnings"]
    runs = [load_run(ex / "run_a.dcm"), load_run(ex / "run_b.dcm")]
    score = score_dynamic_reconstruction(tmp_path / "demo", load_truth(ex / "truth.zarr"), runs, 60, 3_000_000)["graph"]
    assert score["coverage"] >= 0.80 and score["accuracy"] >= 0.65 and score["epe_mm"] <= 2.6
    assert score["centreline_truth_to_pred_mm"] <= 2.6 and score["topology_agreement"] == 1.0
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(tmp_path / "demo" / "graphs_00.vtp"))
    reader.Update()
    poly = reader.GetOutput()
    assert poly.GetNumberOfPoints() > 100 and poly.GetPointData().GetArray("Radius") is not None
    # each key frame's JSON names the two runs' frames it pairs, and its 2D↔2D correspondences
    for k, (ia, ib) in enumerate(summary["pairs"]):
        corr = json.loads((tmp_path / "demo" / f"graphs_{k:02d}.json").read_text())["correspondences"]
        assert (corr["views"]["a"]["source_frame"], corr["views"]["b"]["source_frame"]) == (ia, ib)
        assert len(corr["pairs"]) > 100
    # the B partners the JSON reports are the nodes projected with the key frame's own (motion-corrected)
    # view-B camera from predictions.zarr: the camera score_dynamic_reconstruction scores them with
    from stages.graph.io import read_sparse_predictions

    _, frames = read_sparse_predictions([tmp_path / "demo" / "predictions.zarr"])
    for k, frame in enumerate(frames):
        doc = json.loads((tmp_path / "demo" / f"graphs_{k:02d}.json").read_text())
        pairs = np.asarray(doc["correspondences"]["pairs"], float)
        nodes = np.asarray(doc["nodes"], float)[pairs[:, 0].astype(int)]
        np.testing.assert_allclose(frame.cameras["b"].project(nodes), pairs[:, 3:5], atol=0.01)
        shift = summary["view_b_shifts"][k]["shift_px"]
        np.testing.assert_allclose(runs[1].camera.project(nodes) + shift, pairs[:, 3:5], atol=0.01)


def test_reconstruct_with_self_calibration_reports_it(tmp_path):
    """--calibrate: run B's geometry refined from the vessels first; the report names what was done."""
    from stages.reconstruct import reconstruct

    root = Path(__file__).resolve().parents[1] / "examples"
    summary = reconstruct(root / "run_a.dcm", root / "run_b.dcm", tmp_path / "out", method="visual-hull",
                          k=2, calibrate=True, qca=False)
    cal = summary["calibration"]
    assert isinstance(cal["applied"], bool) and "B" in cal["corrections"]
    assert cal["residual_after"] and cal["residual_before"]
    assert summary["parameters"]["calibrate"] is True and summary["qca"] is None
    saved = json.loads((tmp_path / "out" / "summary.json").read_text())
    assert saved["calibration"]["applied"] == cal["applied"]
    assert "self-calibration" in (tmp_path / "out" / "report.html").read_text()
