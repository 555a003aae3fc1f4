"""``evlatcorr correct``: every frame's latency, then the recording's events corrected by it and written, with a
per-frame CSV report and a figure of the latencies over time."""

from __future__ import annotations

import argparse
import contextlib
import itertools
import math
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from evlatcorr.checks import FEW_EVENTS
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
from evlatcorr.temporal import frame_evidence

__all__ = ["cmd_correct"]


def cmd_correct(args: argparse.Namespace) -> int:
    import h5py

    from evlatcorr.io import EventUtilsRecording
    from evlatcorr.io.h5 import atomic_path, write_header
    from evlatcorr.io.outputs import check_hdf5_name, check_outputs

    check_hdf5_name(args.output)
    report = args.report if args.report is not None else args.output.with_suffix(".csv")
    if report.resolve() == args.output.resolve():
        raise ValueError(f"the report {report} would replace the corrected recording {args.output}: name the "
                         "output .h5 or pass --report")
    figure = None if args.no_figure else args.figure if args.figure is not None else report.with_suffix(".png")
    if args.fuse_frames < 0:
        raise ValueError(f"--fuse-frames must be 0 or more, got {args.fuse_frames}")
    check_outputs([args.input], files=[args.output, report, *([figure] if figure is not None else [])])
    device = parse_device(args.device)
    parse_threshold(args.threshold)  # a bad value fails before any reading
    rec = open_input(args)
    theta = threshold_of_recording(args, rec, device)
    # spatial mode without a curve: the constant latencies (fused as constant mode fuses them) plus the recording's
    # slope over intensity, fitted to its first pairs' agreement (_sloped_maps)
    sloped = sloped_spatial(args, args.mode, theta)
    search_mode = "constant" if sloped else args.mode
    corrector = build_corrector(args, search_mode, args.curve, theta)
    with contextlib.ExitStack() as stack:  # both files appear only when both are complete
        report_tmp = stack.enter_context(atomic_path(report))
        h5 = maps = None
        if not isinstance(rec, EventUtilsRecording):  # our HDF5: the frames are written as they are corrected
            h5 = maps = stack.enter_context(h5py.File(stack.enter_context(atomic_path(args.output)), "w"))
            write_header(h5, rec.sensor_size, source=str(args.input), corrected_mode=args.mode)
        elif args.mode == "spatial":  # an event_utils output has no place for the maps: a scratch file holds them,
            # beside the output, on the disk the user chose for it (the system's temp folder may be in memory)
            args.output.parent.mkdir(parents=True, exist_ok=True)
            scratch = Path(stack.enter_context(tempfile.TemporaryDirectory(prefix=f".{args.output.name}.maps-",
                                                                           dir=args.output.parent)))
            maps = stack.enter_context(h5py.File(scratch / "maps.h5", "w"))
        frames = _correct_frames(args, rec, corrector, theta, device, h5, None if sloped else maps, search_mode)
        if not frames.rows:
            raise ValueError(f"{args.input}: no frames")
        latencies = frames.latencies
        if search_mode == "constant" and args.fuse_frames > 0:
            pairs = None if args.no_pairs else _pair_evidence(args, frames, theta, device)
            latencies = _fused(frames.rows, latencies, frames.evidence, args.fuse_frames, args.search_us, pairs)
        if sloped:
            latencies = _sloped_maps(args, frames, latencies, theta, device, maps)
        _write_corrected(args, rec, h5, frames, latencies, maps)
        write_csv(report_tmp, frames.rows)
    rows = frames.rows
    # the figure last: the corrected recording and its report are written whatever becomes of it
    drawn = None if figure is None else write_figure_or_warn(rows, figure, args.input.name)
    skipped = sum(bool(r["skipped"]) for r in rows)
    few = sum(not r["skipped"] and int(r["events_in_window"]) < FEW_EVENTS for r in rows)
    written = [str(p) for p in (args.output, report, drawn) if p is not None]
    print(f"wrote {', '.join(written[:-1])} and {written[-1]} ({len(rows)} frames, median latency "
          f"{np.median([float(r['latency_us']) for r in rows]):.0f} us"
          + (f", {skipped} without events kept the previous latency" if skipped else "")
          + (f", {few} with under {FEW_EVENTS} events in the window: their latency is a guess" if few else "") + ")")
    return EXIT_OK


