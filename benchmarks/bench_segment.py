"""Benchmark: accuracy and speed of `autocar segment` and `autocar keyframe` → docs/benchmarks/segment.md.

Also writes the figures docs/img/seg_*.png.

    .venv/bin/python benchmarks/bench_segment.py [--quick] [--keyframes-only]

``--keyframes-only`` reruns part 4 alone and replaces that section of the existing document (the
other sections keep their own date; the section says when it was rerun).

1. Held-out simulated frames (data/seg/test: unseen trees, `python -m stages.segment.data test`):
   Dice / clDice of the network and the two classical baselines (baselines on every 3rd frame: slow).
2. Speed of the network at 512² (2 threads; batch 1 and 4), min and median of repeats.
3. Real phantom runs (../shared/data/phantom_xa): held-out-view check (stages.heldout) with masks from the
   network, vesselness and thresholding, all on the same full-contrast frame per run; overlay images.
4. Key frames on the data-re set (data/re, else data/seg/re): pair phase error (truth) and true filling of
   the chosen frames, with the DICOM ECG and with the ECG removed (phase from images).
"""

from __future__ import annotations

import datetime
import itertools
import os
import platform
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
PHANTOM = REPO.parent / "shared" / "data" / "phantom_xa"
DOC = REPO / "docs" / "benchmarks" / "segment.md"
IMG = REPO / "docs" / "img"


def machine() -> str:
    """Shared machine line (benchmarks/machine.py) plus the load average: the box is shared."""
    from machine import machine_description

    return f"{machine_description()}, load average {os.getloadavg()[0]:.1f} at start (shared machine)"


