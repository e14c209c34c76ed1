"""QCA outputs beside qca.json: qca.csv, the plots and the report.html section.

Writes (atomically, :func:`stages.core.artefacts.atomic_path`) in the reconstruction folder:

* ``qca.csv`` — one row per lesion: vessel, segment, %DS, MLD, reference, length, position, the
  across-key-frame %DS range, the two-view uncertainty and the best view;
* ``qca_profiles.png`` — diameter along every named vessel (and any unlabelled one with a lesion):
  measured, reference, the two views' widths, lesions shaded with their %DS;
* ``qca_views.png`` — per lesion (or, without lesions, per proximal segment of the main vessels) the
  foreshortening + overlap map over α −60…60° × β −45…45°, the two runs' angles marked (A, B) and
  the best view starred;
* ``qca_3d.png`` — the tree projected at the two runs' angles, coloured by lumen diameter, lesions
  circled;
* ``graphs_<k>.vtp`` rewritten (:func:`label_centrelines`) with every node's vessel name, segment and id,
  as point and cell string arrays ``VesselName``, ``VesselSegment``, ``VesselId``.

:func:`html_section` returns the report.html section (an HTML fragment string) for a folder's qca.json.
"""

from __future__ import annotations

import csv
import html
import json
from pathlib import Path
from string import Template

import numpy as np

from ..core.artefacts import atomic_path
from ..core.figures import save_png

__all__ = ["write_csv", "write_plots", "html_section", "node_labels", "label_centrelines", "profile_svg"]

CSV_FIELDS = ["vessel", "vessel_id", "segment", "ds_percent", "mld_mm", "reference_mm", "length_mm", "position_mm",
              "ostium_distance_mm", "ds_min_over_frames", "ds_max_over_frames", "uncertainty_mm",
              "best_alpha_deg", "best_beta_deg", "best_foreshortening_percent", "best_overlap_percent"]
MAIN = ("LM", "LAD", "LCX", "RCA", "D", "OM", "AM")
PNG_DPI = 72


def write_csv(path, doc: dict) -> Path:
    with atomic_path(path) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=CSV_FIELDS)
            w.writeheader()
            for vd in doc.get("vessels", []):
                for les in vd["lesions"]:
                    of = les.get("over_frames", {})
                    bv = les.get("best_view", {})
                    w.writerow({"vessel": vd["name"], "vessel_id": vd["id"], "segment": les.get("segment", ""),
                                "ds_percent": f"{les['ds_percent']:.1f}", "mld_mm": f"{les['mld_mm']:.2f}",
                                "reference_mm": f"{les['reference_mm']:.2f}", "length_mm": f"{les['length_mm']:.1f}",
                                "position_mm": f"{les['position_mm']:.1f}",
                                "ostium_distance_mm": f"{les.get('ostium_distance_mm', float('nan')):.1f}",
                                "ds_min_over_frames": of.get("ds_min", ""), "ds_max_over_frames": of.get("ds_max", ""),
                                "uncertainty_mm": les.get("uncertainty_mm", ""),
                                "best_alpha_deg": bv.get("alpha_deg", ""), "best_beta_deg": bv.get("beta_deg", ""),
                                "best_foreshortening_percent": round(bv["foreshortening_percent"], 1) if bv else "",
                                "best_overlap_percent": round(bv["overlap_percent"], 1) if bv else ""})
    return Path(path)


