"""prep-ct: lumen mesh, centreline, Eq. 3/4 labels, input formats and bad inputs (small analytic tubes)."""

from __future__ import annotations

import logging

import numpy as np
import pytest

from stages.anatomy import _rasterise_balls
from stages.core.errors import UserError
from stages.prep_ct import PrepParams, prepare_file, prepare_mask, run_batch, split_trees
from stages.prep_ct.centreline import SurfaceDistance, bifurcation_count
from stages.prep_ct.io import read_label_volume, validate_labels
from stages.prep_ct.labels import centreness, densify_polyline
from stages.core.prepared_case import PreparedCase

FAST = PrepParams(preview=False)


def _capsules(segments, spacing, shape, origin):
    """uint8 mask of a union of straight tubes [(p0, p1, r)] rasterised as balls every 0.05 mm."""
    data = np.zeros(shape, np.uint8)
    for p0, p1, r in segments:
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        n = int(np.linalg.norm(p1 - p0) / 0.05) + 1
        pts = p0 + np.linspace(0, 1, n)[:, None] * (p1 - p0)
        _rasterise_balls(data, np.asarray(origin, float), np.asarray(spacing, float), pts, np.full(n, r), 1)
    return data


def _affine(spacing, origin, rot=np.eye(3)):
    a = np.eye(4)
    a[:3, :3] = rot @ np.diag(spacing)
    a[:3, 3] = origin
    return a


TUBE = [((-12.0, 0, 0), (12.0, 0, 0), 1.5)]
Y = [((-12.0, 0, 0), (0.0, 0, 0), 1.5), ((0.0, 0, 0), (10.0, 7.0, 0), 1.1), ((0.0, 0, 0), (10.0, -7.0, 0), 1.1)]


def _volume(segments, spacing=(0.4, 0.4, 0.4), shape=(80, 60, 30), origin=(-16.0, -12.0, -6.0)):
    return _capsules(segments, spacing, shape, origin), _affine(spacing, origin)


@pytest.fixture(scope="module")
def tube_case():
    data, aff = _volume(TUBE)
    return prepare_mask(data > 0, aff, side="left", case_id="tube", source={}, params=FAST)


@pytest.fixture(scope="module")
def y_case():
    data, aff = _volume(Y)
    return prepare_mask(data > 0, aff, side="left", case_id="y", source={}, params=FAST)


def test_centreness_formula():
    phi = np.array([1.0, 0.5, 0.0, -0.3, 0.25])
    d = np.array([0.0, 0.5, 1.0, 0.2, 0.75])
    np.testing.assert_allclose(centreness(phi, d), [1.0, 0.5, 0.0, 0.0, 0.25])


def test_straight_tube_mesh_centreline_and_labels(tube_case):
    c = tube_case
    mesh = c.mesh()
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.volume > 0
    # surface: radial distance of vertices on the cylinder part equals r within 0.1 mm
    body = np.abs(c.vertices[:, 0]) < 10
    rho = np.linalg.norm(c.vertices[body, 1:], axis=1)
    assert abs(rho.mean() - 1.5) < 0.06 and np.percentile(np.abs(rho - 1.5), 95) < 0.15
    # centreline: one path along the x axis with radius 1.5
    assert bifurcation_count(c.nodes, c.edges) == 0
    mid = np.abs(c.nodes[:, 0]) < 10
    assert np.abs(c.nodes[mid, 1:]).max() < 0.1
    assert np.abs(c.radius[mid] - 1.5).mean() < 0.08
    assert c.nodes[:, 0].min() < -10 and c.nodes[:, 0].max() > 10
    # labels (Eq. 4 occupancy, Eq. 3 centreness = 1 − ρ/r on a straight tube)
    lab = c.labels
    assert lab.voxel_size == 0.5
    x = lab.world_points()
    np.testing.assert_allclose(x / 0.5, np.rint(x / 0.5), atol=1e-6)  # world-aligned lattice
    occ = lab.features["occupancy"]
    cen = lab.features["centreness"]
    sel = np.abs(x[:, 0]) < 9
    rho = np.linalg.norm(x[sel, 1:], axis=1)
    clear = np.abs(rho - 1.5) > 0.12
    assert np.array_equal(occ[sel][clear], (rho[clear] < 1.5).astype(np.uint8))
    inside = (rho < 1.4)
    np.testing.assert_allclose(cen[sel][inside], 1 - rho[inside] / 1.5, atol=0.06)
    assert np.all(cen[occ == 0] == 0)
    assert cen[sel][rho < 0.05].min() > 0.95
    # a band of outside voxels is kept as negatives, up to 1 mm from the wall
    outside = rho[~(rho < 1.5)]
    assert len(outside) > 0.5 * np.count_nonzero(rho < 1.5) and outside.max() < 1.5 + 1.0 + 0.1


