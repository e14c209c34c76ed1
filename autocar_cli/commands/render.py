"""``autocar render``: training-pair shards, simulated XA acquisitions and the seeded data products."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from autocar_cli.common import check_choice, console, progress, set_threads, threads_option, user_errors

MODES = ("pairs", "xa", "se", "re", "example")


@user_errors
def render(
    mode: str = typer.Argument(..., metavar="MODE",
                               help="What to render: pairs (training pairs), xa (simulated XA runs), se or re (the "
                                    "evaluation data sets) or example (the bundled example)."),
    cases: Optional[Path] = typer.Option(None, "--cases", help="prepared case (.zarr) or folder of cases (pairs, xa)"),
    poses: Optional[str] = typer.Option(None, "--poses", help="pose-model artefact (default: the built-in model)"),
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="output shard (pairs) or folder (xa, se, re, example)"),
    n: Optional[int] = typer.Option(None, "--n", help="pairs: number of pairs; se/re: number of cases"),
    seed: int = typer.Option(0, "--seed", help="random seed (pairs, xa)"),
    size: Optional[int] = typer.Option(None, "--size", help="detector size in pixels (square)"),
    misalign_px: float = typer.Option(2.0, "--misalign-px", help="pairs: RMS of view b's 2D TPS warp (px)"),
    misalign_3d: float = typer.Option(0.0, "--misalign-3d", help="pairs: probability that view b shows another cardiac phase"),
    frames: Optional[int] = typer.Option(None, "--frames", help="xa/re/example: frames per run"),
    bits: int = typer.Option(8, "--bits", help="xa: stored bits (8–12)"),
    force: bool = typer.Option(False, "--force", help="se/re/example: rebuild even if up to date"),
    threads: int = threads_option(),
):
    """Render two-view training pairs, simulate XA cine runs, or build the example / SE / RE data sets.

    Examples:

      autocar render pairs --cases data/prepared --n 200 -o out/pairs.zarr

      autocar render xa --cases data/prepared/case_0_left.zarr --frames 30 -o out/sim

      autocar render se --n 90 -o data/se

      autocar render example -o examples
    """
    check_choice(mode, MODES, "mode")
    set_threads(threads)
    from stages.errors import UserError
    from stages.render import products
    from stages.render.pairs import pose_model_from

    if mode not in MODES:
        raise UserError(f"unknown render mode {mode!r}; choose one of {', '.join(MODES)}")
    model = pose_model_from(poses)
    if mode in ("pairs", "xa"):
        from stages.prepared_case import find_cases

        if cases is None:
            raise UserError("--cases is required for render pairs/xa")
        paths = find_cases(cases)
        if not paths:
            raise UserError(f"{cases}: no prepared cases (*.zarr of kind autocar.prepared-case)")
    if mode == "pairs":
        from stages.render.pairs import write_pair_shard

        products.check_training_seed(seed)
        count = n or 100
        dest = out or Path("out/pairs.zarr")
        with progress() as bar:
            task = bar.add_task("rendering pairs", total=count)
            write_pair_shard(dest, paths, model, count, seed, size or 512, misalign_px, misalign_3d,
                             progress=lambda: bar.advance(task), inputs=[str(p) for p in paths] + [str(poses or "default")])
        console.print(f"[green]wrote[/] {count} pairs at {size or 512}² → {dest}")
        return
    if mode == "xa":
        from stages.render.acquire import simulate_acquisition

        if bits < 8 or bits > 12:
            raise UserError(f"--bits must be between 8 and 12, got {bits}")
        dest = out or Path("out/xa")
        for i, p in enumerate(paths):
            d = dest if len(paths) == 1 else dest / p.stem
            nf = frames or 42
            with progress() as bar:
                task = bar.add_task(f"simulating {p.stem}", total=2 * nf)
                r = simulate_acquisition(p, model, d, seed + i, size=size or 512, n_frames=nf, bits=bits,
                                         progress=lambda: bar.advance(task))
            console.print(f"[green]wrote[/] {r['run_a']}, {r['run_b']}, {r['truth']} "
                          f"(clusters {r['poses'][0]['cluster']}/{r['poses'][1]['cluster']}, "
                          f"{r['heart_rate_bpm']:.0f} bpm, median key-frame phase error "
                          f"{float(sorted(r['phase_error'])[len(r['phase_error']) // 2]):.3f})")
        return
    if mode == "example":
        given = {k: v for k, v in (("size", size), ("n_frames", frames)) if v}  # else the example's own defaults
        r = products.make_example(out or Path("examples"), force=force, pose_model=model, **given)
    elif mode == "se":
        with progress() as bar:
            count = n or 90
            task = bar.add_task("data-se", total=2 * count)
            r = products.make_se(out or Path("data/se"), n=count, size=size or 512, force=force, pose_model=model,
                                 progress=lambda: bar.advance(task))
    else:
        with progress() as bar:
            count = n or 21
            task = bar.add_task("data-re", total=count)
            r = products.make_re(out or Path("data/re"), n=count, size=size or 512, n_frames=frames or 42,
                                 force=force, pose_model=model, progress=lambda: bar.advance(task))
    console.print(f"{mode}: {'up to date, skipped' if r.get('skipped') else 'written'} → {r['out']}")


def register(app: typer.Typer) -> None:
    app.command("render")(render)
