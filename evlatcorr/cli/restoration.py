"""``evlatcorr deblur`` and ``evlatcorr interpolate``: a model on every frame (or pair of frames), with the stamped
events and, with ``--correct``, the corrected ones; PNGs, a side-by-side GIF, a per-frame CSV and, with ``--correct``,
a figure of the latencies over time."""

from __future__ import annotations

import argparse
import itertools
import math
import time
from pathlib import Path
from typing import Any, NamedTuple

import torch

from evlatcorr.cli.common import (
    EXIT_OK,
    FrameWarnings,
    build_corrector,
    frames_per_call,
    latency_row,
    open_input,
    parse_device,
    parse_threshold,
    progress,
    recording_curve,
    skip_warning,
    sloped_spatial,
    threshold_of_recording,
    write_csv,
)
from evlatcorr.cli.latency_figure import write_figure_or_warn

__all__ = ["cmd_deblur", "cmd_interpolate"]

GIF_FRAMES = 200  # frames kept in the side-by-side GIF (each held in memory until it is written)


def cmd_deblur(args: argparse.Namespace) -> int:
    return _restore(args, "deblur")


def cmd_interpolate(args: argparse.Namespace) -> int:
    if args.num < 1:
        raise ValueError(f"--num must be >= 1, got {args.num}")
    return _restore(args, "interpolation")


def _restore(args: argparse.Namespace, task: str) -> int:
    """deblur / interpolate: the model on every frame (or pair), with stamped and with corrected events."""
    from evlatcorr.io.outputs import atomic_dir, check_outputs
    from evlatcorr.restore import has_events

    if args.max_frames is not None and args.max_frames < 1:
        raise ValueError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.fuse_frames < 0:
        raise ValueError(f"--fuse-frames must be 0 or more, got {args.fuse_frames}")
    check_outputs([args.input], folders=[args.outdir], overwrite_folders=args.overwrite)
    device = parse_device(args.device)
    parse_threshold(args.threshold)  # a bad value fails before any reading
    run = _restoration(args, task, device)
    rows, gif = [], []
    frame_warnings = FrameWarnings()
    # frames with events wait to be corrected together: on an accelerator the constant search takes several frames in
    # one pass (evlatcorr.search_batched); a CPU takes them one at a time
    per_call = frames_per_call(device, run.search_mode) if run.corrector is not None else 1
    pending: list[tuple[Any, Any]] = []

    def restore(batch, frames, out, seconds: float, skipped: str = "") -> None:
        t0 = time.perf_counter()
        with frame_warnings.naming([batch]):
            plain, corrected = _restored_outputs(run, frames, out)
        rows.append(latency_row(batch, out, run.theta, seconds + time.perf_counter() - t0, skipped))
        # fused: the frame's own estimate, and where the frame's pair with the next frame agreed best
        paired = run.pairs or run.evidence_pairs
        for key in ("frame_latency_us", "pair_latency_us") if paired else ("frame_latency_us",):
            if out is not None and key in out.meta:
                value = float(out.meta[key][0])
                rows[-1][key] = "" if math.isnan(value) else f"{value:.1f}"
        _save_restored(tmp, task, args.model, batch.meta["frame"], *_as_in_the_file(run, frames.blurry[0], plain,
                                                                                 corrected), gif)

    def restore_pending() -> None:
        if pending:
            t0 = time.perf_counter()
            with frame_warnings.naming([batch for batch, _ in pending]):
                outs = _corrected_frames(run, [frames for _, frames in pending])
            share = (time.perf_counter() - t0) / len(pending)  # each frame's share of the call
            for (batch, frames), out in zip(pending, outs):
                restore(batch, frames, out, share)
            pending.clear()

    with atomic_dir(args.outdir, overwrite=args.overwrite) as tmp:
        stream, limit = _restore_inputs(run.rec, args.max_frames, run.pairs or run.evidence_pairs)
        for batch, frames in progress(stream, limit, task):
            if frames is None and run.evidence_pairs:  # a segment's last frame: corrected alone
                restore_pending()  # not in one call with pairs: a batch is all pairs or all single frames
                frames = batch
            elif frames is None:
                restore_pending()  # the frames before it first: rows and images stay in order
                skip_warning(batch, "no_next_frame", f"{args.model} {task} needs the next frame, and this is the last "
                             "of its segment", f"{args.model} {task} needs the next frame, and this is the last of its "
                             "segment")
                rows.append(latency_row(batch, None, run.theta, 0.0, skipped="no next frame"))
                continue
            frames = _with_targets(frames.to(device), task, args.model, args.num if task == "interpolation" else 0)
            if run.corrector is not None and has_events(frames):
                pending.append((batch, frames))
                if len(pending) >= per_call:
                    restore_pending()
                continue
            restore_pending()
            if run.corrector is not None:
                skip_warning(batch, "not_corrected", "no events in its exposure and search window: not corrected",
                             "no events in the exposure and search window: not corrected")
            restore(batch, frames, None, 0.0, "no events" if run.corrector is not None else "")
        restore_pending()
        frame_warnings.summarise()
        if not rows:
            raise ValueError(f"{args.input}: no frames")
        write_csv(tmp / "frames.csv", rows)
        drawn = None if run.corrector is None else write_figure_or_warn(rows, tmp / "latency.png", args.input.name)
        if gif:
            gif[0].save(tmp / "side_by_side.gif", save_all=True, append_images=gif[1:], duration=200, loop=0)
    count = sum(row["skipped"] != "no next frame" for row in rows)  # the frames (or pairs) restored
    panels = "blurry | uncorrected" + (" | corrected" if run.corrector is not None else "")
    print(f"wrote {count} {'frames' if task == 'deblur' else 'pairs'} to {args.outdir} ({args.model}; "
          f"side_by_side.gif: {panels}{f', first {GIF_FRAMES}' if count > GIF_FRAMES else ''}; frames.csv"
          f"{'; latency.png' if drawn else ''})")
    return EXIT_OK


