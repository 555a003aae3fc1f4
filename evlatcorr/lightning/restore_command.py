"""The ``restore`` subcommand: trains or fine-tunes a restoration network (EFNet, GEM, REFID).

It owns the command's arguments, the choice of data and module, the run, and the card it prints
(and exports with the weights).
"""

from __future__ import annotations

import argparse
import json
import math
import time
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch
from lightning.pytorch.utilities import rank_zero_only
from torch import Tensor, nn

from evlatcorr.frames import EventFrames
from evlatcorr.gamma import frame_gamma_argument
from evlatcorr.io.outputs import check_writable_folder
from evlatcorr.lightning.arguments import (
    exit_bad_input,
    parse_devices,
    threshold_argument,
    trainer_or_exit,
)
from evlatcorr.lightning.export import export_network
from evlatcorr.lightning.networks import MODELS, build_adapter, checkpoint_name
from evlatcorr.lightning.restoration import CorrectedRestorationModule, RestorationModule
from evlatcorr.lightning.restoration_data import RecordingRestorationData, SimulatedRestorationData

__all__ = ["SUMMARY", "DESCRIPTION", "add_arguments", "check", "run"]

SUMMARY = "train or fine-tune a restoration network (EFNet, GEM, REFID), optionally with a latency corrector"

