"""report.html (issue 36, finding 9): one self-contained page from stages/report's template, images
embedded, runs shown by file name."""

from __future__ import annotations

import base64
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest

from stages.report import write_report

PNG_1x1 = base64.b64decode("iVBORw0KGgoAAAANSUhEUgAAAAEAAAABCAYAAAAfFcSJAAAADUlEQVR42mP8z8BQDwAEhQGAhKmMIQAAAABJRU5ErkJggg==")


def _page(tmp_path, **kw):
    png = tmp_path / "overlay_00.png"
    png.write_bytes(PNG_1x1)
    frames = [{"key": "00", "nodes": [[0, 0, 0], [10, 0, 0]], "radius": [1, 1], "edges": [[0, 1]], "pos": [0, 1]}]
    args = dict(title="t </script>", summary_rows=[("run A", Path("/very/secret/place/run_a.dcm")), ("n", 3)],
                timings=[("segment", 1.0)], frames_model=frames, overlays=[("00", png)], warnings=["w </script> x"],
                quality={"passed": False, "verdict": "quality: FAILS its own checks", "frames": []})
    args.update(kw)
    return write_report(tmp_path / "report.html", **args).read_text()


def test_images_are_embedded_and_paths_are_file_names(tmp_path):
    page = _page(tmp_path)
    assert "data:image/png;base64," + base64.b64encode(PNG_1x1).decode() in page
    assert 'src="overlay_00.png"' not in page
    assert "run_a.dcm" in page and "/very/secret/place" not in page
    fields = re.findall(r"\$\{(\w+)\}", (Path(__file__).parents[1] / "stages" / "report" / "template.html").read_text())
    assert fields and not [f for f in fields if "${" + f + "}" in page]  # every template field was filled
    assert "quality: FAILS its own checks" in page and 'class="verdict fail"' in page


def test_css_and_script_are_inline(tmp_path):
    page = _page(tmp_path)
    assert "<link" not in page and "<script src" not in page
    assert (Path(__file__).parents[1] / "stages" / "report" / "viewer.js").read_text().strip()[:40] in page
    # a '</script>' inside the data cannot end the model's script element early
    body = page.split('<script type="application/json" id="model">', 1)[1].split("</script>", 1)[0]
    assert "nodes" in body


@pytest.mark.skipif(shutil.which("node") is None, reason="node not installed: the report's script is not run")
def test_viewer_script_runs(tmp_path):
    page = _page(tmp_path)
    model = page.split('<script type="application/json" id="model">', 1)[1].split("</script>", 1)[0]
    js = (Path(__file__).parents[1] / "stages" / "report" / "viewer.js").read_text()
    stub = """
const calls = {stroke: 0};
const ctx2d = {fillRect() {}, beginPath() {}, moveTo() {}, lineTo() {}, stroke() { calls.stroke++; }};
const el = {model: {textContent: MODEL}, view3d: {width: 640, height: 640, getContext: () => ctx2d},
            frame: {value: 0}, frame_label: {textContent: ''}};
const document = {getElementById: id => el[id]};
const window = {};
""".replace("MODEL", repr(model))
    script = tmp_path / "run.js"
    script.write_text(stub + js + "\nif (calls.stroke !== 1) { throw new Error('drew ' + calls.stroke); }\n"
                      "console.log(el.frame_label.textContent);\n")
    out = subprocess.run(["node", str(script)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "00"
