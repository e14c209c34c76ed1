"""Shared test fixtures: the real phantom runs (skipped with a reason when absent) and a CLI runner."""

from __future__ import annotations

from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PHANTOM_DIR = REPO.parent / "shared" / "data" / "phantom_xa"


@pytest.fixture(scope="session")
def phantom_dir() -> Path:
    if not (PHANTOM_DIR / "IM1.dcm").exists():
        pytest.skip(f"real phantom XA runs not found at {PHANTOM_DIR} (../shared/data/phantom_xa beside the checkout)")
    return PHANTOM_DIR


@pytest.fixture()
def cli():
    """Invoke ``autocar`` in-process: cli(args) -> click Result with .exit_code, .stdout, .stderr."""
    from typer.testing import CliRunner

    from autocar_cli.main import app

    runner = CliRunner()

    def invoke(*args):
        return runner.invoke(app, [str(a) for a in args], catch_exceptions=False)

    return invoke


def assert_one_line_error(result, *fragments):
    """A user error: non-zero exit, a single 'error:' line naming the problem, no traceback."""
    assert result.exit_code != 0, result.output
    text = result.stderr.strip()
    assert "Traceback" not in result.output
    lines = [line for line in text.splitlines() if line.strip()]
    error_lines = [line for line in lines if line.startswith("error:")]
    assert len(error_lines) == 1, text
    joined = " ".join(text.split())
    for fragment in fragments:
        assert fragment in joined, (fragment, text)