class _Restoration(NamedTuple):
    """What a deblur / interpolate run applies to every frame (or pair)."""

    rec: Any
    model: torch.nn.Module
    corrector: Any  # an EventLatencyCorrector (streaming with --fuse-frames), or None for --correct none
    theta: float | str
    pairs: bool  # the model reads each frame with the next one
    device: torch.device
    frame_gamma: float = 1.0  # the recording's: its frames are read linear, as EDI and the corrector need them
    linear_model: bool = True  # EDI; a network reads the frames encoded as in the file, as its dataset stored them
    # the corrector reads each frame with the next one for their agreement (evlatcorr.pair_evidence), the model
    # reads the frame alone
    evidence_pairs: bool = False
    # the search the corrector runs ("constant" for spatial mode's constant latencies plus the recording's slope):
    # how many frames one call may take on an accelerator
    search_mode: str = "constant"


def _restoration(args: argparse.Namespace, task: str, device: torch.device) -> _Restoration:
    """The model (weights loaded before any reading), the recording, θ and the corrector."""
    from evlatcorr.restore import build_model, needs_pairs, pair_lead_us, pair_reach_us

    model = build_model(args.model, task, args.ckpt, 0.2, args.num_bins).to(device)  # loads the weights first
    high = args.search_us[1] if args.search_us else None
    rec = open_input(args)
    theta = threshold_of_recording(args, rec, device) if args.model == "edi" or args.correct != "none" else 0.2
    if args.model == "edi":
        model = build_model(args.model, task, None, theta, args.num_bins)
    # spatial mode without a curve: constant mode plus the recording's slope over intensity (as evlatcorr correct)
    sloped = args.correct != "none" and sloped_spatial(args, args.correct, theta)
    mode = "constant" if sloped else args.correct
    corrector = None if args.correct == "none" else build_corrector(args, mode, args.curve, theta)
    config = None if corrector is None else corrector.config
    if mode == "constant" and args.fuse_frames > 0:  # frame by frame: each takes the frames before it
        from evlatcorr.temporal import StreamingLatencyCorrector

        corrector = StreamingLatencyCorrector(corrector, args.fuse_frames, name_frames=False)  # named by frame here
    if sloped:
        fit = recording_curve(args, theta, device)
        if fit is not None and fit.slope_us:
            from evlatcorr.correction import SlopedLatencyCorrector

            corrector = SlopedLatencyCorrector(corrector, fit, config)
    pairs = needs_pairs(args.model, task)
    # a model of single frames: the constant corrector still reads each frame with the next for their agreement
    evidence = not pairs and mode == "constant" and not args.no_pairs
    if pairs or evidence:  # the first frame's events must reach the next exposure's end, plus the latency searched
        rec.after_us = pair_reach_us(rec, high)
    if pairs:  # and REFID reads before the first exposure
        rec.before_us = max(rec.before_us, pair_lead_us(rec))
    return _Restoration(rec, model, corrector, theta, pairs, device, rec.frame_gamma, args.model == "edi", evidence,
                        mode)


