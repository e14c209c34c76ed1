"""Benchmark: accuracy and speed of `autocar segment` and `autocar keyframe` → docs/benchmarks/segment.md.

Also docs/img/seg_*.png. The measurements are stages/segment/validate.py's (simulated test frames, the
phantom's held-out-view check, key frames on data-re), plus the network's speed at 512².
Run: ``python benchmarks/bench_segment.py [--quick] [--keyframes-only]`` (the latter splices its part in).
"""

from __future__ import annotations

import argparse
import datetime
import sys
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from benchmarks.machine import DOCS, load_average, machine_description, repeat_timing, write_section  # noqa: E402
from stages.segment import segment_frames, validate  # noqa: E402
from stages.segment.infer import _unet_prob, overlay_rgb  # noqa: E402
from stages.segment.scores import dice_2d  # noqa: E402

PHANTOM = REPO.parent / "shared" / "data" / "phantom_xa"
DOC = DOCS / "segment.md"
IMG = DOCS.parent / "img"


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


def sim_scores(quick: bool) -> str:
    from stages.segment.data import load_split

    if not any((REPO / "data" / "seg" / "test").glob("*.npz")):
        return "(skipped: no data/seg/test; run `python -m stages.segment.data test`)"
    frames, masks, _ = load_split(REPO / "data" / "seg" / "test")
    if quick:
        frames, masks = frames[::6], masks[::6]
    filled = validate.filled_frames(masks, group=1 if quick else 3)  # quick: the views' groups are broken
    lines = ["| method | frames | Dice mean ± sd (median) | clDice mean ± sd (median) | pooled Dice | "
             "filled frames: n, Dice mean, clDice mean | partially filled frames: n, Dice mean, clDice mean | "
             "no-contrast frames: false-positive px (mean) |", "|---|---|---|---|---|---|---|---|"]
    for m, step in (("unet", 1), ("vesselness", 3), ("threshold", 3)):
        r = validate.score_frames(frames, masks, filled, m, step)
        f, d, c = r["filled"], r["dice"], r["cldice"]
        lines.append(f"| {m} | {r['n']} | {d.mean():.3f} ± {d.std():.3f} ({np.median(d):.3f}) | "
                     f"{c.mean():.3f} ± {c.std():.3f} ({np.median(c):.3f}) | {r['pooled']:.3f} | "
                     f"{f.sum()}, {d[f].mean():.3f}, {c[f].mean():.3f} | {(~f).sum()}, {d[~f].mean():.3f}, "
                     f"{c[~f].mean():.3f} | {len(r['empty_fp'])} frames, "
                     f"{np.mean(r['empty_fp']) if r['empty_fp'] else float('nan'):.0f} |")
    pick = np.linspace(0, len(frames) - 1, 4).round().astype(int)
    preds = [segment_frames(frames[i], method="unet")[1] for i in pick]
    save_panels("seg_sim.png", [(overlay_rgb(frames[i], masks[i]), f"test frame {i}: ground truth") for i in pick]
                + [(overlay_rgb(frames[i], p), f"network (Dice {dice_2d(p, masks[i]):.2f})") for i, p in zip(pick, preds)],
                (2, 4), (16, 8))
    return "\n".join(lines)


def speed() -> str:
    x = (110 + 20 * np.random.default_rng(0).standard_normal((8, 512, 512))).astype(np.float32)
    _unet_prob(x[:1])  # load + warm up
    lines = ["| torch threads | batch | frames/s from the best repeat | frames/s median | repeats |", "|---|---|---|---|---|"]
    for threads, b in ((1, 1), (1, 4), (2, 1), (2, 4)):
        ts = np.array(repeat_timing(lambda: _unet_prob(x[:b], batch=b, threads=threads), 8, warmup=0)["times"]) / b
        lines.append(f"| {threads} | {b} | {1 / ts.min():.1f} | {1 / np.median(ts):.1f} | 8 |")
    return "\n".join(lines) + ("\n\nIncludes normalisation and the sigmoid. `segment` uses 1 thread by default: on this "
                               "oversubscribed shared machine two OpenMP threads are much slower than one.")