DESCRIPTION = """Train and fine-tune the restoration networks (EFNet, GEM, REFID) with Lightning.

Official weights cannot be downloaded everywhere, so the networks are trained here on the
simulator's training photographs (disjoint from the benchmark's test photographs): random crops,
horizontal flips, L1 loss, PSNR/SSIM validation on held-out sequences of the training photographs.
The same command runs on one CPU or, with ``--devices N --strategy ddp``, on many GPUs (bf16 mixed
precision by default on CUDA); ``--resume last`` continues from the last checkpoint, and the
trained network is exported as fp16 safetensors shards that the adapters load by name.

Command line::

    python -m evlatcorr.lightning restore --model efnet --max-steps 2000 --out runs/efnet --export checkpoints
    python -m evlatcorr.lightning restore --model efnet --out runs/efnet --resume last     # continue
    python -m evlatcorr.lightning restore --model gem --accelerator gpu --devices 4 --strategy ddp
    python -m evlatcorr.lightning restore --model refid --refid-layout 4 1                 # REFID 4+1 frames
    python -m evlatcorr.lightning restore --model efnet --checkpoint default --finetune spatial   # corrector + EFNet
    python -m evlatcorr.lightning restore --model efnet --checkpoint default --data my_camera.aedat4 --crop 96 128

``--data PATH`` fine-tunes on a recording instead (any format :func:`evlatcorr.io.open_recording`
reads, any sensor size; see
:class:`~evlatcorr.lightning.restoration_data.RecordingRestorationData`): its frames (pairs of
consecutive frames for REFID) as random crops, every ``--holdout``-th held out to validate, the contrast
threshold estimated for the recording (``--threshold auto``). It implies ``--finetune spatial``.
Recordings of real cameras have no sharp frames: the network is then frozen (a note says so) and
only the latency polynomial trains, by the self-supervised objective, whose value on the held-out
frames is printed before and after; the polynomial is saved as ``OUT/curve.pt`` (for
``evlatcorr deblur --correct spatial --curve``). With sharp frames the network trains by L1 on them
too. A path that does not exist or cannot be read, too few usable frames or nothing to train exits
with code 2 and a one-line message.
"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", choices=sorted(MODELS), required=True)
    p.add_argument("--checkpoint", help="initial weights: 'default' (shipped) or a path; default random")
    p.add_argument("--data", type=Path, default=None, metavar="PATH",
                   help="train on this recording instead of simulated photographs: any format evlatcorr.io reads "
                        "(AEDAT4, our HDF5, event_utils HDF5, GEM npz, a HighREV folder), any sensor size. Implies "
                        "--finetune spatial. Without ground truth (sharp frames; real cameras record none) the "
                        "network is frozen and only the latency polynomial trains, by the self-supervised "
                        "objective (Eq. 21); with sharp frames the network trains by L1 on them too")
    p.add_argument("--finetune", choices=("none", "constant", "spatial"), default=None,
                   help="put a corrector in front and fine-tune on delayed events (CorrectedRestorationModule); "
                        "default: none on simulated data, spatial with --data")
    p.add_argument("--freeze-network", action="store_true", help="with --finetune spatial: train the polynomial only")
    p.add_argument("--curve", type=Path, default=None,
                   help="with --finetune spatial: initial latency polynomial (a curve.pt or checkpoint of "
                        "python -m evlatcorr.training); default zero latency")
    p.add_argument("--threshold", type=threshold_argument, default="auto",
                   help="contrast threshold of the correction: a number, or 'auto' (default): with --data one "
                        "threshold estimated for the recording (evlatcorr.restore.recording_threshold, printed), "
                        "on simulated data 0.2")
    p.add_argument("--holdout", type=int, default=10,
                   help="--data: every K-th usable frame (pair for REFID) is held out for validation, at least one "
                        "(0: none)")
    p.add_argument("--max-frames", type=int, default=None, help="--data: read at most this many frames")
    p.add_argument("--frame-gamma", type=frame_gamma_argument, default=1.0, metavar="G",
                   help="--data with --finetune: the corrector reads the frames raised to G (2.2 for frames encoded "
                        "for display: made linear, as EDI needs them), the network as the file has them (default 1)")
    p.add_argument("--events", choices=("ideal", "delayed", "mixed"), default=None,
                   help="simulated data: events of the training samples (default: ideal; delayed with --finetune)")
    p.add_argument("--max-steps", type=int, default=2000)
    p.add_argument("--max-time", default=None, help="stop after this wall time, DD:HH:MM:SS")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--crop", type=int, nargs=2, default=(64, 64), metavar=("H", "W"),
                   help="training crop (random position, mirrored at random); validation uses whole frames")
    p.add_argument("--size", type=int, nargs=2, default=(128, 160), metavar=("H", "W"), help="simulated size")
    p.add_argument("--photographs", nargs="+", default=None, help="training photographs (default: the training "
                   "split, disjoint from the benchmark's test photographs)")
    p.add_argument("--allow-test-photographs", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--sequences", type=int, default=2, help="simulated training sequences per photograph")
    p.add_argument("--num-frames", type=int, default=3, help="frames per simulated sequence")
    p.add_argument("--lr", type=float, default=None,
                   help="network learning rate, default 2e-4 (5e-5 when fine-tuning or with --data)")
    p.add_argument("--warmup-steps", type=int, default=100)
    p.add_argument("--gradient-clip", type=float, default=None, help="clip the gradient norm (REFID: 0.5)")
    p.add_argument("--refid-layout", type=int, nargs=2, default=(4, 1), metavar=("M", "N"),
                   help="REFID sharp frames per exposure and in the gap (4 1 fits 20 ms exposures 25 ms apart)")
    p.add_argument("--val-every", type=int, default=200, help="validate every N training steps")
    p.add_argument("--accelerator", default="auto")
    p.add_argument("--devices", default="1")
    p.add_argument("--strategy", default="auto")
    p.add_argument("--precision", default=None, help="default bf16-mixed on GPU, 32-true on CPU")
    p.add_argument("--num-workers", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/train"))
    p.add_argument("--resume", default=None, help="'last' or a .ckpt path")
    p.add_argument("--export", type=Path, default=None, help="folder for the fp16 safetensors of the network")


def check(args: argparse.Namespace, p: argparse.ArgumentParser) -> None:
    """Refuse argument combinations argparse cannot see (one line on stderr, exit code 2)."""
    if args.max_steps < 1 or args.batch_size < 1 or args.val_every < 1:
        p.error("--max-steps, --batch-size and --val-every must be >= 1")
    if min(args.crop) < 1:
        p.error(f"--crop must be two sizes >= 1, got {list(args.crop)}")
    if args.holdout < 0:
        p.error(f"--holdout must be >= 0 (0: no validation), got {args.holdout}")
    if args.max_frames is not None and args.max_frames < 1:
        p.error(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.lr is not None and not (math.isfinite(args.lr) and args.lr > 0):
        p.error(f"--lr must be a positive number, got {args.lr}")
    if args.gradient_clip is not None and not (math.isfinite(args.gradient_clip) and args.gradient_clip > 0):
        p.error(f"--gradient-clip must be a positive number, got {args.gradient_clip}")
    if args.warmup_steps < 0 or args.num_workers < 0:
        p.error(f"--warmup-steps and --num-workers must be >= 0, got {args.warmup_steps} and {args.num_workers}")
    if args.sequences < 1 or args.num_frames < 1 or min(args.size) < 1:
        p.error(f"--sequences, --num-frames and --size must be >= 1, got {args.sequences}, {args.num_frames} and "
                f"{list(args.size)}")
    if args.refid_layout[0] < 1 or args.refid_layout[1] < 0:
        p.error(f"--refid-layout M N needs M >= 1 and N >= 0, got {list(args.refid_layout)}")
    if args.finetune is None:
        args.finetune = "spatial" if args.data is not None else "none"
    if args.data is not None and (args.photographs or args.events):
        p.error("--photographs and --events choose simulated data; --data trains on the recording's events as "
                "stamped")
    from evlatcorr.simulation.photographs import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN

    unknown = sorted(set(args.photographs or ()) - set(PHOTOGRAPHS_TRAIN) - set(PHOTOGRAPHS_TEST))
    if unknown:
        p.error(f"unknown --photographs {unknown}; the training photographs are {list(PHOTOGRAPHS_TRAIN)}")
    leaked = sorted(set(args.photographs or ()) & set(PHOTOGRAPHS_TEST))
    if leaked and not args.allow_test_photographs:
        p.error(f"{leaked} belong to the benchmark's test split; training on them would inflate its scores")
    if args.freeze_network and args.finetune != "spatial":
        p.error("--freeze-network needs --finetune spatial (otherwise nothing is trained)")
    if args.curve is not None and args.finetune != "spatial":
        p.error("--curve needs --finetune spatial (the polynomial it starts)")
    # last: the folders are made
    for flag, folder in (("--out", args.out), ("--export", args.export)):
        try:
            if folder is not None:
                check_writable_folder(folder)
        except ValueError as exc:
            p.error(f"{flag}: {exc}")


def _precision(args: argparse.Namespace) -> str:
    if args.precision is not None:
        return args.precision
    gpu = args.accelerator in ("gpu", "cuda") or (args.accelerator == "auto" and torch.cuda.is_available())
    return "bf16-mixed" if gpu else "32-true"


@rank_zero_only
def _note(message: str) -> None:
    """A line for the user, printed once (by the first process under DDP)."""
    print(message, flush=True)


def _resume_path(args: argparse.Namespace) -> Path | None:
    if args.resume == "last":
        resume = args.out / "checkpoints" / "last.ckpt"
        if not resume.is_file():
            raise ValueError(f"--resume last, but {resume} does not exist")
        return resume
    if args.resume:
        resume = Path(args.resume)
        if not resume.is_file():
            raise ValueError(f"--resume: checkpoint {resume} not found")
        return resume
    return None


def _refid_targets(args: argparse.Namespace) -> Any:
    if args.model != "refid":
        return None
    from evlatcorr.adapters.refid import refid_output_times

    m, n = args.refid_layout

    def target_times(frames: EventFrames) -> Tensor:  # supervise every REFID output frame
        return refid_output_times(frames, m, n)

    return target_times


def _corrected_module(args: argparse.Namespace, task: str, train_network: bool, threshold: float,
                      adapter: nn.Module | None = None) -> CorrectedRestorationModule:
    if adapter is None:
        adapter = build_adapter(args.model, args.checkpoint, clamp=False, refid_layout=tuple(args.refid_layout))
    return CorrectedRestorationModule(
        adapter, task, corrector=args.finetune, curve=args.curve, train_network=train_network,
        lr=args.lr or 5e-5, warmup_steps=min(args.warmup_steps, args.max_steps - 1), max_steps=args.max_steps,
        threshold=threshold, frame_gamma=args.frame_gamma)


def _simulated_setup(args: argparse.Namespace) -> tuple[L.LightningDataModule, L.LightningModule, dict[str, Any]]:
    """Data and module for training on the simulator's training photographs."""
    task = MODELS[args.model]
    finetune = args.finetune != "none"
    events = args.events or ("delayed" if finetune else "ideal")
    data = SimulatedRestorationData(task, photographs=args.photographs, size=tuple(args.size), crop=tuple(args.crop),
                                    sequences=args.sequences, num_frames=args.num_frames, events=events,
                                    target_times=_refid_targets(args), batch_size=args.batch_size,
                                    num_workers=args.num_workers, steps_per_epoch=min(args.val_every, args.max_steps),
                                    seed=args.seed)
    if finetune:
        threshold = 0.2 if args.threshold == "auto" else float(args.threshold)
        module: L.LightningModule = _corrected_module(args, task, not args.freeze_network, threshold)
    else:
        module = RestorationModule(args.model, args.checkpoint, lr=args.lr or 2e-4,
                                   warmup_steps=min(args.warmup_steps, args.max_steps - 1),
                                   max_steps=args.max_steps, refid_layout=tuple(args.refid_layout))
    info = {"events": events, "truth": True, "network": "trained" if not args.freeze_network else "frozen",
            "data": {"photographs": data.photographs, "size": list(data.size), "crop": list(data.crop),
                     "sequences": data.sequences, "num_frames": data.num_frames, "exposure_us": data.exposure_us,
                     "interval_us": data.interval_us, "latency_us": list(data.latency_us), "seed": args.seed}}
    return data, module, info


