"""The ``latency`` subcommand: trains the latency polynomial self-supervised, on simulated scenes or a recording."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import lightning as L

from evlatcorr.frames import EventFrames
from evlatcorr.gamma import frame_gamma_argument
from evlatcorr.io.outputs import check_writable_folder
from evlatcorr.lightning.arguments import (
    MIN_FRAME_SIZE,
    exit_bad_input,
    parse_devices,
    threshold_argument,
    trainer_or_exit,
)
from evlatcorr.lightning.data import EventFramesDataModule
from evlatcorr.lightning.latency import LatencyCorrectionModule
from evlatcorr.lightning.latency_data import recording_training_frames, simulated_training_frames
from evlatcorr.spatial import save_curve

__all__ = ["SUMMARY", "DESCRIPTION", "add_arguments", "check", "run"]

#: --val-every's default with --data
DEFAULT_VAL_EVERY = 5

SUMMARY = "train the latency polynomial self-supervised (no ground truth)"

DESCRIPTION = """Self-supervised training of the latency polynomial with Lightning (paper Sec. 3.4).

No ground truth is used: each step finds the frame's constant latency ``l_const`` by the one-pass
search and minimises Eq. (21) through the latency-differentiable EDI. The same command runs on one
CPU or on many GPUs (``--devices N --strategy ddp``).

Command line (simulated training scenes, a checkpoint and the curve under ``--out``)::

    python -m evlatcorr.lightning latency --epochs 5 --out runs/curve
    python -m evlatcorr.lightning latency --devices 2 --strategy ddp --accelerator cpu --epochs 1 --size 32 40
    python -m evlatcorr.lightning latency --data my_camera.aedat4 --crop 96 128 --out runs/my_curve

With ``--data`` the frames of any recording ``evlatcorr.io`` reads are the training data (no ground
truth needed): frames with events, cut into ``--crop`` tiles, every ``--val-every``-th frame held out
for validation, and the recording's contrast threshold estimated (``--threshold auto``, two-frame
consistency) unless given.
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    from evlatcorr.simulate import PHOTOGRAPHS_TRAIN

    p.add_argument("--scenes", nargs="+", default=list(PHOTOGRAPHS_TRAIN),
                   help="simulated training photographs (default: the training split, disjoint from the benchmark's)")
    p.add_argument("--size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"),
                   help="simulated frames' size (default: 96 128)")
    p.add_argument("--epochs", type=int, default=5, help="training epochs (default: 5)")
    p.add_argument("--constant-epochs", type=int, default=2,
                   help="epochs at the full learning rate before it decays linearly towards 0 (default: 2)")
    p.add_argument("--order", type=int, default=5, help="order K of the latency polynomial (default: 5)")
    p.add_argument("--lr", type=float, default=0.02, help="Adam learning rate (default: 0.02)")
    p.add_argument("--num-bins", type=int, default=100, help="EDI sub-intervals per exposure (default: 100)")
    p.add_argument("--accelerator", default="auto", help="Lightning's accelerator: cpu, gpu or auto (default)")
    p.add_argument("--devices", default="1", help="devices (processes) to train on (default: 1)")
    p.add_argument("--strategy", default="auto", help="Lightning's strategy, e.g. ddp with --devices N (default: "
                                                     "auto)")
    p.add_argument("--seed", type=int, default=0, help="seed of the simulated scenes and the training (default: 0)")
    p.add_argument("--out", type=Path, default=Path("runs/latency_curve"),
                   help="folder for last.ckpt and curve.pt (default: runs/latency_curve)")
    p.add_argument("--data", type=Path, help="train on this recording (any format evlatcorr.io reads) instead of "
                                             "simulated scenes")
    p.add_argument("--crop", type=int, nargs=2, metavar=("H", "W"), help="--data: tiles of this size (default: "
                                                                          "whole frames)")
    p.add_argument("--threshold", type=threshold_argument, default=None,
                   help="--data: contrast threshold, or 'auto' (default): one θ for the recording (simulated scenes "
                        "have theirs)")
    p.add_argument("--val-every", type=int, default=None,
                   help=f"--data: every N-th frame is held out (0: none; default {DEFAULT_VAL_EVERY})")
    p.add_argument("--frame-gamma", type=frame_gamma_argument, default=None, metavar="G",
                   help="--data: raise the frames to G as they are read (default 1; 2.2 for frames encoded for "
                        "display), as the curve will read them (evlatcorr --frame-gamma)")
    p.add_argument("--max-steps", type=int, default=-1, help="stop after this many steps (default: --epochs only)")
    p.add_argument("--allow-test-photographs", action="store_true", help=argparse.SUPPRESS)