def phantom(quick: bool) -> str:
    if not (PHANTOM / "IM1.dcm").exists():
        return f"(skipped: {PHANTOM} not found)"
    res = validate.phantom_check(sorted(PHANTOM.glob("*.dcm")), pair_step=7 if quick else 1)
    runs, imgs, masks = res["runs"], res["imgs"], res["masks"]
    lines = [f"{len(res['pairs'])} run pairs × {len(runs) - 2} held-out views each; ε = 3 mm; the same full-contrast "
             "frame per run (median of the later frames) for all methods.", "",
             "| masks | coverage mean ± sd (median) ↑ | distance mm mean ± sd (median) ↓ | vessel px in the collimator region (8 runs) |",
             "|---|---|---|---|"]
    for m, s in res["summary"].items():
        c, d = s["coverage"], s["distance_mm"]
        lines.append(f"| {m} | {c['mean']:.3f} ± {c['sd']:.3f} ({c['median']:.3f}) | "
                     f"{d['mean']:.2f} ± {d['sd']:.2f} ({d['median']:.2f}) | {res['collimator'][m]} |")
    save_panels("seg_phantom.png", [(overlay_rgb(img, m), f"{r.path.stem}: network")
                                    for r, img, m in zip(runs, imgs, masks["unet"])], (2, 4), (16, 8))
    save_panels("seg_phantom_methods.png", [(imgs[7], f"{runs[7].path.stem}")] + [
        (overlay_rgb(imgs[7], masks[m][7]), m) for m in ("unet", "vesselness", "threshold")],
        (1, 4), (20, 5.4), fontsize=10)
    return "\n".join(lines)


def keyframes(quick: bool) -> str:
    root = REPO / "data" / "re"
    if not any(root.glob("case_*/truth.zarr")):
        root = REPO / "data" / "seg" / "re"
    cases = sorted(p.parent for p in root.glob("case_*/truth.zarr"))[:1 if quick else None]
    if not cases:
        return "(skipped: no data-re cases; run `make data-re`)"
    res = validate.keyframe_check(cases, plot_prefix=IMG / "seg_keyframes")
    table = ["| case | phase source | pair phase error median (max) | chosen frames with true filling ≥ 0.9 | "
             "min true filling of chosen frames |", "|---|---|---|---|---|"]
    for r in res["rows"]:
        e, f = r["errors"], r["filling"]
        table.append(f"| {r['case']} | {r['source']} | {np.median(e):.3f} ({e.max():.3f}) | {np.mean(f >= 0.9):.0%} | {f.min():.2f} |")
    table += ["", "| phase source | pairs | median pair phase error (cycles) | 90th pct | chosen frames with true filling ≥ 0.9 |",
              "|---|---|---|---|---|"]
    for src in ("ecg", "images"):
        e = np.concatenate([r["errors"] for r in res["rows"] if r["source"] == src])
        f = np.concatenate([r["filling"] for r in res["rows"] if r["source"] == src])
        table.append(f"| {src} | {len(e)} | {np.median(e):.3f} | {np.percentile(e, 90):.3f} | {np.mean(f >= 0.9):.0%} |")
    a = res["image_phase_errors"]
    table += ["", f"Phase from images, per frame against the truth: median |error| {np.median(a):.3f} cycle, "
              f"90th percentile {np.percentile(a, 90):.3f}."]
    return f"{len(cases)} cases from `{root.relative_to(REPO)}` (network masks).\n\n" + "\n".join(table) + short_runs(cases)


def short_runs(cases) -> str:
    """Phase from images on 37/40-frame windows of every run, no ECG (validate.short_run_check)."""
    rows = validate.short_run_check(cases)
    table = ["", "", "Short runs (issue #35): each run cut to 37 or 40 consecutive frames (from the first frame, "
             "and the window with the most contrast filling), ECG and heart rate removed.", "",
             "| window | windows | period error median (90th pct) | per-frame phase error median (90th pct) | "
             "'no measurable period' fallback |", "|---|---|---|---|---|"]
    for w in ("first", "filled", "all"):
        sel = [r for r in rows if w in ("all", r["window"])]
        pe, ph = np.array([r["period_error"] for r in sel]), np.concatenate([r["phase_errors"] for r in sel])
        table.append(f"| {w} | {len(sel)} | {np.median(pe):.1%} ({np.percentile(pe, 90):.1%}) | "
                     f"{np.median(ph):.3f} ({np.percentile(ph, 90):.3f}) | {np.mean([r['fallback'] for r in sel]):.0%} |")
    return "\n".join(table)


