"""The ``evlatcorr`` command line: correct, deblur, interpolate, simulate and inspect event recordings.

Exit codes: 0 success; 2 bad input (unreadable or unsupported file, bad option, unknown or absent device,
an output that cannot be written or would replace an input); 130 / 143 interrupted (SIGINT / SIGTERM);
1 other errors. A run that fails or is interrupted leaves no output behind and never touches its input.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import itertools
import math
import re
import signal
import sys
import tempfile
import time
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch

from evlatcorr.restore import INTERPOLATION_MODELS, MODELS, search_reach_us
from evlatcorr.sample_warnings import SampleWarning
from evlatcorr.temporal import DEFAULT_FUSED_FRAMES, frame_evidence

__all__ = ["main"]

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT = 0, 1, 2
GIF_FRAMES = 200  # frames kept in the side-by-side GIF (each held in memory until it is written)


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="evlatcorr",
        description="Event-camera latency correction for event-guided deblurring and frame interpolation.",
        epilog="Formats read: AEDAT4 (DAVIS), evlatcorr HDF5, event_utils HDF5, GEM npz pairs, HighREV video folders. "
               "Times are microseconds.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    c = sub.add_parser("correct", help="estimate latency per frame and write corrected events + a CSV report",
                       description="Estimate the latency of every frame, remove it from the events and write them "
                                   "(event_utils input stays event_utils, anything else becomes evlatcorr HDF5), "
                                   "with a per-frame CSV report next to OUT.")
    c.add_argument("input", type=Path, help="recording to correct")
    c.add_argument("output", type=Path, help="corrected recording to write (.h5)")
    c.add_argument("--report", type=Path, help="per-frame CSV report (default: OUT with the suffix .csv)")
    c.add_argument("--mode", choices=("constant", "spatial"), default="constant")
    c.add_argument("--curve", type=Path, help="trained latency curve checkpoint (mode spatial)")
    c.add_argument("--fuse-frames", type=int, default=DEFAULT_FUSED_FRAMES, metavar="N",
                   help="constant mode: each frame's latency from the learned reader's evidence of N frames either "
                        f"side too (a recording's latency changes slowly; default {DEFAULT_FUSED_FRAMES}, 0: each "
                        "frame alone), 0 where that evidence keeps no latency likely; the report keeps each frame's "
                        "own estimate as frame_latency_us")
    _common(c)

    d = sub.add_parser("deblur", help="deblur every frame with EDI or a network; PNGs, a side-by-side GIF, a CSV",
                       description="Deblur every frame with --model and write into OUTDIR: PNGs per frame (blurry, "
                                   "the model's output with the stamped events and, with --correct, with the "
                                   "corrected events), side_by_side.gif (blurry | uncorrected | corrected) and "
                                   "frames.csv (latency, threshold, confidence, the learned reader's spread, "
                                   "events, time per frame). OUTDIR is "
                                   "written under a temporary name and appears only when every frame is done.")
    d.add_argument("input", type=Path)
    d.add_argument("outdir", type=Path)
    _restore_options(d, MODELS)

    i = sub.add_parser("interpolate", help="frames between exposures with EDI or REFID; PNGs, a GIF, a CSV",
                       description="Interpolate --num frames evenly between each pair of consecutive exposures "
                                   "and write them into OUTDIR as PNGs (with the stamped and, with --correct, the "
                                   "corrected events), side_by_side.gif and frames.csv (one row per pair).")
    i.add_argument("input", type=Path)
    i.add_argument("outdir", type=Path)
    i.add_argument("--num", type=int, default=1, help="frames between two exposures (default: 1)")
    _restore_options(i, INTERPOLATION_MODELS)

    s = sub.add_parser("simulate", help="write a simulated recording with known latency (evlatcorr HDF5)")
    s.add_argument("output", type=Path)
    s.add_argument("--image", default="astronaut", help="scikit-image photograph (default: astronaut)")
    s.add_argument("--frames", type=int, default=4)
    s.add_argument("--size", type=int, nargs=2, default=(260, 346), metavar=("H", "W"))
    s.add_argument("--exposure-us", type=float, default=20000.0)
    s.add_argument("--interval-us", type=float, default=25000.0, help="time between exposure starts")
    s.add_argument("--latency-model", choices=("none", "constant", "intensity"), default="constant")
    s.add_argument("--latency-us", type=float, default=4000.0, help="constant latency")
    s.add_argument("--seed", type=int, default=0)

    n = sub.add_parser("info", help="summarise a recording")
    n.add_argument("input", type=Path)
    n.add_argument("--exposure-us", type=float, help="exposure for files that only stamp frame times")
    return p


def _restore_options(p: argparse.ArgumentParser, models: tuple[str, ...]) -> None:
    p.add_argument("--model", choices=models, default="edi", help="restoration model (default: edi)")
    p.add_argument("--ckpt", type=Path, help="network weights (default: the shipped ones)")
    p.add_argument("--correct", nargs="?", const="constant", default="none", choices=("none", "constant", "spatial"),
                   help="latency correction (default: none; --correct alone: constant)")
    p.add_argument("--curve", type=Path, help="trained latency curve checkpoint (--correct spatial)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTDIR")
    p.add_argument("--max-frames", type=int, help="only the first N frames (default: all)")
    p.add_argument("--fuse-frames", type=int, default=DEFAULT_FUSED_FRAMES, metavar="N",
                   help="--correct constant: each frame's latency from the learned reader's evidence of the N frames "
                        f"before it too (frame by frame, as a stream; default {DEFAULT_FUSED_FRAMES}, 0: each frame "
                        "alone), 0 where that evidence keeps no latency likely; frames.csv keeps each frame's own "
                        "estimate as frame_latency_us")
    _common(p)


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--threshold", default="auto",
                   help="contrast threshold θ, or 'auto' (default): one θ for the recording, the one that makes "
                        "consecutive frames' EDI reconstructions agree best (per frame when it has one frame)")
    p.add_argument("--num-bins", type=int, default=500, help="EDI sub-intervals per exposure (default: 500)")
    p.add_argument("--search-us", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="the range the latency lies in, us: bounds the estimate, while the learned reader still "
                        "reads 0 to the exposure time as trained (default: 0 to the exposure time)")
    p.add_argument("--exposure-us", type=float, help="exposure for files that only stamp frame times")


def _threshold(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--threshold must be a number or 'auto', got {text!r}") from None
    if value <= 0:
        raise ValueError(f"--threshold must be positive, got {value}")
    return value


def _open(args: argparse.Namespace, after_us: float | None = None):
    from evlatcorr.io import EventUtilsRecording, open_recording

    rec = open_recording(args.input, after_us=after_us)
    if isinstance(rec, EventUtilsRecording) and getattr(args, "exposure_us", None) is not None:
        rec.exposure_us = args.exposure_us
    return rec


def _device(text: str) -> torch.device:
    """``--device``, refused (exit 2) when unknown or not on this machine."""
    try:
        device = torch.device(text)
    except RuntimeError:
        raise ValueError(f"--device: unknown device {text!r}; use cpu, cuda or cuda:N") from None
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"--device {text}: CUDA is not available on this machine; use --device cpu")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"--device {text}: this machine has {torch.cuda.device_count()} CUDA device(s)")
    elif device.type == "mps" and not torch.backends.mps.is_available():
        raise ValueError(f"--device {text}: MPS is not available on this machine; use --device cpu")
    elif device.type not in ("cpu", "cuda", "mps"):
        raise ValueError(f"--device: unsupported device {text!r}; use cpu, cuda or cuda:N")
    return device


def _recording_threshold(args: argparse.Namespace, rec, device: torch.device) -> float | str:
    """``--threshold``: a number, or for ``auto`` one θ for the recording (two-frame consistency)."""
    from evlatcorr.restore import recording_threshold

    theta = _threshold(args.threshold)
    if theta != "auto":
        return theta
    # what the search says of a frame here, the main pass says again of every frame, by its number; what the reader
    # says of a frame read here (with the wider window of a pair) is said to come from here; of the file, as it is
    with _reworded(lambda message: None if isinstance(message, SampleWarning)
                   else f"estimating the contrast threshold from the first frames: {message}"
                   if re.search(r"\bframe \d+:", str(message)) else str(message)):
        found = recording_threshold(rec, tuple(args.search_us) if args.search_us else None, device=device)
    if found is None:
        warnings.warn("no pair of consecutive frames with events: the contrast threshold is estimated per frame",
                      stacklevel=2)
        return "auto"
    print(f"contrast threshold: {found:.3f} (auto: two-frame consistency of the first frames)", file=sys.stderr)
    return found


def _corrector(args: argparse.Namespace, mode: str = "constant", curve: Path | None = None,
               theta: float | str = 0.2):
    from evlatcorr import EventLatencyCorrector

    kwargs = {}
    if curve is not None:
        if mode != "spatial":
            raise ValueError("--curve needs the spatial mode")
        if not curve.is_file():
            raise ValueError(f"--curve {curve}: no such file")
        kwargs["curve"] = str(curve)
    search = tuple(args.search_us) if args.search_us else None
    if curve is None:
        return EventLatencyCorrector(mode=mode, threshold=theta, num_bins=args.num_bins, search_range=search)
    try:
        return EventLatencyCorrector(mode=mode, threshold=theta, num_bins=args.num_bins, search_range=search,
                                     **kwargs)
    except Exception as exc:  # noqa: BLE001 - whatever the reader raised, the file is not a curve checkpoint
        raise ValueError(f"--curve {curve}: not a latency curve checkpoint ({type(exc).__name__}: {exc})") from None


def _progress(iterable, total: int | None, desc: str):
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="frame", file=sys.stderr, disable=not sys.stderr.isatty())


@contextlib.contextmanager
def _reworded(reword: Callable[[Warning], str | None]):
    """The warnings raised inside, warned again as ``reword`` words them (each a :class:`Warning`; None: not
    again)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        yield
    for w in caught:
        text = reword(w.message)
        if text is not None:
            warnings.warn(text, UserWarning if issubclass(w.category, SampleWarning) else w.category, stacklevel=3)