def save_panels(name: str, panels, shape, figsize, fontsize: int = 9) -> None:
    """docs/img/<name>: (image, title) panels in a ``shape`` grid (a 2D image in grey), axes off, 60 dpi."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(*shape, figsize=figsize)
    for a, (img, title) in zip(ax.flat, panels):
        a.imshow(img, cmap="gray" if np.ndim(img) == 2 else None)
        a.set_title(title, fontsize=fontsize)
    for a in ax.flat:
        a.axis("off")
    fig.tight_layout()
    fig.savefig(IMG / name, dpi=60)
    plt.close(fig)


def sim_scores(quick: bool) -> tuple[str, dict]:
    from stages.segment import segment_frames
    from stages.segment.data import load_split
    from stages.segment.scores import cldice_2d, dice_2d

    frames, masks, _ = load_split(REPO / "data" / "seg" / "test")
    if quick:
        frames, masks = frames[::6], masks[::6]
    # frames come in groups of 3 per view (scene): a frame is "filled" when its visible vessel area is
    # ≥ 80 % of the best-filled frame of its view (the others catch the bolus arriving/washing out)
    area = masks.reshape(len(masks), -1).sum(1).astype(float)
    group = np.arange(len(masks)) // 3 if not quick else np.arange(len(masks))
    best = np.array([area[group == g].max() for g in group])
    filled = area >= 0.8 * np.maximum(best, 1)
    res = {}
    for method, step in (("unet", 1), ("vesselness", 3), ("threshold", 3)):
        d, c, fp, fl, pool = [], [], [], [], np.zeros(3)
        for f, m, isf in zip(frames[::step], masks[::step], filled[::step]):
            _, p = segment_frames(f, method=method)
            if m.sum() == 0:
                fp.append(int(p.sum()))
                continue
            d.append(dice_2d(p, m))
            c.append(cldice_2d(p, m))
            fl.append(isf)
            pool += [(p.astype(bool) & m.astype(bool)).sum(), p.astype(bool).sum(), m.astype(bool).sum()]
        res[method] = {"n": len(d), "dice": np.array(d), "cldice": np.array(c), "empty_fp": fp,
                       "filled": np.array(fl, bool), "pooled": 2 * pool[0] / max(pool[1] + pool[2], 1)}
    lines = ["| method | frames | Dice mean ± sd (median) | clDice mean ± sd (median) | pooled Dice | "
             "filled frames: n, Dice mean, clDice mean | partially filled frames: n, Dice mean, clDice mean | "
             "no-contrast frames: false-positive px (mean) |",
             "|---|---|---|---|---|---|---|---|"]
    for m, r in res.items():
        f = r["filled"]
        lines.append(f"| {m} | {r['n']} | {r['dice'].mean():.3f} ± {r['dice'].std():.3f} ({np.median(r['dice']):.3f}) | "
                     f"{r['cldice'].mean():.3f} ± {r['cldice'].std():.3f} ({np.median(r['cldice']):.3f}) | {r['pooled']:.3f} | "
                     f"{f.sum()}, {r['dice'][f].mean():.3f}, {r['cldice'][f].mean():.3f} | "
                     f"{(~f).sum()}, {r['dice'][~f].mean():.3f}, {r['cldice'][~f].mean():.3f} | "
                     f"{len(r['empty_fp'])} frames, {np.mean(r['empty_fp']) if r['empty_fp'] else float('nan'):.0f} |")
    # figure: a few test frames, truth, network
    from stages.segment.infer import overlay_rgb

    pick = [i for i in np.linspace(0, len(frames) - 1, 4).round().astype(int)]
    preds = [segment_frames(frames[i], method="unet")[1] for i in pick]
    save_panels("seg_sim.png", [(overlay_rgb(frames[i], masks[i]), f"test frame {i}: ground truth") for i in pick]
                + [(overlay_rgb(frames[i], p), f"network (Dice {dice_2d(p, masks[i]):.2f})") for i, p in zip(pick, preds)],
                (2, 4), (16, 8))
    return "\n".join(lines), res


def speed() -> str:
    from stages.segment.infer import _unet_prob

    rng = np.random.default_rng(0)
    x = (110 + 20 * rng.standard_normal((8, 512, 512))).astype(np.float32)
    _unet_prob(x[:1])  # load + warm up
    lines = ["| torch threads | batch | frames/s from the best repeat | frames/s median | repeats |", "|---|---|---|---|---|"]
    for threads in (1, 2):
        for b in (1, 4):
            ts = []
            for _ in range(8):
                t = time.perf_counter()
                _unet_prob(x[:b], batch=b, threads=threads)
                ts.append((time.perf_counter() - t) / b)
            lines.append(f"| {threads} | {b} | {1 / min(ts):.1f} | {1 / np.median(ts):.1f} | 8 |")
    return "\n".join(lines) + ("\n\nIncludes normalisation and the sigmoid. `segment` uses 1 thread by default: on this "
                               "oversubscribed shared machine two OpenMP threads are much slower than one.")


def phantom(quick: bool) -> str:
    from stages.core.dicom_io import read_xa
    from stages.heldout import View, heldout_rows, summarise
    from stages.segment import segment_frames
    from stages.segment.infer import overlay_rgb
    from stages.segment.vesselness import centreline_2d, contrast_frame, fov_mask

    if not (PHANTOM / "IM1.dcm").exists():
        return f"(skipped: {PHANTOM} not found)"
    runs = [read_xa(p) for p in sorted(PHANTOM.glob("*.dcm"))]
    imgs = [contrast_frame(r.frames) for r in runs]
    views, masks = {}, {}
    for method in ("unet", "vesselness", "threshold"):
        vs, ms = [], []
        for r, img in zip(runs, imgs):
            fov = fov_mask(img)
            _, m = segment_frames(img, method=method)
            m = m.astype(bool)
            vs.append(View(r.path.stem, r.camera, m, fov, centreline_2d(m)))
            ms.append(m)
        views[method], masks[method] = vs, ms
    pairs = list(itertools.combinations(range(len(runs)), 2))
    if quick:
        pairs = pairs[::7]
    out = {}
    for method, vs in views.items():
        rows = []
        for pr in pairs:
            rows += heldout_rows(vs, pr)
        out[method] = summarise(rows)["nominal"]
    # collimator check: mask pixels in the dark region touching the border (smoothed image < ½ median) or within 3 px of it
    from scipy import ndimage

    coll = {}
    for method in masks:
        n = 0
        for img, m in zip(imgs, masks[method]):
            sm = ndimage.gaussian_filter(img, 6)
            lab, _ = ndimage.label(sm < 0.5 * np.median(sm))  # dark parts touching the image border
            edge = np.unique(np.r_[lab[0], lab[-1], lab[:, 0], lab[:, -1]])
            dark = ndimage.binary_dilation(np.isin(lab, edge[edge > 0]), iterations=3)
            n += int((m & dark).sum())
        coll[method] = n
    lines = [f"{len(pairs)} run pairs × {len(runs) - 2} held-out views each; ε = 3 mm; the same full-contrast "
             "frame per run (median of the later frames) for all methods.", "",
             "| masks | coverage mean ± sd (median) ↑ | distance mm mean ± sd (median) ↓ | vessel px in the collimator region (8 runs) |",
             "|---|---|---|---|"]
    for m, s in out.items():
        c, d = s["coverage"], s["distance_mm"]
        lines.append(f"| {m} | {c['mean']:.3f} ± {c['sd']:.3f} ({c['median']:.3f}) | "
                     f"{d['mean']:.2f} ± {d['sd']:.2f} ({d['median']:.2f}) | {coll[m]} |")
    save_panels("seg_phantom.png", [(overlay_rgb(img, m), f"{r.path.stem}: network")
                                    for r, img, m in zip(runs, imgs, masks["unet"])], (2, 4), (16, 8))
    save_panels("seg_phantom_methods.png", [(imgs[7], f"{runs[7].path.stem}")] + [
        (overlay_rgb(imgs[7], masks[method][7]), method) for method in ("unet", "vesselness", "threshold")],
        (1, 4), (20, 5.4), fontsize=10)
    return "\n".join(lines)


def keyframes(quick: bool) -> str:
    from stages.keyframe import circ_diff, keyframe_pairs, plot_keyframes, truth_filling
    from stages.render.acquire import load_truth
    from stages.segment import segment_frames
    from stages.core.runs import load_run

    root = REPO / "data" / "re"
    if not any(root.glob("case_*/truth.zarr")):
        root = REPO / "data" / "seg" / "re"
    cases = sorted(p.parent for p in root.glob("case_*/truth.zarr"))
    if quick:
        cases = cases[:1]
    if not cases:
        return "(skipped: no data-re cases; run `make data-re`)"
    rows = {"ecg": [], "images": []}
    fills = {"ecg": [], "images": []}
    abs_err = []
    table = ["| case | phase source | pair phase error median (max) | chosen frames with true filling ≥ 0.9 | "
             "min true filling of chosen frames |", "|---|---|---|---|---|"]
    for n, d in enumerate(cases):
        tr = load_truth(d / "truth.zarr")
        ra, rb = load_run(d / "run_a.dcm"), load_run(d / "run_b.dcm")
        ma = segment_frames(ra.frames, method="unet")
        mb = segment_frames(rb.frames, method="unet")
        tf = {k: truth_filling(tr, k) for k in "ab"}
        for src in ("ecg", "images"):
            if src == "images":
                ra.ecg = rb.ecg = None
            res = keyframe_pairs(ra, rb, {"prob": ma[0], "mask": ma[1]}, {"prob": mb[0], "mask": mb[1]}, k=7)
            err = np.array([circ_diff(tr["a"]["phase"][i], tr["b"]["phase"][j]) for i, j in res["pairs"]])
            f = np.array([tf["a"][i] / tf["a"].max() for i, _ in res["pairs"]] +
                         [tf["b"][j] / tf["b"].max() for _, j in res["pairs"]])
            rows[src] += err.tolist()
            fills[src] += f.tolist()
            if src == "images":
                for k in "ab":
                    abs_err += circ_diff(res["estimates"][k]["phase"], tr[k]["phase"]).tolist()
            table.append(f"| {d.name} | {src} | {np.median(err):.3f} ({err.max():.3f}) | {np.mean(f >= 0.9):.0%} | {f.min():.2f} |")
            if n == 0:
                plot_keyframes(IMG / f"seg_keyframes_{src}.png", res, {"a": tr["a"]["phase"], "b": tr["b"]["phase"]})
    summary = ["", "| phase source | pairs | median pair phase error (cycles) | 90th pct | chosen frames with true filling ≥ 0.9 |",
               "|---|---|---|---|---|"]
    for src in rows:
        e, f = np.array(rows[src]), np.array(fills[src])
        summary.append(f"| {src} | {len(e)} | {np.median(e):.3f} | {np.percentile(e, 90):.3f} | {np.mean(f >= 0.9):.0%} |")
    summary.append("")
    summary.append(f"Phase from images, per frame against the truth: median |error| {np.median(abs_err):.3f} cycle, "
                   f"90th percentile {np.percentile(abs_err, 90):.3f}.")
    return f"{len(cases)} cases from `{root.relative_to(REPO)}` (network masks).\n\n" + "\n".join(table + summary)


NOTES = """
### Notes

