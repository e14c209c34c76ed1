"""The reconstruction's one-page HTML report, self-contained: its CSS, scripts, 3D viewer and every figure are
embedded when it is written (``template.html`` with ``report.css`` and ``viewer.js`` beside it, filled by
:class:`string.Template`; three.js from ``vendor/``; images as ``data:`` URIs, the QCA profiles as inline SVG),
so the file can be mailed or archived on its own and opens offline. Input runs are shown by file name, not by
the path on the machine that ran it.

The 3D viewer (``viewer.js`` on three.js, WebGL): per key frame the lumen as shaded tubes coloured by
diameter, with a colour bar; orbit, zoom, pan and reset; vessel names at their origins and the lesions with
their %DS and length (a click shows the vessel's diameter profile); a key-frame slider and a play button
with the cardiac phase; both runs' C-arm sources and central rays; branches only one run shows drawn faint;
beside it the key frame's reprojection on both runs.

Reads: the template files here, the vendored three.js and the overlay PNGs. Writes: ``report.html`` (atomic).
"""

from __future__ import annotations

import html
import json
from pathlib import Path
from string import Template

import numpy as np

from ..core.artefacts import atomic_path
from ..core.embed import compact_data_uri, data_uri  # noqa: F401  (data_uri: kept importable from here)

_HERE = Path(__file__).parent
THREE_VERSION = "0.170.0"  # stages/report/vendor/README.md: where it comes from and how to refresh it
THREE_JS = _HERE / "vendor" / "three.module.min.js"


def _text(name: str) -> str:
    return (_HERE / name).read_text(encoding="utf-8")


def display_value(value) -> str:
    """Paths shown by file name only (the report may travel to another machine)."""
    if isinstance(value, Path):
        return value.name
    return str(value)


def carm_label(alpha: float, beta: float) -> str:
    """C-arm angles as a cardiologist names them: "LAO 33° CRA 38°"."""
    return f"{'LAO' if alpha >= 0 else 'RAO'} {abs(alpha):.0f}° {'CRA' if beta >= 0 else 'CAU'} {abs(beta):.0f}°"


def camera_view(camera, centre) -> dict:
    """What the viewer draws of a run's C-arm: the source (mm), the central ray's end just past the tree, and
    the four image corners' rays cut at the tree's depth (the beam through the model)."""
    centre = np.asarray(centre, float)
    depth = float(np.dot(centre - camera.source, camera.view_dir))
    corners = [[0.0, 0.0], [0.0, camera.cols - 1.0], [camera.rows - 1.0, camera.cols - 1.0], [camera.rows - 1.0, 0.0]]
    _, dirs = camera.rays(np.asarray(corners))
    ends = camera.source + dirs * (depth / (dirs @ camera.view_dir))[:, None]
    carm = camera.carm or {}
    out = {"source": np.round(camera.source, 1).tolist(),
           "ray_end": np.round(camera.source + 1.15 * depth * camera.view_dir, 1).tolist(),
           "corners": np.round(ends, 1).tolist()}
    if "alpha" in carm and "beta" in carm:
        out["angles"] = carm_label(float(carm["alpha"]), float(carm["beta"]))
    return out


def _segments(frame: dict) -> list[list[int]]:
    from ..graph.vascular import VascularGraph

    nodes = np.asarray(frame["nodes"], float).reshape(-1, 3)
    if not len(nodes):
        return []
    g = VascularGraph(nodes, np.asarray(frame["radius"], float), np.asarray(frame["edges"], np.int64).reshape(-1, 2))
    return [s.tolist() for s in g.segments()]


def _qca_model(qca: dict | None, positions) -> tuple[list, list]:
    """Vessel labels (name at the vessel's origin) and lesion markers for the viewer, from qca.json's content
    (its lesions, and its unconfirmed narrowings marked ``unconfirmed`` with the reason);
    ``positions``: the analysed key frame's node positions."""
    from ..qca.report import profile_svg

    positions = np.asarray(positions, float).reshape(-1, 3)
    vessels, lesions = [], []
    for vd in (qca or {}).get("vessels", []):
        nodes = [int(i) for i in vd.get("nodes") or [] if 0 <= int(i) < len(positions)]
        if not nodes:
            continue
        if vd["name"] != "unlabelled":
            vessels.append({"name": vd["name"], "node": nodes[min(2, len(nodes) - 1)]})
        for les in [*vd["lesions"], *vd.get("unconfirmed_narrowings", [])]:
            # the lesion's MLD point as the vessel's nearest node: the key frames share their nodes
            point = np.asarray(les.get("point_mm", positions[nodes[0]]), float)
            k = int(np.argmin(np.linalg.norm(positions[nodes] - point, axis=1)))
            lesions.append({"id": les["id"], "vessel": vd["name"], "segment": les.get("segment") or "",
                            "ds": round(les["ds_percent"], 1), "length": round(les["length_mm"], 1),
                            "mld": round(les["mld_mm"], 2), "reference": round(les["reference_mm"], 2),
                            "position": round(les["position_mm"], 1), "node": nodes[k],
                            "unconfirmed": les.get("reason", ""),  # only unconfirmed narrowings carry a reason
                            "svg": profile_svg(vd, les["id"])})
    return vessels, lesions


