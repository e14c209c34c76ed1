"""``autocar train``: train the SBP network on prepared cases with online-rendered pairs."""

from __future__ import annotations

from pathlib import Path
from typing import Optional

import typer

from ..common import console, progress, set_threads, threads_option, user_errors


@user_errors
def train_command(
    cases: Path = typer.Argument(..., help="Folder of prepared cases (autocar prep-ct output)."),
    output: Path = typer.Option(..., "-o", "--output", help="Run folder: checkpoint.pt, model.pt, log.csv, val.json."),
    poses: str = typer.Option("default", "--poses", help="Pose model artefact, 'default' (clinical clusters) or 'uniform' (ablation L7)."),
    steps: int = typer.Option(2000, "--steps", min=1, help="Optimiser steps."),
    lr: float = typer.Option(2e-3, "--lr", help="Peak learning rate (AdamW, warm-up then cosine decay)."),
    accum: int = typer.Option(1, "--accum", min=1, help="Gradient accumulation: pairs per optimiser step."),
    ckpt_every: int = typer.Option(50, "--ckpt-every", min=1, help="Write checkpoint.pt every N steps."),
    val_every: int = typer.Option(250, "--val-every", min=0, help="Validate on held-out cases every N steps (0: never)."),
    val_pairs: int = typer.Option(8, "--val-pairs", min=1, help="Fixed validation pairs."),
    size: int = typer.Option(512, "--size", min=64, help="Detector image size in pixels."),
    misalign_px: float = typer.Option(2.0, "--misalign-px", min=0.0, help="RMS of the 2D TPS misalignment of view B (px)."),
    misalign_3d: float = typer.Option(0.1, "--misalign-3d", min=0.0, max=1.0, help="Probability of a different cardiac phase in view B."),
    mask_noise: float = typer.Option(0.0, "--mask-noise", min=0.0, max=1.0,
                                     help="Probability that a pair's masks get segmenter-style errors (breaks, spurious "
                                          "segments, blobs, widened borders) instead of exact silhouettes."),
    unet_masks: float = typer.Option(0.0, "--unet-masks", min=0.0, max=1.0,
                                     help="Probability that a pair's masks are the 2D segmenter's (U-Net) masks of "
                                          "simulated XA frames of the pair instead of exact silhouettes (of the pairs "
                                          "without --mask-noise errors)."),
    seed: int = typer.Option(0, "--seed", help="Seed of the whole data order and initialisation."),
    threads: int = threads_option(),
    device: str = typer.Option("auto", "--device", help="auto (a CUDA GPU when torch sees one, else the CPU), cpu or cuda."),
    workers: int = typer.Option(0, "--workers", min=0,
                                help="Processes rendering pairs ahead of the network (0: none; use several with a GPU)."),
    refresh_every: int = typer.Option(0, "--refresh-every", min=0, help="Re-scan CASES every N steps for cases added while training (0: never)."),
    resume: bool = typer.Option(False, "--resume", help="Continue from OUTPUT/checkpoint.pt."),
    init: Optional[Path] = typer.Option(None, "--init",
                                        help="Start from these weights (model.pt / checkpoint.pt) instead of random "
                                             "ones; with wider --encoder-widths/--unet-widths the network is widened "
                                             "so it starts computing exactly what the weights compute."),
    skeleton_recall: float = typer.Option(0.0, "--skeleton-recall", min=0.0,
                                          help="Weight of the skeleton-recall loss term (centreline voxels; 0: the paper's Eq. 11 only)."),
    encoder_widths: Optional[str] = typer.Option(None, "--encoder-widths",
                                                 help="2D encoder channels per level, e.g. 24,48,64 "
                                                      "(default 16,32,48; with --resume: the checkpoint's; "
                                                      "with --init: those weights' or wider)."),
    unet_widths: Optional[str] = typer.Option(None, "--unet-widths",
                                              help="Sparse U-Net channels per level, e.g. 32,64,96,128 "
                                                   "(default 16,32,48,64)."),
    unet_blocks: Optional[str] = typer.Option(None, "--unet-blocks",
                                              help="Residual blocks per U-Net level, one per width (default 1,1,1,1)."),
):
    """Train the sparse backward projection network (paper Eq. 11 loss) on pairs rendered online.

    Checkpoints every --ckpt-every steps and on Ctrl-C/SIGTERM; --resume continues with the same data order. For data-parallel training run it under torchrun, e.g. `torchrun --nproc_per_node 2 -m stages.sbp.train CASES RUN --steps 1000` (gloo on CPU, NCCL on GPU, one GPU per process). On a GPU, render pairs in --workers processes so the network does not wait for them; the data order is the same with or without workers.

    Examples:

      autocar train data/train_cases -o out/train_sbp --steps 2000

      autocar train data/train_cases -o out/train_sbp --resume
    """
    set_threads(threads)
    from stages.core.errors import UserError
    from stages.sbp.train import TrainConfig, train

    architecture = {}
    for name, text in (("encoder_widths", encoder_widths), ("unet_widths", unet_widths), ("unet_blocks", unet_blocks)):
        if text is None:
            continue
        try:
            architecture[name] = tuple(int(x) for x in text.split(","))
        except ValueError:
            option = "--" + name.replace("_", "-")
            raise UserError(f"{option} {text!r}: give comma-separated integers, e.g. 16,32,48") from None
    cfg = TrainConfig(steps=steps, lr=lr, accum=accum, ckpt_every=ckpt_every, val_every=val_every, val_pairs=val_pairs,
                      size=size, misalign_px=misalign_px, misalign_3d=misalign_3d, mask_noise=mask_noise, unet_masks=unet_masks,
                      seed=seed, pose_model=poses,
                      threads=threads, device=device, workers=workers, refresh_every=refresh_every,
                      init=str(init) if init else "",
                      skeleton_recall_weight=skeleton_recall, architecture=architecture)
    with progress() as bar:
        task = bar.add_task("training", total=steps)

        def report(step, total, row):
            bar.update(task, completed=step, description=f"loss {row['loss']:.3f} recall {row['candidate_recall']:.2f}")

        summary = train(cases, output, cfg, resume=resume, progress=report)
    state = "interrupted at" if summary["interrupted"] else "finished"
    console.print(f"{state} step {summary['step']}/{summary['steps']} in {summary['seconds']:.0f} s; outputs in {output}")


def register(app: typer.Typer) -> None:
    app.command("train")(train_command)