def test_bifurcation_labels_follow_eq3(y_case):
    c = y_case
    assert bifurcation_count(c.nodes, c.edges) == 1
    deg = np.bincount(c.edges.ravel(), minlength=len(c.nodes))
    junction = c.nodes[deg == 3][0]
    assert np.linalg.norm(junction[:2] - [0.3, 0]) < 1.2
    x = c.labels.world_points()
    cen = c.labels.features["centreness"]
    occ = c.labels.features["occupancy"]
    # on the child axis, away from the junction and the tip: c = 1 − ρ/r with r = 1.1
    d = np.array([10.0, 7.0, 0]) / np.linalg.norm([10.0, 7.0, 0])
    along = x @ d
    rho = np.linalg.norm(x - along[:, None] * d, axis=1)
    sel = (along > 4) & (along < 10) & (rho < 1.0) & (x[:, 1] > 0)
    assert sel.sum() > 20
    np.testing.assert_allclose(cen[sel], 1 - rho[sel] / 1.1, atol=0.08)
    # Eq. 3 exactly, with φ from the mesh and d_cl from the stored centreline
    phi = SurfaceDistance(c.vertices, c.faces)(x)
    from scipy.spatial import cKDTree

    dcl = cKDTree(densify_polyline(c.nodes, c.edges, 0.05)).query(x)[0]
    expect = np.where(phi > 0, phi / np.maximum(phi + dcl, 1e-9), 0.0)
    np.testing.assert_allclose(cen, expect, atol=1e-3)
    assert np.array_equal(occ, (phi > 0).astype(np.uint8))


def _write_nifti(path, data, aff_lps):
    import nibabel as nib

    nib.save(nib.Nifti1Image(data, np.diag([-1.0, -1, 1, 1]) @ aff_lps), str(path))


def _write_nrrd(path, data, aff_lps, space="left-posterior-superior"):
    import nrrd

    aff = aff_lps if space.startswith("left-posterior") else np.diag([-1.0, -1, 1, 1]) @ aff_lps
    nrrd.write(str(path), data, {"space": space, "space directions": aff[:3, :3].T, "space origin": aff[:3, 3]})


def _rot(ax, deg):
    t = np.radians(deg)
    c, s = np.cos(t), np.sin(t)
    i, j = [(1, 2), (0, 2), (0, 1)][ax]
    r = np.eye(3)
    r[i, i] = r[j, j] = c
    r[i, j], r[j, i] = -s, s
    return r


def _same_points(a, b, atol=1e-3, msg=""):
    """Two vertex sets are the same set (every point has a partner within atol, both ways)."""
    from scipy.spatial import cKDTree

    a, b = np.asarray(a, float), np.asarray(b, float)
    assert len(a) == len(b), msg
    assert cKDTree(b).query(a)[0].max() < atol, msg
    assert cKDTree(a).query(b)[0].max() < atol, msg