def check(args: argparse.Namespace, parser: argparse.ArgumentParser) -> None:
    """Refuse what would fail later with a traceback, or train nothing and save a curve anyway (one line, exit 2)."""
    from evlatcorr.simulation.photographs import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN

    if args.epochs < 1 or args.max_steps == 0 or args.max_steps < -1:
        parser.error(f"--epochs must be >= 1 and --max-steps >= 1 (or -1: --epochs only), got {args.epochs} and "
                     f"{args.max_steps}: nothing would be trained")
    if args.order < 0 or args.constant_epochs < 0 or args.num_bins < 2:
        parser.error(f"--order and --constant-epochs must be >= 0 and --num-bins >= 2, got {args.order}, "
                     f"{args.constant_epochs} and {args.num_bins}")
    if not (math.isfinite(args.lr) and args.lr > 0):
        parser.error(f"--lr must be a positive number, got {args.lr}")
    given = {"--crop": args.crop, "--threshold": args.threshold, "--val-every": args.val_every,
             "--frame-gamma": args.frame_gamma}
    data_only = [flag for flag, value in given.items() if value is not None]
    if args.data is None and data_only:
        verb = "applies" if len(data_only) == 1 else "apply"
        parser.error(f"{', '.join(data_only)} {verb} to --data (a recording); simulated scenes take --size and "
                     "--scenes")
    if args.data is None:
        unknown = sorted(set(args.scenes) - set(PHOTOGRAPHS_TRAIN) - set(PHOTOGRAPHS_TEST))
        if unknown:
            parser.error(f"unknown --scenes {unknown}; the training photographs are {list(PHOTOGRAPHS_TRAIN)}")
        leaked = sorted(set(args.scenes) & set(PHOTOGRAPHS_TEST))
        if leaked and not args.allow_test_photographs:  # as restore: run.py's spatial rows read this curve
            parser.error(f"{leaked} belong to the benchmark's test split; training on them would inflate its scores")
        if min(args.size) < MIN_FRAME_SIZE:
            parser.error(f"--size must be at least {MIN_FRAME_SIZE} {MIN_FRAME_SIZE}, got {list(args.size)}")
    if args.crop is not None and min(args.crop) < MIN_FRAME_SIZE:
        parser.error(f"--crop must be at least {MIN_FRAME_SIZE} {MIN_FRAME_SIZE}, got {list(args.crop)}")
    if args.val_every is not None and args.val_every < 0:
        parser.error(f"--val-every must be >= 0 (0: no validation), got {args.val_every}")
    try:
        check_writable_folder(args.out)
    except ValueError as exc:
        parser.error(f"--out: {exc}")
    args.threshold = "auto" if args.threshold is None else args.threshold
    args.val_every = DEFAULT_VAL_EVERY if args.val_every is None else args.val_every
    args.frame_gamma = 1.0 if args.frame_gamma is None else args.frame_gamma


def run(args: argparse.Namespace) -> None:
    """Train and save ``OUT/last.ckpt`` and ``OUT/curve.pt`` (the curve ``evlatcorr deblur --curve`` loads)."""
    L.seed_everything(args.seed, workers=True)
    val: list[EventFrames] = []
    # the Trainer first: a setting Lightning refuses fails before any frame is made or read
    trainer = trainer_or_exit(args.error_label, lambda: L.Trainer(
        max_epochs=args.epochs, max_steps=args.max_steps, accelerator=args.accelerator,
        devices=parse_devices(args.devices), strategy=args.strategy, default_root_dir=args.out, log_every_n_steps=1,
        enable_model_summary=False))
    theta = 0.2
    if args.data is not None:
        try:
            frames, val, theta = recording_training_frames(args.data, tuple(args.crop) if args.crop else None,
                                                           args.threshold, val_every=args.val_every,
                                                           frame_gamma=args.frame_gamma)
        except (ValueError, OSError) as exc:  # bad input: one line and exit code 2, as the evlatcorr command
            exit_bad_input(args.error_label, exc)
        print(f"{args.data}: {len(frames)} training and {len(val)} validation samples, threshold {theta:.3f}")
    else:
        frames = simulated_training_frames(args.scenes, tuple(args.size), args.seed)
    if not val:  # no held-out frames (simulated scenes, --val-every 0): no validation loop, where Lightning would
        trainer.limit_val_batches = 0  # otherwise run an empty one and warn "Total length of DataLoader ... is zero"
    module = LatencyCorrectionModule(order=args.order, lr=args.lr, num_bins=args.num_bins, threshold=theta,
                                     constant_epochs=args.constant_epochs,
                                     decay_epochs=max(0, args.epochs - args.constant_epochs))
    trainer.fit(module, EventFramesDataModule(frames, val or None, seed=args.seed))
    args.out.mkdir(parents=True, exist_ok=True)
    trainer.save_checkpoint(args.out / "last.ckpt", weights_only=False)  # every rank: it synchronises; resumable
    if trainer.is_global_zero:
        save_curve(module.latency_model, args.out / "curve.pt", world_size=trainer.world_size,
                   scenes=[str(args.data)] if args.data is not None else list(args.scenes), threshold=theta)
        print(f"world_size={trainer.world_size} coefficients={module.latency_model.coefficients.tolist()} "
              f"saved {args.out / 'curve.pt'}")
