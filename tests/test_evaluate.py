"""autocar evaluate: artefact round trips, matching, tables, defined numbers for bad cases, CLI."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from stages import evaluate as E
from stages.core.errors import UserError
from stages.core.geometry import Camera
from stages.core.prepared_case import PreparedCase
from stages.core.voxels import SparseVoxels
from tests.conftest import assert_one_line_error


def ball_voxels(centre_mm, r_mm, vs=0.5, occ=1.0):
    g = np.arange(-15, 15.01, vs)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    pts = pts[np.linalg.norm(pts - centre_mm, axis=1) <= r_mm]
    v = SparseVoxels.from_world_points(pts, vs)
    v.features["occupancy"] = np.full(len(v), occ, np.float32)
    return v


def line_graph(y=0.0, r=1.0):
    nodes = np.array([[-5, y, 0], [0, y, 0], [5, y, 0]], np.float32)
    return nodes, np.full(3, r, np.float32), np.array([[0, 1], [1, 2]], np.int32)


def make_case(path, case_id="c1"):
    lab = ball_voxels((0, 0, 0), 4.0)
    lab.features["occupancy"] = np.ones(len(lab), np.uint8)
    lab.features["centreness"] = np.ones(len(lab), np.float32)
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=3, radius=4.0)
    nodes, radius, edges = line_graph()
    PreparedCase(case_id, "left", m.vertices, m.faces, nodes, radius, edges, lab).save(path)
    return path


def test_prediction_round_trip(tmp_path):
    v = ball_voxels((1, 0, 0), 3.0, occ=0.9)
    v.features["centreness"] = np.linspace(0, 1, len(v)).astype(np.float32)
    p = E.save_prediction(tmp_path / "p.zarr", v, "c1", graph=line_graph(), stage="test")
    back = E.load_prediction(p)
    assert back.case_id == "c1" and np.array_equal(back.voxels.coords, v.coords)
    assert np.allclose(back.voxels.features["centreness"], v.features["centreness"])
    assert back.graph[0].shape == (3, 3) and back.graph[2].shape == (2, 2)


def test_wrong_kind_is_a_clear_error(tmp_path):
    case = make_case(tmp_path / "case.zarr")
    with pytest.raises(UserError, match="autocar.sparse-prediction"):
        E.load_prediction(case)


def test_case_against_prepared_case(tmp_path):
    case = make_case(tmp_path / "case.zarr")
    pred = E.save_prediction(tmp_path / "p.zarr", ball_voxels((0, 0, 0), 4.0), "c1",
                             graph=line_graph(y=1.0, r=1.5), stage="test")
    rows = E.evaluate_paths([pred], [case])
    r = rows[0]
    assert r["dice"] == 1.0 and r["chamfer_mm"] == 0.0
    assert r["centreline_error_mm"] == pytest.approx(1.0) and r["radius_error_mm"] == pytest.approx(0.5)


def test_mesh_truth_is_voxelised_inside(tmp_path):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=4, radius=5.0)
    m.export(tmp_path / "c1.stl")
    t = E.load_truth(tmp_path / "c1.stl")
    pts = t.voxels.world_points()
    assert np.all(np.linalg.norm(pts, axis=1) <= 5.0 + 1e-6)  # centres inside the sphere only
    # count ≈ volume / voxel volume (polyhedral sphere is slightly smaller than 4/3πr³)
    assert len(pts) == pytest.approx(4 / 3 * np.pi * 125 / 0.125, rel=0.03)


def test_cli_writes_tables_and_aggregates_with_an_empty_case(tmp_path, cli):
    make_case(tmp_path / "truth" / "case_a.zarr", "a")
    make_case(tmp_path / "truth" / "case_b.zarr", "b")
    (tmp_path / "pred").mkdir()
    E.save_prediction(tmp_path / "pred" / "a.zarr", ball_voxels((0.5, 0, 0), 4.0), "a", stage="test")
    empty = SparseVoxels(np.zeros((0, 3)), 0.5, np.zeros(3), {"occupancy": np.zeros(0, np.float32)})
    E.save_prediction(tmp_path / "pred" / "b.zarr", empty, "b", stage="test")
    res = cli("evaluate", tmp_path / "pred", "-t", tmp_path / "truth", "-o", tmp_path / "out" / "m")
    assert res.exit_code == 0, res.output
    for ext in ("zarr", "json", "csv", "md"):
        assert (tmp_path / "out" / f"m.{ext}").exists()
    data = json.loads((tmp_path / "out" / "m.json").read_text())
    rows = {r["case_id"]: r for r in data["rows"]}
    assert rows["b"]["dice"] == 0.0 and rows["b"]["status"] == "empty-prediction"
    assert rows["b"]["chamfer_mm"] is None  # NaN written as null in JSON, with its status beside it
    agg = data["aggregate"]
    assert agg["dice"]["n"] == 2 and agg["dice"]["mean"] == pytest.approx((rows["a"]["dice"] + 0) / 2)
    assert agg["chamfer_mm"]["n"] == 1 and agg["chamfer_mm"]["n_undefined"] == 1
    md = (tmp_path / "out" / "m.md").read_text()
    assert "empty-prediction" in md and "n/a" in md and "undefined for that case" in md
    with open(tmp_path / "out" / "m.csv") as fh:
        lines = list(csv.DictReader(fh))
    assert [r["case_id"] for r in lines] == ["a", "b"] and lines[1]["chamfer_mm"] == ""
    from stages.core.artefacts import read_zarr

    g = read_zarr(tmp_path / "out" / "m.zarr", kind=E.METRICS_KIND, schema_version=1)
    assert np.isnan(g["chamfer_mm"][1]) and g["dice"][1] == 0.0


def test_2d_metrics_from_annotations(tmp_path, cli):
    cam_a = Camera.from_carm(30, 0, 1000, 750, 0.3, 256, 256)
    cam_b = Camera.from_carm(-30, 20, 1000, 750, 0.3, 256, 256)
    # prediction: a graph along x; annotations: three points on it (exact) and one far from it
    nodes = np.array([[-10, 0, 0], [10, 0, 0]], np.float32)
    pred = E.save_prediction(tmp_path / "p.zarr", ball_voxels((0, 0, 0), 0.5), "c",
                             graph=(nodes, np.ones(2), np.array([[0, 1]])), stage="test")
    X = np.array([[-5.0, 0, 0], [0, 0, 0], [5, 0, 0], [0, 0, 12.0]])
    truth_b = cam_b.project(X)
    truth_b[1, 1] += 5.0  # annotated partner 5 px off the prediction's: 1.5·(750/1000)... mm
    pairs = np.hstack([cam_a.project(X), truth_b])
    ann = {"kind": E.ANNOTATION_KIND, "case_id": "c", "camera_a": cam_a.to_dict(), "camera_b": cam_b.to_dict(),
           "pairs": pairs.tolist()}
    (tmp_path / "ann.json").write_text(json.dumps(ann))
    res = cli("evaluate", tmp_path / "p.zarr", "-a", tmp_path / "ann.json", "-o", tmp_path / "m")
    assert res.exit_code == 0, res.output
    r = json.loads((tmp_path / "m.json").read_text())["rows"][0]
    spacing = cam_b.isocentre_spacing  # 0.3 · 750/1000 = 0.225 mm
    assert r["coverage"] == pytest.approx(0.75)  # the 4th query projects far from the graph in A
    assert r["epe_mm"] == pytest.approx(5 * spacing / 3, abs=0.02)
    assert r["accuracy"] == pytest.approx(0.75)


def test_missing_or_empty_annotations_are_clear_errors(tmp_path, cli):
    pred = E.save_prediction(tmp_path / "p.zarr", ball_voxels((0, 0, 0), 1.0), "c", stage="test")
    res = cli("evaluate", pred, "-a", tmp_path / "nope.json", "-o", tmp_path / "m")
    assert_one_line_error(res, "nope.json", "no such file")
    (tmp_path / "empty.json").write_text(json.dumps({"camera_a": {}, "camera_b": {}, "pairs": []}))
    res = cli("evaluate", pred, "-a", tmp_path / "empty.json", "-o", tmp_path / "m")
    assert_one_line_error(res, "empty.json", "no annotated pairs")
    res = cli("evaluate", pred, "-o", tmp_path / "m")
    assert_one_line_error(res, "--truth")


def test_unmatched_case_id_is_a_clear_error(tmp_path, cli):
    make_case(tmp_path / "t" / "x.zarr", "x")
    make_case(tmp_path / "t" / "y.zarr", "y")
    (tmp_path / "p").mkdir()
    E.save_prediction(tmp_path / "p" / "a.zarr", ball_voxels((0, 0, 0), 1.0), "zzz", stage="test")
    E.save_prediction(tmp_path / "p" / "b.zarr", ball_voxels((0, 0, 0), 1.0), "x", stage="test")
    res = cli("evaluate", tmp_path / "p", "-t", tmp_path / "t", "-o", tmp_path / "m")
    assert_one_line_error(res, "a.zarr", "zzz")
