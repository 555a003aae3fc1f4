"""What the commands share: reading the options, the recording, its threshold and the corrector; progress; warnings
said of frames by their number; the per-frame CSV rows."""

from __future__ import annotations

import argparse
import contextlib
import csv
import math
import re
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import torch

from evlatcorr.sample_warnings import FrameWarning, SampleWarning

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT = 0, 1, 2


def parse_threshold(text: str) -> float | str:
    """``--threshold``: ``"auto"`` or a positive finite number (the training commands' rule), refused with a
    ValueError (exit 2) before any reading otherwise.

    Example:
        >>> parse_threshold("0.25"), parse_threshold("auto")
        (0.25, 'auto')
    """
    from evlatcorr.lightning.arguments import threshold_argument

    try:
        return threshold_argument(text)
    except argparse.ArgumentTypeError as exc:
        raise ValueError(f"--threshold {exc}") from None


def open_input(args: argparse.Namespace):
    """The recording ``args.input``; with ``--search-us``, each frame's events reach as far as the search reads (by
    default: the exposure time past the exposure's end)."""
    import inspect

    from evlatcorr.io import open_recording, recording_class
    from evlatcorr.restore import search_reach_us

    reader, kwargs = recording_class(args.input), {}
    accepted = inspect.signature(reader.__init__).parameters
    for option, why in (("exposure_us", "stamp each frame's exposure"), ("events_topic", "have no topics"),
                        ("image_topic", "have no topics")):
        if getattr(args, option, None) is None:
            continue
        if option in accepted:  # exposure_us: event_utils HDF5 and ROS1 bags; topics: ROS1 bags
            kwargs[option] = getattr(args, option)
        else:
            warnings.warn(f"--{option.replace('_', '-')} is not used: {reader.format_name} recordings {why}",
                          stacklevel=2)
    rec = open_recording(args.input, frame_gamma=getattr(args, "frame_gamma", 1.0), **kwargs)
    if getattr(args, "search_us", None):
        rec.after_us = search_reach_us(rec, args.search_us[1])
    return rec


def parse_device(text: str) -> torch.device:
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


def parse_cpu_or_cuda(text: str) -> torch.device:
    """``--device`` of a script that runs on a CPU or the CUDA device only (the benchmarks): ``cpu`` or ``cuda``, as
    :func:`parse_device` takes them.

    Raises:
        ValueError: for any other device, or ``cuda`` on a machine without it.
    """
    if text not in ("cpu", "cuda"):
        raise ValueError(f"--device must be cpu or cuda, got {text!r}")
    return parse_device(text)


def threshold_of_recording(args: argparse.Namespace, rec, device: torch.device) -> float | str:
    """``--threshold``: a number, or for ``auto`` one θ for the recording (two-frame consistency)."""
    from evlatcorr.restore import recording_threshold

    theta = parse_threshold(args.threshold)
    if theta != "auto":
        return theta
    # what the search says of a frame here, the main pass says again of every frame, by its number; what the reader
    # says of a frame read here (with the wider window of a pair) is said to come from here, the first of each kind in
    # full and its other frames in one line when the pass ends; of the file, as it is
    said = _ThresholdPassWords()
    with _reworded(said):
        found = recording_threshold(rec, tuple(args.search_us) if args.search_us else None, device=device)
    said.summarise()
    if found is None:
        warnings.warn("no pair of consecutive frames with events: the contrast threshold is estimated per frame",
                      stacklevel=2)
        return "auto"
    print(f"contrast threshold: {found:.3f} (auto: two-frame consistency of the first frames)", file=sys.stderr)
    return found


class _ThresholdPassWords:
    """How a warning of the threshold's pass is said again (see :func:`threshold_of_recording`)."""

    PREFIX = "estimating the contrast threshold from the first frames: "

    def __init__(self) -> None:
        self.later = _LaterFrames()

    def __call__(self, message: Warning) -> str | None:
        if isinstance(message, SampleWarning):
            return None
        if isinstance(message, FrameWarning):
            if self.later.first(message.kind, self.PREFIX + message.summary):
                return self.PREFIX + message.text
            self.later.add(message.kind, [message.frame])
            return None
        return self.PREFIX + str(message) if re.search(r"\bframe \d+:", str(message)) else str(message)

    def summarise(self) -> None:
        for line in self.later.lines():
            warnings.warn(line, stacklevel=3)