@pytest.mark.parametrize("oblique", [False, True])
def test_nifti_nrrd_npy_give_the_same_world_mesh(tmp_path, oblique):
    spacing = (0.35, 0.42, 0.5)  # anisotropic
    data = _capsules([((-6.0, 0, 0), (6.0, 1.0, 0.5), 1.2)], spacing, (44, 20, 14), (-7.5, -3.5, -3.2))
    rot = _rot(2, 25) @ _rot(0, 10) if oblique else np.eye(3)
    origin = np.array([12.0, -30.0, 55.0])
    aff = _affine(spacing, origin, rot)
    np.save(tmp_path / "m.npy", data)
    _write_nifti(tmp_path / "m.nii.gz", data, aff)
    _write_nrrd(tmp_path / "m.nrrd", data, aff)
    _write_nrrd(tmp_path / "r.nrrd", data, aff, space="right-anterior-superior")
    outs = {}
    for name in ("m.nii.gz", "m.nrrd", "r.nrrd"):
        (p,) = prepare_file(tmp_path / name, tmp_path / f"{name}.zarr", FAST)
        outs[name] = PreparedCase.load(p)
    (p,) = prepare_file(tmp_path / "m.npy", tmp_path / "npy.zarr", FAST, affine=aff)
    ref = PreparedCase.load(p)
    for name, case in outs.items():
        _same_points(case.vertices, ref.vertices, msg=name)
    if not oblique:  # the plain .npy + spacing + origin path gives the same mesh too
        (p,) = prepare_file(tmp_path / "m.npy", tmp_path / "plain.zarr", FAST, spacing=spacing, origin=origin)
        _same_points(PreparedCase.load(p).vertices, ref.vertices)
    else:  # the oblique mesh is the axis-aligned one rotated about the origin of the volume
        (p,) = prepare_file(tmp_path / "m.npy", tmp_path / "plain.zarr", FAST, spacing=spacing, origin=(0, 0, 0))
        straight = PreparedCase.load(p).vertices.astype(float)
        _same_points(straight @ rot.T + origin, ref.vertices)


def test_nifti_ras_affine_becomes_lps(tmp_path):
    import nibabel as nib

    data = np.zeros((5, 6, 7), np.uint8)
    data[2, 3, 4] = 1
    aff_ras = np.diag([0.5, 0.5, 0.5, 1.0])
    aff_ras[:3, 3] = [10, 20, 30]
    nib.save(nib.Nifti1Image(data, aff_ras), str(tmp_path / "a.nii"))
    _, aff, _ = read_label_volume(tmp_path / "a.nii")
    world = aff @ [2, 3, 4, 1]
    np.testing.assert_allclose(world[:3], [-11.0, -21.5, 32.0])


def test_split_by_labels_and_by_components():
    data, aff = _volume([((-12.0, -6, 0), (10.0, -6, 0), 1.2), ((-12.0, 6, 0), (10.0, 6, 0), 1.0)])
    two = data.copy()
    two[:, 30:, :][data[:, 30:, :] > 0] = 2  # y > 0 half labelled 2
    sides = split_trees(two, aff)
    assert [s for s, _ in sides] == ["left", "right"]
    assert sides[1][1].sum() == np.count_nonzero(two == 2)
    # binary: the component with larger LPS x centroid is left; here both span x, so shift one
    binary = _capsules([((-12.0, -6, 0), (-2.0, -6, 0), 1.2), ((2.0, 6, 0), (12.0, 6, 0), 1.0)],
                       (0.4, 0.4, 0.4), (80, 60, 30), (-16.0, -12.0, -6.0))
    sides = dict(split_trees(binary, aff))
    left_x = np.argwhere(sides["left"])[:, 0].mean()
    right_x = np.argwhere(sides["right"])[:, 0].mean()
    assert left_x > right_x


def test_bad_inputs(tmp_path, caplog):
    with pytest.raises(UserError, match="empty label"):
        validate_labels(np.zeros((4, 4, 4)), "e.npy")
    with pytest.raises(UserError, match="intensity"):
        validate_labels(np.linspace(-1000, 400, 64).reshape(4, 4, 4), "ct.nii")
    with caplog.at_level(logging.WARNING):
        out = validate_labels(np.array([0.0, 0.2, 0.7, 0.9]).reshape(1, 2, 2), "prob.npy")
    assert out.dtype == np.uint8 and out.ravel().tolist() == [0, 0, 1, 1]
    assert "thresholded at 0.5" in caplog.text
    with pytest.raises(UserError, match="unknown input type"):
        prepare_file(tmp_path / "x.dcm", tmp_path / "o.zarr", FAST)
    np.save(tmp_path / "a.npy", np.ones((3, 3, 3), np.uint8))
    with pytest.raises(UserError, match="spacing"):
        prepare_file(tmp_path / "a.npy", tmp_path / "o.zarr", FAST)