def _threshold_device(args: argparse.Namespace) -> str:
    """Where to estimate the threshold: the current GPU when training runs on GPUs, else the CPU."""
    gpu = args.accelerator in ("gpu", "cuda") or (args.accelerator == "auto" and torch.cuda.is_available())
    return "cuda" if gpu and torch.cuda.is_available() else "cpu"


def _read_recording(args: argparse.Namespace, task: str) -> RecordingRestorationData:
    """Read ``--data`` into samples and say what was found (and what was left out, and why)."""
    data = RecordingRestorationData(args.data, task, tuple(args.crop), args.holdout, args.max_frames,
                                    args.batch_size, args.num_workers,
                                    steps_per_epoch=min(args.val_every, args.max_steps), seed=args.seed)
    data.read()
    found = data.summary
    what = "pairs of consecutive frames" if data.pairs else "frames"
    left = [f"{found['left_out_no_events']} without events in the exposure and latency-search window"] \
        if found["left_out_no_events"] else []
    if found["left_out_cut_short"]:
        left.append(f"frame(s) {found['left_out_cut_short']}, whose event window runs past the end of the events")
    _note(f"{args.data}: {found['format']}, (H, W)={tuple(found['sensor_size'])}, {found['frames_read']} frames read; "
          f"{found['train']} {what} to train on (random {args.crop[0]}x{args.crop[1]} crops), {found['val']} held out "
          f"for validation" + (f"; left out: {'; '.join(left)}" if left else ""))
    if not data.has_truth and found["samples_with_truth"]:
        _note(f"only {found['samples_with_truth']} of {found['samples']} samples have {_truth_name(task)}: "
              "they are ignored")
    return data


