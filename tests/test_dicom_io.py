"""XA DICOM reading (real phantom runs), writing and round trip, bad files."""

import logging

import numpy as np
import pydicom
import pytest

from stages.core.dicom_io import XAGeometry, read_xa, write_xa
from stages.core.errors import UserError

PHANTOM_TABLE = {  # from the phantom README: α, β, SID, SOD, frames
    1: (31.3, 0.1, 860, 720, 14), 2: (-27.3, -0.1, 865, 720, 12), 3: (-0.8, -23.2, 891, 720, 12),
    4: (0.1, 28.7, 907, 720, 10), 5: (-26.5, -32.7, 931, 720, 16), 6: (24.0, -18.8, 939, 720, 9),
    7: (-29.3, 25.5, 976, 720, 9), 8: (30.7, 23.6, 976, 720, 8),
}


def test_all_phantom_runs_read(phantom_dir, caplog):
    for i, (alpha, beta, sid, sod, n) in PHANTOM_TABLE.items():
        caplog.clear()
        with caplog.at_level(logging.WARNING):
            run = read_xa(phantom_dir / f"IM{i}.dcm")
        g = run.geometry
        assert (g.alpha, g.beta, g.sid, g.sod) == pytest.approx((alpha, beta, sid, sod))
        assert run.frames.shape == (n, 512, 512) and run.frames.dtype == np.float32
        assert 0 < run.frames.mean() < 255 and run.frames.std() > 5  # real image content decoded
        np.testing.assert_allclose(np.diff(run.frame_times_ms), 66.6667, atol=1e-3)
        assert g.spacing == pytest.approx((0.390625, 0.390625))
        if i <= 4:  # no ImagerPixelSpacing: FieldOfViewDimensions 200 mm / 512, and it says so
            assert g.spacing_source == "FieldOfViewDimensions/matrix"
            assert any("FieldOfViewDimensions" in r.getMessage() for r in caplog.records)
        else:
            assert g.spacing_source == "ImagerPixelSpacing"
        assert run.camera.isocentre_spacing == pytest.approx(0.390625 * sod / sid)


def test_written_run_reads_back_identically(tmp_path):
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 4096, size=(7, 48, 64)).astype(np.uint16)
    geom = XAGeometry(-30.5, 25.25, 1100.0, 760.0, (0.278, 0.3), 48, 64)
    path = write_xa(tmp_path / "run.dcm", frames, geom, 66.6667, bits_stored=12, heart_rate_bpm=70,
                    r_wave_times_ms=[120.0, 977.0])
    run = read_xa(path)
    np.testing.assert_array_equal(run.frames, frames)
    assert run.geometry == geom
    np.testing.assert_allclose(run.frame_times_ms, np.arange(7) * 66.6667, rtol=1e-6)
    assert run.ecg == {"r_wave_time_vector_ms": [120.0, 977.0], "heart_rate_bpm": 70.0}
    assert run.bits_stored == 12
    ds = pydicom.dcmread(path)  # plain pydicom agrees
    assert ds.Modality == "XA" and int(ds.NumberOfFrames) == 7 and float(ds.PositionerPrimaryAngle) == -30.5
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.dcm"]


def _xa_file(tmp_path, name="x.dcm", **overrides):
    geom = XAGeometry(10.0, 5.0, 1000.0, 750.0, (0.3, 0.3), 8, 8)
    path = write_xa(tmp_path / name, np.zeros((2, 8, 8), np.uint8), geom, 66.7)
    ds = pydicom.dcmread(path)
    for key, value in overrides.items():
        if value is None:
            delattr(ds, key)
        else:
            setattr(ds, key, value)
    ds.save_as(path)
    return path


