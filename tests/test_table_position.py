"""A table that moved between runs: read from the header (GE's private table block) or a geometry JSON
(``TablePosition``), and every run's camera placed in the first run's patient frame."""

from __future__ import annotations

import json

import numpy as np
import pytest

from stages.core.errors import UserError
from stages.core.geometry import Camera, cameras_on_one_table, table_position_from_dict
from stages.core.runs import load_run, place_on_one_table


def test_a_moved_table_moves_the_patient_not_the_image():
    cam = Camera.from_carm(30, -20, 1000, 750, 0.3, 256, 256)
    offset = np.array([4.0, -7.0, 12.0])
    moved = cam.on_table_moved_by(offset)
    X = np.random.default_rng(0).uniform(-40, 40, (50, 3))
    # during the run the patient point X stood at X + offset in the room
    np.testing.assert_allclose(moved.project(X), cam.project(X + offset), atol=1e-9)
    assert moved.carm["table_offset_mm"] == [4.0, -7.0, 12.0] and moved.carm["alpha"] == 30


def test_cameras_on_one_table_uses_the_first_run_as_reference(caplog):
    cams = [Camera.from_carm(a, 0, 1000, 750, 0.3, 64, 64) for a in (-30, 30, 0)]
    tables = [np.array([1.0, 2.0, 3.0]), np.array([1.0, 2.0, 3.0]), np.array([1.0, -8.0, 23.0])]
    out, offsets = cameras_on_one_table(cams, tables, ["A", "B", "C"])
    assert out[0] is cams[0] and out[1] is cams[1]  # same table: untouched
    assert offsets == {"C": [0.0, -10.0, 20.0]}
    np.testing.assert_allclose(out[2].source, cams[2].source - [0.0, -10.0, 20.0])
    # one run without a table position: nothing can be placed, the header cameras stand, and it is said
    with caplog.at_level("WARNING"):
        same, none = cameras_on_one_table(cams, [tables[0], None, tables[2]], ["A", "B", "C"])
    assert none == {} and all(a is b for a, b in zip(same, cams))
    assert "the table position is known for A, C only" in caplog.text


@pytest.mark.parametrize("value, fragment", [
    ([1.0, 2.0], "TablePosition must be [x, y, z] in mm"),
    ("0 0 0", "TablePosition must be [x, y, z] in mm"),
    ([0.0, float("nan"), 0.0], "TablePosition is nan"),
    ([0.0, "12", 0.0], "TablePosition must be a number"),
    ([0.0, 0.0, 5000.0], "is beyond ±2000 mm"),
])
def test_a_malformed_table_position_is_refused_naming_the_key(value, fragment):
    with pytest.raises(UserError) as exc:
        table_position_from_dict({"TablePosition": value}, source="g.json")
    assert fragment in str(exc.value) and "g.json" in str(exc.value)
    assert table_position_from_dict({}, source="g.json") is None


def test_phantom_header_table_positions(phantom_dir):
    a, b = load_run(phantom_dir / "IM1.dcm"), load_run(phantom_dir / "IM6.dcm")
    np.testing.assert_allclose(a.table_mm, [9.2, 84.0, 503.9])
    np.testing.assert_allclose(b.table_mm, [7.7, 55.1, 470.2])
    header_b = b.camera
    offsets = place_on_one_table([a, b], ["IM1", "IM6"])
    assert offsets == {"IM6": [-1.5, -28.9, -33.7]}
    assert np.linalg.norm(b.camera.source - header_b.source) == pytest.approx(np.linalg.norm([1.5, 28.9, 33.7]))


def test_frames_path_carries_the_table_position(phantom_dir, tmp_path):
    from stages.core.runs import export_frames

    folder = export_frames(phantom_dir / "IM6.dcm", tmp_path / "IM6")
    assert json.loads((folder / "geometry.json").read_text())["TablePosition"] == [7.7, 55.1, 470.2]
    runs_dicom = [load_run(phantom_dir / "IM1.dcm"), load_run(phantom_dir / "IM6.dcm")]
    runs_frames = [load_run(phantom_dir / "IM1.dcm"), load_run(folder)]
    assert place_on_one_table(runs_dicom) == place_on_one_table(runs_frames)
    np.testing.assert_allclose(runs_frames[1].camera.matrix, runs_dicom[1].camera.matrix, rtol=1e-12)


