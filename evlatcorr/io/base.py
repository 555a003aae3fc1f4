"""The reader interface: recordings yield ``EventFrames`` frame by frame with bounded memory.

Every reader converts its file's conventions once, at the edge, to ours: timestamps in
microseconds (float64), polarity ±1, sensor size ``(H, W)``, frames as float ``(C, H, W)`` in
[0, 1]. A reader implements two streams, both in time order:

- :meth:`Recording.frames`: :class:`FrameInfo` (exposure start/end in µs and the image);
- :meth:`Recording.iter_event_chunks`: structured numpy chunks with fields ``x, y, t, p``.

:meth:`Recording.__iter__` merges them in one pass: it holds the events of the frames still
waiting for their window to be complete and drops every event that no later frame can need, so
memory is bounded by one frame's window plus one chunk, whatever the length of the recording.
Readers whose file stores frames and events as separate streams (HDF5, NPZ) pull events only as
far as the current frame needs; readers of interleaved files (AEDAT4) override :meth:`Recording._items`.

A recording may hold several independent *segments* (sequences with their own time base, e.g.
the videos of a HighREV split or the files of a GEM folder). Events never cross a segment
boundary; frame indices run on across segments.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.gamma import linear_frames
from evlatcorr.io.batching import frame_batch
from evlatcorr.io.conversions import (
    TIME_UNITS,
    iter_events_as_chunks,
    structured_events,
    to_microseconds,
    to_unit_image,
)
from evlatcorr.io.records import EVENT_DTYPE, FrameInfo, RecordingError, SegmentEnd
from evlatcorr.io.streaming import FrameStream, interleave
from evlatcorr.io.summary import event_summary, frame_summary
from evlatcorr.io.validation import check_chunk, warn_coverage
from evlatcorr.io.windows import check_time_range, cut_window, event_window, resolve_segment, segment_chunks

__all__ = [
    "EVENT_DTYPE",
    "FrameInfo",
    "Recording",
    "RecordingError",
    "SegmentEnd",
    "TIME_UNITS",
    "iter_events_as_chunks",
    "structured_events",
    "to_microseconds",
    "to_unit_image",
]

class Recording:
    """Base class of readers: frames with their events, streamed in one pass.

    Iterating yields one :class:`~evlatcorr.EventFrames` (batch of 1) per frame, whose events
    are those with ``exposure_start - before_us <= t < exposure_end + after_us``. ``after_us``
    defaults to the frame's exposure time, the corrector's default latency search range: the
    latency search needs events stamped up to the largest searched latency after exposure end.

    Args:
        path: the file or folder.
        before_us: events to include before exposure start (µs, >= 0).
        after_us: events to include after exposure end (µs, >= 0); ``None``: the exposure time.

    Attributes:
        sensor_size: ``(H, W)``.
        format_name: short name of the format.
        frame_gamma: the frames' images are raised to this power as they are read (default 1: kept as they are).
            EDI needs linear intensity, as a DAVIS's raw frames are; images encoded for display (PNG or video
            frames, sRGB) are about ``image ** 2.2``: ``open_recording(path, frame_gamma=2.2)``.

    Example:
        >>> from evlatcorr.io import open_recording
        >>> rec = open_recording("cradle_lowlight.aedat4", after_us=20_000)  # doctest: +SKIP
        >>> for batch in rec:  # doctest: +SKIP
        ...     print(batch.meta["frame"], len(batch.events))
    """

    format_name = "?"
    #: readers that can find a frame's events without reading the ones before it
    random_access = False
    #: how long after its window starts a frame may still arrive in the file (µs). Readers whose
    #: ``_items`` yields every frame before the events it needs (the default) use 0; interleaved
    #: files (AEDAT4) keep this much of the past events while no frame is waiting.
    _frame_delay_us: float = 0.0
    frame_gamma: float = 1.0

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file or directory")
        if not np.isfinite(before_us) or before_us < 0:
            raise ValueError(f"before_us must be a finite number >= 0, got {before_us}")
        if after_us is not None and (not np.isfinite(after_us) or after_us < 0):
            raise ValueError(f"after_us must be None or a finite number >= 0, got {after_us}")
        self.before_us, self.after_us = float(before_us), after_us
        self.sensor_size: tuple[int, int] = (0, 0)
        #: names of the independent segments, for recordings of several (empty: one segment)
        self.segment_names: list[str] = []
        self._times: list[tuple[float, float, int]] | None = None
        #: the most events held at once during the last pass of ``__iter__`` (a memory check)
        self.peak_buffered_events = 0

    # to implement -------------------------------------------------------------------------
    def frames(self) -> Iterator[FrameInfo]:
        """Frames (with images) in time order."""
        raise NotImplementedError

    def iter_event_chunks(self) -> Iterator[np.ndarray]:
        """Event chunks (structured arrays with x, y, t in µs, p ±1) in time order, each event once.

        For recordings of several segments the chunks of all segments follow each other.
        """
        for item in self._segmented_chunks():
            if not isinstance(item, SegmentEnd):
                yield item

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        """Event chunks with a :class:`SegmentEnd` after each segment but the last (default: one segment)."""
        raise NotImplementedError

    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        return [(f.exposure_start, f.exposure_end, f.segment) for f in self.frames()]

    def _read_frame_window(self, index: int) -> tuple[FrameInfo, np.ndarray, tuple[float | None, float]]:
        """Random-access readers: frame ``index``, its window's events and ``(first, last)`` event time
        of its segment (``(None, -inf)`` when it has none)."""
        raise NotImplementedError

    def _read_events_between(self, segment: int, t0: float, t1: float) -> np.ndarray:
        """Random-access readers: the events with ``t0 <= t < t1`` of ``segment``, reading only those."""
        raise NotImplementedError

    # frame index and windows --------------------------------------------------------------
    def frame_times(self) -> list[tuple[float, float, int]]:
        """``(exposure_start, exposure_end, segment)`` of every frame, without reading images (cached)."""
        if self._times is None:
            self._times = self._read_frame_times()
        return self._times

    def window(self, start: float, end: float) -> tuple[float, float]:
        """The event window ``[lo, hi)`` of a frame with exposure ``[start, end)`` (µs)."""
        return event_window(start, end, self.before_us, self.after_us)

    @property
    def num_frames(self) -> int:
        """Number of frames (reads the frame index once, without images)."""
        return len(self.frame_times())

    def __len__(self) -> int:
        return self.num_frames

    @property
    def num_segments(self) -> int:
        """Number of independent segments (sequences with their own time base); see ``segment_names``."""
        return max(1, len(self.segment_names))

    def _resolve_segment(self, segment: int | None) -> int:
        return resolve_segment(segment, self.num_segments, self.path)

    # streaming ----------------------------------------------------------------------------
    def _items(self) -> Iterator[FrameInfo | np.ndarray | SegmentEnd]:
        """Frames, event chunks and segment ends merged in one stream.

        The default pulls events lazily: after each frame, only as many chunks as its window
        needs. Frames of a segment come before the :class:`SegmentEnd` that closes it.
        """
        return interleave(self.frames(), self._segmented_chunks(), self.window)

    def _check_chunk(self, chunk: np.ndarray, newest: float, segment: int) -> None:
        check_chunk(chunk, newest, segment, self.sensor_size, self.path)

    def __iter__(self) -> Iterator[EventFrames]:
        """Stream the frames: one pass over the events, holding only those a waiting frame may need.

        After a pass, ``peak_buffered_events`` tells the most events held at once.
        """
        self.peak_buffered_events = 0
        stream = FrameStream(self.path, self.window, self._check_chunk, self._frame_delay_us, self.num_segments > 1)
        try:
            for info, events, lo, hi in stream.windows(self._items()):
                self.peak_buffered_events = stream.peak_buffered
                yield self._batch(info, events, lo, hi)
        finally:  # also when the pass fails or stops early
            self.peak_buffered_events = stream.peak_buffered

    def _batch(self, info: FrameInfo, events: np.ndarray, lo: float, hi: float) -> EventFrames:
        """Wrap one frame and its events as a batch of 1."""
        return linear_frames(frame_batch(info, events, lo, hi, self.sensor_size, self.path), self.frame_gamma)

    # random access --------------------------------------------------------------------------
    def frame(self, index: int) -> EventFrames:
        """One frame with its window's events.

        Readers with random access (HDF5) read only that frame and its window; the others
        stream up to it.
        """
        n = self.num_frames
        if not -n <= index < n:
            raise IndexError(f"{self.path}: frame {index} out of range ({n} frames)")
        index %= n
        if self.random_access:
            return self._frame_random_access(index)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # warnings about other frames
            for batch in self:
                if batch.meta["frame"] == index:
                    return batch
        raise RecordingError(f"{self.path}: frame {index} not found")  # pragma: no cover

    def _frame_random_access(self, index: int) -> EventFrames:
        info, events, (first, last) = self._read_frame_window(index)
        lo, hi = self.window(info.exposure_start, info.exposure_end)
        if len(events):  # what streaming checks chunk by chunk: sorted, finite, on the sensor
            self._check_chunk(events, -np.inf, info.segment)
        warn_coverage(self.path, info, lo, hi, events, first, last, exhausted=last < hi)
        return self._batch(info, events, lo, hi)

    def events_between(self, t0: float, t1: float, segment: int | None = None) -> Events:
        """Events with ``t0 <= t < t1`` (µs), one sample.

        Readers with an index (HDF5) read only that slice; the others stream the file up to ``t1``.
        Recordings of several segments need ``segment``.
        """
        check_time_range(t0, t1)
        segment = self._resolve_segment(segment)
        if self.random_access:
            events = self._read_events_between(segment, t0, t1)
        else:
            events = cut_window(segment_chunks(self._segmented_chunks(), segment), t0, t1)
        return Events.from_numpy(events, sensor_size=self.sensor_size)

    # summary --------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """A summary (format, sensor size, frames, exposures, events and their span), reading no images."""
        times = self.frame_times()
        return {"file": str(self.path), "format": self.format_name, "sensor_size (H, W)": self.sensor_size,
                "segments": self.num_segments, **frame_summary(times),
                **event_summary(self._segmented_chunks(), times)}

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, sensor_size={self.sensor_size})"
