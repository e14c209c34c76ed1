"""The cohort outputs of a batch: ``studies.csv``, ``vessels.csv``, ``lesions.csv`` and ``index.html``.

Rewritten whole, each atomically (temporary sibling, then rename), every time a study finishes: a reader
never sees half a file, and a long batch is useful before it ends. Rows follow the plan's order, one per
study pair, so a retried or resumed study replaces its row instead of adding one.

Reads: nothing. Writes: the four files in the batch's output folder.
"""

from __future__ import annotations

import csv
import html
import io
from collections import Counter
from pathlib import Path
from urllib.parse import quote

from ..core.artefacts import atomic_path

STUDY_COLUMNS = ["study", "pair", "run_a", "run_b", "more_runs", "status", "error", "seconds", "worker", "worker_peak_rss_mb",
                 "key_frames", "quality", "verdict", "pieces", "reprojection_a_mm", "reprojection_b_mm", "lesion_count", "pairing",
                 "separation_deg", "total_seconds_recorded", "folder", "report"]
VESSEL_COLUMNS = ["study", "pair", "key_frame", "vessel", "length_mm", "mean_diameter_mm", "min_diameter_mm"]
LESION_COLUMNS = ["study", "pair", "vessel", "segment", "ds_percent", "mld_mm", "reference_mm", "length_mm",
                  "position_mm", "best_view", "best_alpha_deg", "best_beta_deg"]
FILES = ("studies.csv", "vessels.csv", "lesions.csv", "index.html")


def write_cohort(out, results: list[dict], extra_columns=(), title: str = "AutoCAR cohort") -> None:
    """``results``: the finished studies' results (:func:`stages.batch.study.study_result`), in plan order."""
    out = Path(out)
    studies = [r["study"] for r in results]
    _write_csv(out / "studies.csv", STUDY_COLUMNS + [c for c in extra_columns if c not in STUDY_COLUMNS], studies)
    _write_csv(out / "vessels.csv", VESSEL_COLUMNS, [v for r in results for v in r["vessels"]])
    _write_csv(out / "lesions.csv", LESION_COLUMNS, [les for r in results for les in r["lesions"]])
    with atomic_path(out / "index.html") as tmp:
        tmp.write_text(index_html(out, studies, title), encoding="utf-8")


def _write_csv(path: Path, columns: list[str], rows: list[dict]) -> None:
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=columns, extrasaction="ignore", lineterminator="\n")
    w.writeheader()
    w.writerows(rows)
    with atomic_path(path) as tmp:
        tmp.write_text(buf.getvalue(), encoding="utf-8")


_SHOWN = ["study", "pair", "status", "seconds", "key_frames", "quality", "pieces", "reprojection_a_mm",
          "reprojection_b_mm", "lesion_count", "separation_deg", "error"]
_STYLE = """body{font:14px/1.4 system-ui,sans-serif;margin:2em;color:#222}h1{font-size:1.4em}
table{border-collapse:collapse}th,td{border:1px solid #ccc;padding:3px 8px;text-align:left;vertical-align:top}
th{background:#f0f0f0;cursor:pointer;user-select:none}th:after{content:" \\2195";color:#999}
.ok{color:#176f2c}.failed{color:#b00020;font-weight:bold}.skipped{color:#555}.counts span{margin-right:1.5em}
td.num{text-align:right}"""
# sort a column on a header click (numbers as numbers, then text); a second click reverses
_SCRIPT = """document.querySelectorAll('table.sortable th').forEach(function(th,i){th.addEventListener('click',function(){
var tb=th.closest('table').tBodies[0],rows=Array.from(tb.rows),up=th.dataset.dir!=='asc';th.dataset.dir=up?'asc':'desc';
rows.sort(function(a,b){var x=a.cells[i].textContent,y=b.cells[i].textContent,p=parseFloat(x),q=parseFloat(y);
var c=(!isNaN(p)&&!isNaN(q))?p-q:x.localeCompare(y);return up?c:-c;});rows.forEach(function(r){tb.appendChild(r);});});});"""


def index_html(out: Path, studies: list[dict], title: str) -> str:
    """One self-contained page: the counts, the failures with their errors, and a sortable table of every
    study linking its report.html (relative links, so the folder can be moved or shared as a whole)."""
    esc = html.escape
    counts = Counter(s["status"] for s in studies)
    parts = [f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(title)}</title>"
             f"<style>{_STYLE}</style></head><body><h1>{esc(title)}</h1>",
             "<p class='counts'>" + "".join(f"<span class='{k}'>{k}: {counts.get(k, 0)}</span>"
                                            for k in ("ok", "skipped", "failed"))
             + f"<span>study pairs listed: {len(studies)}</span></p>"]
    failed = [s for s in studies if s["status"] == "failed"]
    if failed:
        parts.append("<h2>Failures</h2><ul>" + "".join(
            f"<li><b>{esc(_label(s))}</b>: {esc(str(s['error']))}</li>" for s in failed) + "</ul>")
    parts.append("<h2>Studies</h2><p>Click a column to sort. A study's name opens its report.</p>"
                 "<table class='sortable'><thead><tr>" + "".join(f"<th>{esc(c)}</th>" for c in _SHOWN)
                 + "</tr></thead><tbody>")
    for s in studies:
        cells = []
        for c in _SHOWN:
            value = s.get(c, "")
            text = esc("" if value is None else str(value))
            if c == "study" and s["status"] != "failed" and s.get("folder"):
                try:
                    rel = Path(s["folder"]).resolve().relative_to(Path(out).resolve())
                    text = f"<a href='{quote(rel.as_posix())}/report.html'>{text}</a>"
                except ValueError:  # a study folder outside OUT (not written by batch): no link
                    pass
            cls = s["status"] if c == "status" else "num" if isinstance(value, (int, float)) else ""
            cells.append(f"<td class='{cls}'>{text}</td>" if cls else f"<td>{text}</td>")
        parts.append("<tr>" + "".join(cells) + "</tr>")
    parts.append("</tbody></table>")
    parts.append(f"<script>{_SCRIPT}</script></body></html>")
    return "\n".join(parts)


def _label(s: dict) -> str:
    return f"{s['study']}/{s['pair']}" if s.get("pair") else str(s["study"])
