"""Checks on what a reader streams: event chunks, frame order, and warnings about a window's coverage.

Each check raises a :class:`RecordingError` (or warns) with a message that names the file and,
where it applies, the frame, so a user can tell which recording is broken and how.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from evlatcorr.io.records import FrameInfo, RecordingError
from evlatcorr.sample_warnings import FrameWarning, user_stacklevel

__all__ = ["check_chunk", "check_frame_order", "warn_coverage", "warn_unused_events"]


def check_chunk(chunk: np.ndarray, newest: float, segment: int, sensor_size: tuple[int, int], path: Path) -> None:
    """A non-empty chunk must hold finite times, sorted and not before ``newest``, on the sensor ``(H, W)``."""
    t = chunk["t"]
    if not np.isfinite(t).all():
        raise RecordingError(f"{path}: event timestamps contain NaN or infinite values")
    if t[0] < newest or (len(t) > 1 and bool(np.any(t[1:] < t[:-1]))):
        raise RecordingError(f"{path}: events are not sorted by time (segment {segment}, near "
                             f"t = {float(t[0]):.0f} us after {newest:.0f} us)")
    h, w = sensor_size
    x_lo, x_hi, y_lo, y_hi = int(chunk["x"].min()), int(chunk["x"].max()), int(chunk["y"].min()), int(chunk["y"].max())
    if x_lo < 0 or x_hi >= w or y_lo < 0 or y_hi >= h:
        raise RecordingError(
            f"{path}: event coordinates x in [{x_lo}, {x_hi}], y in [{y_lo}, {y_hi}] fall outside the sensor (H, W)="
            f"{sensor_size} near t = {float(t[0]):.0f} us")


def check_frame_order(info: FrameInfo, previous_start: float, lo: float, released: float, newest: float,
                      path: Path) -> None:
    """A new frame must have a positive exposure, come in time order, and find its window's events still held.

    Args:
        info: the new frame.
        previous_start: exposure start of the frame before it (µs).
        lo: start of its event window (µs).
        released: the newest event already dropped while no frame waited (µs).
        newest: the newest event read so far (µs), for the message.
        path: the recording, for the message.
    """
    if not info.exposure_end > info.exposure_start:
        raise RecordingError(f"{path}: frame {info.index} has exposure end {info.exposure_end} us "
                             f"<= start {info.exposure_start} us")
    if info.exposure_start < previous_start:
        raise RecordingError(f"{path}: frame {info.index} starts its exposure at {info.exposure_start:.0f} "
                             f"us, before the previous frame ({previous_start:.0f} us): frames must be in time order")
    if lo <= released:
        raise RecordingError(f"{path}: frame {info.index} came {newest - lo:.0f} us after its window "
                             f"start ({lo:.0f} us) in the file, after events it needs were released; "
                             "raise max_frame_delay_us")


def warn_coverage(path: Path, info: FrameInfo, lo: float, hi: float, events: np.ndarray, first: float | None,
                  newest: float, exhausted: bool) -> None:
    """Warn when a frame's window ``[lo, hi)`` starts before the first event or ends past the last one, or when
    its exposure holds no event.

    Args:
        first: time of the first event of the frame's segment (``None``: it has none).
        newest: time of the newest event read.
        exhausted: whether the segment's events are all read (so ``newest`` is the last one).
    """
    name = f"{path}: frame {info.index}"

    def warn(kind: str, text: str, summary: str) -> None:
        warnings.warn(FrameWarning(kind, info.index, text, summary), stacklevel=user_stacklevel())

    if first is None:
        warn("segment_without_events", f"{name}: no events at all in its segment; its window [{lo:.0f}, {hi:.0f}) us "
             "is empty", "no events at all in the segment")
        return
    if first - lo > 0.1 * (hi - lo):  # a short gap is just a quiet scene; a long one, a missing stream
        warn("window_before_events", f"{name}: its window starts at {lo:.0f} us, {first - lo:.0f} us before the first "
             f"event ({first:.0f} us); events before that are missing",
             "the window starts well before the first event; events before that are missing")
    if exhausted and newest < hi:
        warn("events_end_early", f"{name}: events end at {newest:.0f} us, before the end of its window {hi:.0f} us "
             f"(exposure end + {hi - info.exposure_end:.0f} us); late events are missing",
             "the events end before the end of the window; late events are missing")
    inside = int(((events["t"] >= info.exposure_start) & (events["t"] < info.exposure_end)).sum())
    if inside == 0:
        warn("exposure_without_events", f"{name} has no events inside its exposure [{info.exposure_start:.0f}, "
             f"{info.exposure_end:.0f}) us", "no events inside the exposure")


def warn_unused_events(path: Path, count: int, last_frame: int, segment_label: str, past_us: float,
) -> None:
    """Warn that ``count`` events come after the last frame's window (frames may be missing): no frame reads them
    (``evlatcorr correct`` still writes them, at the last frame's latency)."""
    warnings.warn(f"{path}: {count} events after the window of the last frame ({last_frame}){segment_label} lie in "
                  f"no frame's window (they run {past_us:.0f} us past its window)", stacklevel=user_stacklevel())