class _FrameWarnings:
    """The library's warnings about samples of a call, said of the frames they are (``frame 12``, not ``sample 0``):
    the first of each kind in full as it happens, and at the end one line for the other frames it happened to."""

    def __init__(self) -> None:
        self.later: dict[str, tuple[str, list[int]]] = {}

    def naming(self, batches: list):
        """A context in which the warnings of one call on ``batches`` (in the call's sample order) are reworded."""
        numbers = [int(batch.meta["frame"]) for batch in batches]

        def reword(message: Warning) -> str | None:
            if not isinstance(message, SampleWarning):
                return str(message)
            if message.kind not in self.later:
                self.later[message.kind] = (message.summary, [])
                return _option_names(message.naming([f"frame {n}" for n in numbers]))
            self.later[message.kind][1].extend(numbers[i] for i in message.samples)
            return None

        return _reworded(reword)

    def summarise(self) -> None:
        """One warning per kind for the frames after its first."""
        for summary, numbers in self.later.values():
            if numbers:
                warnings.warn(f"{len(numbers)} more frame{'s' if len(numbers) > 1 else ''} "
                              f"({_number_ranges(numbers)}): {_option_names(summary)}", stacklevel=2)
        self.later.clear()


def _option_names(text: str) -> str:
    """The library's words for a setting in the command line's: ``search_range`` is ``--search-us`` here."""
    return text.replace("search_range ", "--search-us ")


