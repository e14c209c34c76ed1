"""Malformed DICOM input (issue 36, finding 4): header claims are checked against the pixel data before
anything is allocated, truncated files are refused by `info` and `reconstruct` alike, and a seeded fuzz
subset (tests/fuzz_dicom.py, the harness; `make fuzz` runs thousands) ends without a traceback or a hang."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, assert_one_line_error
from stages.core.dicom_io import XAGeometry, read_xa, write_xa

EXAMPLE = REPO / "examples" / "run_a.dcm"


def _with(path: Path, src: Path, **tags) -> Path:
    import warnings

    import pydicom

    ds = pydicom.dcmread(src)
    with warnings.catch_warnings():  # the invalid values are the point
        warnings.simplefilter("ignore")
        for key, value in tags.items():
            setattr(ds, key, value)
    buf = io.BytesIO()
    ds.save_as(buf, enforce_file_format=False)
    path.write_bytes(buf.getvalue())
    return path


@pytest.fixture()
def raw_run(tmp_path):
    frames = (np.arange(4 * 32 * 32) % 251).astype(np.uint8).reshape(4, 32, 32)
    return write_xa(tmp_path / "raw.dcm", frames, XAGeometry(20.0, 5.0, 1000.0, 750.0, (0.3, 0.3), 32, 32), 66.7)


@pytest.mark.parametrize("frames", ["2000000000", "100000000000"])
@pytest.mark.parametrize("source", ["raw", "example"])
def test_lying_number_of_frames_is_refused_by_info(cli, tmp_path, raw_run, frames, source):
    src = raw_run if source == "raw" else EXAMPLE
    bad = _with(tmp_path / "lying.dcm", src, NumberOfFrames=frames)
    result = cli("info", bad)
    assert_one_line_error(result, "lying.dcm", f"claims {frames} frame(s)")
    assert result.exit_code == 2


def test_lying_rows_are_refused_before_decoding(tmp_path, raw_run):
    from stages.core.errors import UserError

    bad = _with(tmp_path / "rows.dcm", raw_run, Rows=4096)
    with pytest.raises(UserError, match="rows.dcm: header claims 4 frame.*pixel data holds 4096 bytes"):
        read_xa(bad)


@pytest.mark.parametrize("size", [20_000, 1_500_000])
def test_truncated_run_is_refused_by_info_and_reconstruct(cli, tmp_path, size, capfd):
    cut = tmp_path / "cut.dcm"
    cut.write_bytes(EXAMPLE.read_bytes()[:size])
    result = cli("info", cut)
    assert_one_line_error(result, "cut.dcm", "truncated DICOM file")
    assert "UserWarning" not in result.output and "site-packages" not in result.output
    result = cli("reconstruct", cut, REPO / "examples" / "run_b.dcm", "-o", tmp_path / "out", "--method", "visual-hull")
    assert_one_line_error(result, "cut.dcm", "truncated DICOM file")
    assert "modality" not in result.stderr and not (tmp_path / "out").exists()
    assert "UserWarning" not in capfd.readouterr().err  # nothing raw on the real stderr either


def test_truncated_uncompressed_pixel_data(tmp_path, raw_run):
    from stages.core.errors import UserError

    cut = tmp_path / "cut.dcm"
    data = raw_run.read_bytes()
    cut.write_bytes(data[: len(data) - 1000])
    with pytest.raises(UserError, match="cut.dcm: truncated|cut.dcm: header claims"):
        read_xa(cut)


def test_non_finite_angle_is_refused(cli, tmp_path, raw_run):
    bad = _with(tmp_path / "inf.dcm", raw_run, PositionerSecondaryAngle="inf")
    assert_one_line_error(cli("info", bad), "inf.dcm", "PositionerSecondaryAngle", "no finite number")


def test_info_prints_ecg_rounded(cli):
    result = cli("info", EXAMPLE)
    assert result.exit_code == 0, result.output
    text = " ".join(result.stderr.split()) + " ".join(result.stdout.split())
    assert "heart rate 63 bpm" in text and "R waves at -564, 317" in text
    assert "r_wave_time_vector_ms" not in text and "316.5113830566406" not in text


def test_seeded_fuzz_subset_has_no_traceback_and_no_hang():
    import fuzz_dicom  # tests/fuzz_dicom.py, next to this file

    result = fuzz_dicom.fuzz(40, seed=1234)
    assert result["cases"] == 40
    assert result["tracebacks"] == 0 and result["hangs"] == 0, result["failures"][:3]
    outcomes = result["read_outcomes"]
    assert outcomes.get("refused", 0) >= 10  # the mutations do reach the checks