def _restore_inputs(rec, max_frames: int | None, pairs: bool):
    """``(batch, frames)`` for the first ``max_frames`` frames, and their number; ``frames`` is the batch, or
    for pairs the batch with the next frame (``None`` for the last frame of a segment)."""
    from evlatcorr.restore import pair_frames

    limit = len(rec) if max_frames is None else min(len(rec), max_frames)
    frames_read = itertools.islice(rec, limit + 1 if pairs else limit)  # a pair reads one frame more
    stream = pair_frames(frames_read) if pairs else ((b, b) for b in frames_read)
    return itertools.islice(stream, limit), limit


def _with_targets(frames, task: str, model: str, num: int):
    """The times to restore: ``num`` between a pair's exposures, mid-exposure for REFID deblurring."""
    from evlatcorr.restore import between_times

    if task == "interpolation":
        return frames.replace(target_times=between_times(frames, num))
    if model == "refid":
        return frames.replace(target_times=((frames.exposure_start + frames.exposure_end) / 2)[:, None])
    return frames


def _corrected_frames(run: _Restoration, frames: list) -> list:
    """The corrector's output for each of ``frames`` (single frames with events, consecutive), from one call."""
    from evlatcorr.frames import EventFrames

    outs = run.corrector(frames[0] if len(frames) == 1 else EventFrames.cat(frames))
    outs = outs.split() if len(frames) > 1 else [outs]
    if run.pairs:  # REFID reads before the exposure: the corrected events start where the stamped ones do
        outs = [out.replace(corrected=out.corrected.since(one.exposure_start - run.rec.before_us))
                for one, out in zip(frames, outs)]
    return outs


def _restored_outputs(run: _Restoration, frames, out):
    """The model's output with the stamped events and with the corrected ones in ``out`` (the stamped ones again
    where there is no ``out``)."""
    from evlatcorr.gamma import linear_frames

    gamma = 1.0 if run.linear_model else 1 / run.frame_gamma  # a network: the frames encoded back as in the file
    if run.evidence_pairs:  # the pair was the corrector's evidence; the model reads the frame alone
        frames, out = (None if f is None else _single(f) for f in (frames, out))
    with torch.no_grad():
        plain = run.model(linear_frames(frames, gamma)).output
        corrected = plain if out is None else run.model(linear_frames(out, gamma)).output
    if run.device.type == "cuda":
        torch.cuda.synchronize(run.device)  # so the row's time is the frame's
    return plain, corrected


def _single(frames):
    """A pair of frames as its first frame alone."""
    return frames.replace(blurry_next=None, exposure_start_next=None, exposure_end_next=None)


def _as_in_the_file(run: _Restoration, blurry, plain, corrected):
    """The blurry frame and the outputs to write, encoded as the file's frames are: the blurry frame and EDI's
    outputs are linear, a network's are as it read them; ``corrected`` is ``None`` without a corrector."""
    from evlatcorr.gamma import display_image

    def output_to_file(image):
        return display_image(image, run.frame_gamma) if run.linear_model and image is not None else image

    corrected = corrected if run.corrector is not None else None
    return display_image(blurry, run.frame_gamma), output_to_file(plain), output_to_file(corrected)


def _save_restored(tmp: Path, task: str, name: str, i: int, blurry, plain, corrected, gif: list) -> None:
    """PNGs of frame ``i``'s outputs (and of the blurry frame when deblurring); panels for the GIF while it has
    room. ``corrected`` is ``None`` without a corrector."""
    from PIL import Image

    from evlatcorr.restore import side_by_side, to_uint8

    outputs = _restored_images(plain, task)
    fixed = _restored_images(corrected if corrected is not None else plain, task)
    if task == "deblur":
        Image.fromarray(to_uint8(blurry)).save(tmp / f"frame_{i:05d}_blurry.png")
    for k, (a, c) in enumerate(zip(outputs, fixed)):
        tag = f"frame_{i:05d}" if task == "deblur" else f"frame_{i:05d}_{k + 1:02d}"
        Image.fromarray(to_uint8(a)).save(tmp / f"{tag}_{name}.png")
        if corrected is not None:
            Image.fromarray(to_uint8(c)).save(tmp / f"{tag}_{name}_corrected.png")
        if len(gif) < GIF_FRAMES:
            panels = [blurry, a] + ([c] if corrected is not None else [])
            gif.append(Image.fromarray(side_by_side(panels)).quantize(colors=256))


def _restored_images(output, task: str) -> list:
    """The images of one sample's output: one ``(C, H, W)`` when deblurring, else one per target time."""
    return [output[0]] if task == "deblur" and output.dim() == 4 else list(output[0])