def viewer_model(frames_model, overlays=(), qca: dict | None = None) -> dict:
    """The JSON the 3D viewer reads: per key frame the graph's nodes, radii and branches (which ones one run
    alone shows), its phase, its C-arm views and its overlay image; the diameter colour range; the QCA labels.

    ``frames_model``: per key frame ``{key, nodes, radius, edges}`` and optionally ``phase`` ({run: phase}),
    ``cameras`` ({run: :func:`camera_view`}) and ``one_view`` (branch indices, :mod:`stages.quality`)."""
    overlay_of = {str(k): compact_data_uri(p) for k, p in overlays}
    nonempty = [np.asarray(f["nodes"]) for f in frames_model if len(f["nodes"])]
    allpts = np.concatenate(nonempty) if nonempty else np.zeros((1, 3))
    extent = float(np.ptp(allpts, axis=0).max()) if len(allpts) > 1 else 100.0
    radii = np.concatenate([np.asarray(f["radius"], float) for f in frames_model if len(f["radius"])] or [np.ones(1)])
    lo, hi = (float(v) for v in np.percentile(2 * radii, [2, 98]))
    lo, hi = np.floor(lo * 10) / 10, max(np.ceil(hi * 10) / 10, np.floor(lo * 10) / 10 + 0.1)
    frames = []
    for f in frames_model:
        frames.append({"key": str(f["key"]), "nodes": np.round(np.asarray(f["nodes"], float), 2).tolist(),
                       "radius": np.round(np.asarray(f["radius"], float), 2).tolist(), "segments": _segments(f),
                       "one_view": [int(i) for i in f.get("one_view", [])], "phase": f.get("phase") or {},
                       "cameras": f.get("cameras") or {}, "overlay": overlay_of.get(str(f["key"]))})
    keys = [str(f["key"]) for f in frames_model]
    analysed = keys.index(str(qca["frame"])) if qca and str(qca.get("frame")) in keys else 0
    vessels, lesions = _qca_model(qca, frames_model[analysed]["nodes"] if frames_model else np.zeros((0, 3)))
    centre = 0.5 * (allpts.min(0) + allpts.max(0))  # the bounding box's centre: the whole tree fits the first view
    return {"centre": np.round(centre, 2).tolist(), "extent": max(extent, 10.0), "frames": frames,
            "diameter_mm": [float(lo), float(hi)], "vessels": vessels, "lesions": lesions,
            "qca_frame": (qca or {}).get("frame")}


def _quality_rows(quality: dict | None) -> str:
    rows = []
    for f in (quality or {}).get("frames", []):
        pcs = ", ".join(f"{p['length_mm']:.0f}" + (f" @ {p['distance_mm']:.0f}" if i else "")
                        for i, p in enumerate(f["pieces"])) or "none"
        out = ", ".join(f"{b['length_mm']:.0f} mm" for b in f["branches_outside_masks"]) or "none"
        cat = ", ".join(f"{b['length_mm']:.0f} mm" for b in f["catheter_like"]) or "none"
        rep = ", ".join(f"{v}: {'n/a' if d is None else f'{d:.2f}'}" for v, d in f["reprojection_mm"].items()) or "n/a"
        verdict = "passed" if f["passed"] else "; ".join(f["problems"])
        cells = [f["key"], f"{len(f['pieces'])}: {pcs}", out, cat, rep, verdict]
        rows.append("<tr>" + "".join(f"<td>{html.escape(str(c))}</td>" for c in cells) + "</tr>")
    return "".join(rows) or '<tr><td colspan="6">no checks</td></tr>'


def _script_text(text: str) -> str:
    # '</script' inside an embedded script would end its element early; '<\/' means the same to JavaScript
    return text.replace("</script", "<\\/script").replace("</SCRIPT", "<\\/SCRIPT")


def write_report(path, *, title: str, summary_rows, timings, frames_model, overlays, warnings,
                 quality: dict | None = None, sections: str = "", qca: dict | None = None) -> Path:
    """Write the report: the 3D viewer (module docstring) with each key frame's overlay beside it, quality
    checks, summary, timings, warnings. ``overlays``: (key, PNG path) pairs. ``sections``: further HTML (e.g.
    the QCA section of :func:`stages.qca.html_section`), placed after the summary. ``qca``: qca.json's content,
    for the vessel names and lesion markers in the viewer."""
    model = viewer_model(frames_model, overlays, qca)
    verdict = (quality or {}).get("verdict", "quality: not checked")
    fields = {
        "title": html.escape(title),
        "css": _text("report.css"),
        "three_version": THREE_VERSION,
        "three_js": _script_text(THREE_JS.read_text(encoding="utf-8")),
        "viewer_js": _script_text(_text("viewer.js")),
        "verdict": html.escape(verdict),
        "verdict_class": "pass" if (quality or {}).get("passed") else "fail",
        "summary_rows": "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(display_value(v))}</td></tr>"
                                for k, v in summary_rows),
        "quality_rows": _quality_rows(quality),
        "overlay_keys": html.escape(", ".join(f"{k} ({Path(p).name})" for k, p in overlays)) or "none",
        "timing_rows": "".join(f"<tr><td>{html.escape(n)}</td><td>{t:.2f} s</td></tr>" for n, t in timings),
        "sections": sections,
        "warnings": "".join(f"<li>{html.escape(w)}</li>" for w in warnings) or "<li>none</li>",
        # '</' escaped as JSON allows: no '</script' can end the model's element early
        "model_json": json.dumps(model, separators=(",", ":")).replace("</", "<\\/"),
    }
    page = Template(_text("template.html")).substitute(fields)
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return Path(path)
