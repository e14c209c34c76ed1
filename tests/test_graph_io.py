"""Artefacts of the graph stage, the .vtp/.stl/.json exports (read back with real readers) and the
``autocar graph-opt`` command, including its one-line errors."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import numpy as np
import pytest

from stages.core.export import lumen_mesh, write_graph_json, write_lumen_surface, write_vtp
from stages.core.errors import UserError
from stages.core.geometry import Camera
from stages.graph.io import PredictionFrame, read_sparse_predictions, write_sparse_predictions
from stages.graph.synthetic import render_mask, smooth_warp, synthetic_tree, voxelise_prediction
from stages.graph.vascular import VascularGraph
from stages.core.voxels import SparseVoxels
from tests.conftest import assert_one_line_error

CAMS = {"a": Camera.from_carm(30, 20, 1100, 750, 0.3, 384, 384), "b": Camera.from_carm(-35, -15, 1100, 750, 0.3, 384, 384)}


@pytest.fixture(scope="module")
def tree():
    return synthetic_tree(0)


def _predictions(path, tree, n_frames=2, masks=True):
    frames = []
    for k in range(n_frames):
        t = tree.copy(nodes=smooth_warp(tree.nodes, tree.nodes.mean(0), angle_deg=3 * k, bend_mm=k,
                                        translation=(0.5 * k, 0, 0.5 * k)))
        m = {v: render_mask(t, c) for v, c in CAMS.items()} if masks else {}
        frames.append(PredictionFrame(f"kf{k}", voxelise_prediction(t, noise=0.05, seed=k), m))
    return write_sparse_predictions(path, frames, case_id="synth0", cameras=CAMS if masks else None)


# ---------------------------------------------------------------------------------------------- exports
def test_vtp_opens_in_vtk_with_radius(tmp_path, tree):
    path = write_vtp(tmp_path / "c.vtp", tree)
    root = ET.parse(path).getroot()  # well-formed XML whatever VTK says
    piece = root.find("PolyData/Piece")
    assert int(piece.get("NumberOfPoints")) == len(tree)
    assert int(piece.get("NumberOfLines")) == len(tree.segments())
    vtk = pytest.importorskip("vtk", reason="vtk (test-only dependency) not installed; XML checked above")
    from vtk.util.numpy_support import vtk_to_numpy

    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    poly = reader.GetOutput()
    assert reader.GetErrorCode() == 0
    assert poly.GetNumberOfPoints() == len(tree)
    assert poly.GetNumberOfLines() == len(tree.segments())
    pts = vtk_to_numpy(poly.GetPoints().GetData())
    assert np.abs(pts - tree.nodes).max() < 1e-4
    radius = vtk_to_numpy(poly.GetPointData().GetArray("Radius"))
    assert np.abs(radius - tree.radius).max() < 1e-4
    assert poly.GetPointData().GetArray("MaximumInscribedSphereRadius") is not None
    # polylines cover every edge exactly once
    lines = poly.GetLines()
    conn = vtk_to_numpy(lines.GetConnectivityArray())
    offs = vtk_to_numpy(lines.GetOffsetsArray())
    walked = set()
    for a, b in zip(offs[:-1], offs[1:]):
        seg = conn[a:b]
        walked |= {tuple(sorted(p)) for p in zip(seg[:-1].tolist(), seg[1:].tolist())}
    assert walked == {tuple(sorted(e)) for e in tree.edges.tolist()}


def test_lumen_surface_is_watertight_with_tube_volume(tmp_path):
    x = np.linspace(0, 30, 61)
    tube = VascularGraph(np.c_[x, 0 * x, 0 * x], np.full(61, 1.5), np.c_[np.arange(60), np.arange(1, 61)])
    mesh = lumen_mesh(tube, voxel_mm=0.25)
    assert mesh.is_watertight and mesh.volume > 0
    expected = np.pi * 1.5 ** 2 * 30 + 4 / 3 * np.pi * 1.5 ** 3  # capsule
    assert abs(mesh.volume - expected) / expected < 0.05
    import trimesh

    for suffix in (".stl", ".ply"):
        path = write_lumen_surface(tmp_path / f"t{suffix}", tube, voxel_mm=0.4)
        back = trimesh.load(path)
        assert back.is_watertight and abs(back.volume - expected) / expected < 0.08

def test_blocked_marching_cubes_gives_the_triangles_of_one_run_over_the_field():
    """Meshing only the blocks that hold a tube, then stitching them, gives the surface of marching cubes over the
    whole field: the same vertices (to float32 rounding), the same triangles, one closed surface."""
    from skimage.measure import marching_cubes

    import stages.core.export as export

    t = np.linspace(0, 4 * np.pi, 200)  # a helix and a straight branch: crosses many block faces and edges
    helix = np.c_[12 * np.cos(t), 12 * np.sin(t), 3 * t]
    branch = helix[100] + np.c_[np.linspace(0, 25, 50), np.linspace(0, 10, 50), np.zeros(50)]
    P = np.vstack([helix, branch])
    r = np.r_[np.linspace(2.0, 1.0, 200), np.full(50, 0.8)]
    E = np.vstack([np.c_[np.arange(199), np.arange(1, 200)], np.c_[np.r_[100, np.arange(200, 249)], np.arange(200, 250)]])
    origin = P.min(0) - 3.0
    shape = tuple((np.ceil((P.max(0) + 3.0 - origin) / 0.4).astype(int) + 1).tolist())
    field = np.full(shape, -1.6, np.float32)
    export._capsule_field(field, P, r, E, origin, 0.4)
    level = 4e-4
    v_all, f_all, _, _ = marching_cubes(field, level=level)
    for block in (7, 16):
        v, f = export._blocked_marching_cubes(field, level, block)
        assert len(f) == len(f_all)
        # the same triangles: compare them as sorted triples of (rounded) vertex positions
        def triangles(verts, faces):
            tri = np.round(verts[faces], 3).reshape(len(faces), 9)
            return tri[np.lexsort(tri.T[::-1])]

        np.testing.assert_allclose(triangles(v, f), triangles(v_all.astype(np.float64), f_all), atol=2e-3)
    import trimesh

    mesh = trimesh.Trimesh(v, f, process=True)
    assert mesh.is_watertight and len(mesh.split(only_watertight=False)) == 1



def test_lumen_surface_of_far_apart_pieces_stays_within_its_memory_cap(monkeypatch):
    """Two tubes ~1 m apart would need a 12 GiB field in one box: each piece gets its own box instead,
    and a piece too long for the cap is meshed on a coarser grid."""
    import stages.core.export as export

    x = np.linspace(0, 20, 41)
    near = np.c_[x, 0 * x, 0 * x]
    far = near + [900.0, -400.0, 550.0]
    edges = np.c_[np.arange(40), np.arange(1, 41)]
    graph = VascularGraph(np.vstack([near, far]), np.full(82, 1.5), np.vstack([edges, edges + 41]))
    monkeypatch.setattr(export, "MAX_FIELD_VOXELS", 2_000_000)
    assert export._field_voxels(graph.nodes, graph.radius, 0.4) > 1e9  # 12 GiB of float32 in one box
    mesh = lumen_mesh(graph, voxel_mm=0.4)
    expected = 2 * (np.pi * 1.5 ** 2 * 20 + 4 / 3 * np.pi * 1.5 ** 3)
    assert mesh.is_watertight and abs(mesh.volume - expected) / expected < 0.05
    assert mesh.bounds[1][0] > 915 and mesh.bounds[0][0] < 0  # both pieces are there
    # one piece too long for the cap: a coarser grid, still a closed tube of the right volume
    long_x = np.linspace(0, 300, 301)
    long = VascularGraph(np.c_[long_x, 0.3 * long_x, 0 * long_x], np.full(301, 2.0),
                         np.c_[np.arange(300), np.arange(1, 301)])
    monkeypatch.setattr(export, "MAX_FIELD_VOXELS", 200_000)
    mesh = lumen_mesh(long, voxel_mm=0.4)
    length = 300 * np.hypot(1, 0.3)
    expected = np.pi * 2.0 ** 2 * length + 4 / 3 * np.pi * 2.0 ** 3
    assert mesh.is_watertight and abs(mesh.volume - expected) / expected < 0.15


def test_graph_json_round_trip(tmp_path, tree):
    path = write_graph_json(tmp_path / "g.json", tree, key_frame="kf0")
    d = json.loads(path.read_text())
    assert d["units"] == "mm" and d["frame"] == "LPS" and d["key_frame"] == "kf0"
    assert "correspondences" not in d  # no cameras given
    back = VascularGraph.from_dict(d)
    assert np.abs(back.nodes - tree.nodes).max() < 1e-3 and np.array_equal(back.edges, tree.edges)


def test_graph_json_correspondences_are_the_nodes_projections(tmp_path, tree):
    small = Camera.from_carm(-35, -15, 1100, 750, 0.3, 96, 96)  # a narrow view: part of the tree falls outside
    cams = {"a": CAMS["a"], "b": small}
    d = json.loads(write_graph_json(tmp_path / "g.json", tree, cams, {"a": 12, "b": 30}).read_text())
    corr = d["correspondences"]
    assert corr["views"]["a"]["source_frame"] == 12 and corr["views"]["b"]["source_frame"] == 30
    assert (corr["views"]["b"]["rows"], corr["views"]["b"]["cols"]) == (96, 96)
    px = {v: corr["views"][v]["pixels"] for v in "ab"}
    assert len(px["a"]) == len(px["b"]) == len(tree)
    outside_b = [i for i, p in enumerate(px["b"]) if p is None]
    assert 0 < len(outside_b) < len(tree)  # nodes outside an image are null there, not clipped
    pairs = np.asarray(corr["pairs"], float)
    idx = pairs[:, 0].astype(int)
    assert idx.tolist() == [i for i in range(len(tree)) if px["a"][i] is not None and px["b"][i] is not None]
    assert np.abs(pairs[:, 1:3] - CAMS["a"].project(tree.nodes[idx])).max() < 0.01
    assert np.abs(pairs[:, 3:5] - small.project(tree.nodes[idx])).max() < 0.01
    assert np.all((pairs[:, 3:5] >= -0.5) & (pairs[:, 3:5] <= 95.5))


# ---------------------------------------------------------------------------------------------- artefacts + stage
def test_prediction_artefact_round_trip(tmp_path, tree):
    path = _predictions(tmp_path / "p.zarr", tree)
    case, frames = read_sparse_predictions(path)
    assert case == "synth0" and [f.key for f in frames] == ["kf0", "kf1"]
    assert set(frames[1].masks) == {"a", "b"} and frames[1].masks["a"].shape == (384, 384)
    assert np.allclose(frames[0].cameras["b"].matrix, CAMS["b"].matrix)
    assert {"occupancy", "centreness"} <= set(frames[0].voxels.features)
    assert frames[0].source_frames == {}  # optional


def test_prediction_artefact_keeps_source_frames_and_images(tmp_path, tree):
    vox = voxelise_prediction(tree, noise=0.0, seed=0)
    image = np.random.default_rng(0).uniform(0, 255, (CAMS["a"].rows, CAMS["a"].cols)).astype(np.float32)
    path = write_sparse_predictions(tmp_path / "p.zarr", [PredictionFrame("00", vox, {}, CAMS, {"a": 3, "b": 17},
                                                                          {"a": image})], case_id="x")
    _, frames = read_sparse_predictions(path)
    assert frames[0].source_frames == {"a": 3, "b": 17}
    assert set(frames[0].images) == {"a"} and np.array_equal(frames[0].images["a"], image)
    wrong = write_sparse_predictions(tmp_path / "w.zarr", [PredictionFrame("00", vox, {}, CAMS, {}, {"a": image[:10]})],
                                     case_id="x")
    with pytest.raises(UserError, match="image 'a' is 10×"):
        read_sparse_predictions(wrong)


def test_graph_opt_cli_writes_tracked_graphs_and_exports(tmp_path, tree, cli):
    pytest.importorskip("torch")
    from stages.graph.io import read_vascular_graphs

    pred = _predictions(tmp_path / "p.zarr", tree)
    out = tmp_path / "g.zarr"
    result = cli("graph-opt", pred, "-o", out)
    assert result.exit_code == 0, result.output
    attrs, tracked = read_vascular_graphs(out)
    assert attrs["kind"] == "autocar.vascular-graphs" and attrs["case_id"] == "synth0"
    assert tracked.keys == ["kf0", "kf1"]
    g0, g1 = tracked.graphs
    assert np.array_equal(g0.node_id, g1.node_id) and np.array_equal(g0.edges, g1.edges)
    assert tracked.deformations[0] is None and tracked.deformations[1].params.shape[1] == 6
    assert len(g0.bifurcations()) == 4
    from scipy.spatial import cKDTree

    truth1 = tree.copy(nodes=smooth_warp(tree.nodes, tree.nodes.mean(0), angle_deg=3, bend_mm=1, translation=(0.5, 0, 0.5)))
    d = cKDTree(truth1.sample(0.1)[0]).query(g1.nodes)[0]
    assert d.mean() < 0.4
    r_err = np.abs(g1.radius - truth1.radius[cKDTree(truth1.nodes).query(g1.nodes)[1]])
    assert np.median(r_err) < 0.2
    for key in ("kf0", "kf1"):
        for suffix in (".vtp", ".stl", ".json"):
            assert (tmp_path / f"g_{key}{suffix}").is_file()
    # the JSON's 2D↔2D correspondences land on the vessels of both views' masks
    d = json.loads((tmp_path / "g_kf1.json").read_text())
    assert d["key_frame"] == "kf1" and d["case_id"] == "synth0"
    pairs = np.asarray(d["correspondences"]["pairs"], float)
    visible = [[i for i, p in enumerate(d["correspondences"]["views"][v]["pixels"]) if p is not None] for v in "ab"]
    assert pairs[:, 0].astype(int).tolist() == sorted(set(visible[0]) & set(visible[1]))
    assert len(pairs) > 100  # this fixture's tree runs partly outside view a
    _, frames = read_sparse_predictions(pred)
    for view, cols in (("a", slice(1, 3)), ("b", slice(3, 5))):
        rc = np.rint(pairs[:, cols]).astype(int)
        assert frames[1].masks[view][rc[:, 0], rc[:, 1]].mean() > 0.95


def test_graph_opt_cli_errors(tmp_path, cli):
    empty = SparseVoxels(np.array([[0, 0, 0], [0, 0, 1]]), 0.5, np.zeros(3),
                         {"occupancy": np.array([0.05, 0.1], np.float32), "centreness": np.zeros(2, np.float32)})
    path = write_sparse_predictions(tmp_path / "empty.zarr", [PredictionFrame("kf0", empty)], case_id="x")
    result = cli("graph-opt", path, "-o", tmp_path / "g.zarr")
    assert_one_line_error(result, "empty.zarr", "kf0", "occupancy")
    assert not (tmp_path / "g.zarr").exists()
    from stages.core.artefacts import write_zarr

    with write_zarr(tmp_path / "other.zarr", kind="autocar.pose-model", schema_version=1, stage="x") as g:
        g.attrs["x"] = 1
    result = cli("graph-opt", tmp_path / "other.zarr", "-o", tmp_path / "g.zarr")
    assert_one_line_error(result, "other.zarr", "autocar.sparse-prediction")
    result = cli("graph-opt", tmp_path / "missing.zarr", "-o", tmp_path / "g.zarr")
    assert_one_line_error(result, "missing.zarr")


def test_graph_opt_single_voxel_prediction_gives_one_node_graph(tmp_path):
    pytest.importorskip("torch")
    from stages.graph.io import read_vascular_graphs
    from stages.graph.stage import run_graph_opt

    vox = SparseVoxels(np.array([[0, 0, 0], [0, 0, 1]]), 0.5, np.zeros(3),
                       {"occupancy": np.array([0.9, 0.1], np.float32), "centreness": np.ones(2, np.float32)})
    pred = write_sparse_predictions(tmp_path / "p.zarr", [PredictionFrame("a", vox), PredictionFrame("b", vox)],
                                    case_id="dot")
    summary = run_graph_opt(pred, tmp_path / "g.zarr")
    _, tracked = read_vascular_graphs(tmp_path / "g.zarr")
    assert [len(g) for g in tracked.graphs] == [1, 1] and np.allclose(tracked.graphs[1].nodes, 0, atol=1e-6)
    assert not (tmp_path / "g_a.stl").exists() and (tmp_path / "g_a.vtp").exists()
    assert summary["frames"][0]["edges"] == 0