class _CorrectedFrames(NamedTuple):
    """What ``evlatcorr correct`` keeps of every frame until the events are written: its CSV row, its latency (a
    number: its map, in spatial mode, is written to ``frames/estimated_latency_map`` as it comes, of the output or,
    where the output is not our HDF5, of a scratch file), its exposure and the reader's evidence for fusing. A
    recording of thousands of frames keeps thousands of numbers, not images."""

    rows: list[dict]
    latencies: list[torch.Tensor]
    starts: list[float]
    ends: list[float]
    evidence: list[tuple[Any, Any]]
    extremes: list[float]  # the lowest and highest latency of any frame's map, µs


def _correct_frames(args: argparse.Namespace, rec, corrector, theta, device: torch.device, h5,
                    maps=None, mode: str | None = None) -> _CorrectedFrames:
    """Every frame's latency (``corrector``; a frame without events keeps the previous one), its blurry image appended
    to ``h5``'s ``frames/blurry`` as it comes when ``h5`` is an open file, and in spatial mode its latency map to
    ``maps``'s ``frames/estimated_latency_map`` (an open file: the output or a scratch one). ``mode``: the
    corrector's (default ``args.mode``)."""
    from evlatcorr.frames import EventFrames
    from evlatcorr.restore import has_events

    mode = mode or args.mode
    kept = _CorrectedFrames([], [], [], [], [], [math.inf, -math.inf])
    fused = ("; the latency written is fused with the frames either side (--fuse-frames; frame_latency_us keeps "
             "this one)") if mode == "constant" and args.fuse_frames > 0 else ""
    frame_warnings = FrameWarnings({"fallback": fused, "clipped": fused, "flat": fused, "few_events": fused})
    pending: list[Any] = []  # frames with events not yet corrected, searched in one call (frames_per_call)

    def record(batch, out, seconds: float, skipped: str = "") -> None:
        kept.rows.append(latency_row(batch, out, theta, seconds, skipped=skipped))
        kept.evidence.append(frame_evidence(out)[0][1:] if mode == "constant" and not skipped else (None, None))
        latency = out.latency[0, 0].cpu()
        kept.extremes[:] = [min(kept.extremes[0], float(latency.min())), max(kept.extremes[1], float(latency.max()))]
        if mode == "constant":  # one latency for the whole frame
            kept.latencies.append(latency.reshape(-1)[0].double())
        elif maps is not None:
            _append_frame(maps, "frames/estimated_latency_map", latency[None].float().numpy())
            kept.latencies.append(latency.double().mean())
        else:
            kept.latencies.append(latency)
        kept.starts.append(float(batch.exposure_start))
        kept.ends.append(float(batch.exposure_end))
        if h5 is not None:
            _append_frame(h5, "frames/blurry", batch.blurry[0].cpu().numpy())

    def correct_pending() -> None:
        if pending:
            t0 = time.perf_counter()
            with frame_warnings.naming(pending):
                out = corrector(pending[0] if len(pending) == 1 else EventFrames.cat(pending))
            seconds = (time.perf_counter() - t0) / len(pending)  # each frame's share of the call
            for batch, part in zip(pending, out.split() if len(pending) > 1 else [out]):
                record(batch, part, seconds)
            pending.clear()

    per_call = frames_per_call(device, mode)
    for batch in progress(rec, len(rec), "correct"):
        batch = batch.to(device)
        if has_events(batch):
            pending.append(batch)
            if len(pending) >= per_call:
                correct_pending()
            continue
        correct_pending()  # the frames before it first: it takes the latency of the last of them
        previous = float(kept.latencies[-1].mean()) if kept.latencies else 0.0
        skip_warning(batch, "kept_previous_latency", f"no events in its exposure and search window; its events keep "
                     f"the previous frame's latency ({previous:.0f} us)",
                     "no events in the exposure and search window; the events keep the previous frame's latency")
        h, w = batch.sensor_size
        record(batch, batch.replace(latency=torch.full((1, 1, h, w), previous, dtype=torch.float64, device=device)),
               0.0, skipped="no events")
    correct_pending()
    frame_warnings.summarise()
    return kept


def _append_frame(h5, name: str, image: np.ndarray) -> None:
    """One more frame's ``image`` :math:`(C, H, W)` on the dataset ``name`` :math:`(N, C, H, W)` of an open file (made
    at the first)."""
    if name not in h5:
        h5.create_dataset(name, shape=(0, *image.shape), maxshape=(None, *image.shape), dtype=image.dtype,
                          compression="lzf", chunks=(1, *image.shape))
    images = h5[name]
    images.resize(len(images) + 1, axis=0)
    images[-1] = image