def test_bad_files(tmp_path):
    text = tmp_path / "notes.dcm"
    text.write_text("hello")
    with pytest.raises(UserError, match="notes.dcm: not a DICOM file"):
        read_xa(text)
    with pytest.raises(UserError, match=r"x.dcm: missing C-arm geometry tag\(s\) PositionerPrimaryAngle"):
        read_xa(_xa_file(tmp_path, PositionerPrimaryAngle=None))
    with pytest.raises(UserError, match="ct.dcm: modality CT is not X-ray angiography"):
        read_xa(_xa_file(tmp_path, "ct.dcm", Modality="CT"))
    with pytest.raises(UserError, match="nospacing.dcm: no pixel spacing"):
        read_xa(_xa_file(tmp_path, "nospacing.dcm", ImagerPixelSpacing=None))
    with pytest.raises(UserError, match="sod.dcm: SOD"):
        read_xa(_xa_file(tmp_path, "sod.dcm", DistanceSourceToPatient="1200"))
    good = _xa_file(tmp_path, "trunc.dcm")
    good.write_bytes(good.read_bytes()[:200])
    with pytest.raises(UserError, match="trunc.dcm"):
        read_xa(good)
    with pytest.raises(UserError, match="no such file"):
        read_xa(tmp_path / "absent.dcm")


def test_pixel_spacing_fallback_scaled_by_magnification(tmp_path, caplog):
    path = _xa_file(tmp_path, ImagerPixelSpacing=None, PixelSpacing=[0.2, 0.2])
    with caplog.at_level(logging.WARNING):
        g = read_xa(path).geometry
    assert g.spacing == pytest.approx((0.2 * 1000 / 750, 0.2 * 1000 / 750))
    assert g.spacing_source == "PixelSpacing×SID/SOD"


def test_cli_info_reports_geometry_and_bad_files(cli, tmp_path):
    from conftest import assert_one_line_error

    path = write_xa(tmp_path / "ok.dcm", np.zeros((3, 8, 8), np.uint8), XAGeometry(-30.0, 25.0, 1000.0, 750.0, (0.3, 0.3), 8, 8), 66.7)
    result = cli("info", path)
    assert result.exit_code == 0, result.output
    assert "-30.0°" in result.stderr and "1000 / 750 mm" in result.stderr
    bad = tmp_path / "bad.dcm"
    bad.write_text("nope")
    assert_one_line_error(cli("info", bad), "bad.dcm", "not a DICOM file")


def test_single_r_wave_time_reads_as_a_list(tmp_path):
    path = write_xa(tmp_path / "r.dcm", np.zeros((2, 8, 8), np.uint8), XAGeometry(0.0, 0.0, 1000.0, 750.0, (0.3, 0.3), 8, 8),
                    66.7, r_wave_times_ms=[412.5])
    assert read_xa(path).ecg["r_wave_time_vector_ms"] == [412.5]


def test_seeded_writes_are_byte_identical(tmp_path):
    frames = np.arange(2 * 8 * 8, dtype=np.uint16).reshape(2, 8, 8)
    geom = XAGeometry(5.0, 5.0, 1000.0, 750.0, (0.3, 0.3), 8, 8)
    a = write_xa(tmp_path / "a.dcm", frames, geom, 66.7, uid_seed="case-7", study_uid="1.2.3.4")
    b = write_xa(tmp_path / "b.dcm", frames, geom, 66.7, uid_seed="case-7", study_uid="1.2.3.4")
    assert a.read_bytes() == b.read_bytes()
    assert read_xa(a).metadata["StudyInstanceUID"] == "1.2.3.4"


def test_compress_lossless_keeps_pixels_and_geometry(tmp_path):
    from stages.core.dicom_io import XAGeometry, compress_lossless, read_xa, write_xa

    rng = np.random.default_rng(0)
    frames = np.clip(rng.normal(110, 8, (6, 96, 96)), 0, 255).astype(np.uint8)
    frames[:, 40:46, 10:90] = 30  # a dark vessel
    path = write_xa(tmp_path / "r.dcm", frames, XAGeometry(30.0, -20.0, 1000.0, 750.0, (0.3, 0.3), 96, 96), 66.7)
    before = read_xa(path)
    size = path.stat().st_size
    compress_lossless(path)
    after = read_xa(path)
    assert np.array_equal(after.frames, frames) and np.allclose(after.camera.matrix, before.camera.matrix)
    assert path.stat().st_size < 0.8 * size  # noisy 8-bit frames: measured ~0.6× of raw
    import pydicom

    assert pydicom.dcmread(path).file_meta.TransferSyntaxUID == "1.2.840.10008.1.2.4.70"
