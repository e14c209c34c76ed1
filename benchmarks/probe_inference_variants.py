"""Probe: two inference-time changes to the shipped SBP network that do not need retraining, on data-se.

1. **Hysteresis thresholding**: keep voxels with occupancy ≥ ``low`` only when 26-connected (through such
   voxels) to one ≥ ``high``, instead of one threshold at ½. Aims at the thin distal branches the
   network predicts weakly (docs/MODEL_CARD.md: they are what Dice and clDice miss).
2. **Undoing view B's misalignment**: with view B unwarped the network scores far better, so this asks
   whether the misalignment can be found at inference. View B's mask is shifted by ``t`` px
   perpendicular to the epipolar lines (the only direction two views can see; a shift along them only
   changes depth) for t = −3…3; for each shift the network predicts again. Reported: the Dice of the
   best shift (an oracle that uses the truth), and the Dice of the shift each truth-free score picks —
   voxels with occupancy ≥ ½, their mean occupancy, Σ occupancy·centreness, and how well the prediction
   reprojects onto both masks (2D Dice of the projected voxels with each mask). For reference, the Dice
   with view B not misaligned at all.

Run:  python benchmarks/probe_inference_variants.py [--limit 12]
Writes docs/benchmarks/inference_probes.md. Missing data-se: says so and exits 0.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

HYSTERESIS = [(0.5, 0.3), (0.5, 0.2), (0.6, 0.3)]
SHIFTS_PX = [-3, -2, -1, 0, 1, 2, 3]
METRICS = ("dice", "cldice", "chamfer_mm", "hd95_mm")


def hysteresis(coords: np.ndarray, occ: np.ndarray, high: float, low: float) -> np.ndarray:
    """Boolean keep-mask: voxels ≥ ``low`` 26-connected (through such voxels) to a voxel ≥ ``high``."""
    from scipy import ndimage

    weak = occ >= low
    c = coords[weak]
    if not len(c):
        return weak
    lo = c.min(0)
    grid = np.zeros(c.max(0) - lo + 1, bool)
    grid[tuple((c - lo).T)] = True
    label, n = ndimage.label(grid, structure=np.ones((3, 3, 3)))
    lab = label[tuple((c - lo).T)]
    seeded = np.zeros(n + 1, bool)
    seeded[lab[occ[weak] >= high]] = True
    seeded[0] = False
    keep = np.zeros(len(coords), bool)
    keep[weak] = seeded[lab]
    return keep


def _score(pred, keep, truth) -> list[float]:
    from stages.metrics import metrics_3d
    from stages.voxels import SparseVoxels

    m = metrics_3d(SparseVoxels(pred.coords, pred.voxel_size, pred.origin, {"occupancy": keep.astype(np.float32)}),
                   truth, workers=2)
    return [m[k] for k in METRICS]


def perpendicular_direction(cam_a, cam_b) -> np.ndarray:
    """Unit (row, col) direction in view B across the epipolar lines, at the image centre of view A."""
    o, d = cam_a.rays(np.array([[cam_a.rows / 2, cam_a.cols / 2]]))
    x = o[0] + d[0] * np.linalg.norm(cam_a.source)  # near the isocentre
    e = cam_b.project((x + 10 * d[0])[None])[0] - cam_b.project(x[None])[0]
    e /= np.linalg.norm(e)
    return np.array([-e[1], e[0]])


def reprojection_dice(points, cam, mask) -> float:
    from scipy import ndimage

    rc = np.rint(cam.project(points)).astype(int)
    ok = np.all(rc >= 0, 1) & (rc[:, 0] < mask.shape[0]) & (rc[:, 1] < mask.shape[1])
    img = np.zeros(mask.shape, bool)
    img[rc[ok, 0], rc[ok, 1]] = True
    img = ndimage.binary_closing(ndimage.binary_dilation(img), iterations=1)
    return float(2 * (img & mask).sum() / max(img.sum() + mask.sum(), 1))


def main(argv=None) -> int:
    from se_eval import add_se_arguments, se_or_say

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_se_arguments(ap)
    ap.set_defaults(limit=12)
    args = ap.parse_args(argv)
    data = se_or_say(args.data)
    if data is None:
        return 0
    import torch
    from scipy import ndimage

    from machine import write_section
    from se_eval import se_pairs
    from stages.sbp.model import prepare_pair
    from stages.train import load_weights

    torch.set_num_threads(args.threads)
    model = load_weights()
    post = {"occupancy ≥ ½ (shipped)": []} | {f"hysteresis {h:g} / {lo:g}": [] for h, lo in HYSTERESIS}
    picks = {"oracle (best Dice)": [], "no shift (shipped)": [], "most voxels ≥ ½": [], "highest mean occupancy": [],
             "largest Σ occupancy·centreness": [], "best reprojection onto both masks": []}
    unwarped = []  # the reference: view B without its misalignment (what the shifts try to approach)
    for p, p0 in zip(se_pairs(data, args.limit, args.misalign_px), se_pairs(data, args.limit, 0.0)):
        pred0 = model.predict(prepare_pair(p0.mask_a, p0.mask_b, p0.cam_a, p0.cam_b, model.config), side=p.case.side)
        unwarped.append(_score(pred0, pred0.features["occupancy"] >= 0.5, p.truth)[0])
        n = perpendicular_direction(p.cam_a, p.cam_b)
        H, W = p.mask_b.shape
        rr, cc = np.mgrid[0:H, 0:W].astype(float)
        per_shift = []
        for t in SHIFTS_PX:
            mb = p.mask_b if t == 0 else ndimage.map_coordinates(
                p.mask_b.astype(np.float32), [rr - t * n[0], cc - t * n[1]], order=1) >= 0.5
            pred = model.predict(prepare_pair(p.mask_a, mb, p.cam_a, p.cam_b, model.config), side=p.case.side)
            occ, cen = pred.features["occupancy"], pred.features["centreness"]
            on = occ >= 0.5
            pts = pred.world_points()[on]
            per_shift.append({"dice": _score(pred, on, p.truth)[0], "n": int(on.sum()),
                              "mean_occ": float(occ[on].mean()) if on.any() else 0.0,
                              "occ_cen": float((occ * cen).sum()),
                              "reproj": (reprojection_dice(pts, p.cam_a, p.mask_a)
                                         + reprojection_dice(pts, p.cam_b, mb))})
            if t == 0:
                for name in post:
                    keep = on if name.startswith("occupancy") else hysteresis(
                        pred.coords, occ, *[float(x) for x in name.split()[1::2]])
                    post[name].append(_score(pred, keep, p.truth))
        dice = [s["dice"] for s in per_shift]
        for name, key in (("oracle (best Dice)", "dice"), ("most voxels ≥ ½", "n"),
                          ("highest mean occupancy", "mean_occ"), ("largest Σ occupancy·centreness", "occ_cen"),
                          ("best reprojection onto both masks", "reproj")):
            best = int(np.argmax([s[key] for s in per_shift]))
            picks[name].append((dice[best], SHIFTS_PX[best]))
        picks["no shift (shipped)"].append((dice[SHIFTS_PX.index(0)], 0))
        print(f"pair {p.index}: Dice by shift {np.round(dice, 3).tolist()}", flush=True)

    base = np.array(post["occupancy ≥ ½ (shipped)"])
    lines = ["| post-processing | Dice ↑ | clDice ↑ | Chamfer mm ↓ | HD95 mm ↓ | Dice better on |",
             "|---|---|---|---|---|---|"]
    for name, rows in post.items():
        r = np.array(rows)
        lines.append(f"| {name} | " + " | ".join(f"{v:.3f}" if i < 2 else f"{v:.2f}" for i, v in enumerate(r.mean(0)))
                     + f" | {np.mean(r[:, 0] > base[:, 0]):.0%} |")
    lines += ["", "| shift of view B chosen by | Dice ↑ | mean chosen shift (px) | Dice better than no shift on |",
              "|---|---|---|---|"]
    ref = np.array([d for d, _ in picks["no shift (shipped)"]])
    for name, rows in picks.items():
        d = np.array([x for x, _ in rows])
        lines.append(f"| {name} | {d.mean():.3f} | {np.mean([abs(s) for _, s in rows]):.1f} | "
                     f"{np.mean(d > ref + 1e-9):.0%} |")
    lines.append(f"| (view B without misalignment: the reference) | {np.mean(unwarped):.3f} | | "
                 f"{np.mean(np.array(unwarped) > ref + 1e-9):.0%} |")
    body = (f"First {len(base)} pairs of data-se, ground-truth silhouettes, view B with a {args.misalign_px:g} px RMS "
            f"TPS misalignment (seeded per pair), shipped weights, {args.threads} torch threads.\n\n"
            + "\n".join(lines) + "\n")
    write_section("inference_probes", "Inference-time variants of the SBP network (probe, not shipped)",
                  "python benchmarks/probe_inference_variants.py", body)
    print(body)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