def _truth_name(task: str) -> str:
    return "sharp frames" if task == "deblur" else "target frames (or sharp frames)"


def _network_role(args: argparse.Namespace, data: RecordingRestorationData, task: str) -> str:
    """``"trained"`` or ``"frozen"``: decided (and refused) before the threshold is estimated."""
    truth = _truth_name(task)
    if args.finetune == "none":
        if not data.has_truth:
            raise ValueError(f"{args.data} has no {truth}, so --finetune none has nothing to train {args.model} on; "
                             "use --finetune spatial (the default with --data) to train the latency polynomial")
        network = "trained"
    else:
        network = "trained" if data.has_truth and not args.freeze_network else "frozen"
        if not data.has_truth and args.finetune == "constant":
            raise ValueError(f"nothing to train: {args.data} has no {truth}, so {args.model} stays frozen, and "
                             "--finetune constant has no parameters (it searches one latency per frame); use "
                             "--finetune spatial")
    if args.export is not None and network == "frozen":
        raise ValueError(f"--export writes the network's weights, but {args.model} stays frozen on {args.data}; "
                         f"the trained latency polynomial is saved as {args.out / 'curve.pt'}")
    if not data.has_truth:
        _note(f"note: {args.data} has no {truth}: {args.model} is frozen (its weights are not changed) and only "
              "the latency polynomial trains, by the self-supervised objective (Eq. 21)")
    elif network == "trained":
        _note(f"{args.data} has {truth}: {args.model} trains by L1 on them" + (
            ", the latency polynomial by the self-supervised objective (Eq. 21)" if args.finetune == "spatial" else ""))
    return network