def test_label_touching_the_border_is_capped(caplog):
    data, aff = _volume(TUBE)
    cut = data[8:, :, :]  # the tube now leaves the volume at index 0 of axis 0
    assert cut[0].any()
    with caplog.at_level(logging.WARNING):
        case = prepare_mask(cut > 0, aff, side="left", case_id="b", source={}, params=FAST)
    assert "touches the volume border" in caplog.text
    assert case.mesh().is_watertight
    assert case.source["touches_border"] == ["axis 0 start"]


def test_meshes_watertight_or_refused(tmp_path, caplog):
    import trimesh

    tube = trimesh.creation.cylinder(radius=1.2, height=16, sections=48)
    # oblique: skimage's 3D thinning erases a perfectly grid-aligned rod of even width entirely
    tube.apply_transform(trimesh.transformations.rotation_matrix(1.1, [0.3, 1, 0.2]))
    tube.export(tmp_path / "ok.stl")
    (p,) = prepare_file(tmp_path / "ok.stl", tmp_path / "ok.zarr", FAST)
    case = PreparedCase.load(p)
    assert case.mesh().is_watertight
    assert abs(np.median(case.radius) - 1.2) < 0.15
    open_tube = trimesh.Trimesh(tube.vertices, tube.faces[np.linalg.norm(tube.triangles_center, axis=1) < 7.5])
    open_tube.export(tmp_path / "open.ply")
    with pytest.raises(UserError, match="not watertight"):
        prepare_file(tmp_path / "open.ply", tmp_path / "open.zarr", FAST)
    holed = trimesh.Trimesh(tube.vertices, tube.faces[1:])  # one triangle missing: repaired, logged
    holed.export(tmp_path / "holed.obj")
    with caplog.at_level(logging.WARNING):
        prepare_file(tmp_path / "holed.obj", tmp_path / "holed.zarr", FAST)
    assert "holes filled" in caplog.text


def test_batch_skips_a_bad_case(tmp_path):
    data, aff = _volume(TUBE)
    np.save(tmp_path / "good.npy", data)
    np.save(tmp_path / "empty.npy", np.zeros((8, 8, 8), np.uint8))
    tasks = [{"kind": "file", "path": str(tmp_path / n), "output": str(tmp_path / "out"),
              "params": FAST.to_dict(), "spacing": [0.4, 0.4, 0.4], "label": n} for n in ("empty.npy", "good.npy")]
    results = run_batch(tasks, jobs=1)
    errors = {t["label"]: e for t, _, e in results}
    assert "empty label" in errors["empty.npy"]
    assert errors["good.npy"] is None
    assert (tmp_path / "out" / "good_left.zarr").exists()


def test_cli_prep_ct(tmp_path):
    from typer.testing import CliRunner

    from autocar_cli.main import app

    data, _ = _volume(Y)
    np.save(tmp_path / "y.npy", data)
    runner = CliRunner()
    res = runner.invoke(app, ["prep-ct", str(tmp_path / "y.npy"), "--spacing", "0.4", "-o", str(tmp_path / "y.zarr")])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "y.zarr").exists() and (tmp_path / "y.png").exists()
    case = PreparedCase.load(tmp_path / "y.zarr")
    assert case.side == "left" and bifurcation_count(case.nodes, case.edges) == 1
    res = runner.invoke(app, ["prep-ct", str(tmp_path / "y.txt"), "-o", str(tmp_path / "o")])
    assert res.exit_code == 2


def test_marching_cubes_vertices_near_grid_points_keep_the_mesh_watertight(tmp_path):
    """Synthetic seed 65 has blurred-mask values within 1e-4 of the iso-level at fine-grid points; the
    block merge used to fuse distinct vertices there and fold the mesh ("non-watertight", case skipped)."""
    from stages.prep_ct import prepare_synthetic
    from stages.prep_ct.mesh import OFF_LEVEL, _keep_off_level

    field = np.array([0.4995, 0.5, 0.50001, 0.2, 0.9], np.float32)
    _keep_off_level(field)
    np.testing.assert_allclose(field, [0.5 - OFF_LEVEL, 0.5 + OFF_LEVEL, 0.5 + OFF_LEVEL, 0.2, 0.9], rtol=0, atol=1e-7)
    written = prepare_synthetic(65, tmp_path, FAST)
    assert sorted(p.name for p in written) == ["case_0065_left.zarr", "case_0065_right.zarr"]
    assert all(PreparedCase.load(p).mesh().is_watertight for p in written)


