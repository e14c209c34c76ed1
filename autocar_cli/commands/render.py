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
    out: Optional[Path] = typer.Option(None, "--out", "-o", help="output shard (pairs) or folder (xa, se, re, example; "
                                                                 "new or empty unless --force or --resume)"),
    n: Optional[int] = typer.Option(None, "--n", help="pairs: number of pairs; se/re: number of cases"),
    seed: int = typer.Option(0, "--seed", help="random seed (pairs, xa)"),
    size: Optional[int] = typer.Option(None, "--size", help="detector size in pixels (square)"),
    misalign_px: float = typer.Option(2.0, "--misalign-px", help="pairs: RMS of view b's 2D TPS warp (px)"),
    misalign_3d: float = typer.Option(0.0, "--misalign-3d", help="pairs: probability that view b shows another cardiac phase"),
    frames: Optional[int] = typer.Option(None, "--frames", help="xa/re/example: frames per run"),
    bits: int = typer.Option(8, "--bits", help="xa: stored bits (8–12)"),
    runs: int = typer.Option(2, "--runs", min=2, max=3,
                             help="re: runs per case; 3 adds run_c.dcm from another standard angle (runs A and B "
                                  "stay those of the two-run set), for reconstructions from every run of a study"),
    force: bool = typer.Option(False, "--force", help="xa/se/re/example: first remove what this mode wrote in the "
                                                      "output folder (nothing else), then build it all, even if up to date"),
    resume: bool = typer.Option(False, "--resume", help="xa/se/re/example: continue in a non-empty output folder: keep "
                                                        "the prepared cases (se, re), the finished cases (re, xa), and "
                                                        "make the rest"),
    threads: int = threads_option(),
):
    """Render two-view training pairs, simulate XA cine runs, or build the example / SE / RE data sets.

    An output folder (xa, se, re, example) follows the policy of every autocar output folder: a non-empty one is refused unless --force or --resume; a data set whose manifest.json records the same parameters and version, or runs simulated with the same settings, is up to date: nothing to do (exit 0) with or without --resume; while it is built the folder holds RUNNING (manifest.json, or summary.json for xa, replaces it at the end). A pair shard (pairs) is replaced atomically.

    Examples:

      autocar render pairs --cases data/prepared --n 200 -o out/pairs.zarr

      autocar render xa --cases data/prepared/case_0_left.zarr --frames 30 -o out/sim

      autocar render se --n 90 -o data/se

      autocar render re -o data/re --resume

      autocar render re --runs 3 -o data/re3

      autocar render example -o examples
    """
    check_choice(mode, MODES, "mode")
    set_threads(threads)
    from stages.core.errors import UserError
    from stages.render import products
    from stages.render.pairs import pose_model_from

    if mode not in MODES:
        raise UserError(f"unknown render mode {mode!r}; choose one of {', '.join(MODES)}")
    if force and resume:
        raise UserError("--force and --resume exclude each other: --force starts afresh, --resume reuses")
    model = pose_model_from(poses)
    if runs != 2 and mode != "re":
        raise UserError(f"--runs {runs}: only render re makes more than two runs per case")
    if mode in ("pairs", "xa"):
        from stages.core.prepared_case import find_cases

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
        if bits < 8 or bits > 12:
            raise UserError(f"--bits must be between 8 and 12, got {bits}")
        nf = frames or 42
        with progress() as bar:
            def start(p):
                task = bar.add_task(f"simulating {p.stem}", total=2 * nf)
                return lambda: bar.advance(task)

            r = products.simulate_runs(paths, model, out or Path("out/xa"), seed, size=size or 512, n_frames=nf,
                                       bits=bits, force=force, resume=resume, pose_source=poses, on_start=start)
        for run in r["runs"]:
            d = run["dir"]
            state = "kept (up to date)" if run["reused"] else "[green]wrote[/]"
            facts = (f" (clusters {run['clusters'][0]}/{run['clusters'][1]}, {run['heart_rate_bpm']:.0f} bpm, median "
                     f"key-frame phase error {run['median_phase_error']:.3f})") if "clusters" in run else ""
            console.print(f"{state} {d / 'run_a.dcm'}, {d / 'run_b.dcm'}, {d / 'truth.zarr'}{facts}")
        if r["skipped"]:
            console.print(f"xa: up to date, skipped → {r['out']}")
        return
    if mode == "example":
        given = {k: v for k, v in (("size", size), ("n_frames", frames)) if v}  # else the example's own defaults
        r = products.make_example(out or Path("examples"), force=force, resume=resume, pose_model=model, **given)
    elif mode == "se":
        with progress() as bar:
            count = n or 90
            task = bar.add_task("data-se", total=2 * count)
            r = products.make_se(out or Path("data/se"), n=count, size=size or 512, force=force, resume=resume,
                                 pose_model=model, progress=lambda: bar.advance(task))
    else:
        with progress() as bar:
            count = n or 21
            task = bar.add_task("data-re", total=count)
            r = products.make_re(out or Path("data/re"), n=count, size=size or 512, n_frames=frames or 42,
                                 force=force, resume=resume, pose_model=model, progress=lambda: bar.advance(task),
                                 n_runs=runs)
    console.print(f"{mode}: {'up to date, skipped' if r.get('skipped') else 'written'} → {r['out']}")


def register(app: typer.Typer) -> None:
    app.command("render")(render)