def _number_ranges(numbers: list[int]) -> str:
    """Sorted whole numbers as runs: ``[1, 2, 3, 7]`` -> ``"1-3, 7"``."""
    runs: list[list[int]] = []
    for n in sorted(set(numbers)):
        if runs and n == runs[-1][1] + 1:
            runs[-1][1] = n
        else:
            runs.append([n, n])
    return ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)


def _skip_warning(batch, why: str) -> None:
    warnings.warn(f"frame {batch.meta['frame']}: {why}", stacklevel=2)


def _latency_row(batch, out, theta, seconds: float, skipped: str = "") -> dict:
    """One CSV row: the frame, its latency (mean, min, max of the map), θ, the search's confidence and what set
    the latency (``source``: sharpness, ghost, reader or fallback), the learned reader's spread and the hot pixels
    it left out."""
    row = {"frame": batch.meta["frame"], "exposure_start_us": f"{float(batch.exposure_start):.1f}",
           "exposure_end_us": f"{float(batch.exposure_end):.1f}"}
    if out is not None and out.latency is not None:
        lat = out.latency[0, 0]
        cand, score = out.meta.get("etf_curve", (None, None))
        finite = score[0][torch.isfinite(score[0])] if score is not None else None
        row.update(latency_us=f"{float(lat.mean()):.1f}", latency_min_us=f"{float(lat.min()):.1f}",
                   latency_max_us=f"{float(lat.max()):.1f}",
                   score=f"{float(finite.min()):.5f}" if finite is not None and len(finite) else "",
                   confidence=f"{float(out.meta['latency_confidence'][0]):.3f}"
                   if "latency_confidence" in out.meta else "",
                   fallback=int(bool(out.meta["latency_fallback"][0])) if "latency_fallback" in out.meta else "",
                   source=out.meta["latency_source"][0] if out.meta.get("latency_source") else "",
                   spread_us=_spread_of(out),
                   hot_pixels=out.meta["hot_pixels"][0] if out.meta.get("hot_pixels") else "")
        theta = out.meta.get("threshold", theta)
    else:
        row.update(latency_us="", latency_min_us="", latency_max_us="", score="", confidence="", fallback="",
                   source="", spread_us="", hot_pixels="")
    theta = float(theta.flatten()[0]) if isinstance(theta, torch.Tensor) else theta
    row.update(threshold=f"{theta:.4f}" if isinstance(theta, float) else str(theta),
               events_in_window=len(batch.events), skipped=skipped, time_s=f"{seconds:.3f}")
    return row