def _write_corrected(args: argparse.Namespace, rec, h5, frames: _CorrectedFrames,
                     latencies: list[torch.Tensor], maps=None) -> None:
    """The corrected events (each frame's events by ``latencies``, or in spatial mode by its map on ``maps``): into
    ``h5`` (our format, with the frames' exposures and latencies), or chunk by chunk into an event_utils file like
    the input."""
    from evlatcorr.io import EventWriter, write_event_utils

    on_disk = None if maps is None else maps.get("frames/estimated_latency_map")
    starts, ends = frames.starts, frames.ends
    corrected = _corrected_stream(rec, np.array(starts), latencies, on_disk, frames.extremes)
    if h5 is None:
        first = next((chunk for chunk in corrected if len(chunk)), None)
        if first is None:
            raise ValueError(f"{args.input}: no events")
        write_event_utils(args.output, itertools.chain([first], corrected), like=rec, sensor_size=rec.sensor_size)
        return
    writer = EventWriter(h5, "events")
    for chunk in corrected:
        writer.append(chunk["x"], chunk["y"], chunk["t"], chunk["p"])
    h5["frames/exposure_start"] = np.array(starts)
    h5["frames/exposure_end"] = np.array(ends)
    h5["frames/estimated_latency"] = np.array([float(m.mean()) for m in latencies], dtype=np.float32)


def _pair_evidence(args: argparse.Namespace, frames: _CorrectedFrames, theta, device: torch.device
                   ) -> list[torch.Tensor | None] | None:
    """Each frame's agreement with the next one over its candidates (:func:`evlatcorr.pair_evidence.pair_log_odds`),
    from a second pass over the recording whose windows reach the next exposure; None for a frame without one (the
    last of a segment, a frame without the reader's evidence, a pair that tells nothing). None in all where θ is
    estimated per frame: no pair of consecutive frames has events. The rows get ``pair_latency_us``: where the
    pair agrees best, empty where it tells nothing."""
    from evlatcorr.pair_evidence import pair_log_odds
    from evlatcorr.restore import pair_frames, pair_reach_us

    for row in frames.rows:
        row["pair_latency_us"] = ""
    if isinstance(theta, str):  # no pair of consecutive frames with events (threshold_of_recording said so)
        return None
    rec = open_input(args)
    rec.after_us = pair_reach_us(rec, args.search_us[1] if args.search_us else None)
    out: list[torch.Tensor | None] = []
    with warnings.catch_warnings():  # what the reader says of a frame's window, the main pass has said
        warnings.simplefilter("ignore")
        for k, (_, pair) in enumerate(progress(pair_frames(rec), len(rec), "pairs")):
            candidates, log_p = frames.evidence[k] if k < len(frames.evidence) else (None, None)
            if pair is None or log_p is None or frames.rows[k]["skipped"]:
                out.append(None)
                continue
            log_odds = pair_log_odds(pair.to(device), float(theta), candidates)
            out.append(log_odds)
            if log_odds is not None:
                frames.rows[k]["pair_latency_us"] = f"{float(candidates[log_odds.argmax()]):.1f}"
    return out + [None] * (len(frames.rows) - len(out))


def _fused(rows: list[dict], latencies: list[torch.Tensor], evidence: list[tuple[Any, Any]],
           frames: int, search_range: list[float] | None = None,
           pairs: list[torch.Tensor | None] | None = None) -> list[torch.Tensor]:
    """Each frame's constant latency fused with its neighbours' evidence (:func:`evlatcorr.temporal.fuse_latencies`)
    and, where given, each frame's agreement with the next (``pairs``), kept inside ``search_range`` where one is
    given; a frame without events keeps the fused latency before it. The rows get ``frame_latency_us`` (the frame's
    own estimate) and the fused ``latency_us``."""
    from evlatcorr.temporal import fuse_latencies

    own = torch.tensor([float(m.mean()) for m in latencies], dtype=torch.float64)
    fused = fuse_latencies(own, [c for c, _ in evidence], [p for _, p in evidence], frames, frames,
                           pair_log_odds=pairs)
    if search_range:
        fused = fused.clamp(*search_range)
    for k, row in enumerate(rows):
        if row["skipped"]:
            fused[k] = fused[k - 1] if k else 0.0
        row["frame_latency_us"] = row["latency_us"]
        row["latency_us"] = row["latency_min_us"] = row["latency_max_us"] = f"{float(fused[k]):.1f}"
    return [torch.full_like(m, float(v)) for m, v in zip(latencies, fused)]


