"""Event windows: which events belong to a frame, and cutting them out of time-ordered chunks.

A frame with exposure ``[start, end)`` gets the events of ``[start - before_us, end + after_us)``;
``after_us = None`` means the exposure time (the corrector's default latency search range).
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path

import numpy as np

from evlatcorr.io.records import EVENT_DTYPE, SegmentEnd

__all__ = ["check_time_range", "cut_window", "event_window", "resolve_segment", "segment_chunks"]


def event_window(start: float, end: float, before_us: float, after_us: float | None) -> tuple[float, float]:
    """The event window ``[lo, hi)`` of a frame with exposure ``[start, end)`` (µs).

    Example:
        >>> event_window(100.0, 120.0, 5.0, None)
        (95.0, 140.0)
    """
    after = (end - start) if after_us is None else after_us
    return start - before_us, end + after


def cut_window(chunks: Iterable[np.ndarray], lo: float, hi: float) -> np.ndarray:
    """The events with ``lo <= t < hi`` of time-ordered chunks; stops at the first chunk that reaches ``hi``.

    Example:
        >>> from evlatcorr.io.conversions import structured_events
        >>> c = structured_events(np.zeros(4), np.zeros(4), np.array([1.0, 2.0, 3.0, 4.0]), np.ones(4))
        >>> cut_window([c[:2], c[2:]], 2.0, 4.0)["t"].tolist()
        [2.0, 3.0]
    """
    parts = []
    for chunk in chunks:
        if not len(chunk) or chunk["t"][-1] < lo:
            continue
        a, b = np.searchsorted(chunk["t"], [lo, hi], side="left")
        if b > a:
            parts.append(chunk[a:b])
        if chunk["t"][-1] >= hi:
            break
    return np.concatenate(parts) if parts else np.zeros(0, dtype=EVENT_DTYPE)


def segment_chunks(items: Iterable[np.ndarray | SegmentEnd], segment: int) -> Iterator[np.ndarray]:
    """The chunks of one segment from a stream of chunks and :class:`SegmentEnd` markers."""
    current = 0
    for item in items:
        if isinstance(item, SegmentEnd):
            current += 1
            if current > segment:
                return
        elif current == segment:
            yield item


def check_time_range(t0: float, t1: float) -> None:
    """``[t0, t1)`` must not run backwards."""
    if not t1 >= t0:
        raise ValueError(f"events_between needs t1 >= t0, got [{t0}, {t1})")


def resolve_segment(segment: int | None, num_segments: int, path: Path) -> int:
    """``segment`` checked against ``num_segments``; ``None`` is allowed only for a recording of one segment."""
    if segment is None:
        if num_segments > 1:
            raise ValueError(f"{path} holds {num_segments} independent segments (sequences); "
                             f"pass segment=0..{num_segments - 1}")
        return 0
    if not 0 <= segment < num_segments:
        raise ValueError(f"{path}: segment must be in [0, {num_segments}), got {segment}")
    return segment