def write_plots(folder, doc: dict, qca, maps: dict) -> list[str]:
    """The three PNGs (module docstring); returns their file names."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import LineCollection

    folder = Path(folder)
    written = []
    vessels = [vd for vd in doc["vessels"] if vd["name"] in MAIN or vd["lesions"]]
    vessels.sort(key=lambda vd: (MAIN.index(vd["name"]) if vd["name"] in MAIN else len(MAIN), vd["id"]))
    vessels = vessels[:9]
    if vessels:
        n = len(vessels)
        fig, axes = plt.subplots(n, 1, figsize=(8, 1.9 * n + 0.4), squeeze=False)
        for ax, vd in zip(axes[:, 0], vessels):
            p = vd["profile"]
            ax.plot(p["s_mm"], p["diameter_mm"], color="k", lw=1.4, label="diameter")
            ax.plot(p["s_mm"], p["reference_mm"], color="tab:blue", ls="--", lw=1.0, label="reference")
            for view, col in (("a", "tab:orange"), ("b", "tab:green")):
                if p.get(f"view_{view}_mm"):
                    ax.plot(p["s_mm"], p[f"view_{view}_mm"], color=col, lw=0.6, alpha=0.7, label=f"view {view.upper()}")
            for les in vd["lesions"]:
                ax.axvspan(les["start_mm"], les["end_mm"], color="tab:red", alpha=0.15)
                ax.annotate(f"{les['ds_percent']:.0f} %", (les["position_mm"], les["mld_mm"]), color="tab:red",
                            fontsize=8, ha="center", va="top")
            ax.set_ylabel("Ø mm")
            ax.set_title(f"{vd['name']} ({vd['id']}, {vd['length_mm']:.0f} mm)", fontsize=9, loc="left")
            ax.set_ylim(bottom=0)
        axes[-1, 0].set_xlabel("distance from the vessel origin (mm)")
        axes[0, 0].legend(fontsize=7, ncol=5, loc="upper right")
        fig.subplots_adjust(left=0.08, right=0.98, top=1 - 0.35 / fig.get_figheight(), bottom=0.5 / fig.get_figheight(),
                            hspace=0.55)
        save_png(fig, folder / "qca_profiles.png", dpi=PNG_DPI)
        written.append("qca_profiles.png")

    panels = [(les["id"], f"{vd['name']} {les['ds_percent']:.0f} % at {les['position_mm']:.0f} mm")
              for vd in doc["vessels"] for les in vd["lesions"] if les["id"] in maps][:6]
    if not panels:
        panels = [(f"{vd['id']}.proximal", f"proximal {vd['name']}") for vd in doc["vessels"]
                  if f"{vd['id']}.proximal" in maps and vd["name"] in ("LAD", "LCX", "RCA", "LM")][:4]
    if panels:
        cols = min(len(panels), 3)
        rows = (len(panels) + cols - 1) // cols
        fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols + 0.8, 3.2 * rows), squeeze=False)
        for ax in axes.ravel():
            ax.axis("off")
        for ax, (key, title) in zip(axes.ravel(), panels):
            m = maps[key]
            ax.axis("on")
            score = m["foreshortening"] + m["overlap"]
            a, b = m["alphas"], m["betas"]
            im = ax.imshow(np.minimum(score, 100.0).T, origin="lower", extent=[a[0], a[-1], b[0], b[-1]],
                           aspect="auto", cmap="viridis_r", vmin=0, vmax=100)
            ax.contour(a, b, m["overlap"].T, levels=[1.0], colors="w", linewidths=0.6)
            for view, ang in (doc.get("run_angles") or {}).items():
                ax.plot(ang["alpha_deg"], ang["beta_deg"], "o", mfc="none", mec="r", ms=8)
                ax.annotate(view.upper(), (ang["alpha_deg"], ang["beta_deg"]), color="r", xytext=(5, 5),
                            textcoords="offset points", fontsize=9)
            best = m["best"]
            ax.plot(best["alpha_deg"], best["beta_deg"], "*", color="gold", mec="k", ms=13)
            ax.set_title(title, fontsize=9)
            ax.set_xlabel("α (RAO − / LAO +) °", fontsize=8)
            ax.set_ylabel("β (CAU − / CRA +) °", fontsize=8)
            ax.tick_params(labelsize=7)
        fig.subplots_adjust(left=0.07, right=0.88, top=0.92, bottom=0.14 if rows == 1 else 0.08, wspace=0.3, hspace=0.45)
        cax = fig.add_axes([0.91, 0.15, 0.015, 0.7])
        fig.colorbar(im, cax=cax, label="foreshortening + overlap % (capped at 100)")
        save_png(fig, folder / "qca_views.png", dpi=PNG_DPI)
        written.append("qca_views.png")

    tree = qca.tree
    from .views import view_directions

    angles = [(view.upper(), ang["alpha_deg"], ang["beta_deg"]) for view, ang in (doc.get("run_angles") or {}).items()]
    if not angles:
        angles = [("AP", 0.0, 0.0), ("LAO 90", 90.0, 0.0)]
    fig, axes = plt.subplots(1, len(angles), figsize=(4.6 * len(angles), 4.6), squeeze=False)
    segs, dia = [], []
    for v in qca.reported():
        segs.append(np.stack([v.nodes[:-1], v.nodes[1:]], 1))
    e = np.concatenate(segs) if segs else np.zeros((0, 2), int)
    dia = 2 * 0.5 * (tree.radius[e[:, 0]] + tree.radius[e[:, 1]]) if len(e) else np.zeros(0)
    for ax, (name, a, b) in zip(axes[0], angles):
        _, c, r = view_directions([a], [b])
        P = np.stack([tree.nodes @ c[0, 0], -(tree.nodes @ r[0, 0])], 1)  # screen right, screen up
        lc = LineCollection(P[e], array=dia, cmap="plasma", linewidths=1.5 + dia)
        ax.add_collection(lc)
        for vd in doc["vessels"]:
            for les in vd["lesions"]:
                q = np.asarray(les["point_mm"])
                ax.plot(q @ c[0, 0], -(q @ r[0, 0]), "o", mfc="none", mec="tab:red", ms=14, mew=1.5)
        if len(P):
            ax.set_xlim(P[:, 0].min() - 5, P[:, 0].max() + 5)
            ax.set_ylim(P[:, 1].min() - 5, P[:, 1].max() + 5)
        ax.set_aspect("equal")
        ax.set_title(f"view {name} (α {a:.0f}°, β {b:.0f}°)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
        fig.colorbar(lc, ax=ax, label="lumen Ø mm", shrink=0.8)
    fig.subplots_adjust(left=0.02, right=0.98, top=0.92, bottom=0.03, wspace=0.1)
    save_png(fig, folder / "qca_3d.png", dpi=PNG_DPI)
    written.append("qca_3d.png")
    return written


def html_section(source, folder=None) -> str:
    """The report.html section for a QCA result: ``source`` is a reconstruction folder (reads its
    qca.json) or the qca.json content itself. The figures are embedded (``data:`` URIs, read from ``folder``,
    by default the folder of qca.json or the one it names), so the section needs no file beside it."""
    from ..core.embed import data_uri  # plots are line art: PNG keeps them sharp

    if isinstance(source, (str, Path)):
        path = Path(source)
        path = path / "qca.json" if path.is_dir() else path
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            return f"<h2>Quantitative coronary analysis</h2><p>No readable {html.escape(str(path))}.</p>"
        folder = folder or path.parent
    else:
        doc = source
        folder = folder or doc.get("reconstruction")
    esc = html.escape
    parts = ["<h2>Quantitative coronary analysis (3D QCA)</h2>"]
    if doc.get("message"):
        parts.append(f"<p><b>{esc(doc['message'])}</b></p>")
    if doc.get("frame") is not None:
        parts.append(f"<p>Key frame {esc(str(doc['frame']))} ({esc(str(doc.get('frame_reason', '')))}); "
                     f"tree side: {esc(str(doc.get('side')))}.</p>")
    lesion_rows = []
    for vd in doc.get("vessels", []):
        for les in vd["lesions"]:
            of = les.get("over_frames", {})
            bv = les.get("best_view")
            best = (f"{'LAO' if bv['alpha_deg'] >= 0 else 'RAO'} {abs(bv['alpha_deg']):.0f}° "
                    f"{'CRA' if bv['beta_deg'] >= 0 else 'CAU'} {abs(bv['beta_deg']):.0f}° "
                    f"({bv['foreshortening_percent']:.0f} % / {bv['overlap_percent']:.0f} %)") if bv else ""
            rng = f"{of['ds_min']:.0f}–{of['ds_max']:.0f}" if of else ""
            unc = f"± {les['uncertainty_mm']:.2f}" if "uncertainty_mm" in les else ""
            lesion_rows.append(
                f"<tr><td>{esc(vd['name'])}</td><td>{esc(les.get('segment') or '')}</td>"
                f"<td><b>{les['ds_percent']:.0f}</b></td><td>{les['mld_mm']:.2f} {unc}</td>"
                f"<td>{les['reference_mm']:.2f}</td><td>{les['length_mm']:.1f}</td><td>{les['position_mm']:.1f}</td>"
                f"<td>{rng}</td><td>{esc(best)}</td></tr>")
    if lesion_rows:
        parts.append("<table><tr><th>vessel</th><th>segment</th><th>%DS</th><th>MLD mm</th><th>reference mm</th>"
                     "<th>length mm</th><th>from origin mm</th><th>%DS over key frames</th>"
                     "<th>best view (foreshortening / overlap)</th></tr>" + "".join(lesion_rows) + "</table>")
    elif doc.get("vessels"):
        parts.append(f"<p>No lesion of {doc.get('parameters', {}).get('min_ds', 20):.0f} % diameter stenosis or more.</p>")
    unconfirmed = [(vd, n) for vd in doc.get("vessels", []) for n in vd.get("unconfirmed_narrowings", [])]
    if unconfirmed:
        items = "; ".join(f"{esc(vd['name'])} {n['ds_percent']:.0f} % at {n['position_mm']:.0f} mm "
                          f"({esc(n.get('reason', ''))})" for vd, n in unconfirmed)
        parts.append(f"<p>Narrowings of the model that the views do not confirm, not reported as lesions: {items}.</p>")
    vrows = "".join(f"<tr><td>{esc(vd['name'])}</td><td>{vd['length_mm']:.0f}</td><td>{vd['proximal_diameter_mm']:.2f}</td>"
                    f"<td>{len(vd['lesions'])}</td></tr>" for vd in doc.get("vessels", []) if vd["name"] != "unlabelled")
    if vrows:
        parts.append("<table><tr><th>vessel</th><th>length mm</th><th>proximal Ø mm</th><th>lesions</th></tr>"
                     + vrows + "</table>")
    if sr := (doc.get("sr") or {}):
        parts.append("<p>" + ("DICOM Structured Report of these figures: qca_sr.dcm." if sr.get("file")
                              else esc(sr.get("reason", ""))) + "</p>")
    for png, alt in (("qca_profiles.png", "diameter profiles"), ("qca_views.png", "view maps"), ("qca_3d.png", "3D by diameter")):
        if png in (doc.get("plots") or []) and folder is not None and (Path(folder) / png).is_file():
            parts.append(f'<figure><img src="{data_uri(Path(folder) / png)}" alt="{alt}">'
                         f"<figcaption>{alt} ({png})</figcaption></figure>")
    return "\n".join(parts)


def node_labels(doc: dict, nodes) -> dict[str, list[str]]:
    """Per graph node the vessel name, segment ("proximal LAD", …) and vessel id QCA gave it ("" where none).

    ``nodes``: the analysed key frame's node positions (segments are thirds of a vessel's length, as for the
    lesions). A junction node belongs to the parent vessel: a branch's first node is its parent's."""
    n = len(nodes)
    out = {"VesselName": [""] * n, "VesselSegment": [""] * n, "VesselId": [""] * n}
    pts = np.asarray(nodes, float)
    for first_pass in (True, False):
        for vd in doc.get("vessels", []):
            idx = [int(i) for i in vd.get("nodes") or []]
            if not idx:
                continue
            s = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(pts[idx], axis=0), axis=1))]
            third = np.minimum((3 * s / max(s[-1], 1e-9)).astype(int), 2)
            for j, i in enumerate(idx):
                if first_pass and j == 0 and vd.get("parent") is not None:
                    continue  # the junction on the parent: named by the parent
                if out["VesselName"][i]:
                    continue  # named already (parents come first in qca.json; a node gets one vessel)
                out["VesselName"][i] = vd["name"]
                out["VesselId"][i] = vd["id"]
                out["VesselSegment"][i] = "" if vd["name"] == "unlabelled" else \
                    f"{('proximal', 'mid', 'distal')[third[j]]} {vd['name']}"
    return out


def label_centrelines(recon, tracked, doc: dict, frame_index: int) -> list[str]:
    """Rewrite each key frame's ``graphs_<key>.vtp`` in ``recon`` with the vessel labels of :func:`node_labels`
    (the tracked graphs share their nodes, so the analysed frame's names hold for every key frame). Returns
    the file names rewritten."""
    from ..core.export import write_vtp

    labels = node_labels(doc, tracked.graphs[frame_index].nodes)
    written = []
    for key, graph in zip(tracked.keys, tracked.graphs):
        path = Path(recon) / f"graphs_{key}.vtp"
        if path.exists() and len(graph) == len(labels["VesselName"]):
            write_vtp(path, graph, node_labels=labels)
            written.append(path.name)
    return written


_SVG = Template("""<svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 $w $h" width="$w" height="$h" class="profile" \
role="img" aria-label="$label"><rect width="$w" height="$h" fill="#fff"/>$spans\
<polyline fill="none" stroke="#1f77b4" stroke-dasharray="5 3" stroke-width="1.2" points="$ref"/>\
<polyline fill="none" stroke="#000" stroke-width="1.6" points="$dia"/>$views$marks\
<line x1="$x0" y1="$y0" x2="$x1" y2="$y0" stroke="#555"/><line x1="$x0" y1="$y0" x2="$x0" y2="$ytop" stroke="#555"/>\
$ticks<text x="$xmid" y="${xl}" font-size="11" text-anchor="middle">distance from the vessel origin (mm)</text>\
<text x="12" y="$ymid" font-size="11" text-anchor="middle" transform="rotate(-90 12 $ymid)">lumen Ø (mm)</text>\
<text x="$x0" y="14" font-size="12" font-weight="bold">$title</text>\
<text x="$x1" y="14" font-size="10" text-anchor="end">— diameter  - - reference$view_key</text></svg>""")


def profile_svg(vd: dict, lesion_id: str | None = None, width: int = 520, height: int = 200) -> str:
    """A vessel's diameter profile (measured and reference, and each view's width where measured) as an inline SVG
    figure; its lesions shaded with their %DS, ``lesion_id`` in a stronger colour (grey when it is one of the
    vessel's unconfirmed narrowings). Drawn from qca.json alone (no plotting library)."""
    p = vd["profile"]
    s = np.asarray(p["s_mm"], float)
    d = np.asarray(p["diameter_mm"], float)
    r = np.asarray(p["reference_mm"], float)
    if len(s) < 2:
        return ""
    x0, x1, ytop, y0 = 44.0, width - 10.0, 24.0, height - 34.0
    smax = max(float(s[-1]), 1e-6)
    dmax = max(float(np.nanmax(np.r_[d, r])), 1.0) * 1.1

    def X(v):
        return x0 + (x1 - x0) * np.asarray(v, float) / smax

    def Y(v):
        return y0 - (y0 - ytop) * np.asarray(v, float) / dmax

    def pts(v):
        return " ".join(f"{a:.1f},{b:.1f}" for a, b in zip(X(s), Y(v)) if np.isfinite(b))

    spans, marks = [], []
    shown = [(les, "#d62728", "#b00") for les in vd.get("lesions", [])]
    shown += [(n, "#777", "#444") for n in vd.get("unconfirmed_narrowings", []) if n["id"] == lesion_id]
    for les, fill, ink in shown:
        strong = les["id"] == lesion_id
        xa, xb = X(les["start_mm"]), X(les["end_mm"])
        spans.append(f'<rect x="{xa:.1f}" y="{ytop:.1f}" width="{max(xb - xa, 1.0):.1f}" height="{y0 - ytop:.1f}" '
                     f'fill="{fill}" fill-opacity="{0.35 if strong else 0.12}"/>')
        marks.append(f'<text x="{X(les["position_mm"]):.1f}" y="{Y(les["mld_mm"]) + 14:.1f}" font-size="11" '
                     f'fill="{ink}" text-anchor="middle">{les["ds_percent"]:.0f} %</text>')
    views = []
    for key, colour in (("view_a_mm", "#ff7f0e"), ("view_b_mm", "#2ca02c")):
        if p.get(key) is not None:  # clipped to the plot: an overlap can make one view's width read very wide
            views.append(f'<polyline fill="none" stroke="{colour}" stroke-width="0.8" stroke-opacity="0.8" '
                         f'points="{pts(np.minimum(np.asarray(p[key], float), dmax))}"/>')
    step = 10.0 if smax <= 120 else 20.0
    ticks = [f'<text x="{X(t):.1f}" y="{y0 + 13:.1f}" font-size="10" text-anchor="middle">{t:.0f}</text>'
             for t in np.arange(0.0, smax + 1e-6, step)]
    ticks += [f'<text x="{x0 - 4:.1f}" y="{Y(t) + 3:.1f}" font-size="10" text-anchor="end">{t:.0f}</text>'
              for t in np.arange(0.0, dmax, 1.0)]
    title = f"{vd['name']} ({vd['id']}, {vd['length_mm']:.0f} mm)"
    return _SVG.substitute(w=width, h=height, label=html.escape(f"diameter profile of {title}"), spans="".join(spans),
                           ref=pts(r), dia=pts(d), marks="".join(marks), x0=x0, x1=x1, y0=y0, ytop=ytop,
                           views="".join(views), view_key=" · thin: view A (orange), B (green)" if views else "",
                           ticks="".join(ticks), xmid=0.5 * (x0 + x1), xl=height - 6, ymid=0.5 * (ytop + y0),
                           title=html.escape(title))
