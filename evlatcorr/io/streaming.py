"""The one-pass merge of a reader's frames and event chunks into each frame's event window.

:class:`FrameStream` holds the events of the frames still waiting for their window to be complete
and drops every event that no later frame can need, so memory is bounded by one frame's window
plus one chunk, whatever the length of the recording. :func:`interleave` builds the stream it
reads for readers whose file stores frames and events apart (HDF5, NPZ).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import numpy as np

from evlatcorr.io.records import SEGMENT_END, FrameInfo, SegmentEnd
from evlatcorr.io.validation import check_frame_order, warn_coverage, warn_unused_events
from evlatcorr.io.windows import cut_window

__all__ = ["FrameStream", "FrameWindow", "interleave"]

Window = Callable[[float, float], tuple[float, float]]
Item = FrameInfo | np.ndarray | SegmentEnd


class FrameWindow(NamedTuple):
    """A frame with the events of its window ``[lo, hi)`` (µs)."""

    info: FrameInfo
    events: np.ndarray
    lo: float
    hi: float


def interleave(frames: Iterable[FrameInfo], chunks: Iterator[np.ndarray | SegmentEnd],
               window: Window) -> Iterator[Item]:
    """Frames, event chunks and segment ends merged in one stream, pulling events lazily.

    After each frame, only as many chunks as its window needs are pulled. Frames of a segment
    come before the :class:`SegmentEnd` that closes it.
    """
    segment, newest, done = 0, -np.inf, False
    pending_end = False  # a SegmentEnd was pulled from chunks but not yet passed on
    for info in frames:
        while info.segment > segment:  # finish the current segment's events
            if not pending_end:
                for item in chunks:
                    if isinstance(item, SegmentEnd):
                        break
                    yield item
            yield SEGMENT_END
            segment, newest, pending_end = segment + 1, -np.inf, False
        yield info
        _, hi = window(info.exposure_start, info.exposure_end)
        while newest < hi and not done and not pending_end:
            try:
                item = next(chunks)
            except StopIteration:
                done = True
                break
            if isinstance(item, SegmentEnd):
                pending_end = True
                break
            if len(item):
                newest = float(item["t"][-1])
            yield item
    if not pending_end:
        yield from chunks  # what is left: events after the last frame (for the warning)


@dataclass
class _SegmentState:
    """Book-keeping of one segment while streaming."""

    segment: int = 0
    pending: deque = field(default_factory=deque)  # (FrameInfo, lo, hi) waiting for events up to hi
    buffer: deque = field(default_factory=deque)  # event chunks, in time order
    newest: float = -np.inf  # time of the newest event read
    first: float | None = None  # time of the first event of the segment
    last_start: float = -np.inf  # exposure start of the last frame seen
    last_frame: FrameInfo | None = None  # last frame emitted
    last_lo: float = -np.inf
    last_hi: float = -np.inf
    released: float = -np.inf  # newest event dropped while no frame was waiting
    later: int = 0  # events dropped after the last emitted frame's window
    buffered: int = 0  # events held in buffer


class FrameStream:
    """Hands each frame of a stream of frames, chunks and segment ends the events of its window.

    Args:
        path: the recording, for messages.
        window: ``(exposure_start, exposure_end) -> (lo, hi)``, the frame's event window.
        check_chunk: ``(chunk, newest, segment)``, raises for a chunk that cannot be used.
        frame_delay_us: how long after its window starts a frame may still arrive in the stream (µs);
            this much of the past events is kept while no frame is waiting.
        several_segments: whether messages should name the segment.

    Attributes:
        peak_buffered: the most events held at once so far.
    """

    def __init__(self, path: Path, window: Window, check_chunk: Callable[[np.ndarray, float, int], None],
                 frame_delay_us: float, several_segments: bool) -> None:
        self.path, self.window, self.check_chunk = path, window, check_chunk
        self.frame_delay_us, self.several_segments = frame_delay_us, several_segments
        self.peak_buffered = 0

    def windows(self, items: Iterable[Item]) -> Iterator[FrameWindow]:
        """Each frame with its window's events, as soon as the stream has passed the window's end."""
        s = _SegmentState()
        for item in items:
            if isinstance(item, SegmentEnd):
                yield from self._close_segment(s)
                s = _SegmentState(segment=s.segment + 1)
                continue
            if isinstance(item, FrameInfo):
                self._add_frame(s, item)
                frame_waiting = True
            elif len(item):
                frame_waiting = bool(s.pending)
                self._add_chunk(s, item)
            else:
                continue
            while s.pending and s.newest >= s.pending[0][2]:
                info, lo, hi = s.pending.popleft()
                yield self._emit(s, info, lo, hi, exhausted=False)
            self._trim(s, no_frame_waiting=not frame_waiting)
        yield from self._close_segment(s)

    def _add_frame(self, s: _SegmentState, info: FrameInfo) -> None:
        lo, hi = self.window(info.exposure_start, info.exposure_end)
        check_frame_order(info, s.last_start, lo, s.released, s.newest, self.path)
        s.last_start = info.exposure_start
        s.pending.append((info, lo, hi))
        s.later = 0

    def _add_chunk(self, s: _SegmentState, chunk: np.ndarray) -> None:
        self.check_chunk(chunk, s.newest, s.segment)
        if s.first is None:
            s.first = float(chunk["t"][0])
        s.newest = float(chunk["t"][-1])
        s.buffer.append(chunk)
        s.buffered += len(chunk)
        self.peak_buffered = max(self.peak_buffered, s.buffered)

    def _trim(self, s: _SegmentState, no_frame_waiting: bool) -> None:
        """Drop the chunks no present or future frame can need (frames come in time order)."""
        if s.pending:
            cut = s.pending[0][1]
        elif not no_frame_waiting:
            cut = s.last_lo  # a frame was just emitted: later ones start no earlier
        else:
            cut = max(s.last_lo, s.newest - self.frame_delay_us)
        while s.buffer and s.buffer[0]["t"][-1] < cut:
            dropped = s.buffer.popleft()
            s.buffered -= len(dropped)
            if not s.pending and no_frame_waiting:
                s.released = max(s.released, float(dropped["t"][-1]))
                s.later += int((dropped["t"] >= s.last_hi).sum()) if s.last_frame is not None else 0

    def _emit(self, s: _SegmentState, info: FrameInfo, lo: float, hi: float, exhausted: bool) -> FrameWindow:
        events = cut_window(s.buffer, lo, hi)
        warn_coverage(self.path, info, lo, hi, events, s.first, s.newest, exhausted)
        s.last_frame, s.last_lo, s.last_hi = info, lo, hi
        return FrameWindow(info, events, lo, hi)

    def _close_segment(self, s: _SegmentState) -> Iterator[FrameWindow]:
        while s.pending:
            info, lo, hi = s.pending.popleft()
            yield self._emit(s, info, lo, hi, exhausted=True)
        if s.last_frame is not None and s.newest - s.last_hi > s.last_hi - s.last_lo:
            # events go on for longer than a window past the last frame: frames may be missing
            later = s.later + sum(int((c["t"] >= s.last_hi).sum()) for c in s.buffer)
            if later:
                label = f" of segment {s.segment}" if self.several_segments else ""
                warn_unused_events(self.path, later, s.last_frame.index, label, s.newest - s.last_hi)
        s.buffer.clear()