def _spread_of(out) -> str:
    """The learned reader's spread (µs) of a corrected frame, empty where it has none (other scores)."""
    spread = out.meta.get("latency_spread_us")
    value = float(spread[0]) if spread is not None else math.nan
    return "" if math.isnan(value) else f"{value:.0f}"


def _write_csv(path: Path, rows: list[dict]) -> None:
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["frame"])
        w.writeheader()
        w.writerows(rows)


def cmd_correct(args: argparse.Namespace) -> int:
    import h5py

    from evlatcorr.io import EventUtilsRecording
    from evlatcorr.io.h5 import atomic_path, write_header
    from evlatcorr.io.outputs import check_outputs

    report = args.report if args.report is not None else args.output.with_suffix(".csv")
    if report.resolve() == args.output.resolve():
        raise ValueError(f"the report {report} would replace the corrected recording {args.output}: name the "
                         "output .h5 or pass --report")
    if args.fuse_frames < 0:
        raise ValueError(f"--fuse-frames must be 0 or more, got {args.fuse_frames}")
    check_outputs([args.input], files=[args.output, report])
    device = _device(args.device)
    _threshold(args.threshold)  # a bad value fails before any reading
    high = args.search_us[1] if args.search_us else None
    rec = _open(args)
    if high is not None:  # the events the search reads (by default: the exposure time's)
        rec.after_us = search_reach_us(rec, high)
    theta = _recording_threshold(args, rec, device)
    corrector = _corrector(args, args.mode, args.curve, theta)
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
        frames = _correct_frames(args, rec, corrector, theta, device, h5, maps)
        if not frames.rows:
            raise ValueError(f"{args.input}: no frames")
        latencies = frames.latencies
        if args.mode == "constant" and args.fuse_frames > 0:
            latencies = _fused(frames.rows, latencies, frames.evidence, args.fuse_frames, args.search_us)
        _write_corrected(args, rec, h5, frames, latencies, maps)
        _write_csv(report_tmp, frames.rows)
    rows = frames.rows
    skipped = sum(bool(r["skipped"]) for r in rows)
    print(f"wrote {args.output} and {report} ({len(rows)} frames, median latency "
          f"{np.median([float(r['latency_us']) for r in rows]):.0f} us"
          + (f", {skipped} without events kept the previous latency" if skipped else "") + ")")
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
                    maps=None) -> _CorrectedFrames:
    """Every frame's latency (``corrector``; a frame without events keeps the previous one), its blurry image appended
    to ``h5``'s ``frames/blurry`` as it comes when ``h5`` is an open file, and in spatial mode its latency map to
    ``maps``'s ``frames/estimated_latency_map`` (an open file: the output or a scratch one)."""
    from evlatcorr.frames import EventFrames
    from evlatcorr.restore import has_events

    kept = _CorrectedFrames([], [], [], [], [], [math.inf, -math.inf])
    frame_warnings = _FrameWarnings()
    pending: list[Any] = []  # frames with events not yet corrected, searched in one call (_frames_per_call)

    def record(batch, out, seconds: float, skipped: str = "") -> None:
        kept.rows.append(_latency_row(batch, out, theta, seconds, skipped=skipped))
        kept.evidence.append(frame_evidence(out)[0][1:] if args.mode == "constant" and not skipped else (None, None))
        latency = out.latency[0, 0].cpu()
        kept.extremes[:] = [min(kept.extremes[0], float(latency.min())), max(kept.extremes[1], float(latency.max()))]
        if args.mode == "constant":  # one latency for the whole frame
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

    per_call = _frames_per_call(device, args.mode)
    for batch in _progress(rec, len(rec), "correct"):
        batch = batch.to(device)
        if has_events(batch):
            pending.append(batch)
            if len(pending) >= per_call:
                correct_pending()
            continue
        correct_pending()  # the frames before it first: it takes the latency of the last of them
        previous = float(kept.latencies[-1].mean()) if kept.latencies else 0.0
        _skip_warning(batch, f"no events in its exposure and search window; its events keep the previous "
                             f"frame's latency ({previous:.0f} us)")
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