def test_table_placement_makes_a_moved_run_agree_with_the_others(phantom_dir):
    """IM6's table stood 44 mm from IM1–IM4's: a two-view hull of IM1+IM2 projected into IM6 explains
    much more of IM6's vessels once IM6's camera follows its table (header cameras: 0.43)."""
    from stages.evaluate.heldout import heldout_rows, load_views

    from stages.evaluate.heldout import run_heldout

    views = load_views(phantom_dir)
    names = [v.name for v in views]
    i, j, k = names.index("IM1"), names.index("IM2"), names.index("IM6")
    assert views[k].table_offset_mm == [-1.5, -28.9, -33.7] and views[j].table_offset_mm is None
    result = run_heldout(phantom_dir, pairs=[(i, j)], views=views, calibrate=False, fit_pose=False)
    assert set(result["table_offsets_mm"]) == {"IM5", "IM6", "IM7", "IM8"}  # what the JSON reports
    placed = [r for r in heldout_rows(views, (i, j)) if r["heldout"] == "IM6"][0]
    views[k].camera = load_run(phantom_dir / "IM6.dcm").camera  # the header camera, table ignored
    header = [r for r in heldout_rows(views, (i, j)) if r["heldout"] == "IM6"][0]
    assert placed["coverage"] > header["coverage"] + 0.2
    assert placed["distance_mm"] < 0.5 * header["distance_mm"]


def test_reconstruct_places_run_b_on_run_a_table_and_says_so(cli, phantom_dir, tmp_path):
    """The real phantom's IM6 was acquired with the table 44 mm from IM1's: reconstruct moves run B's camera
    by it, prints it among its last lines and keeps it in summary.json and the report."""
    out = tmp_path / "im1_im6"
    result = cli("reconstruct", phantom_dir / "IM1.dcm", phantom_dir / "IM6.dcm", "-o", out, "--method", "visual-hull",
                 "-k", "1", "--no-qca")
    assert result.exit_code == 0, result.stdout + result.stderr
    assert "run B: the table moved (-1.5, -28.9, -33.7) mm (x, y, z) from run A's" in result.stdout + result.stderr
    summary = json.loads((out / "summary.json").read_text())
    assert summary["table_offsets_mm"] == {"run B": [-1.5, -28.9, -33.7]}
    assert "run B: table moved from run A" in (out / "report.html").read_text()  # the report's summary row


def test_calibrate_places_the_runs_first_and_reports_it(phantom_dir):
    from stages.calibration.stage import run_calibration

    result = run_calibration([phantom_dir / "IM1.dcm", phantom_dir / "IM6.dcm"])
    assert [r["table_offset_mm"] for r in result["runs"]] == [None, [-1.5, -28.9, -33.7]]
    assert result["summary_lines"][0].startswith("IM6: the table stood (-1.5, -28.9, -33.7) mm (x, y, z) from IM1's")


def test_ge_private_table_block_is_read_and_bad_values_are_ignored():
    """Without the phantom: a header with GE's private table block gives (lateral, vertical, longitudinal) as
    (x, y, z); a block without the creator, or with a value that is not a number, gives no table position."""
    from pydicom.dataset import Dataset

    from stages.core.dicom_io import table_position

    ds = Dataset()
    block = ds.private_block(0x0019, "DLX_SERIE_01", create=True)
    block.add_new(0x21, "DS", "55.1")  # vertical
    block.add_new(0x22, "DS", "470.2")  # longitudinal
    block.add_new(0x23, "DS", "7.7")  # lateral
    assert table_position(ds) == ((7.7, 55.1, 470.2), "DLX_SERIE_01 (0019,xx21–23)")
    assert table_position(Dataset()) == (None, "")
    del ds[block.get_tag(0x22)]
    assert table_position(ds) == (None, "")  # one of the three missing
    block.add_new(0x22, "LO", "n/a")  # a value that is not a number (as a corrupt header may hold)
    assert table_position(ds) == (None, "")
