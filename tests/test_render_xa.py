"""Simulated XA acquisitions: DICOM output, sidecar truth, exact correspondences, realism, CLI."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from stages.poses import PoseModel
from stages.render.phantom import tube_case

PHANTOM = Path(__file__).resolve().parents[1] / ".." / "shared" / "data" / "phantom_xa"


@pytest.fixture(scope="module")
def acquisition(tmp_path_factory):
    from stages.render.acquire import simulate_acquisition

    out = tmp_path_factory.mktemp("acq")
    res = simulate_acquisition(tube_case(21), PoseModel.default(seed=0), out, seed=99, size=192, n_frames=24,
                               n_correspondences=55)
    return res


def test_dicoms_open_with_pydicom_and_reader_with_identical_geometry(acquisition):
    import pydicom

    from stages.core.dicom_io import read_xa
    from stages.render.acquire import load_truth

    truth = load_truth(acquisition["truth"])
    for k in "ab":
        path = acquisition[f"run_{k}"]
        ds = pydicom.dcmread(path)
        assert ds.Modality == "XA" and int(ds.NumberOfFrames) == 24 and ds.pixel_array.shape == (24, 192, 192)
        run = read_xa(path)
        g = truth["attrs"]["runs"][k]["geometry"]
        assert run.geometry.alpha == pytest.approx(float(ds.PositionerPrimaryAngle)) == pytest.approx(g["alpha"])
        assert run.geometry.beta == pytest.approx(g["beta"])
        assert run.geometry.sid == pytest.approx(g["sid"]) and run.geometry.sod == pytest.approx(g["sod"])
        assert run.geometry.spacing == pytest.approx(tuple(g["spacing"]))
        assert run.geometry.spacing == pytest.approx(tuple(float(v) for v in ds.ImagerPixelSpacing))
        np.testing.assert_allclose(run.frame_times_ms, np.arange(24) * float(ds.FrameTime))
        assert run.ecg and len(run.ecg["r_wave_time_vector_ms"]) >= 2
        # vessels dark: masked pixels darker than the rest in well-filled frames
        f = run.frames[-8]
        m = truth[k]["masks"][-8].astype(bool)
        assert m.sum() > 50 and f[m].mean() < f[~m].mean() - 10
    # the two runs come from different pose-model clusters
    assert truth["attrs"]["runs"]["a"]["cluster"] != truth["attrs"]["runs"]["b"]["cluster"]


def test_ground_truth_correspondences_are_exact(acquisition):
    from stages.core.dicom_io import read_xa
    from stages.render.acquire import load_truth

    truth = load_truth(acquisition["truth"])
    motion = truth["motion"]
    cams = {k: read_xa(acquisition[f"run_{k}"], load_pixels=False).camera for k in "ab"}
    kf = truth["keyframes"]
    assert kf["pairs"].shape == (7, 2) and kf["uv_a"].shape[1] >= 50
    for p, (i, j) in enumerate(kf["pairs"]):
        for k, frame, uv in (("a", i, kf["uv_a"][p]), ("b", j, kf["uv_b"][p])):
            X = motion.apply(kf["ref_points"][p].astype(float), truth[k]["phase"][frame], truth[k]["resp"][frame])
            err = np.linalg.norm(cams[k].project(X) - uv, axis=1)
            assert err.max() <= 0.5, (p, k, err.max())
        # correspondences are on the vessels: inside (or touching) the GT 2D mask of both frames
        for k, frame, uv in (("a", i, kf["uv_a"][p]), ("b", j, kf["uv_b"][p])):
            from scipy import ndimage

            mask = ndimage.binary_dilation(truth[k]["masks"][frame].astype(bool))
            ij = np.rint(uv).astype(int)
            assert mask[ij[:, 0], ij[:, 1]].mean() > 0.95
    # key frames matched by cardiac phase, and a deformation is really present between the runs
    assert np.median(kf["phase_error"]) < 0.05
    nodes_a = truth["a"]["nodes"]
    assert np.abs(nodes_a - nodes_a[0]).max() > 1.0


def test_truth_frames_follow_the_motion_model(acquisition):
    from stages.render.acquire import load_truth

    truth = load_truth(acquisition["truth"])
    m = truth["motion"]
    for k in "ab":
        t = truth[k]["time_s"]
        np.testing.assert_allclose(m.phase_at(t), truth[k]["phase"], atol=1e-12)
        X = m.apply(truth["reference_nodes"].astype(float), truth[k]["phase"][5], truth[k]["resp"][5])
        np.testing.assert_allclose(X, truth[k]["nodes"][5], atol=1e-3)
    # the bolus fills then the run stays mostly opacified
    c = truth["a"]["concentration"]
    assert c[0] < 0.5 and c.max() > 0.95


@pytest.mark.skipif(not PHANTOM.exists(), reason="../shared/data/phantom_xa (real phantom XA runs) is absent")
def test_simulated_statistics_in_the_range_of_the_real_runs(acquisition):
    from stages.core.dicom_io import read_xa
    from stages.render.realism import frame_statistics

    real = [frame_statistics(read_xa(PHANTOM / f"IM{i}.dcm").frames[4]) for i in (1, 5)]
    sim = frame_statistics(read_xa(acquisition["run_a"]).frames[-6])
    lo = min(r["background_mean"] for r in real)
    hi = max(r["background_mean"] for r in real)
    assert lo - 25 <= sim["background_mean"] <= hi + 25
    assert 2.0 <= sim["noise_std"] <= 12.0
    assert 3.0 <= sim["cnr"] <= 40.0


def test_example_pose_model_keeps_two_views_with_the_tree_well_inside():
    from stages.render.pairs import visible_fraction
    from stages.render.products import EXAMPLE_VIEWS, example_pose_model

    case = tube_case(21)
    base = PoseModel.default(seed=0)
    m = example_pose_model(case, base, margin=0.08)
    assert m.n_clusters == 2 and m.cluster_names == ["RAO caudal", "LAO cranial"]
    np.testing.assert_allclose(m.centres, EXAMPLE_VIEWS)
    assert 0 < len(m) < 2 * len(base) / base.n_clusters  # the clusters' poses, some left out
    for i in range(len(m)):
        assert visible_fraction(case.nodes, m.pose(i).camera(), 0.08 * 512) == 1.0
    a, b = m.sample_pair(np.random.default_rng(0))
    assert {a.cluster, b.cluster} == {0, 1}


def test_cli_render_pairs_and_errors(tmp_path):
    from typer.testing import CliRunner

    from autocar_cli.main import app
    from stages.render.pairs import load_pair_shard

    tube_case(31).save(tmp_path / "cases" / "case_x.zarr")
    runner = CliRunner()
    res = runner.invoke(app, ["render", "pairs", "--cases", str(tmp_path / "cases"), "--n", "3", "--size", "128",
                              "--out", str(tmp_path / "p.zarr"), "--seed", "4"])
    assert res.exit_code == 0, res.output
    shard = load_pair_shard(tmp_path / "p.zarr")
    assert shard["mask_a"].shape == (3, 128, 128) and shard["mask_b"].any()
    # the stored camera reproduces the stored silhouette
    from stages.core.prepared_case import PreparedCase
    from stages.render.raster import rasterise_mask

    case = PreparedCase.load(tmp_path / "cases" / "case_x.zarr")
    m = rasterise_mask(case.vertices + shard["translation"][0], case.faces, shard["cameras_a"][0])
    assert np.array_equal(m, shard["mask_a"][0].astype(bool))
    bad = runner.invoke(app, ["render", "pairs", "--cases", str(tmp_path / "cases"), "--poses",
                              str(tmp_path / "cases" / "case_x.zarr")])
    assert bad.exit_code == 2 and "autocar.pose-model" in bad.output
    bad = runner.invoke(app, ["render", "pairs", "--cases", str(tmp_path / "cases"), "--n", "1", "--seed", "1000000"])
    assert bad.exit_code == 2 and "reserved" in bad.output


# ------------------------------------------------------------------ output folders (xa, se, re, example)
@pytest.fixture()
def tube_products(monkeypatch):
    """The data products with tube phantoms for their procedural trees (prep-ct takes ~10 s a tree)."""
    from stages.render import products

    def tube_tree(folder, seed, side=None):
        side = side or products._side(seed)
        path = Path(folder) / f"case_{seed:07d}_{side}.zarr"
        if not path.exists():
            case = tube_case(seed % 97)
            case.case_id, case.side = path.stem, side
            case.save(path)
        return path

    monkeypatch.setattr(products, "ensure_case", tube_tree)
    return products


def _names(folder):
    return {p.name for p in Path(folder).iterdir()}


def _mtime(path):
    path = Path(path)
    return (path / "zarr.json" if path.is_dir() else path).stat().st_mtime_ns


def test_cli_render_se_refuses_resumes_replaces_and_skips_when_up_to_date(tmp_path, cli, tube_products):
    from conftest import assert_one_line_error
    from stages.render.pairs import load_pair_shard

    out = tmp_path / "se"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    se = ["render", "se", "--n", "1", "--out", out]
    assert_one_line_error(cli(*se, "--size", "64"), "se", "not empty", "--force", "--resume")
    assert _names(out) == {"notes.txt"}
    (out / "notes.txt").unlink()
    result = cli(*se, "--size", "64")
    assert result.exit_code == 0, result.output
    assert {"cases", "pairs.zarr", "manifest.json"} <= _names(out) and "RUNNING" not in _names(out)
    case = next((out / "cases").glob("*.zarr"))
    pairs, case_time = _mtime(out / "pairs.zarr"), _mtime(case)
    # up to date: nothing to do, with or without --resume
    for extra in ([], ["--resume"]):
        result = cli(*se, "--size", "64", *extra)
        assert result.exit_code == 0 and "up to date, skipped" in result.output, result.output
        assert _mtime(out / "pairs.zarr") == pairs
    # other parameters: refused without a flag; --resume keeps the prepared tree and renders the pairs again
    assert_one_line_error(cli(*se, "--size", "96"), "se", "not empty", "--resume to keep its prepared cases")
    assert _mtime(out / "pairs.zarr") == pairs
    result = cli(*se, "--size", "96", "--resume")
    assert result.exit_code == 0, result.output
    assert load_pair_shard(out / "pairs.zarr")["mask_a"].shape == (1, 96, 96) and _mtime(case) == case_time
    # --force: the tree is prepared again, a file autocar did not write stays
    (out / "notes.txt").write_text("mine")
    result = cli(*se, "--size", "96", "--force")
    assert result.exit_code == 0, result.output
    assert "notes.txt" in _names(out) and _mtime(case) != case_time
    # another kind of run does not --resume into it
    assert_one_line_error(cli("render", "re", "--n", "1", "--out", out, "--resume"), "written by autocar render se")


def test_cli_render_re_resume_keeps_finished_cases(tmp_path, cli, tube_products):
    import json

    from conftest import assert_one_line_error

    out = tmp_path / "re"
    re_ = ["render", "re", "--size", "64", "--frames", "12", "--out", out]
    result = cli(*re_, "--n", "1")
    assert result.exit_code == 0, result.output
    truth = _mtime(out / "case_2000000" / "truth.zarr")
    assert_one_line_error(cli(*re_, "--n", "2"), "re", "not empty", "--resume to keep its finished cases")
    assert not (out / "case_2000001").exists()
    result = cli(*re_, "--n", "2", "--resume")
    assert result.exit_code == 0, result.output
    assert _mtime(out / "case_2000000" / "truth.zarr") == truth  # finished: kept
    assert (out / "case_2000001" / "truth.zarr").exists() and "RUNNING" not in _names(out)
    manifest = json.loads((out / "manifest.json").read_text())
    assert [item["dir"] for item in manifest["items"]] == ["case_2000000", "case_2000001"]
    result = cli(*re_, "--n", "2")
    assert result.exit_code == 0 and "up to date, skipped" in result.output, result.output


def test_cli_render_xa_and_example_folders(tmp_path, cli, tube_products):
    from conftest import assert_one_line_error

    tube_case(31).save(tmp_path / "cases" / "c1.zarr")
    out = tmp_path / "xa"
    xa = ["render", "xa", "--cases", tmp_path / "cases", "--size", "64", "--frames", "8", "--out", out]
    result = cli(*xa)
    assert result.exit_code == 0, result.output
    assert {"run_a.dcm", "run_b.dcm", "truth.zarr", "summary.json"} <= _names(out)
    run_a = _mtime(out / "run_a.dcm")
    result = cli(*xa)
    assert result.exit_code == 0 and "up to date, skipped" in result.output, result.output
    assert_one_line_error(cli(*xa[:4], "--size", "64", "--frames", "10", "--out", out), "xa", "not empty")
    assert _mtime(out / "run_a.dcm") == run_a
    # the bundled example's folder holds files autocar did not write: --force keeps them
    ex = tmp_path / "examples"
    ex.mkdir()
    (ex / "README.md").write_text("mine")
    example = ["render", "example", "--size", "64", "--frames", "8", "--out", ex]
    assert_one_line_error(cli(*example), "examples", "not empty", "--force", "--resume")
    assert _names(ex) == {"README.md"}
    result = cli(*example, "--force")
    assert result.exit_code == 0, result.output
    assert _names(ex) == {"README.md", "run_a.dcm", "run_b.dcm", "truth.zarr", "manifest.json"}
    result = cli(*example)
    assert result.exit_code == 0 and "up to date, skipped" in result.output, result.output


def test_a_third_run_leaves_runs_a_and_b_as_they_were(tmp_path, acquisition):
    """render re --runs 3: run C from a third pose cluster, between the two runs; A and B byte-identical."""
    from stages.core.dicom_io import read_xa
    from stages.render.acquire import load_truth, simulate_acquisition

    res = simulate_acquisition(tube_case(21), PoseModel.default(seed=0), tmp_path, seed=99, size=192, n_frames=24,
                               n_correspondences=55, n_runs=3)
    for k in "ab":
        assert Path(res[f"run_{k}"]).read_bytes() == Path(acquisition[f"run_{k}"]).read_bytes()
    truth = load_truth(res["truth"])
    runs = truth["attrs"]["runs"]
    assert len({runs[k]["cluster"] for k in "abc"}) == 3
    # acquired in the pause between A and B, same study
    assert truth["a"]["time_s"][-1] < truth["c"]["time_s"][0] and truth["c"]["time_s"][-1] < truth["b"]["time_s"][0]
    cam_c = read_xa(res["run_c"], load_pixels=False).camera
    # run C's key frames are at the phase of run A's, and the annotated points project where the truth says
    kf = truth["keyframes"]
    for n, ((i, _), c) in enumerate(zip(kf["pairs"], kf["frames_c"])):
        d = abs(truth["c"]["phase"][c] - truth["a"]["phase"][i])
        assert min(d, 1 - d) < 0.1
        P = truth["motion"].apply(kf["ref_points"][n], truth["c"]["phase"][c], truth["c"]["resp"][c])
        np.testing.assert_allclose(cam_c.project(P), kf["uv_c"][n], atol=1e-3)
