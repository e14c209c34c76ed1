"""Image statistics used to compare simulated XA frames with real ones (docs/SIMULATION.md).

Reads frames given as arrays (any bit depth, vessels dark); writes nothing. The same automatic
procedure is applied to real and simulated frames, so the numbers are comparable:

* field of view: pixels whose heavily smoothed value exceeds half the median (drops the dark
  collimator/shutter border), eroded by 12 px;
* local background: a grey closing with a 15 px disc (fills thin dark structures), lightly smoothed;
* vessel response: local background − frame; pixel noise σₙ: robust (MAD) std of the frame minus its
  σ = 2 px Gaussian smoothing, over background pixels;
* vessel pixels: response > 6 σₙ (connected components ≥ 30 px), inside the field of view;
* CNR = mean vessel response / σₙ; background mean and std: raw values over non-vessel field-of-view
  pixels (the std includes anatomy, not only noise).

All intensities are reported on an 8-bit scale (values × 255 / (2^bits − 1)).
"""

from __future__ import annotations

import numpy as np

__all__ = ["frame_statistics", "realism_report"]


def frame_statistics(frame: np.ndarray, bits: int = 8, vessel_mask: np.ndarray | None = None) -> dict:
    """Statistics of one frame (see the module docstring); ``vessel_mask`` overrides the automatic one."""
    from scipy import ndimage

    f = np.asarray(frame, dtype=np.float64) * (255.0 / (2 ** bits - 1))
    smooth = ndimage.gaussian_filter(f, 8)
    fov = smooth > 0.5 * np.median(smooth)
    fov = ndimage.binary_erosion(fov, iterations=12)
    yy, xx = np.mgrid[-7:8, -7:8]
    disc = (yy ** 2 + xx ** 2) <= 49
    bg_local = ndimage.gaussian_filter(ndimage.grey_closing(f, footprint=disc), 1.0)
    response = bg_local - f
    hp = f - ndimage.gaussian_filter(f, 2.0)
    bg_guess = fov & (response < np.percentile(response[fov], 80))
    noise = 1.4826 * np.median(np.abs(hp[bg_guess] - np.median(hp[bg_guess])))
    if vessel_mask is None:
        vessel = fov & (response > 6.0 * noise)
        lab, n = ndimage.label(vessel)
        if n:
            sizes = ndimage.sum(vessel, lab, index=np.arange(1, n + 1))
            vessel = np.isin(lab, 1 + np.flatnonzero(sizes >= 30))
    else:
        vessel = fov & np.asarray(vessel_mask, bool)
    background = fov & ~ndimage.binary_dilation(vessel, iterations=3)
    cnr = float(response[vessel].mean() / noise) if vessel.any() else 0.0
    return {
        "cnr": cnr,
        "vessel_contrast": float(response[vessel].mean()) if vessel.any() else 0.0,
        "noise_std": float(noise),
        "background_mean": float(f[background].mean()),
        "background_std": float(f[background].std()),
        "vessel_fraction": float(vessel.sum() / max(fov.sum(), 1)),
        "fov_fraction": float(fov.mean()),
    }


def realism_report(sim_runs, real_runs, png, n_show: int = 4) -> list[dict]:
    """Figure of simulated frames beside real ones (top: simulated, bottom: real) and per-run statistics.

    Statistics are taken on the frame with the most opacified vessels of each run (largest vessel
    fraction among its last half), the same rule for both kinds. Returns one dict per run.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ..core.figures import save_png
    from ..core.dicom_io import read_xa

    rows = []
    shown = {"simulated": [], "real": []}
    for kind, paths in (("simulated", sim_runs), ("real", real_runs)):
        for p in paths:
            run = read_xa(p)
            T = len(run.frames)
            cands = range(T // 2, T)
            stats = [frame_statistics(run.frames[i], run.bits_stored) for i in cands]
            best = int(np.argmax([s["vessel_fraction"] for s in stats]))
            s = dict(stats[best], run=str(p), kind=kind, frame=list(cands)[best])
            rows.append(s)
            if len(shown[kind]) < n_show:
                shown[kind].append((run.frames[s["frame"]] * 255.0 / (2 ** run.bits_stored - 1), p))
    n = max(len(shown["simulated"]), len(shown["real"]))
    fig, axes = plt.subplots(2, n, figsize=(3.2 * n, 6.6))
    for r, kind in enumerate(("simulated", "real")):
        for c in range(n):
            ax = axes[r, c]
            ax.axis("off")
            if c < len(shown[kind]):
                img, p = shown[kind][c]
                ax.imshow(img, cmap="gray", vmin=0, vmax=255)
                ax.set_title(f"{kind}: {p.parent.name}/{p.name}" if kind == "simulated" else f"real: {p.name}", fontsize=8)
    fig.tight_layout()
    save_png(fig, png, dpi=80)
    return rows


def main(argv=None) -> None:
    """``python -m stages.render.realism [WORK_DIR]``: simulate 3 cases (procedural prep-ct trees of seeds
    3 100 000–2, outside the training range; 512², 30 frames), compare with ../shared/data/phantom_xa,
    write docs/img/simulation_vs_phantom.png and print the Markdown table used in docs/SIMULATION.md.
    Runs already in WORK_DIR are reused; delete it after changing the simulator."""
    import sys
    from pathlib import Path

    from ..poses import PoseModel
    from .acquire import simulate_acquisition
    from .products import ensure_case

    argv = sys.argv[1:] if argv is None else argv
    root = Path(__file__).resolve().parents[2]
    work = Path(argv[0]) if argv else root / "out" / "realism"
    model = PoseModel.default(0)
    sims = []
    for i, s in enumerate((3_100_000, 3_100_001, 3_100_002)):
        d = work / f"case{i}"
        if not (d / "run_b.dcm").exists():
            simulate_acquisition(ensure_case(work / "cases", s), model, d, s, size=512, n_frames=30)
        sims += [d / "run_a.dcm", d / "run_b.dcm"]
    real_dir = root / ".." / "shared" / "data" / "phantom_xa"
    real = sorted(real_dir.glob("IM*.dcm"))
    rows = realism_report(sims, real, root / "docs" / "img" / "simulation_vs_phantom.png")
    print("| run | kind | frame | CNR | vessel contrast | noise σₙ | background mean | background std |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        p = Path(r["run"])
        name = f"{p.parent.name}/{p.name}"
        print(f"| {name} | {r['kind']} | {r['frame']} | {r['cnr']:.1f} | {r['vessel_contrast']:.1f} | "
              f"{r['noise_std']:.1f} | {r['background_mean']:.1f} | {r['background_std']:.1f} |")
    for kind in ("simulated", "real"):
        sel = [r for r in rows if r["kind"] == kind]
        if sel:
            rng = {k: (min(r[k] for r in sel), max(r[k] for r in sel))
                   for k in ("cnr", "vessel_contrast", "noise_std", "background_mean", "background_std")}
            print(f"| **{kind} range** | | | {rng['cnr'][0]:.1f}–{rng['cnr'][1]:.1f} | "
                  f"{rng['vessel_contrast'][0]:.0f}–{rng['vessel_contrast'][1]:.0f} | {rng['noise_std'][0]:.1f}–{rng['noise_std'][1]:.1f} | "
                  f"{rng['background_mean'][0]:.1f}–{rng['background_mean'][1]:.1f} | {rng['background_std'][0]:.1f}–{rng['background_std'][1]:.1f} |")


if __name__ == "__main__":
    main()
