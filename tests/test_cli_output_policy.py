"""`autocar reconstruct`'s output policy (issue 36): inputs checked before the folder is touched, a non-empty
folder refused unless --force/--resume, RUNNING → summary.json, clean failures on SIGTERM and on OS errors.

The runs are tiny (128², 6 frames, three dark lines) so a whole reconstruction takes ~10 s here.
"""

from __future__ import annotations

import errno
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from conftest import REPO, assert_one_line_error
from stages.core.dicom_io import XAGeometry, write_xa

FAST = ["--method", "visual-hull", "--seg-method", "threshold"]


def _lines_run(path, alpha, shift=0):
    from skimage.draw import line_aa

    frames = np.full((6, 128, 128), 200, np.uint8)
    for t in range(6):
        img = np.full((128, 128), 200.0)
        for r0, c0, r1, c1 in ((10, 64, 110, 60), (60, 62, 100, 100), (40, 63, 20, 110)):
            rr, cc, v = line_aa(r0, c0 + (t + shift) % 2, r1, c1)
            for dr in (-1, 0, 1):
                img[np.clip(rr + dr, 0, 127), cc] -= 120 * v
        frames[t] = np.clip(img, 0, 255).astype(np.uint8)
    return write_xa(path, frames, XAGeometry(alpha, 0.0, 1000.0, 750.0, (0.6, 0.6), 128, 128), 66.7, study_uid="1.2.3")


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("runs")
    return _lines_run(d / "a.dcm", 30.0), _lines_run(d / "b.dcm", -30.0, 1)


@pytest.fixture(scope="module")
def done(runs, tmp_path_factory):
    """One finished reconstruction with two key frames."""
    from typer.testing import CliRunner

    from autocar_cli.main import app

    out = tmp_path_factory.mktemp("done") / "out"
    result = CliRunner().invoke(app, ["reconstruct", *map(str, runs), "-o", str(out), *FAST, "-k", "2"],
                                catch_exceptions=False)
    assert result.exit_code == 0, result.output
    return out, result


def _copy(src: Path, dst: Path) -> Path:
    shutil.copytree(src, dst)
    return dst


def _names(folder: Path) -> set[str]:
    return {p.name for p in folder.iterdir()}


def test_finished_folder_has_summary_with_quality_and_no_marker(done):
    out, result = done
    names = _names(out)
    assert "RUNNING" not in names and "summary.json" in names
    assert not [n for n in names if ".tmp-" in n]
    summary = json.loads((out / "summary.json").read_text())
    q = summary["quality"]
    assert isinstance(q["passed"], bool) and q["verdict"].startswith("quality:")
    assert len(q["frames"]) == len(summary["pairs"])
    for f in q["frames"]:
        assert f["pieces"] and f["pieces"][0]["distance_mm"] == 0.0
        assert set(f["reprojection_mm"]) == {"a", "b"}
        assert {"far_pieces", "branches_outside_masks", "catheter_like", "problems", "passed"} <= set(f)
    # the verdict is the CLI's last word before the "wrote" line
    tail = [line for line in result.stderr.splitlines() if line.strip()][-2:]
    assert tail[0].startswith("quality:") and tail[1].startswith("wrote")


def test_progress_is_plain_lines_when_not_on_a_terminal(done):
    _, result = done
    lines = result.stderr.splitlines()
    pred = [line for line in lines if line.startswith("3D prediction (visual-hull), key frames: ")]
    assert [line.split(": ")[1].split(",")[0] for line in pred] == ["1/2", "2/2"]
    assert any(line.startswith("graph optimisation, key frames: 1/1") for line in lines)
    assert "\x1b[" not in result.stderr  # no terminal control codes in a log