class _LaterFrames:
    """The frames each kind of warning is said of after its first: said in full once, then in one line a kind."""

    def __init__(self) -> None:
        self.kinds: dict[str, tuple[str, list[int]]] = {}

    def first(self, kind: str, summary: str) -> bool:
        """Whether ``kind`` comes for the first time (then ``summary`` is what its later frames are said to share)."""
        if kind in self.kinds:
            return False
        self.kinds[kind] = (summary, [])
        return True

    def add(self, kind: str, frames: list[int]) -> None:
        self.kinds[kind][1].extend(frames)

    def lines(self) -> list[str]:
        """``"3 more frames (4-6): SUMMARY"`` for each kind said of later frames; then forgets them."""
        lines = [f"{len(frames)} more frame{'s' if len(frames) > 1 else ''} ({_number_ranges(frames)}): {summary}"
                 for summary, frames in self.kinds.values() if frames]
        self.kinds.clear()
        return lines


#: the recording's slope over intensity is fitted to its first pairs, as its contrast threshold is estimated from them
CURVE_PAIRS = 12


def sloped_spatial(args: argparse.Namespace, mode: str, theta) -> bool:
    """Whether spatial ``mode`` runs as constant mode plus the recording's slope over intensity: without ``--curve``
    or ``--no-pairs``, and with one θ for the recording."""
    return mode == "spatial" and args.curve is None and not args.no_pairs and not isinstance(theta, str)


def recording_curve(args: argparse.Namespace, theta: float, device: torch.device):
    """One curve ``ψ(L) = a + b · f(L)`` for the recording, fitted to the agreement of its first :data:`CURVE_PAIRS`
    pairs with events (:func:`evlatcorr.pair_curve.fit_pair_curve`), or None where no pair tells anything; the slope
    found is said on stderr."""
    import itertools

    from evlatcorr.frames import EventFrames
    from evlatcorr.pair_curve import fit_pair_curve
    from evlatcorr.restore import has_events, pair_frames, pair_reach_us

    rec = open_input(args)
    rec.after_us = pair_reach_us(rec, args.search_us[1] if args.search_us else None)
    pairs = [pair.to(device) for _, pair in itertools.islice(pair_frames(rec), CURVE_PAIRS)
             if pair is not None and has_events(pair)]
    fit = None
    with warnings.catch_warnings():  # what the pairs' frames say, the main pass says of them
        warnings.simplefilter("ignore")
        with contextlib.suppress(ValueError):  # no pair tells anything: no slope
            fit = fit_pair_curve(EventFrames.cat(pairs), float(theta)) if pairs else None
    print("latency over intensity: " + (f"{fit.slope_us:.0f} us later at black than at white (fitted to the first "
                                        f"{fit.pairs_used} pairs' agreement)" if fit is not None and fit.slope_us
                                        else "no slope (one latency per frame)"), file=sys.stderr)
    return fit