def _recording_threshold(args: argparse.Namespace, data: RecordingRestorationData) -> float:
    """``--threshold``, or with ``auto`` one threshold estimated for the recording (0.2 when none can be)."""
    from evlatcorr.restore import recording_threshold

    if args.threshold != "auto":
        return float(args.threshold)
    with warnings.catch_warnings():  # the reader's notes on windows were given by the read above
        warnings.simplefilter("ignore")
        data.recording.frame_gamma = args.frame_gamma  # θ from linear frames; the samples were read as they are
        try:
            estimated = recording_threshold(data.recording, device=_threshold_device(args))
        finally:
            data.recording.frame_gamma = 1.0
    if estimated is None:
        _note("contrast threshold: 0.2 (auto: no pair of consecutive frames with events to estimate one)")
        return 0.2
    _note(f"contrast threshold: {float(estimated):.3f} (auto: two-frame consistency of the first frames)")
    return float(estimated)


def _recording_setup(args: argparse.Namespace) -> tuple[L.LightningDataModule, L.LightningModule, dict[str, Any]]:
    """``--data``: samples from the recording; the network trains only where it has ground truth."""
    task = MODELS[args.model]
    adapter = None
    if args.finetune != "none":  # weights that do not load fail before the recording is read
        adapter = build_adapter(args.model, args.checkpoint, clamp=False, refid_layout=tuple(args.refid_layout))
    data = _read_recording(args, task)
    network = _network_role(args, data, task)
    threshold = 0.2 if args.finetune == "none" else _recording_threshold(args, data)
    if args.finetune == "none":
        module: L.LightningModule = RestorationModule(
            args.model, args.checkpoint, lr=args.lr or 5e-5, warmup_steps=min(args.warmup_steps, args.max_steps - 1),
            max_steps=args.max_steps, refid_layout=tuple(args.refid_layout))
    else:
        module = _corrected_module(args, task, network == "trained", threshold, adapter)
    found = data.summary
    info = {"events": "recorded", "truth": data.has_truth, "network": network,
            "threshold": None if args.finetune == "none" else round(threshold, 4), "frame_gamma": args.frame_gamma,
            "data": {"recording": str(args.data), **{k: found[k] for k in ("format", "sensor_size", "frames_read")},
                     "crop": list(data.crop), "train_samples": found["train"], "val_samples": found["val"],
                     "pairs": data.pairs, "holdout": args.holdout, "max_frames": args.max_frames, "seed": args.seed}}
    return data, module, info


def _metric(metrics: dict[str, Any], key: str, digits: int) -> float | None:
    return round(float(metrics[key]), digits) if key in metrics else None


