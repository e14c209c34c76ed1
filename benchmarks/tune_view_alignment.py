"""Tune and measure the inter-run motion correction (stages/view_alignment.py) on cases never evaluated on.

For every key-frame pair that ``autocar reconstruct`` picks (our U-Net masks, our key frames), the
*true* shift of view B across its epipolar lines is the one that puts the simulator's correspondences
on each other's epipolar planes (median angle difference, searched every 0.25 px). Each setting of the
joint fit (:func:`stages.view_alignment.estimate_run_shifts`: slope of the shift per frame, how far a
pair may leave the fitted value, the least mismatch gain for a pair to be shifted, the prior against
large shifts in mismatch per px) is scored by the
absolute error of its shift against that truth; "header" is no correction. The default is chosen on
the tuning set (data/re_tuning, seeds :data:`stages.render.products.SEED_RE_TUNING` +, disjoint from
training and from data-re); ``--data data/re`` repeats the measurement on data-re as a check only.

A last row checks the default's shifts the way ``autocar reconstruct`` does, with the shipped SBP network
(a shift is kept only if the prediction with it holds more voxels of occupancy ≥ ½; ``--no-network``
skips it).

Run:  python benchmarks/tune_view_alignment.py [--cases 12] [--data data/re_tuning] [--no-network]
Writes data/re_tuning (the cases, once), out/tune_align/<case>.npz (masks of the key frames, cached by
the runs' and segmenter's content) and docs/benchmarks/view_alignment[_<data>].md.
"""

from __future__ import annotations

import argparse
import hashlib
import itertools
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

SLOPES = (0.0, 0.25, 0.5, 1.0)
WINDOWS = (1.0, 2.0, 4.0)
GAINS = (None, 0.0, 0.02, 0.05, 0.08)  # None: every pair shifted, however little it gains
PRIORS = (0.0, 0.002, 0.003, 0.004, 0.006, 0.008)  # mismatch per px of shift
SHOWN = 25  # rows of the table (best first; the default is always shown)


def key_frame_masks(case: Path, cache: Path) -> dict:
    """The masks of the key-frame pairs ``autocar reconstruct`` would use for ``case`` (cached)."""
    from re_eval import SEG_WEIGHTS
    from table1 import hash_file

    from stages.keyframe import keyframe_pairs
    from stages.segment import load_run, segment_run

    h = hashlib.sha256(b"v1")
    for f in (case / "run_a.dcm", case / "run_b.dcm", SEG_WEIGHTS):
        hash_file(h, f)
    path = cache / f"{case.name}_{h.hexdigest()[:12]}.npz"
    if path.exists():
        return dict(np.load(path))
    runs = [load_run(case / "run_a.dcm"), load_run(case / "run_b.dcm")]
    masks = [segment_run(run) for run in runs]
    kf = keyframe_pairs(runs[0], runs[1], masks_a={"prob": masks[0]["prob"], "mask": masks[0]["mask"]},
                        masks_b={"prob": masks[1]["prob"], "mask": masks[1]["mask"]})
    pairs = np.array(list(dict.fromkeys(kf["pairs"])), int)
    out = {"pairs": pairs, "masks_a": np.stack([np.asarray(masks[0]["mask"][i], np.uint8) for i, _ in pairs]),
           "masks_b": np.stack([np.asarray(masks[1]["mask"][j], np.uint8) for _, j in pairs])}
    cache.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(path, **out)
    return out


def true_shifts(truth: dict, cam_a, cam_b, pairs) -> np.ndarray:
    """Per pair, the shift across view B's epipolar lines that best fits the simulator's correspondences."""
    from stages.evaluate import truth_correspondences
    from stages.view_alignment import _across_direction, _plane_frame, epipolar_angles

    frame = _plane_frame(cam_a, cam_b)
    u, _ = _across_direction(cam_b, frame)
    steps = np.arange(-40.0, 40.001, 0.25)
    out = []
    for k, (ia, ib) in enumerate(pairs):
        ann = truth_correspondences(truth, cam_a, cam_b, int(ia), int(ib), 200, [0, k])
        ta = epipolar_angles(cam_a, ann["pairs"][:, :2], frame)
        miss = [np.median(np.abs(ta - epipolar_angles(cam_b.shifted(*(s * u)), ann["pairs"][:, 2:], frame)))
                for s in steps]
        out.append(steps[int(np.argmin(miss))])
    return np.asarray(out)


