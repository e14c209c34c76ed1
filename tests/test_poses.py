"""Pose model: fitting the phantom runs, the default model and its pair sampler, `autocar fit-poses`."""

import numpy as np
import pytest

from conftest import assert_one_line_error
from stages.core.errors import UserError
from stages.poses import PoseModel, fit_poses


def test_default_sampler_never_repeats_a_cluster_and_keeps_frequencies():
    model = PoseModel.default(seed=0)
    assert model.n_clusters == 9 and len(model) == 1800
    rng = np.random.default_rng(123)
    counts = np.zeros(9)
    for _ in range(10_000):
        a, b = model.sample_pair(rng)
        assert a.cluster != b.cluster
        counts[a.cluster] += 1
        counts[b.cluster] += 1
    freq = counts / counts.sum()
    assert np.abs(freq - model.cluster_probabilities).max() < 0.02
    # parameters are drawn jointly: every sampled pose is a recorded row
    a, _ = model.sample_pair(rng)
    rows = np.c_[model.table["alpha"], model.table["sid"], model.table["sod"], model.table["spacing_row"]]
    assert np.isclose(rows, [a.alpha, a.sid, a.sod, a.spacing[0]]).all(axis=1).any()


def test_default_model_ranges():
    t = PoseModel.default(seed=1).table
    assert (t["sod"] < t["sid"]).all()
    assert 900 <= t["sid"].min() and t["sid"].max() <= 1200 and 700 <= t["sod"].min() and t["sod"].max() <= 800
    sp = t["spacing_row"]
    assert 0.2 < np.median(sp) < 0.4 and np.mean(sp > 0.4) > np.mean(sp < 0.2)  # heavier upper tail


def test_same_seed_same_model():
    a, b = PoseModel.default(seed=5), PoseModel.default(seed=5)
    np.testing.assert_array_equal(a.table["alpha"], b.table["alpha"])
    ra, rb = np.random.default_rng(9), np.random.default_rng(9)
    assert [a.sample_pair(ra) for _ in range(5)] == [b.sample_pair(rb) for _ in range(5)]


def test_uniform_sphere_model_samples_independently():
    m = PoseModel.uniform_sphere(seed=0)
    assert m.sampling == "independent" and m.n_clusters == 1
    rng = np.random.default_rng(0)
    pairs = [m.sample_pair(rng) for _ in range(200)]
    assert all(a != b for a, b in pairs)
    assert np.ptp([p[0].alpha for p in pairs]) > 300


def test_fit_phantom_and_save_load(phantom_dir, tmp_path):
    model, skipped = fit_poses(phantom_dir, n_clusters=4, seed=0)
    assert len(model) == 8 and not skipped
    assert sorted(np.bincount(model.labels, minlength=4) > 0) == [True] * 4
    model.save(tmp_path / "p.zarr")
    back = PoseModel.load(tmp_path / "p.zarr")
    np.testing.assert_array_equal(back.labels, model.labels)
    np.testing.assert_allclose(back.table["alpha"], model.table["alpha"])
    with pytest.raises(UserError, match="8 usable run"):
        fit_poses(phantom_dir, n_clusters=9)


def test_cli_fit_poses_phantom(cli, phantom_dir, tmp_path):
    out = tmp_path / "x.zarr"
    result = cli("fit-poses", phantom_dir, "-o", out, "--clusters", "4")
    assert result.exit_code == 0, result.output
    assert out.is_dir() and (tmp_path / "x.png").stat().st_size > 10_000
    assert "FieldOfViewDimensions" in result.stderr  # the spacing fallback is reported
    assert PoseModel.load(out).n_clusters == 4


def test_cli_default_model(cli, tmp_path):
    result = cli("fit-poses", "--default", "-o", tmp_path / "d.zarr")
    assert result.exit_code == 0, result.output
    assert "LAO caudal" in result.stderr and PoseModel.load(tmp_path / "d.zarr").n_clusters == 9


def test_cli_bad_inputs(cli, tmp_path):
    empty = tmp_path / "empty"
    empty.mkdir()
    assert_one_line_error(cli("fit-poses", empty, "-o", tmp_path / "o.zarr"), "empty", "no files found")
    (empty / "a.dcm").write_text("not dicom")
    (empty / "b.dcm").write_bytes(b"\0" * 300)
    result = cli("fit-poses", empty, "-o", tmp_path / "o.zarr", "--clusters", "2")
    assert_one_line_error(result, "none of 2 file(s) is a usable XA run")
    assert not (tmp_path / "o.zarr").exists() and not (tmp_path / "o.png").exists()
    assert_one_line_error(cli("fit-poses", "-o", tmp_path / "o.zarr"), "exactly one of")
    # an artefact of another kind is refused by name
    cli("fit-poses", "--default", "-o", tmp_path / "d.zarr")
    from stages.core.artefacts import write_zarr

    with write_zarr(tmp_path / "other.zarr", kind="autocar.other", schema_version=1, stage="t"):
        pass
    with pytest.raises(UserError, match="other.zarr: expected an artefact of kind 'autocar.pose-model'"):
        PoseModel.load(tmp_path / "other.zarr")


def test_cli_skips_unreadable_files_with_reasons(cli, phantom_dir, tmp_path):
    import shutil

    folder = tmp_path / "mixed"
    folder.mkdir()
    for i in (1, 2, 5, 6):
        (folder / f"IM{i}.dcm").symlink_to(phantom_dir / f"IM{i}.dcm")
    (folder / "junk.dcm").write_text("garbage")
    result = cli("fit-poses", folder, "-o", tmp_path / "m.zarr", "--clusters", "2")
    assert result.exit_code == 0, result.output
    assert "skipped 1 file" in result.stderr and "not a DICOM file" in result.stderr
    shutil.rmtree(folder)


def test_help_is_useful(cli):
    result = cli("--help")
    assert result.exit_code == 0 and "fit-poses" in result.stdout
    result = cli("fit-poses", "--help")
    assert "--clusters" in result.stdout and "--default" in result.stdout