def weights_info() -> str:
    try:
        import torch

        from stages.segment import load_model
        from stages.segment.weights import DEFAULT_WEIGHTS

        net, thr, info = load_model()
        run = lambda r: (f"{r.get('steps')} steps × batch {r.get('batch')} crops {r.get('crop')}² on "  # noqa: E731
                         f"{r.get('frames')} frames ({r.get('seconds', 0) / 60:.0f} min, 1 thread)")
        recipe = (f"{run(info['init'])}, then fine-tuned {run(info)} at lr {info.get('lr')} with partially filled frames "
                  f"drawn {info.get('partial_weight')}× as often" if "init" in info else run(info))  # two-stage: mk/segment.mk
        return (f"weights `stages/weights/seg.pt`: {DEFAULT_WEIGHTS.stat().st_size / 1e6:.2f} MB, "
                f"{sum(p.numel() for p in net.parameters())} parameters, threshold {thr}, trained {recipe}; torch {torch.__version__}")
    except Exception as exc:  # noqa: BLE001 - the report says what failed
        return f"weights: {exc}"


KEYFRAME_HEAD = """### Key frames on data-re

Targets: median pair phase error ≤ 0.05 cycle; every chosen frame ≥ 90 % of the run's maximal filling
(true filling = fraction of the lumen volume holding contrast, from the truth sidecar).
"""
KEYFRAME_END = "![key frames, ECG]"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames and cases (a trial run)")
    ap.add_argument("--keyframes-only", action="store_true", help="rerun the key-frame part and splice it in")
    args = ap.parse_args()
    quick = args.quick
    cmd = ".venv/bin/python benchmarks/bench_segment.py" + " ".join(["", *sys.argv[1:]])
    IMG.mkdir(parents=True, exist_ok=True)
    t0, load = time.time(), load_average()
    if args.keyframes_only:  # spliced between the section's heading and its figures
        if not DOC.exists() or KEYFRAME_HEAD not in DOC.read_text():
            sys.exit(f"{DOC}: no key-frame section to replace; run the whole benchmark first")
        kf, text = keyframes(quick), DOC.read_text()
        start = text.index(KEYFRAME_HEAD) + len(KEYFRAME_HEAD)
        when = (f"Section rerun alone on {datetime.date.today().isoformat()} (`{cmd}`, {time.time() - t0:.0f} s; "
                f"{machine_description()}, {load} at start (shared machine)).")
        DOC.write_text(text[:start] + "\n" + when + "\n\n" + kf + "\n\n" + text[text.index(KEYFRAME_END, start):])
        print(kf)
        return
    sim, sp, ph, kf = sim_scores(quick), speed(), phantom(quick), keyframes(quick)
    body = f"""{load} at start (shared machine). Wall time {time.time() - t0:.0f} s. Timings: min and median of repeats.

{weights_info()}.

### Held-out simulated frames (unseen trees, data/seg/test)

Targets: Dice ≥ 0.85 and clDice ≥ 0.85 (network). Baselines on every 3rd frame.

{sim}

![simulated test frames](../img/seg_sim.png)

### Speed at 512² (2-core machine)

Target ≥ 10 frames/s.

{sp}

### Real phantom: held-out-view check (`stages.evaluate.heldout`)

{ph}

![phantom overlays](../img/seg_phantom.png)
![methods on one phantom run](../img/seg_phantom_methods.png)

{KEYFRAME_HEAD}
{kf}

![key frames, ECG](../img/seg_keyframes_ecg.png)
![key frames, images only](../img/seg_keyframes_images.png)

### Notes

The test set, its ground truth and the key-frame cases: [SEGMENTATION.md](../SEGMENTATION.md#the-benchmarks-data)."""
    print(write_section("segment", "Vessel segmentation and key frames (`autocar segment`, `autocar keyframe`)",
                        cmd, body).read_text())


if __name__ == "__main__":
    main()