def build_corrector(args: argparse.Namespace, mode: str = "constant", curve: Path | None = None,
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
    if getattr(args, "no_pairs", False):  # frames read with the next one: each alone
        kwargs["pair_weight"] = 0.0
    if curve is None:
        return EventLatencyCorrector(mode=mode, threshold=theta, num_bins=args.num_bins, search_range=search,
                                     **kwargs)
    try:
        return EventLatencyCorrector(mode=mode, threshold=theta, num_bins=args.num_bins, search_range=search,
                                     **kwargs)
    except Exception as exc:  # noqa: BLE001 - whatever the reader raised, the file is not a curve checkpoint
        raise ValueError(f"--curve {curve}: not a latency curve checkpoint ({type(exc).__name__}: {exc})") from None


def progress(iterable, total: int | None, desc: str):
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
            category = UserWarning if issubclass(w.category, (SampleWarning, FrameWarning)) else w.category
            warnings.warn(text, category, stacklevel=3)


class FrameWarnings:
    """The library's warnings about samples of a call, said of the frames they are (``frame 12``, not ``sample 0``):
    the first of each kind in full as it happens, and at the end one line for the other frames it happened to."""

    def __init__(self, notes: dict[str, str] | None = None) -> None:
        self.later = _LaterFrames()
        #: what the command adds to a kind's warning (e.g. that the latency it names is fused afterwards)
        self.notes = notes or {}

    def naming(self, batches: list):
        """A context in which the warnings of one call on ``batches`` (in the call's sample order) are reworded."""
        numbers = [int(batch.meta["frame"]) for batch in batches]

        def reword(message: Warning) -> str | None:
            if not isinstance(message, SampleWarning):
                return str(message)
            note = self.notes.get(message.kind, "")
            if self.later.first(message.kind, _option_names(message.summary + note)):
                return _option_names(message.naming([f"frame {n}" for n in numbers]) + note)
            self.later.add(message.kind, [numbers[i] for i in message.samples])
            return None

        return _reworded(reword)

    def summarise(self) -> None:
        """One warning per kind for the frames after its first."""
        for line in self.later.lines():
            warnings.warn(line, stacklevel=2)


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


def skip_warning(batch, kind: str, why: str, summary: str) -> None:
    """Warn that the command passed over frame ``batch`` (``why``, with its figures; ``summary`` without them, said
    at the end of several frames at once)."""
    frame = int(batch.meta["frame"])
    warnings.warn(FrameWarning(kind, frame, f"frame {frame}: {why}", summary), stacklevel=2)


def latency_row(batch, out, theta, seconds: float, skipped: str = "") -> dict:
    """One CSV row: the frame, its latency (mean, min, max of the map), θ, the search's confidence and what set
    the latency (``source``: reader, sharpness, ghost or fallback), the learned reader's spread and the hot pixels
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
    # the events the latency was estimated from (the exposure and search window) where the corrector counted them
    counted = out.meta.get("events_in_window") if out is not None else None
    row.update(threshold=f"{theta:.4f}" if isinstance(theta, float) else str(theta),
               events_in_window=int(counted[0]) if counted is not None else len(batch.events), skipped=skipped,
               time_s=f"{seconds:.3f}")
    return row


def _spread_of(out) -> str:
    """The learned reader's spread (µs) of a corrected frame, empty where it has none (other scores)."""
    spread = out.meta.get("latency_spread_us")
    value = float(spread[0]) if spread is not None else math.nan
    return "" if math.isnan(value) else f"{value:.0f}"


def write_csv(path: Path, rows: list[dict]) -> None:
    """``rows`` as CSV, the columns of every row in the order they first appear (a frame skipped before the first
    corrected one has fewer), empty where a row has none."""
    columns = list(dict.fromkeys(key for row in rows for key in row)) or ["frame"]
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=columns, restval="")
        w.writeheader()
        w.writerows(rows)


class WarningPrinter:
    """A ``warnings.showwarning`` for the command line: each distinct message once, as one line ``evlatcorr COMMAND:
    warning: MESSAGE`` on stderr, above the progress bar (a user needs what happened to their data, not the source
    line of the library that noticed it, nor the same line again from another place that noticed it too). Of a
    :class:`~evlatcorr.sample_warnings.FrameWarning` the first of each kind is said in full as it happens, and
    :meth:`summarise` says the frames of the others in one line a kind (a recording still for hundreds of frames gets
    two lines, not hundreds)."""

    def __init__(self, command: str) -> None:
        self.command = command
        self.seen: set[str] = set()
        self.later = _LaterFrames()

    def __call__(self, message, category, filename, lineno, file=None, line=None) -> None:  # noqa: ARG002 (the hook)
        if isinstance(message, FrameWarning) and not self.later.first(message.kind, message.summary):
            self.later.add(message.kind, [message.frame])
            return
        self._write(str(message), file)

    def summarise(self, file=None) -> None:
        """One line a kind of frame warning for the frames after its first."""
        for line in self.later.lines():
            self._write(line, file)

    def _write(self, text: str, file=None) -> None:
        from tqdm import tqdm

        if text not in self.seen:
            self.seen.add(text)
            tqdm.write(f"evlatcorr {self.command}: warning: {text}", file=sys.stderr if file is None else file)


def frames_per_call(device: torch.device, mode: str) -> int:
    """Frames of a recording corrected in one call: on an accelerator the constant search takes several frames in
    one pass (:mod:`evlatcorr.search_batched`); a CPU searches frame by frame, so it gets them one at a time."""
    from evlatcorr import search_batched

    return search_batched.MAX_FRAMES if mode == "constant" and device.type != "cpu" else 1
