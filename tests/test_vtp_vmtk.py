"""Centreline .vtp files as VMTK and 3D Slicer expect them: radius arrays, one ``CenterlineIds`` per branch,
the coordinate system in the field data, and QCA's vessel names, read back with VTK's own reader."""

from __future__ import annotations

import numpy as np
import pytest

from stages.anatomy import generate
from stages.core.export import write_vtp
from stages.graph.io import write_vascular_graphs
from stages.graph.optimise import TrackedGraphs
from stages.graph.vascular import VascularGraph
from stages.qca.truth import truth_graph

vtk = pytest.importorskip("vtk", reason="vtk (a dev dependency) reads the .vtp files back")
from vtk.util.numpy_support import vtk_to_numpy  # noqa: E402


def _read(path):
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return reader.GetOutput()


def _strings(array):
    return [array.GetValue(i) for i in range(array.GetNumberOfValues())]


@pytest.fixture(scope="module")
def graph():
    g, _, _ = truth_graph(generate(1000003).tree("left"))
    return g


def test_arrays_cells_and_coordinate_system(tmp_path, graph):
    poly = _read(write_vtp(tmp_path / "c.vtp", graph))
    segs = graph.segments()
    assert poly.GetNumberOfPoints() == len(graph) and poly.GetNumberOfCells() == len(segs)
    pd, cd, fd = poly.GetPointData(), poly.GetCellData(), poly.GetFieldData()
    np.testing.assert_allclose(vtk_to_numpy(pd.GetArray("Radius")), graph.radius, rtol=1e-4)
    np.testing.assert_allclose(vtk_to_numpy(pd.GetArray("MaximumInscribedSphereRadius")), graph.radius, rtol=1e-4)
    assert vtk_to_numpy(cd.GetArray("CenterlineIds")).tolist() == list(range(len(segs)))
    assert _strings(fd.GetAbstractArray("SPACE")) == ["LPS"] and _strings(fd.GetAbstractArray("Units")) == ["mm"]
    # each cell is one branch, its points in order
    for i, seg in enumerate(segs):
        ids = poly.GetCell(i).GetPointIds()
        assert [ids.GetId(k) for k in range(ids.GetNumberOfIds())] == seg.tolist()


def test_labels_must_match_the_nodes(tmp_path, graph):
    with pytest.raises(ValueError, match="nodes"):
        write_vtp(tmp_path / "c.vtp", graph, node_labels={"VesselName": ["LAD"]})


def test_qca_names_every_key_frame_vtp(tmp_path, graph):
    from stages.qca import qca_for_reconstruction
    from stages.qca.analysis import QCAParams

    frames = [graph, VascularGraph(graph.nodes * 0.98, graph.radius * 1.01, graph.edges, graph.node_id)]
    tracked = TrackedGraphs(["00", "01"], frames, [None, None], np.zeros(len(graph), np.int64), [])
    rec = tmp_path / "rec"
    rec.mkdir()
    write_vascular_graphs(rec / "graphs.zarr", tracked, case_id="test")
    for key, g in zip(tracked.keys, frames):
        write_vtp(rec / f"graphs_{key}.vtp", g)  # as graph-opt writes them, before QCA
    doc = qca_for_reconstruction(rec, params=QCAParams(), plots=False, views=False)
    assert sorted(doc["labelled_exports"]) == ["graphs_00.vtp", "graphs_01.vtp"]
    named = {vd["name"] for vd in doc["vessels"]}
    assert {"LAD", "LCX"} <= named
    for key, g in zip(tracked.keys, frames):
        poly = _read(rec / f"graphs_{key}.vtp")
        pd, cd = poly.GetPointData(), poly.GetCellData()
        np.testing.assert_allclose(vtk_to_numpy(pd.GetArray("Radius")), g.radius, rtol=1e-4)
        names = _strings(pd.GetAbstractArray("VesselName"))
        segments = _strings(pd.GetAbstractArray("VesselSegment"))
        for vd in doc["vessels"]:
            inner = vd["nodes"][1:]  # the first node of a branch is its parent's junction
            assert {names[i] for i in inner} == {vd["name"]}
            if vd["name"] != "unlabelled":
                assert {s.split(" ", 1)[1] for s in (segments[i] for i in inner)} == {vd["name"]}
                assert segments[inner[0]].startswith("proximal") and segments[inner[-1]].startswith("distal")
        cell_names = _strings(cd.GetAbstractArray("VesselName"))
        assert len(cell_names) == poly.GetNumberOfCells() and named <= set(cell_names) | {""}
        assert vtk_to_numpy(cd.GetArray("CenterlineIds")).tolist() == list(range(poly.GetNumberOfCells()))
