"""Artefact store: round trips, header validation and atomic writes."""

import numpy as np
import pytest

from stages.core.artefacts import artefact_attributes, atomic_path, load_npz, read_zarr, save_npz, write_zarr
from stages.core.errors import UserError
from stages.core.voxels import SparseVoxels


def test_zarr_roundtrip_with_header(tmp_path):
    path = tmp_path / "a.zarr"
    coords = np.arange(30, dtype=np.int32).reshape(10, 3)
    with write_zarr(path, kind="autocar.test", schema_version=3, stage="unit", inputs=[tmp_path / "in.dcm"],
                    parameters={"k": 9, "eps": np.float32(0.5)}) as g:
        g.create_array("coords", data=coords)
        g.require_group("frame0").create_array("mask", data=np.eye(4, dtype=bool))
    g = read_zarr(path, kind="autocar.test", schema_version=3)
    np.testing.assert_array_equal(g["coords"][...], coords)
    assert g["frame0/mask"][...].dtype == bool
    attrs = dict(g.attrs)
    assert attrs["writer"]["stage"] == "unit" and attrs["writer"]["package"] == "autocar"
    assert attrs["parameters"] == {"k": 9, "eps": 0.5}
    assert attrs["inputs"] == [str(tmp_path / "in.dcm")]
    assert artefact_attributes(path)["kind"] == "autocar.test"


def test_wrong_kind_or_version_names_file_and_expectation(tmp_path):
    path = tmp_path / "a.zarr"
    with write_zarr(path, kind="autocar.test", schema_version=1, stage="unit"):
        pass
    with pytest.raises(UserError, match=r"a\.zarr: expected an artefact of kind 'autocar.other', found 'autocar.test'"):
        read_zarr(path, kind="autocar.other", schema_version=1)
    with pytest.raises(UserError, match=r"a\.zarr: autocar.test artefact has schema version 1, this autocar reads version 2"):
        read_zarr(path, kind="autocar.test", schema_version=2)
    with pytest.raises(UserError, match="no such artefact"):
        read_zarr(tmp_path / "missing.zarr", kind="autocar.test", schema_version=1)
    (tmp_path / "junk.zarr").mkdir()
    with pytest.raises(UserError, match="junk.zarr: not a readable zarr"):
        read_zarr(tmp_path / "junk.zarr", kind="autocar.test", schema_version=1)


def test_failed_write_leaves_nothing_and_keeps_previous(tmp_path):
    path = tmp_path / "a.zarr"
    with write_zarr(path, kind="autocar.test", schema_version=1, stage="unit") as g:
        g.create_array("x", data=np.arange(3))
    with pytest.raises(RuntimeError):
        with write_zarr(path, kind="autocar.test", schema_version=1, stage="unit") as g:
            g.create_array("x", data=np.arange(5))
            raise RuntimeError("crash mid-write")
    # the old artefact survives intact, no temporary sibling is left
    np.testing.assert_array_equal(read_zarr(path, kind="autocar.test", schema_version=1)["x"][...], np.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.zarr"]
    with pytest.raises(ValueError):
        with atomic_path(tmp_path / "b.png") as tmp:
            tmp.write_bytes(b"partial")
            raise ValueError("boom")
    assert not (tmp_path / "b.png").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["a.zarr"]


def test_npz_roundtrip_and_validation(tmp_path):
    path = tmp_path / "p.npz"
    save_npz(path, {"m": np.ones((4, 4), np.uint8)}, kind="autocar.pairs", schema_version=1, stage="unit")
    arrays, attrs = load_npz(path, kind="autocar.pairs", schema_version=1)
    assert arrays["m"].sum() == 16 and attrs["kind"] == "autocar.pairs"
    with pytest.raises(UserError, match="expected an artefact of kind"):
        load_npz(path, kind="autocar.other", schema_version=1)
    np.savez(tmp_path / "plain.npz", a=np.ones(2))
    with pytest.raises(UserError, match="plain.npz: NPZ file has no autocar header"):
        load_npz(tmp_path / "plain.npz", kind="autocar.pairs", schema_version=1)
    (tmp_path / "bad.npz").write_bytes(b"not a zip")
    with pytest.raises(UserError, match="bad.npz: not a readable NPZ"):
        load_npz(tmp_path / "bad.npz", kind="autocar.pairs", schema_version=1)


def test_sparse_voxels_roundtrip_and_dense(tmp_path):
    mask = np.zeros((6, 7, 8), bool)
    mask[1:4, 2, 3:7] = True
    occ = mask.astype(np.float32) * 0.75
    sv = SparseVoxels.from_dense(mask, 0.5, origin=[-10, 0, 5], offset=(2, -3, 1), features={"occupancy": occ})
    assert len(sv) == mask.sum()
    np.testing.assert_allclose(sv.world_points()[0], np.array([-10, 0, 5]) + (np.array([1, 2, 3]) + [2, -3, 1]) * 0.5)
    with write_zarr(tmp_path / "v.zarr", kind="autocar.test", schema_version=1, stage="unit") as g:
        sv.write_to_group(g.require_group("voxels"))
    back = SparseVoxels.read_from_group(read_zarr(tmp_path / "v.zarr", kind="autocar.test", schema_version=1)["voxels"])
    np.testing.assert_array_equal(back.coords, sv.coords)
    np.testing.assert_allclose(back.features["occupancy"], 0.75)
    dense, lo = back.to_dense()
    assert dense.sum() == mask.sum() and tuple(lo) == (3, -1, 4)


def test_sparse_voxels_subset_keeps_grid_and_features():
    sv = SparseVoxels(np.array([[0, 0, 0], [1, 2, 3], [4, 5, 6]], np.int32), 0.5, np.array([1.0, 2.0, 3.0]),
                      {"occupancy": np.array([0.2, 0.9, 0.6], np.float32)})
    sub = sv.subset(sv.features["occupancy"] >= 0.5)
    assert len(sub) == 2 and sub.voxel_size == 0.5 and np.allclose(sub.origin, [1, 2, 3])
    assert np.array_equal(sub.coords, [[1, 2, 3], [4, 5, 6]])
    assert np.allclose(sub.features["occupancy"], [0.9, 0.6])
    assert np.allclose(sub.world_points()[0], [1.5, 3.0, 4.5])


def test_load_torch_file_names_the_file_and_the_problem(tmp_path):
    from stages.core.artefacts import load_torch_file
    from stages.core.errors import UserError

    with pytest.raises(UserError, match=r"w\.pt: no such weights file \(hint\)"):
        load_torch_file(tmp_path / "w.pt", " (hint)")
    (tmp_path / "bad.pt").write_text("not a torch file")
    with pytest.raises(UserError, match="bad.pt: not a readable weights file"):
        load_torch_file(tmp_path / "bad.pt")


def test_json_export_converts_numpy_paths_and_non_finite(tmp_path):
    import json
    from collections import OrderedDict
    from pathlib import Path

    from stages.core.artefacts import write_json

    doc = {"a": np.arange(3), "b": [np.float32(1.5), float("nan"), (1, 2)], "c": OrderedDict(p=Path("x/y")),
           "d": {"inf": float("inf"), "n": None, "flag": True, "i": np.int64(4)}}
    out = json.loads(write_json(tmp_path / "doc.json", doc).read_text())
    assert out == {"a": [0, 1, 2], "b": [1.5, None, [1, 2]], "c": {"p": "x/y"},
                   "d": {"inf": None, "n": None, "flag": True, "i": 4}}
