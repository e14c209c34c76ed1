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
  circled.

:func:`html_section` returns the report.html section (an HTML fragment string) for a folder's qca.json.
"""

from __future__ import annotations

import csv
import html
import json
from pathlib import Path

import numpy as np

from ..core.artefacts import atomic_path

__all__ = ["write_csv", "write_plots", "html_section"]

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


def _save(fig, path):
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=PNG_DPI)


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
        _save(fig, folder / "qca_profiles.png")
        plt.close(fig)
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
        _save(fig, folder / "qca_views.png")
        plt.close(fig)
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
    _save(fig, folder / "qca_3d.png")
    plt.close(fig)
    written.append("qca_3d.png")
    return written


def html_section(source) -> str:
    """The report.html section for a QCA result: ``source`` is a reconstruction folder (reads its
    qca.json) or the qca.json content itself. Image paths are relative (the report sits beside them)."""
    if isinstance(source, (str, Path)):
        path = Path(source)
        path = path / "qca.json" if path.is_dir() else path
        try:
            doc = json.loads(path.read_text())
        except (OSError, ValueError):
            return f"<h2>Quantitative coronary analysis</h2><p>No readable {html.escape(str(path))}.</p>"
    else:
        doc = source
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
    vrows = "".join(f"<tr><td>{esc(vd['name'])}</td><td>{vd['length_mm']:.0f}</td><td>{vd['proximal_diameter_mm']:.2f}</td>"
                    f"<td>{len(vd['lesions'])}</td></tr>" for vd in doc.get("vessels", []) if vd["name"] != "unlabelled")
    if vrows:
        parts.append("<table><tr><th>vessel</th><th>length mm</th><th>proximal Ø mm</th><th>lesions</th></tr>"
                     + vrows + "</table>")
    for png, alt in (("qca_profiles.png", "diameter profiles"), ("qca_views.png", "view maps"), ("qca_3d.png", "3D by diameter")):
        if png in (doc.get("plots") or []):
            parts.append(f'<figure><img src="{png}" alt="{alt}"><figcaption>{alt}</figcaption></figure>')
    return "\n".join(parts)
