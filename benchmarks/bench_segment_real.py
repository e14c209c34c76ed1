"""Benchmark: the U-Net and the Frangi baseline on the real phantom frames, without ground truth → docs/benchmarks/segment_real.md.

Per phantom run (its full-contrast frame, as the held-out check takes it): vessel area, connected pieces,
largest piece's share, centreline length, pieces at the field-of-view border and collimator corners,
catheter-like straight pieces and whether each mask holds them, and the two segmenters' agreement; then, for
a few run pairs (correspondence reconstruction, pair calibration, fitted held-out poses), what fraction of each
held-out view's centreline the reconstruction explains, with each segmenter's masks; the same frames with burned-in
text, a white collimator or a white detector border put in. The measurements live in
stages/segment/real_frames.py. ``--before JSON`` (an earlier run's ``--json``) adds a before → after table.

    OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_segment_real.py [--pairs 0-2,1-3] [--overlays DIR]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import load_average, write_section  # noqa: E402

PHANTOM = REPO.parent / "shared" / "data" / "phantom_xa"
METHODS = ("unet", "vesselness")
DEFAULT_PAIRS = "0-2,1-3,4-6,5-7"  # IM1+IM3, IM2+IM4 (within IM1–IM4), IM5+IM7, IM6+IM8
SUMMARY_KEYS = ("area_px", "area_pct_fov", "pieces", "largest_share", "centreline_px", "border_pieces", "corner_px")


def md_table(head: list[str], body: list[list]) -> str:
    """A Markdown table: the header cells, then one row of cells per item of ``body``."""
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    return "\n".join(lines + ["| " + " | ".join(str(c) for c in row) + " |" for row in body])


def run_table(rows: list[dict]) -> str:
    body = [[r["run"], m, f"{s['area_px']} ({s['area_pct_fov']:.1f} %)", s["pieces"], f"{s['largest_share']:.2f}",
             s["centreline_px"], f"{s['border_pieces']} ({s['border_px']})", s["corner_px"]]
            for r in rows for m, s in ((m, r["stats"][m]) for m in METHODS)]
    return md_table(["run", "segmenter", "area px (% of FOV)", "pieces", "largest piece share", "centreline px",
                     "pieces at the border (px)", "px in collimator corners"], body)


def catheter_table(rows: list[dict]) -> str:
    body = [[r["run"], len(c), f"{c[0]['length_px']:.0f} ({c[0]['rms_px']:.2f})", f"{c[0]['in_mask']['unet']:.0%}",
             f"{c[0]['in_mask']['vesselness']:.0%}"] if c else [r["run"], 0, "–", "–", "–"]
            for r, c in ((r, r["catheter"]) for r in rows)]
    return md_table(["run", "straight pieces ≥ 60 px (union of both masks)", "longest px (RMS px)",
                     "its centreline in the U-Net mask", "in the vesselness mask"], body)


def _three(a: list[dict]) -> list[str]:
    """Mean Dice (and its minimum) and the two mean centreline shares of a list of :func:`agreement` dicts."""
    return [f"{np.mean([v['dice'] for v in a]):.3f}, {min(v['dice'] for v in a):.3f}",
            f"{np.mean([v['a_in_b'] for v in a]):.3f}", f"{np.mean([v['b_in_a'] for v in a]):.3f}"]


def agreement_table(rows: list[dict]) -> str:
    body = [[r["run"], *_three([r["agreement"]])] for r in rows] + [["mean", *_three([r["agreement"] for r in rows])]]
    return md_table(["run", "Dice U-Net vs vesselness (min)", "U-Net centreline within 3 px of vesselness centreline",
                     "vesselness centreline within 3 px of U-Net centreline"], body)


def single_table(rows: list[dict]) -> str:
    return md_table(["segmenter", "Dice, last raw frame vs full-contrast frame (mean, min)",
                     "raw-frame centreline within 3 px of the full-contrast one",
                     "full-contrast centreline within 3 px of the raw-frame one"],
                    [[m, *_three([r["single_frame"][m] for r in rows])] for m in METHODS])


def stress_table(rows: list[dict]) -> str:
    body = []
    for name in rows[0]["stress"]:
        for m in METHODS:
            v = [r["stress"][name][m] for r in rows]
            body.append([name, m, sum(x["false_px"] for x in v),
                         f"{np.mean([x['dice_vs_clean'] for x in v]):.3f}, {min(x['dice_vs_clean'] for x in v):.3f}"])
    return md_table(["artefact put into every run's frame", "segmenter",
                     "vessel px within 12 px of it, not in the clean mask (sum over the runs)",
                     "Dice vs the clean frame's mask (mean, min)"], body)


def summary(rows: list[dict]) -> dict:
    """Per segmenter, the mean over runs of each per-run figure (and the explained fractions when measured)."""
    out = {m: {k: float(np.mean([r["stats"][m][k] for r in rows])) for k in SUMMARY_KEYS} for m in METHODS}
    for m in METHODS:
        out[m]["catheter_in_mask"] = float(np.mean([r["catheter"][0]["in_mask"][m] for r in rows if r["catheter"]]
                                                   or [np.nan]))
    for k in ("dice", "a_in_b", "b_in_a"):
        out.setdefault("agreement", {})[k] = float(np.mean([r["agreement"][k] for r in rows]))
    for m in METHODS:
        out[m]["single_frame_dice"] = float(np.mean([r["single_frame"][m]["dice"] for r in rows]))
        for name in rows[0]["stress"]:
            out[m][f"{name}: false px"] = float(sum(r["stress"][name][m]["false_px"] for r in rows))
            out[m][f"{name}: Dice vs clean"] = float(np.mean([r["stress"][name][m]["dice_vs_clean"] for r in rows]))
    return out


def heldout_table(explained: dict) -> tuple[str, dict]:
    out = ["| pair | segmenter | held-out views | coverage nominal pose | coverage fitted pose | distance mm fitted (per-row median) |",
           "|---|---|---|---|---|---|"]
    means = {}
    for m, rows in explained.items():
        for pair in dict.fromkeys(r["pair"] for r in rows):
            sel = {p: [r for r in rows if r["pair"] == pair and r["pose"] == p] for p in ("nominal", "fitted")}
            out.append(f"| {pair} | {m} | {len(sel['fitted'])} | {np.mean([r['coverage'] for r in sel['nominal']]):.3f} | "
                       f"{np.mean([r['coverage'] for r in sel['fitted']]):.3f} | "
                       f"{np.nanmean([r['distance_mm'] for r in sel['fitted']]):.2f} "
                       f"({np.nanmean([r['distance_median_mm'] for r in sel['fitted']]):.2f}) |")
        fit = [r for r in rows if r["pose"] == "fitted"]
        means[m] = {"coverage_fitted": float(np.mean([r["coverage"] for r in fit])),
                    "coverage_nominal": float(np.mean([r["coverage"] for r in rows if r["pose"] == "nominal"])),
                    "distance_fitted_mm": float(np.nanmean([r["distance_mm"] for r in fit]))}
        out.append(f"| all | {m} | {len(fit)} | {means[m]['coverage_nominal']:.3f} | {means[m]['coverage_fitted']:.3f} | "
                   f"{means[m]['distance_fitted_mm']:.2f} |")
    return "\n".join(out), means


def _num(v: float) -> str:
    return f"{v:.0f}" if abs(v) >= 100 else f"{v:.3f}"


def before_after(before: dict, after: dict) -> str:
    out = ["| segmenter | figure (mean over runs) | before | after |", "|---|---|---|---|"]
    for m in METHODS:
        for k in after.get(m, {}):
            if k in before.get(m, {}):
                out.append(f"| {m} | {k} | {_num(before[m][k])} | {_num(after[m][k])} |")
    for k in ("dice", "a_in_b", "b_in_a"):
        out.append(f"| both | agreement {k} | {before['agreement'][k]:.3f} | {after['agreement'][k]:.3f} |")
    return "\n".join(out)


def save_overlay(path: Path, r: dict) -> None:
    from PIL import Image

    from stages.segment.infer import overlay_rgb

    tiles = [overlay_rgb(r["img"], np.zeros_like(r["fov"])), *(overlay_rgb(r["img"], r["masks"][m], r["fov"]) for m in METHODS)]
    Image.fromarray(np.concatenate(tiles, 1)).save(path)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(PHANTOM), help="folder of the phantom's *.dcm runs")
    ap.add_argument("--pairs", default=DEFAULT_PAIRS,
                    help="run index pairs for the held-out part, e.g. 0-2,1-3 ('none' to skip, 'all' for all 28)")
    ap.add_argument("--overlays", default=None, help="write <run>.png overlays (frame | U-Net | vesselness) here")
    ap.add_argument("--json", default=str(REPO / "out" / "segment_real.json"), help="write the figures here")
    ap.add_argument("--before", default=None, help="an earlier run's --json: add a before → after table")
    ap.add_argument("--before-label", default="an earlier run of this script", help="what --before measured")
    args = ap.parse_args(argv)
    data = Path(args.data)
    files = sorted(data.glob("*.dcm"))
    if not files:
        print(f"{data}: phantom runs not found. Nothing measured.")
        return 0

    from stages.core.dicom_io import read_xa
    from stages.segment.real_frames import heldout_explained, measure_run

    t0, load = time.time(), load_average()
    rows = []
    for f in files:
        r = measure_run(read_xa(f).frames, METHODS)
        rows.append({"run": f.stem, **r})
        if args.overlays:
            Path(args.overlays).mkdir(parents=True, exist_ok=True)
            save_overlay(Path(args.overlays) / f"{f.stem}.png", r)
        print(f"{f.stem}: " + ", ".join(f"{m} {r['stats'][m]['area_px']} px / {r['stats'][m]['pieces']} pieces"
                                       for m in METHODS), flush=True)
    figures = summary(rows)
    held = "(not measured: `--pairs none`)"
    if args.pairs != "none":
        import itertools

        pairs = (list(itertools.combinations(range(len(files)), 2)) if args.pairs == "all" else
                 [tuple(int(v) for v in p.split("-")) for p in args.pairs.split(",")])
        held, means = heldout_table(heldout_explained(data, pairs, METHODS))
        for m in METHODS:
            figures[m].update(means[m])
    seconds = time.time() - t0
    Path(args.json).parent.mkdir(parents=True, exist_ok=True)
    Path(args.json).write_text(json.dumps(figures, indent=1))
    compare = ""
    if args.before:
        compare = (f"### Before → after\n\nBefore: {args.before_label}.\n\n") + before_after(json.loads(Path(args.before).read_text()), figures) + "\n\n"
    body = f"""{load} at start (shared machine). Wall time {seconds:.0f} s.