def network_checked_errors(per_case) -> tuple[np.ndarray, int, int]:
    """Shift errors of the default fit after the check ``autocar reconstruct`` applies (a shift is kept
    only if the SBP prediction with it holds more confident voxels than with the header geometry)."""
    import torch

    from stages.evaluate import truth_side
    from stages.methods3d import load_predictor
    from stages.reconstruct import predict_with_checked_shift
    from stages.render.acquire import load_truth
    from stages.view_alignment import estimate_run_shifts

    torch.set_num_threads(2)
    predict = load_predictor("sbp")
    errors, n_applied, n_kept = [], 0, 0
    for curves, pairs, truth, _, (km, cam_a, cam_b, case) in per_case:
        side = truth_side(load_truth(case / "truth.zarr"))
        for k, est in enumerate(estimate_run_shifts(curves, pairs[:, 0], pairs[:, 1])):
            kept = False
            if est.applied:
                n_applied += 1
                _, _, kept = predict_with_checked_shift(predict, km["masks_a"][k].astype(bool),
                                                        km["masks_b"][k].astype(bool), cam_a, cam_b, est, side)
                n_kept += kept
            errors.append(abs((est.across_px if kept else 0.0) - truth[k]))
    return np.asarray(errors), n_applied, n_kept


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", type=int, default=12, help="tuning cases (seeds SEED_RE_TUNING + 0 … n−1)")
    ap.add_argument("--data", default=str(ROOT / "data" / "re_tuning"))
    ap.add_argument("--cache", default=str(ROOT / "out" / "tune_align"))
    ap.add_argument("--no-network", action="store_true",
                    help="skip the row that checks the default's shifts with the shipped SBP network (~5 min)")
    args = ap.parse_args(argv)
    data = Path(args.data)

    from machine import write_section

    from stages.render.acquire import load_truth
    from stages.render.products import SEED_RE_TUNING, make_re
    from stages.segment import load_run
    from stages.view_alignment import (MIN_GAIN, PRIOR_PER_PX, REFINE_PX, SLOPE_PX, estimate_run_shifts,
                                       mismatch_curve)

    tuning = data.resolve() == (ROOT / "data" / "re_tuning").resolve()
    if tuning:
        make_re(data, n=args.cases, seed=SEED_RE_TUNING, jobs=1)
    cases = sorted(p for p in data.glob("case_*") if (p / "truth.zarr").exists())[:args.cases]
    if not cases:
        print(f"{data}: no cases (make data-re?)")
        return 0
    per_case = []
    for case in cases:
        runs = [load_run(case / "run_a.dcm"), load_run(case / "run_b.dcm")]
        cam_a, cam_b = runs[0].camera, runs[1].camera
        km = key_frame_masks(case, Path(args.cache))
        curves = [mismatch_curve(ma, mb, cam_a, cam_b) for ma, mb in zip(km["masks_a"], km["masks_b"])]
        truth = true_shifts(load_truth(case / "truth.zarr"), cam_a, cam_b, km["pairs"])
        per_case.append((curves, km["pairs"], truth, cam_b.isocentre_spacing, (km, cam_a, cam_b, case)))
        print(f"{case.name}: true shifts {np.round(truth, 1).tolist()} px", flush=True)

    def errors(slope, window, gain, prior):
        out = []
        for curves, pairs, truth, _, _ in per_case:
            est = estimate_run_shifts(curves, pairs[:, 0], pairs[:, 1], slope_px=slope, window_px=window,
                                      min_gain=-np.inf if gain is None else gain, prior_per_px=prior)
            out.append(np.abs(np.array([e.across_px for e in est]) - truth))
        return np.concatenate(out)

    truth_all = np.concatenate([t for _, _, t, _, _ in per_case])
    spacing = np.concatenate([np.full(len(t), s) for _, _, t, s, _ in per_case])
    default = (SLOPE_PX, REFINE_PX, MIN_GAIN, PRIOR_PER_PX)

    def row(label, err):
        return (f"| {label} | {err.mean():.2f} | {(err * spacing).mean():.2f} | {np.mean(err < 2):.0%} | "
                f"{np.mean(err < 4):.0%} | {err.max():.1f} |")

    results = {s: errors(*s) for s in itertools.product(SLOPES, WINDOWS, GAINS, PRIORS)}
    best = min(results, key=lambda s: results[s].mean())
    lines = [f"{len(cases)} cases of {data.name} ({len(truth_all)} key-frame pairs), our segmentation and key "
             f"frames. True shift across view B's epipolar lines: mean |shift| {np.abs(truth_all).mean():.2f} px "
             f"({(np.abs(truth_all) * spacing).mean():.2f} mm at the isocentre), over 4 px on "
             f"{np.mean(np.abs(truth_all) > 4):.0%} of the pairs.", "",
             "| setting (slope px/frame, window px, least gain, prior per px) | mean error (px) ↓ | mean error (mm) ↓ | within 2 px ↑ | within 4 px ↑ | largest (px) |",
             "|---|---|---|---|---|---|", row("header geometry (no correction)", np.abs(truth_all))]
    ranked = sorted(results, key=lambda s: results[s].mean())
    for s in [r for n, r in enumerate(ranked) if n < SHOWN or r == default]:
        label = f"{s[0]:g}, {s[1]:g}, {'none' if s[2] is None else f'{s[2]:g}'}, {s[3]:g}"
        label += " (default)" if s == default else ""
        lines.append(row(label, results[s]))
    lines.append(f"({len(ranked)} settings tried; the best {SHOWN} shown.)")
    if not args.no_network:
        checked, n_applied, n_kept = network_checked_errors(per_case)
        lines += ["", "**Checked by the prediction** (what `autocar reconstruct` does with the default: a shift is "
                  "kept only if the shipped SBP network, given view B shifted, predicts more voxels of occupancy "
                  "≥ ½ than with the header geometry):", "",
                  "| setting | mean error (px) ↓ | mean error (mm) ↓ | within 2 px ↑ | within 4 px ↑ | largest (px) |",
                  "|---|---|---|---|---|---|", row("default, shifts unchecked", results[default]),
                  row("default, checked by the prediction", checked), "",
                  f"{n_applied} key-frame pairs got a shift from the fit; the prediction kept {n_kept} of them."]
    lines += ["", f"Lowest mean error: slope {best[0]:g}, window {best[1]:g} px, least gain "
              f"{'none' if best[2] is None else best[2]}, prior {best[3]:g} per px."
              + ("" if tuning else " (A check on an evaluation set: the default is chosen on data/re_tuning.)")]
    body = "\n".join(lines)
    topic = "view_alignment" if tuning else f"view_alignment_{data.name}"
    cmd = "python benchmarks/tune_view_alignment.py" + "".join(
        f" --{k} {getattr(args, k)}" for k in ("cases", "data") if getattr(args, k) != ap.get_default(k))
    write_section(topic, "Inter-run motion correction: view B's shift against the simulator's truth", cmd, body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