def _mtime(path):
    return (path / "zarr.json").stat().st_mtime_ns


def test_cli_prep_ct_folder_refuses_a_non_empty_one(tmp_path, cli):
    from conftest import assert_one_line_error

    data, _ = _volume(TUBE)
    np.save(tmp_path / "tube.npy", data)
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = cli("prep-ct", tmp_path / "tube.npy", "--spacing", "0.4", "--no-preview", "-o", out)
    assert_one_line_error(result, "out", "not empty", "--force", "--resume")
    assert {p.name for p in out.iterdir()} == {"notes.txt"}
    result = cli("prep-ct", tmp_path / "tube.npy", "--spacing", "0.4", "-o", out, "--force", "--resume")
    assert_one_line_error(result, "exclude each other")
    # --resume into a folder another command wrote is refused too
    (out / "RUNNING").write_text('{"command": "reconstruct"}')
    result = cli("prep-ct", tmp_path / "tube.npy", "--spacing", "0.4", "-o", out, "--resume")
    assert_one_line_error(result, "out", "written by autocar reconstruct", "--force")
    assert {p.name for p in out.iterdir()} == {"notes.txt", "RUNNING"}


def test_cli_prep_ct_folder_up_to_date_resume_and_force(tmp_path, cli):
    import json

    from conftest import assert_one_line_error

    tube, _ = _volume(TUBE)
    y, _ = _volume(Y)
    np.save(tmp_path / "tube.npy", tube)
    np.save(tmp_path / "y.npy", y)
    out = tmp_path / "out"
    fast = ["--spacing", "0.4", "--no-preview", "-o", out]
    result = cli("prep-ct", tmp_path / "tube.npy", *fast)
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.iterdir()}
    assert {"tube_left.zarr", "summary.json", ".autocar-manifest.json"} <= names and "RUNNING" not in names
    first, summary_time = _mtime(out / "tube_left.zarr"), (out / "summary.json").stat().st_mtime_ns
    # the same batch again, with or without --resume: up to date, nothing touched
    for extra in ([], ["--resume"]):
        result = cli("prep-ct", tmp_path / "tube.npy", *fast, *extra)
        assert result.exit_code == 0, result.output
        assert "up to date" in result.output and "nothing to do" in result.output
        assert _mtime(out / "tube_left.zarr") == first
        assert (out / "summary.json").stat().st_mtime_ns == summary_time
    # another input into the same folder: refused without a flag, added with --resume
    result = cli("prep-ct", tmp_path / "tube.npy", tmp_path / "y.npy", *fast)
    assert_one_line_error(result, "out", "not empty", "--force", "--resume")
    assert not (out / "y_left.zarr").exists()
    result = cli("prep-ct", tmp_path / "tube.npy", tmp_path / "y.npy", *fast, "--resume")
    assert result.exit_code == 0, result.output
    assert _mtime(out / "tube_left.zarr") == first  # kept
    added = PreparedCase.load(out / "y_left.zarr")
    assert bifurcation_count(added.nodes, added.edges) == 1
    summary = json.loads((out / "summary.json").read_text())
    assert summary["prepared"] == ["y_left.zarr"] and summary["kept"] == ["tube_left.zarr"]
    assert "kept 1 up-to-date case(s)" in result.output
    # --force: what prep-ct wrote goes (y_left.zarr too), every case is prepared again, other files stay
    (out / "notes.txt").write_text("mine")
    result = cli("prep-ct", tmp_path / "tube.npy", *fast, "--force")
    assert result.exit_code == 0, result.output
    names = {p.name for p in out.iterdir()}
    assert {"tube_left.zarr", "notes.txt", "summary.json"} <= names and "y_left.zarr" not in names
    assert _mtime(out / "tube_left.zarr") != first
    assert json.loads((out / "summary.json").read_text())["kept"] == []