{len(files)} real runs of the static phantom (`{data}`), each reduced to its full-contrast frame (median of the
later half of the frames, `stages.evaluate.heldout.contrast_mask`); `unet` = `segment_frames(..., method="unet")`
(what `autocar reconstruct` uses), `vesselness` = the held-out check's Frangi + hysteresis. Border = within 8 px of
the open field's edge; corners = that border zone within 80 px of a corner of the open field's bounding box.
Measurements: `stages/segment/real_frames.py`.

{compare}### Per run

{run_table(rows)}

### Catheter-like straight pieces

A centreline branch between junctions of ≥ 60 px whose RMS distance from its axis is ≤ 1.2 px, found in the
union of both masks; the longest per run, and how much of its centreline each mask holds.

{catheter_table(rows)}

### Agreement between the segmenters

{agreement_table(rows)}

### Noise: one raw frame instead of the full-contrast median

{single_table(rows)}

### Clinical artefacts put into the phantom's frames

The phantom carries no burned-in text and its collimator is dark; each run's full-contrast frame is segmented again
with white text (three lines, PIL's default font ×2, at the frame's top value 255) or black text (0) in the field's
upper left, with the dark collimator region turned white, or with a 6-px white detector border
(`stages.segment.real_frames.stress_frames`).

{stress_table(rows)}

### What the reconstruction explains in the held-out views

Per pair: `--heldout-method correspondence` reconstruction from the pair's own masks (pair calibration on),
projected into the 6 other runs; coverage = fraction of the held-out view's centreline (the same segmenter's)
within 3 mm at the isocentre (`stages.evaluate.heldout.heldout_rows`).

{held}
"""
    cmd = "OMP_NUM_THREADS=1 .venv/bin/python benchmarks/bench_segment_real.py" + " ".join(["", *(argv or sys.argv[1:])])
    print(write_section("segment_real", "The segmenters on the real phantom frames (issue 35, item 6)", cmd, body).read_text())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