* Simulated test set: 16 unseen trees (cases 24–31, both sides) × 2 views × 3 frames, rendered by the
  current XA engine; the mean is over the frames with visible vessels. Some frames catch the contrast
  arriving or washing out (only the ostium or a proximal stub visible, next to the contrast-filled
  catheter, which the ground truth excludes). "Filled frames" = ≥ 80 % of their view's best visible
  area (3 frames of one pose per group), what key-frame selection uses.
* Ground truth (`stages.segment.data.visible_vessel`, schema 2): contrast-weighted iodine path
  ≥ 0.3 mm *and* inside the collimator's open field. Schema 1 also labelled vessel behind the
  collimator blades, where the frame is black; those invisible pixels counted as misses along the
  border of many test frames.
* Key frames: with `data/re` present (the full data-re set) the script uses it, else the 4 cases of
  `data/seg/re` (`make_re(out="data/seg/re", n=4)`, seeds 2 000 000–2 000 003).
* Phase from images is the fallback when a run has no ECG; it needs ≥ 1.3 heartbeats of filled frames,
  which short runs with a late bolus do not have (then 70 bpm is assumed, with a warning).
"""


KEYFRAME_HEAD = """### Key frames on data-re

Targets: median pair phase error ≤ 0.05 cycle; every chosen frame ≥ 90 % of the run's maximal filling
(true filling = fraction of the lumen volume holding contrast, from the truth sidecar).
"""
KEYFRAME_END = "![key frames, ECG]"


def rerun_keyframes(quick: bool) -> None:
    """Part 4 only, spliced into the existing document between its heading and its figures."""
    if not DOC.exists() or KEYFRAME_HEAD not in DOC.read_text():
        sys.exit(f"{DOC}: no key-frame section to replace; run the whole benchmark first")
    t0 = time.time()
    kf = keyframes(quick)
    text = DOC.read_text()
    start = text.index(KEYFRAME_HEAD) + len(KEYFRAME_HEAD)
    end = text.index(KEYFRAME_END, start)
    when = (f"Section rerun alone on {datetime.date.today().isoformat()} "
            f"(`.venv/bin/python benchmarks/bench_segment.py --keyframes-only{' --quick' if quick else ''}`, "
            f"{time.time() - t0:.0f} s; {machine()}).")
    DOC.write_text(text[:start] + "\n" + when + "\n\n" + kf + "\n\n" + text[end:])
    print(kf)


def main() -> None:
    quick = "--quick" in sys.argv
    if "--keyframes-only" in sys.argv:
        rerun_keyframes(quick)
        return
    IMG.mkdir(parents=True, exist_ok=True)
    head = machine()
    t0 = time.time()
    sim_md, _ = sim_scores(quick)
    sp = speed()
    ph = phantom(quick)
    kf = keyframes(quick)
    try:
        import torch

        from stages.segment import load_model

        _, thr, info = load_model()
        wsize = (REPO / "stages" / "weights" / "seg.pt").stat().st_size / 1e6
        nparam = sum(p.numel() for p in load_model()[0].parameters())
        def run_text(r: dict) -> str:
            return (f"{r.get('steps')} steps × batch {r.get('batch')} crops {r.get('crop')}² on {r.get('frames')} frames "
                    f"({r.get('seconds', 0) / 60:.0f} min, 1 thread)")

        winfo = f"weights `stages/weights/seg.pt`: {wsize:.2f} MB, {nparam} parameters, threshold {thr}, "
        if "init" in info:  # two-stage recipe (mk/segment.mk)
            winfo += (f"trained {run_text(info['init'])}, then fine-tuned {run_text(info)} at lr {info.get('lr')} "
                      f"with partially filled frames drawn {info.get('partial_weight')}× as often")
        else:
            winfo += f"trained {run_text(info)}"
        winfo += f"; torch {torch.__version__}"
    except Exception as exc:  # noqa: BLE001 - the report says what failed
        winfo = f"weights: {exc}"
    md = f"""## Vessel segmentation and key frames (`autocar segment`, `autocar keyframe`)

Command: `.venv/bin/python benchmarks/bench_segment.py{' --quick' if quick else ''}` — {datetime.date.today().isoformat()},
{head}; Python {platform.python_version()}. Wall time {time.time() - t0:.0f} s. Timings on a shared
machine: min and median of repeats.

{winfo}.

### Held-out simulated frames (unseen trees, data/seg/test)

Targets: Dice ≥ 0.85 and clDice ≥ 0.85 (network). Baselines on every 3rd frame.

{sim_md}

![simulated test frames](../img/seg_sim.png)

### Speed at 512² (2-core machine)

Target ≥ 10 frames/s.

{sp}

### Real phantom: held-out-view check (`stages.heldout`)

{ph}

![phantom overlays](../img/seg_phantom.png)
![methods on one phantom run](../img/seg_phantom_methods.png)

{KEYFRAME_HEAD}
{kf}

![key frames, ECG](../img/seg_keyframes_ecg.png)
![key frames, images only](../img/seg_keyframes_images.png)
""" + NOTES
    DOC.parent.mkdir(parents=True, exist_ok=True)
    DOC.write_text(md)
    print(md)


if __name__ == "__main__":
    main()