def _sloped_maps(args: argparse.Namespace, frames: _CorrectedFrames, latencies: list[torch.Tensor], theta,
                 device: torch.device, maps) -> list[torch.Tensor]:
    """Spatial mode without a curve: one curve ``ψ(L) = a + b · f(L)`` for the recording, fitted to the agreement of
    its first pairs (:func:`~evlatcorr.cli.common.recording_curve`), and each frame's map its constant latency
    (``latencies``, fused) plus the curve's departure from its single latency at the frame's intensities, held inside
    the search range. The maps go to ``maps``'s ``frames/estimated_latency_map``, the rows get
    their mean, lowest and highest latency; returns each frame's mean. Without a slope every map is one latency."""
    fit = recording_curve(args, theta, device)
    frames.extremes[:] = [math.inf, -math.inf]
    out = []
    for k, (batch, row) in enumerate(zip(open_input(args), frames.rows)):
        h, w = batch.sensor_size
        base = float(latencies[k].mean())
        latency = torch.full((1, h, w), base, dtype=torch.float64)
        if fit is not None and fit.slope_us:
            low, high = args.search_us or (0.0, float(batch.exposure_end - batch.exposure_start))
            departure = fit.departure(batch.blurry.to(device))[0].double().cpu()
            latency = (latency + departure).clamp(min(low, base), max(high, base))
        _append_frame(maps, "frames/estimated_latency_map", latency.float().numpy())
        lowest, highest = float(latency.min()), float(latency.max())
        frames.extremes[:] = [min(frames.extremes[0], lowest), max(frames.extremes[1], highest)]
        row["latency_us"] = f"{float(latency.mean()):.1f}"
        row["latency_min_us"], row["latency_max_us"] = f"{lowest:.1f}", f"{highest:.1f}"
        out.append(latency.mean())
    return out


def _corrected_stream(rec, starts: np.ndarray, latencies: list[torch.Tensor], on_disk=None,
                      extremes: list[float] | None = None):
    """Corrected events in time order, chunk by chunk.

    Each event takes the latency of the frame whose interval ``[start_i, start_{i+1})`` holds its
    stamp (at its pixel): ``latencies`` (one per frame, or maps), or the maps :math:`(F, 1, H, W)` of the dataset
    ``on_disk``, read a chunk's frames at a time (``extremes``: their lowest and highest latency). Shifted events are
    held back until no later chunk can precede them.
    """
    maps = torch.stack(latencies).numpy()  # (F,): one latency per frame, or (F, H, W) maps
    low, high = (float(maps.min()), float(maps.max())) if on_disk is None else extremes
    hold_back = high - min(0.0, low) + 1.0
    width = rec.sensor_size[1]
    pending: list[np.ndarray] = []
    for chunk in rec.iter_event_chunks():
        if not len(chunk):
            continue
        frame = np.clip(np.searchsorted(starts, chunk["t"], side="right") - 1, 0, len(starts) - 1)
        shifted = chunk.copy()
        if on_disk is not None:  # the maps of the frames this chunk spans
            needed, frame = np.unique(frame, return_inverse=True)
            block = on_disk[needed.tolist()].reshape(len(needed), -1)
            shifted["t"] = chunk["t"] - block[frame, chunk["y"].astype(np.int64) * width + chunk["x"].astype(np.int64)]
        elif maps.ndim == 1:
            shifted["t"] = chunk["t"] - maps[frame]
        else:
            shifted["t"] = chunk["t"] - maps.reshape(len(starts), -1)[frame, chunk["y"].astype(np.int64) * width
                                                                      + chunk["x"].astype(np.int64)]
        pending.append(shifted)
        merged = np.concatenate(pending)
        merged = merged[np.argsort(merged["t"], kind="stable")]
        safe = float(chunk["t"][-1]) - hold_back
        cut = int(np.searchsorted(merged["t"], safe, side="left"))
        if cut:
            yield merged[:cut]
        pending = [merged[cut:]]
    if pending and len(pending[0]):
        yield pending[0]