def _trainer(args: argparse.Namespace, truth: bool, has_val: bool) -> L.Trainer:
    """The Trainer: checkpoints the best validation score (PSNR with ground truth, else the objective)."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    if truth:
        monitor, mode = "val/psnr", "max"
    elif has_val:
        monitor, mode = "val/corrector", "min"
    else:
        monitor, mode = None, "min"
    checkpointing = ModelCheckpoint(dirpath=args.out / "checkpoints", save_last=True, monitor=monitor, mode=mode,
                                    save_top_k=1, filename="best-{step}")
    return L.Trainer(max_steps=args.max_steps, max_time=args.max_time, max_epochs=-1,
                     accelerator=args.accelerator, devices=parse_devices(args.devices), strategy=args.strategy,
                     precision=_precision(args), default_root_dir=args.out, callbacks=[checkpointing],
                     gradient_clip_val=args.gradient_clip, limit_val_batches=None if has_val else 0,
                     log_every_n_steps=10, enable_model_summary=False, num_sanity_val_steps=0,
                     inference_mode=False)  # no_grad: metric states of a validation before fit stay trainable


def _card(args: argparse.Namespace, trainer: L.Trainer, info: dict[str, Any], seconds: float,
          before: dict[str, Any], final: dict[str, Any]) -> dict[str, Any]:
    """The run's card: validation metrics, steps, configuration (printed, and exported with the weights)."""
    layout = tuple(args.refid_layout)
    card = {
        "model": args.model, "name": checkpoint_name(args.model, layout), "task": MODELS[args.model],
        "command": args.command_line,
        "steps": int(trainer.global_step), "train_seconds": round(seconds, 1),
        "val_psnr": _metric(final, "val/psnr", 3), "val_ssim": _metric(final, "val/ssim", 4),
        "val_blurry_psnr": _metric(final, "val/blurry_psnr", 3), "events": info["events"], "data": info["data"],
        "world_size": trainer.world_size, "precision": str(trainer.precision),
        "device": torch.cuda.get_device_name() if trainer.strategy.root_device.type == "cuda" else
        f"CPU, {torch.get_num_threads()} threads", "torch": torch.__version__,
    }
    if args.model == "refid":
        card["refid_layout"] = list(layout)
    if args.data is not None:
        card.update(finetune=args.finetune, network=info["network"], threshold=info["threshold"],
                    val_objective_before=_metric(before, "val/corrector", 5),
                    val_objective_after=_metric(final, "val/corrector", 5))
    return card


def _save(args: argparse.Namespace, card: dict[str, Any], module: L.LightningModule, info: dict[str, Any],
          val_samples: int, seconds: float, resumed: bool) -> None:
    """On the first process: the curve (``--data``), the objective before and after, the export, the card."""
    if args.data is not None and args.finetune == "spatial":
        from evlatcorr.spatial import save_curve

        card["curve"] = str(args.out / "curve.pt")
        save_curve(module.latency_model, card["curve"], scenes=[str(args.data)], threshold=info["threshold"],
                   network=args.model, steps=card["steps"])
    if card.get("val_objective_before") is not None:
        print(f"self-supervised objective (Eq. 21) on {val_samples} held-out sample(s): "
              f"{card['val_objective_before']:.5f} before, {card['val_objective_after']:.5f} after "
              f"{card['steps']} steps ({seconds:.1f} s)")
    if args.export is not None:
        export_network(module.adapter, card, args.export, resumed=resumed, from_shipped=args.checkpoint == "default")
    print(json.dumps(card, indent=2))


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Train; returns the card (validation metrics, steps, configuration).

    Bad input (a missing or unreadable recording, too few usable frames, a checkpoint that does not
    fit, nothing to train) prints one line on stderr and exits with code 2, like bad arguments.
    """
    L.seed_everything(args.seed, workers=True)
    try:
        resume = _resume_path(args)
        data, module, info = _recording_setup(args) if args.data is not None else _simulated_setup(args)
    except (ValueError, OSError) as exc:  # RecordingError is a ValueError; FileNotFoundError an OSError
        exit_bad_input(args.error_label, exc)
    has_val = args.data is None or bool(data.val_samples)
    trainer = trainer_or_exit(args.error_label, lambda: _trainer(args, info["truth"], has_val))
    before: dict[str, Any] = {}
    if args.data is not None and has_val:  # the held-out objective of the starting point
        before = trainer.validate(module, data, ckpt_path=resume, verbose=False)[0]
    start = time.perf_counter()
    trainer.fit(module, data, ckpt_path=resume)
    seconds = time.perf_counter() - start
    final = trainer.validate(module, data, verbose=False)[0] if has_val else {}
    if args.data is not None:
        # every rank: it synchronises; with the optimiser and loops, resumable
        trainer.save_checkpoint(args.out / "checkpoints" / "last.ckpt", weights_only=False)
    card = _card(args, trainer, info, seconds, before, final)
    if trainer.is_global_zero:
        _save(args, card, module, info, len(data.val_samples) if args.data is not None else 0, seconds,
              resume is not None)
    return card