def _frames_per_call(device: torch.device, mode: str) -> int:
    """Frames of a recording corrected in one call: on an accelerator the constant search takes several frames in
    one pass (:mod:`evlatcorr.search_batched`); a CPU searches frame by frame, so it gets them one at a time."""
    from evlatcorr import search_batched

    return search_batched.MAX_FRAMES if mode == "constant" and device.type != "cpu" else 1


def _fused(rows: list[dict], latencies: list[torch.Tensor], evidence: list[tuple[Any, Any]],
           frames: int, search_range: list[float] | None = None) -> list[torch.Tensor]:
    """Each frame's constant latency fused with its neighbours' evidence (:func:`evlatcorr.temporal.fuse_latencies`),
    kept inside ``search_range`` where one is given; a frame without events keeps the fused latency before it. The
    rows get ``frame_latency_us`` (the frame's own estimate) and the fused ``latency_us``."""
    from evlatcorr.temporal import fuse_latencies

    own = torch.tensor([float(m.mean()) for m in latencies], dtype=torch.float64)
    fused = fuse_latencies(own, [c for c, _ in evidence], [p for _, p in evidence], frames, frames)
    if search_range:
        fused = fused.clamp(*search_range)
    for k, row in enumerate(rows):
        if row["skipped"]:
            fused[k] = fused[k - 1] if k else 0.0
        row["frame_latency_us"] = row["latency_us"]
        row["latency_us"] = row["latency_min_us"] = row["latency_max_us"] = f"{float(fused[k]):.1f}"
    return [torch.full_like(m, float(v)) for m, v in zip(latencies, fused)]


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


def cmd_deblur(args: argparse.Namespace) -> int:
    return _restore(args, "deblur")


def cmd_interpolate(args: argparse.Namespace) -> int:
    if args.num < 1:
        raise ValueError(f"--num must be >= 1, got {args.num}")
    return _restore(args, "interpolation")