def test_report_is_self_contained_and_shows_file_names(done, runs):
    out, _ = done
    page = (out / "report.html").read_text()
    import re

    # every figure is embedded (the two key frames' overlays at least); nothing refers to a file beside the page
    assert 'src="overlay_' not in page and page.count("data:image/") >= 2
    assert all(src.startswith("data:") for src in re.findall(r'<img[^>]*\ssrc="([^"]*)"', page))
    assert str(Path(runs[0]).parent) not in page  # no absolute path of this machine
    assert "a.dcm" in page and "Quality checks" in page
    assert "<link" not in page and 'src="http' not in page


def test_non_empty_folder_is_refused_naming_force_and_resume(cli, runs, tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    result = cli("reconstruct", *runs, "-o", out, *FAST)
    assert_one_line_error(result, "out", "not empty", "--force", "--resume")
    assert _names(out) == {"notes.txt"}


@pytest.mark.parametrize("args, fragment", [
    (["--seg-method", "magic"], "unknown --seg-method 'magic'"),
    (["--side", "middle"], "unknown --side 'middle'"),
    (["--method", "sbp", "--weights", "/no/such/weights.pt"], "weights.pt: no such file (--weights)"),
    (["--force", "--resume"], "exclude each other"),
])
def test_bad_options_are_refused_before_anything_is_written(cli, runs, tmp_path, args, fragment):
    out = tmp_path / "out"
    base = ["--method", "visual-hull", "--seg-method", "threshold"]
    result = cli("reconstruct", *runs, "-o", out, *base, *args)
    assert_one_line_error(result, fragment)
    assert not out.exists()


def test_unreadable_run_creates_no_folder(cli, runs, tmp_path):
    bad = tmp_path / "bad.dcm"
    bad.write_bytes(Path(runs[0]).read_bytes()[:5000])
    out = tmp_path / "out"
    assert_one_line_error(cli("reconstruct", bad, runs[1], "-o", out, *FAST), "bad.dcm", "truncated")
    assert not out.exists()


def test_failure_after_the_folder_was_made_removes_it(cli, tmp_path):
    flat = XAGeometry(30.0, 0.0, 1000.0, 750.0, (0.6, 0.6), 64, 64)
    a = write_xa(tmp_path / "a.dcm", np.full((4, 64, 64), 180, np.uint8), flat, 66.7, study_uid="1")
    b = write_xa(tmp_path / "b.dcm", np.full((4, 64, 64), 180, np.uint8),
                 XAGeometry(-30.0, 0.0, 1000.0, 750.0, (0.6, 0.6), 64, 64), 66.7, study_uid="1")
    out = tmp_path / "deep" / "out"
    assert_one_line_error(cli("reconstruct", a, b, "-o", out, *FAST), "no vessel found")
    assert not out.exists()


def test_resume_reuses_matching_stages_and_recomputes_changed_ones(cli, done, runs, tmp_path):
    out = _copy(done[0], tmp_path / "out")
    before = (out / "masks_a.zarr" / "zarr.json").stat().st_mtime_ns
    result = cli("reconstruct", *runs, "-o", out, *FAST, "-k", "2", "--resume")
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reused"] == ["masks_a", "masks_b", "keyframes", "predictions", "graphs"]
    assert (out / "masks_a.zarr" / "zarr.json").stat().st_mtime_ns == before
    assert "RUNNING" not in _names(out)
    # another key-frame count: the masks are reused, key frames and everything after them recomputed
    result = cli("reconstruct", *runs, "-o", out, *FAST, "-k", "1", "--resume")
    assert result.exit_code == 0, result.output
    summary = json.loads((out / "summary.json").read_text())
    assert summary["reused"] == ["masks_a", "masks_b"] and len(summary["pairs"]) == 1
    # another segmentation method: nothing is reused
    result = cli("reconstruct", *runs, "-o", out, "--method", "visual-hull", "--seg-method", "vesselness", "-k", "1",
                 "--resume")
    assert result.exit_code == 0, result.output
    assert json.loads((out / "summary.json").read_text())["reused"] == []


def test_force_clears_only_what_autocar_wrote(cli, done, runs, tmp_path):
    out = _copy(done[0], tmp_path / "out")
    (out / "notes.txt").write_text("mine")
    assert (out / "graphs_01.vtp").exists()
    result = cli("reconstruct", *runs, "-o", out, *FAST, "-k", "1", "--force")
    assert result.exit_code == 0, result.output
    names = _names(out)
    assert "notes.txt" in names  # not ours: kept
    assert "graphs_00.vtp" in names and not [n for n in names if n.startswith(("graphs_01", "overlay_01"))]
    assert json.loads((out / "summary.json").read_text())["reused"] == []


def test_sigterm_removes_temporaries_and_leaves_the_marker(runs, tmp_path, cli):
    out = tmp_path / "out"
    env = {**os.environ, "OMP_NUM_THREADS": "1", "COLUMNS": "200"}
    proc = subprocess.Popen([sys.executable, "-m", "autocar_cli.main", "reconstruct", *map(str, runs), "-o", str(out),
                             *FAST, "-k", "2"], cwd=REPO, env=env, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL,
                            text=True)
    seen = []
    for line in proc.stderr:  # wait for the slow stage, then stop it the way a batch system does
        seen.append(line)
        if "graph optimisation" in line:
            proc.send_signal(signal.SIGTERM)
            break
    rest = proc.stderr.read()
    rc = proc.wait(timeout=120)
    text = "".join(seen) + rest
    assert rc == 143, text
    assert "Traceback" not in text and "terminated" in text
    names = _names(out)
    assert "RUNNING" in names and "summary.json" not in names
    assert not [n for n in names if ".tmp-" in n], names
    # the interrupted folder is refused as it is, and --resume continues it from the graph optimisation
    assert_one_line_error(cli("reconstruct", *runs, "-o", out, *FAST, "-k", "2"), "--force", "--resume")
    result = cli("reconstruct", *runs, "-o", out, *FAST, "-k", "2", "--resume")
    assert result.exit_code == 0, result.output
    assert json.loads((out / "summary.json").read_text())["reused"] == ["masks_a", "masks_b", "keyframes", "predictions"]
    assert "RUNNING" not in _names(out)


def test_os_error_on_output_is_one_error_line(cli, runs, tmp_path, monkeypatch):
    import stages.core.artefacts as artefacts

    real_replace = os.replace

    def full_disk(src, dst):
        if str(dst).endswith(".zarr"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real_replace(src, dst)

    monkeypatch.setattr(artefacts.os, "replace", full_disk)
    out = tmp_path / "out"
    result = cli("reconstruct", *runs, "-o", out, *FAST, "-k", "1")
    assert_one_line_error(result, "masks_a.zarr", "cannot write", "No space left on device")
    assert result.exit_code == 2
    assert not out.exists()  # it held nothing but the marker: a failed run leaves no folder it created


def _mount_tmpfs(where: Path, size: str, read_only: bool = False) -> bool:
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    where.mkdir(parents=True, exist_ok=True)
    opts = f"size={size}" + (",ro" if read_only else "")
    return subprocess.run(["mount", "-t", "tmpfs", "-o", opts, "tmpfs", str(where)], capture_output=True).returncode == 0


@pytest.mark.parametrize("kind", ["full", "read-only"])
def test_real_full_or_read_only_file_system(cli, runs, tmp_path, kind):
    mnt = tmp_path / "mnt"
    if not _mount_tmpfs(mnt, "256k", read_only=kind == "read-only"):
        pytest.skip("needs root to mount a small tmpfs")
    try:
        out = mnt / "out"
        result = cli("reconstruct", *runs, "-o", out, *FAST, "-k", "1")
        fragment = "No space left on device" if kind == "full" else "Read-only file system"
        assert_one_line_error(result, str(mnt), fragment)
        assert result.exit_code == 2
        if out.exists():
            assert not [n for n in _names(out) if ".tmp-" in n]
    finally:
        for _ in range(5):
            if subprocess.run(["umount", str(mnt)], capture_output=True).returncode == 0:
                break
            time.sleep(0.5)
