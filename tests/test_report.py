"""report.html (issue 36, finding 9): one self-contained page from stages/report's template, images
embedded, runs shown by file name."""

from __future__ import annotations

import base64
import re
from pathlib import Path


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


def test_three_js_is_embedded_and_every_image_is_data(tmp_path):
    import json

    from stages.report import THREE_JS, THREE_VERSION

    page = _page(tmp_path)
    assert THREE_JS.read_text()[-200:] in page and f"three.js {THREE_VERSION}" in page
    assert (THREE_JS.parent / "LICENSE").read_text().startswith("The MIT License")
    assert not re.findall(r"<img[^>]*\ssrc=\"(?!data:)", page)
    model = json.loads(page.split('<script type="application/json" id="model">', 1)[1].split("</script>", 1)[0])
    frame = model["frames"][0]
    assert frame["segments"] == [[0, 1]] and frame["overlay"].startswith("data:image/")
    assert model["diameter_mm"][0] <= 2.0 <= model["diameter_mm"][1]


def test_lesions_and_vessels_from_qca_reach_the_viewer(tmp_path):
    import json

    qca = {"frame": "00", "vessels": [{
        "id": "v0", "name": "LAD", "length_mm": 10.0, "nodes": [0, 1], "parent": None,
        "profile": {"s_mm": [0, 5, 10], "diameter_mm": [2, 1, 2], "reference_mm": [2, 2, 2]},
        "lesions": [{"id": "v0.l0", "ds_percent": 50.0, "mld_mm": 1.0, "reference_mm": 2.0, "length_mm": 4.0,
                     "position_mm": 5.0, "start_mm": 3.0, "end_mm": 7.0, "segment": "mid LAD"}]}]}
    page = _page(tmp_path, qca=qca)
    model = json.loads(page.split('<script type="application/json" id="model">', 1)[1].split("</script>", 1)[0])
    assert model["vessels"] == [{"name": "LAD", "node": 1}]
    (les,) = model["lesions"]
    assert les["id"] == "v0.l0" and les["ds"] == 50.0 and les["length"] == 4.0
    assert les["svg"].startswith("<svg") and "50 %" in les["svg"]


def test_vendored_three_js_is_the_recorded_release():
    import hashlib

    from stages.report import THREE_JS, THREE_VERSION

    readme = (THREE_JS.parent / "README.md").read_text()
    assert f"**{THREE_VERSION}**" in readme
    assert f"sha256 {hashlib.sha256(THREE_JS.read_bytes()).hexdigest()}" in readme  # unmodified since vendored
    assert "import" not in THREE_JS.read_text()[:2000].split("*/", 1)[1][:50]  # one self-contained module


def test_a_branch_one_view_misses_is_marked_for_the_viewer():
    import numpy as np

    from stages.core.geometry import Camera
    from stages.graph.synthetic import render_mask, synthetic_tree
    from stages.quality import frame_quality

    tree = synthetic_tree(0)
    tree = tree.copy(nodes=tree.nodes - tree.nodes.mean(0))  # in both fields of view
    cams = {"a": Camera.from_carm(30, 20, 1100, 750, 0.3, 384, 384), "b": Camera.from_carm(-35, -15, 1100, 750, 0.3, 384, 384)}
    full = {v: render_mask(tree, c) for v, c in cams.items()}
    assert frame_quality(tree, full, cams)["one_view_segments"] == []
    segs = tree.segments()
    deg = tree.degrees()
    terminal = [i for i, s in enumerate(segs) if deg[s[-1]] == 1 or deg[s[0]] == 1]
    k = max(terminal, key=lambda i: len(segs[i]))
    # view B's mask without that branch: its projection erased (a 4-pixel band)
    mask_b = full["b"].copy()
    rows, cols = np.mgrid[: mask_b.shape[0], : mask_b.shape[1]]
    for r, c in cams["b"].project(tree.nodes[segs[k][2:]]):
        mask_b[(rows - r) ** 2 + (cols - c) ** 2 <= 16] = 0
    masks = {"a": full["a"], "b": mask_b}
    assert k in frame_quality(tree, masks, cams)["one_view_segments"]


def test_overlay_panels_draw_each_segment_where_it_projects(tmp_path):
    """The overlay PNG: runs side by side under their titles, a run below 400 px enlarged 2×, and each segment drawn
    in its colormap colour over the pixels it joins (pixel centres at integer indices)."""
    import numpy as np
    from matplotlib import colormaps
    from PIL import Image

    from stages.core.figures import draw_overlay_panels

    big = np.full((512, 512), 100.0)
    big[0, 0], big[-1, -1] = 0.0, 200.0  # the grey range: 100 shows as 127
    small = big[::2, ::2].copy()
    seg_big = np.array([[100.0, 50.0, 100.0, 450.0]])  # a horizontal line at row 100
    seg_small = np.array([[30.0, 200.0, 220.0, 200.0]])  # a vertical line at column 200
    path = draw_overlay_panels(tmp_path / "o.png", [big, small], ["run A", "run B"], [seg_big, seg_small],
                               np.array([0.9]), title_px=22, gap_px=8)
    im = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert im.shape == (22 + 512 + 8, 8 + 512 + 8 + 512 + 8, 3)  # the 256² run shown at 512²
    colour = (np.asarray(colormaps["turbo"](0.9))[:3] * 255).round()
    assert np.abs(im[22 + 100, 8 + 250] - colour).max() <= 10  # on run A's line
    assert np.abs(im[22 + 140, 8 + 250] - 127).max() <= 1  # off it: the grey frame
    # run B's vertical line, at column 200 of the 256² frame: (200 + 0.5) × 2 − 0.5 = 400.5 in the enlarged panel
    x0 = 8 + 512 + 8
    assert np.abs(im[22 + 2 * 120, x0 + 400] - colour).max() <= 10
    assert np.abs(im[22 + 2 * 120, x0 + 380] - colour).max() > 50