def _restore(args: argparse.Namespace, task: str) -> int:
    """deblur / interpolate: the model on every frame (or pair), with stamped and with corrected events."""
    from evlatcorr.io.outputs import atomic_dir, check_outputs

    if args.max_frames is not None and args.max_frames < 1:
        raise ValueError(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.fuse_frames < 0:
        raise ValueError(f"--fuse-frames must be 0 or more, got {args.fuse_frames}")
    check_outputs([args.input], folders=[args.outdir], overwrite_folders=args.overwrite)
    device = _device(args.device)
    _threshold(args.threshold)  # a bad value fails before any reading
    run = _restoration(args, task, device)
    rows, gif, count = [], [], 0
    frame_warnings = _FrameWarnings()
    with atomic_dir(args.outdir, overwrite=args.overwrite) as tmp:
        stream, limit = _restore_inputs(run.rec, args.max_frames, run.pairs)
        for batch, frames in _progress(stream, limit, task):
            t0 = time.perf_counter()
            if frames is None:
                _skip_warning(batch, f"{args.model} {task} needs the next frame, and this is the last of its segment")
                rows.append(_latency_row(batch, None, run.theta, 0.0, skipped="no next frame"))
                continue
            frames = _with_targets(frames.to(device), task, args.model, args.num if task == "interpolation" else 0)
            with frame_warnings.naming([batch]):
                plain, corrected, out, skipped = _restore_frames(run, frames, batch)
            rows.append(_latency_row(batch, out, run.theta, time.perf_counter() - t0, skipped))
            if out is not None and "frame_latency_us" in out.meta:  # fused: the frame's own estimate too
                rows[-1]["frame_latency_us"] = f"{float(out.meta['frame_latency_us'][0]):.1f}"
            _save_restored(tmp, task, args.model, batch.meta["frame"], frames.blurry[0], plain,
                           corrected if run.corrector is not None else None, gif)
            count += 1
        frame_warnings.summarise()
        if not rows:
            raise ValueError(f"{args.input}: no frames")
        _write_csv(tmp / "frames.csv", rows)
        if gif:
            gif[0].save(tmp / "side_by_side.gif", save_all=True, append_images=gif[1:], duration=200, loop=0)
    panels = "blurry | uncorrected" + (" | corrected" if run.corrector is not None else "")
    print(f"wrote {count} {'frames' if task == 'deblur' else 'pairs'} to {args.outdir} ({args.model}; "
          f"side_by_side.gif: {panels}{f', first {GIF_FRAMES}' if count > GIF_FRAMES else ''}; frames.csv)")
    return EXIT_OK


class _Restoration(NamedTuple):
    """What a deblur / interpolate run applies to every frame (or pair)."""

    rec: Any
    model: torch.nn.Module
    corrector: Any  # an EventLatencyCorrector (streaming with --fuse-frames), or None for --correct none
    theta: float | str
    pairs: bool  # the model reads each frame with the next one
    device: torch.device


def _restoration(args: argparse.Namespace, task: str, device: torch.device) -> _Restoration:
    """The model (weights loaded before any reading), the recording, θ and the corrector."""
    from evlatcorr.restore import build_model, needs_pairs, pair_lead_us, pair_reach_us

    model = build_model(args.model, task, args.ckpt, 0.2, args.num_bins).to(device)  # loads the weights first
    high = args.search_us[1] if args.search_us else None
    rec = _open(args)
    if high is not None:  # the events the search reads (by default: the exposure time's)
        rec.after_us = search_reach_us(rec, high)
    theta = _recording_threshold(args, rec, device) if args.model == "edi" or args.correct != "none" else 0.2
    if args.model == "edi":
        model = build_model(args.model, task, None, theta, args.num_bins)
    corrector = None if args.correct == "none" else _corrector(args, args.correct, args.curve, theta)
    if args.correct == "constant" and args.fuse_frames > 0:  # frame by frame: each takes the frames before it
        from evlatcorr.temporal import StreamingLatencyCorrector

        corrector = StreamingLatencyCorrector(corrector, args.fuse_frames)
    pairs = needs_pairs(args.model, task)
    if pairs:  # the first frame's events must reach the next exposure's end, plus the latency searched
        rec.after_us = pair_reach_us(rec, high)
        rec.before_us = max(rec.before_us, pair_lead_us(rec))  # and REFID reads before the first exposure
    return _Restoration(rec, model, corrector, theta, pairs, device)


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


def _restore_frames(run: _Restoration, frames, batch):
    """The model's output with the stamped events and with the corrected ones (the same without a corrector
    or without events to correct), the corrector's output and why correction was skipped."""
    from evlatcorr.restore import has_events

    with torch.no_grad():
        plain = run.model(frames).output
    out, skipped, corrected = None, "", plain
    if run.corrector is not None:
        if has_events(frames):
            out = run.corrector(frames)
            if run.pairs:  # REFID reads before the exposure: the corrected events start where the stamped ones do
                out = out.replace(corrected=out.corrected.since(frames.exposure_start - run.rec.before_us))
            with torch.no_grad():
                corrected = run.model(out).output
        else:
            skipped = "no events"
            _skip_warning(batch, "no events in its exposure and search window: not corrected")
    if run.device.type == "cuda":
        torch.cuda.synchronize(run.device)  # so the row's time is the frame's
    return plain, corrected, out, skipped


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


def cmd_simulate(args: argparse.Namespace) -> int:
    from evlatcorr.io import write_sequence
    from evlatcorr.simulate import simulate

    seq = simulate(args.image, num_frames=args.frames, height=args.size[0], width=args.size[1],
                   exposure_us=args.exposure_us, frame_interval_us=args.interval_us, latency=args.latency_model,
                   latency_us=args.latency_us, seed=args.seed)
    write_sequence(args.output, seq)
    print(f"wrote {args.output}: {args.frames} frames {args.size[1]}x{args.size[0]}, "
          f"{len(seq.delayed_events)} events, latency {args.latency_model} "
          f"({float(seq.true_latency.mean()):.0f} us mean)")
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    rec = _open(args)
    for key, value in rec.info().items():
        print(f"{key:40s} {value}")
    return EXIT_OK


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so every ``finally`` and temporary-file cleanup runs."""


def _on_sigterm(signum, frame) -> None:  # noqa: ARG001
    raise _Terminated()


def main(argv: Sequence[str] | None = None) -> int:
    from evlatcorr.io import RecordingError

    args = _parser().parse_args(argv)
    command = {"correct": cmd_correct, "deblur": cmd_deblur, "interpolate": cmd_interpolate,
               "simulate": cmd_simulate, "info": cmd_info}
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if _main_thread() else None
    try:
        with warnings.catch_warnings():  # restores the filters and warnings.showwarning on the way out
            warnings.simplefilter("always")  # every warning reaches the printer, which keeps each message once
            warnings.showwarning = _warning_printer(args.command)
            return command[args.command](args)
    except (RecordingError, ValueError, OSError) as exc:  # bad input, or an OS error on the user's paths
        print(f"evlatcorr {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, _Terminated)
        print(f"evlatcorr {args.command}: {'terminated' if terminated else 'interrupted'}; no output was written",
              file=sys.stderr)
        return 128 + (signal.SIGTERM if terminated else signal.SIGINT)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _warning_printer(command: str) -> Callable[..., None]:
    """A ``warnings.showwarning`` for the command line: each distinct message once, as one line ``evlatcorr COMMAND:
    warning: MESSAGE`` on stderr, above the progress bar (a user needs what happened to their data, not the source
    line of the library that noticed it, nor the same line again from another place that noticed it too)."""
    from tqdm import tqdm

    seen: set[str] = set()

    def show(message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ARG001 (the hook's signature)
        text = str(message)
        if text not in seen:
            seen.add(text)
            tqdm.write(f"evlatcorr {command}: warning: {text}", file=sys.stderr if file is None else file)

    return show


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()


if __name__ == "__main__":
    sys.exit(main())
