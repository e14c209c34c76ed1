"""The reconstruction's one-page HTML report, self-contained: its CSS, script and overlay images are
embedded when it is written (``template.html`` with ``report.css`` and ``viewer.js`` beside it, filled by
:class:`string.Template`; PNGs as ``data:`` URIs), so the file can be mailed or archived on its own.
Input runs are shown by file name, not by the path on the machine that ran it.

Reads: the template files here and the overlay PNGs. Writes: ``report.html`` (atomic).
"""

from __future__ import annotations

import base64
import html
import json
from pathlib import Path
from string import Template

import numpy as np

from ..core.artefacts import atomic_path

_HERE = Path(__file__).parent


def _text(name: str) -> str:
    return (_HERE / name).read_text(encoding="utf-8")


def data_uri(png_path) -> str:
    """A PNG file as a ``data:image/png;base64,...`` URI."""
    return "data:image/png;base64," + base64.b64encode(Path(png_path).read_bytes()).decode("ascii")


def display_value(value) -> str:
    """Paths shown by file name only (the report may travel to another machine)."""
    if isinstance(value, Path):
        return value.name
    return str(value)


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


def write_report(path, *, title: str, summary_rows, timings, frames_model, overlays, warnings,
                 quality: dict | None = None, sections: str = "") -> Path:
    """Write the report: 3D model (canvas, drag to rotate, slider over key frames), quality checks,
    overlays (embedded), summary, timings, warnings. ``overlays``: (key, PNG path) pairs. ``sections``: further
    HTML (e.g. the QCA section of :func:`stages.qca.html_section`), placed after the summary."""
    nonempty = [np.asarray(f["nodes"]) for f in frames_model if len(f["nodes"])]
    allpts = np.concatenate(nonempty) if nonempty else np.zeros((1, 3))
    extent = float(np.ptp(allpts, axis=0).max()) if len(allpts) > 1 else 100.0
    model = {"centre": allpts.mean(0).tolist(), "extent": max(extent, 10.0), "frames": frames_model}
    verdict = (quality or {}).get("verdict", "quality: not checked")
    fields = {
        "title": html.escape(title),
        "css": _text("report.css"),
        "viewer_js": _text("viewer.js"),
        "verdict": html.escape(verdict),
        "verdict_class": "pass" if (quality or {}).get("passed") else "fail",
        "summary_rows": "".join(f"<tr><td>{html.escape(str(k))}</td><td>{html.escape(display_value(v))}</td></tr>"
                                for k, v in summary_rows),
        "quality_rows": _quality_rows(quality),
        "overlays": "".join(f'<figure><img src="{data_uri(p)}" alt="overlay {html.escape(k)}"><figcaption>key frame '
                            f"{html.escape(k)} ({html.escape(Path(p).name)})</figcaption></figure>" for k, p in overlays),
        "timing_rows": "".join(f"<tr><td>{html.escape(n)}</td><td>{t:.2f} s</td></tr>" for n, t in timings),
        "sections": sections,
        "warnings": "".join(f"<li>{html.escape(w)}</li>" for w in warnings) or "<li>none</li>",
        # '</' inside the JSON would end the script element early
        "model_json": json.dumps(model).replace("</", "<\\/"),
    }
    page = Template(_text("template.html")).substitute(fields)
    with atomic_path(path) as tmp:
        tmp.write_text(page, encoding="utf-8")
    return Path(path)
