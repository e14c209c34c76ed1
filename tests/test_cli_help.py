"""The CLI's help and start-up (issue 36, finding 8): no heavy import behind `autocar --help`, no `<bool>`
metavar on flags, choices listed, examples in the main commands, paragraphs not broken mid-sentence,
and --threads on every compute command."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys

import pytest

from conftest import REPO

HEAVY = ("numpy", "scipy", "torch", "zarr", "matplotlib", "skimage", "pydicom", "sklearn", "networkx", "trimesh", "numcodecs")
MINE = ("info", "prep-ct", "fit-poses", "render", "train", "segment", "keyframe", "reconstruct", "graph-opt")


def test_importing_the_cli_imports_no_heavy_library():
    code = ("import sys, json, autocar_cli.main; "
            f"print(json.dumps(sorted(m for m in {HEAVY!r} if m in sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True)
    assert json.loads(out.stdout) == []


def _help(cli, *cmd):
    result = cli(*cmd, "--help")
    assert result.exit_code == 0, result.output
    return result.stdout


@pytest.mark.parametrize("cmd", MINE)
def test_flags_show_no_bool_metavar(cli, cmd):
    assert "<bool>" not in _help(cli, cmd)


def test_root_help_has_no_bool_metavar(cli):
    assert "<bool>" not in _help(cli)


@pytest.mark.parametrize("cmd", ["reconstruct", "info", "segment", "keyframe", "render"])
def test_main_commands_show_examples(cli, cmd):
    text = _help(cli, cmd)
    assert "Examples" in text and f"autocar {cmd} " in text


def test_choices_are_listed(cli, monkeypatch):
    from stages.methods3d import METHODS

    monkeypatch.setenv("COLUMNS", "200")  # so the metavar column is not folded
    text = _help(cli, "reconstruct")
    assert "[" + "|".join(METHODS) + "]" in text
    assert "[unet|vesselness|threshold]" in text and "[left|right]" in text


@pytest.mark.parametrize("cmd", ["reconstruct", "segment", "keyframe", "graph-opt", "render", "train", "prep-ct", "evaluate"])
def test_compute_commands_take_threads(cli, cmd):
    assert "--threads" in _help(cli, cmd)


def test_help_paragraphs_are_not_broken_mid_sentence():
    from autocar_cli.main import app

    for command in app.registered_commands:
        name = command.name or command.callback.__name__
        if name not in MINE:
            continue
        doc = inspect.cleandoc(command.callback.__doc__ or "")
        broken = [p for p in doc.split("\n\n") if "\n" in p.strip()]
        assert not broken, (name, broken)


def test_cli_copies_of_library_constants_agree():
    from autocar_cli.commands import graph_opt, reconstruct, segment
    from stages.graph.init import DEFAULT_OCCUPANCY_THRESHOLD
    from stages.reconstruct import SEG_METHODS, SIDES
    from stages.segment.infer import METHODS

    from stages import methods3d

    assert (reconstruct.METHODS, reconstruct.DEFAULT_METHOD) == (methods3d.METHODS, methods3d.DEFAULT_METHOD)
    assert graph_opt.DEFAULT_OCCUPANCY_THRESHOLD == DEFAULT_OCCUPANCY_THRESHOLD
    assert tuple(segment.SEG_METHODS) == tuple(METHODS) == tuple(reconstruct.SEG_METHODS) == SEG_METHODS
    assert tuple(reconstruct.SIDES) == SIDES


def test_bad_choice_is_one_error_line(cli, tmp_path):
    from conftest import assert_one_line_error

    assert_one_line_error(cli("segment", tmp_path / "x.dcm", "-o", tmp_path / "m.zarr", "--method", "magic"),
                          "unknown --method 'magic'", "unet, vesselness, threshold")


def test_threads_reach_torch_and_the_environment():
    code = ("import os, torch; from autocar_cli.common import set_threads; set_threads(1); "
            "a = torch.get_num_threads(); set_threads(3); print(a, torch.get_num_threads(), os.environ['OMP_NUM_THREADS'])")
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, check=True,
                         env={"PATH": "/usr/bin:/bin", "OMP_NUM_THREADS": "2"})
    assert out.stdout.split() == ["1", "3", "3"]


def test_progress_off_a_terminal_is_plain_lines(capsys):
    from autocar_cli.common import PlainProgress, console, progress

    assert not console.is_terminal and isinstance(progress(), PlainProgress)
    bar = PlainProgress()
    task = bar.add_task("rendering pairs", total=20)
    for _ in range(20):
        bar.advance(task)
    lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    counts = [line.split(": ")[1].split(",")[0] for line in lines]
    assert counts == [f"{n}/20" for n in (1, 3, 5, 7, 9, 11, 13, 15, 17, 19, 20)]
    assert all(line.startswith("rendering pairs: ") for line in lines) and "ETA" in lines[0] and "ETA" not in lines[-1]
