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
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = [
    "EVENT_DTYPE",
    "FrameInfo",
    "Recording",
    "RecordingError",
    "SegmentEnd",
    "TIME_UNITS",
    "structured_events",
    "to_microseconds",
    "to_unit_image",
]

#: Our in-memory layout of an event chunk (t in µs; p ±1).
EVENT_DTYPE = np.dtype([("x", np.int32), ("y", np.int32), ("t", np.float64), ("p", np.int8)])


class RecordingError(ValueError):
    """A recording that cannot be read as asked; the message names the file and, where it applies, the frame."""


@dataclass
class FrameInfo:
    """One frame of a recording.

    Attributes:
        index: frame number in the recording (running on across segments).
        exposure_start: exposure start in µs.
        exposure_end: exposure end in µs.
        image: the blurry frame as float32 :math:`(C, H, W)` in [0, 1].
        sharp: optional ground-truth sharp frame :math:`(C, H, W)` (mid-exposure).
        segment: index of the independent segment (sequence) holding the frame.
        targets: optional ground truth ``(times (T,) µs, frames (T, C, H, W))``.
        meta: extra information for ``EventFrames.meta`` (source file names, ...).
    """

    index: int
    exposure_start: float
    exposure_end: float
    image: np.ndarray
    sharp: np.ndarray | None = None
    segment: int = 0
    targets: tuple[np.ndarray, np.ndarray] | None = None
    meta: dict[str, Any] = field(default_factory=dict)


class SegmentEnd:
    """Marker yielded by :meth:`Recording._items` between independent segments."""


SEGMENT_END = SegmentEnd()


def structured_events(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray,
                      where: str | None = None) -> np.ndarray:
    """Pack columns into our structured layout: t as float64 µs, polarity {0,1}, ±1 or bool as ±1.

    Columns may be 1-D or ``(N, 1)`` (some datasets store column vectors). They are validated the way
    :class:`~evlatcorr.Events` validates its input, vectorised over the chunk: one length, integer
    pixel coordinates, and polarities all in {0, 1}, all in {-1, +1}, or bool.

    Args:
        x, y, t, p: the columns (t already in µs).
        where: the file and dataset they come from, to start error messages with; with it the
            error is a :class:`RecordingError`, without a plain :class:`ValueError`.

    Raises:
        RecordingError: (a :class:`ValueError`) for columns of different lengths, non-integer
            coordinates, or a polarity outside {0, 1} / {-1, +1} / bool.

    Example:
        >>> ev = structured_events(np.array([1]), np.array([2]), np.array([3.0]), np.array([0]))
        >>> int(ev["p"][0]), float(ev["t"][0])
        (-1, 3.0)
        >>> try:
        ...     structured_events(np.array([1]), np.array([2]), np.array([3.0]), np.array([5]), where="a.h5: /events")
        ... except RecordingError as exc:
        ...     print(exc)
        a.h5: /events: polarity must be 0/1, -1/+1 or bool, got values [5]
    """
    error = RecordingError if where else ValueError
    prefix = f"{where}: " if where else ""
    x, y, t, p = (np.asarray(v).reshape(-1) for v in (x, y, t, p))
    n = len(t)
    if not len(x) == len(y) == len(p) == n:
        raise error(f"{prefix}event columns differ in length: x {len(x)}, y {len(y)}, t {n}, p {len(p)}")
    for name, v in (("x", x), ("y", y)):
        if v.dtype.kind == "f" and n and not bool(np.all(v == np.round(v))):
            raise error(f"{prefix}{name} must hold integer pixel coordinates, got fractional or NaN values")
    out = np.empty(n, dtype=EVENT_DTYPE)
    out["x"], out["y"], out["t"] = x, y, t
    out["p"] = _signed_polarity(p, error, prefix)
    return out


def _signed_polarity(p: np.ndarray, error: type[ValueError], prefix: str) -> np.ndarray:
    """±1 from polarities all in {0, 1}, all in {-1, +1}, or bool (vectorised, a few passes)."""
    if p.dtype == np.bool_:
        return np.where(p, 1, -1)
    if not len(p):
        return np.zeros(0, dtype=np.int8)
    if p.dtype.kind in "iu":
        lo, hi = int(p.min()), int(p.max())
        bad = None if lo >= -1 and hi <= 1 else (p < -1) | (p > 1)
        negative = lo == -1
    elif p.dtype.kind == "f":
        ok = (p == 1) | (p == 0) | (p == -1)  # False for NaN and fractions
        bad = None if bool(ok.all()) else ~ok
        negative = bool(np.any(p == -1))
    else:
        raise error(f"{prefix}polarity must be 0/1, -1/+1 or bool, got dtype {p.dtype}")
    if bad is not None:
        values = np.unique(p[bad])[:6].tolist()
        raise error(f"{prefix}polarity must be 0/1, -1/+1 or bool, got values {values}")
    if negative and bool(np.any(p == 0)):
        raise error(f"{prefix}polarity mixes the 0/1 and -1/+1 conventions (it holds -1, 0 and 1)")
    # 0/1 and ±1 agree on "positive means ON"; only a 0 needs care: it is OFF in the 0/1 convention
    return np.where(p > 0, 1, -1)


#: factors from a file's time unit to µs
TIME_UNITS = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}


def to_microseconds(t: Any, scale: float) -> Any:
    """File times times ``scale`` (see ``TIME_UNITS``), as float64 µs rounded to the nanosecond.

    Rounding makes whole-µs stamps stored in seconds come back exact (float seconds carry no
    more than ns precision anyway).

    Example:
        >>> float(to_microseconds(np.float64(0.002113), 1e6))
        2113.0
    """
    t = np.asarray(t, dtype=np.float64)
    return t * scale if scale == 1.0 else np.round(t * scale, 3)


def to_unit_image(a: np.ndarray, where: str, channels_last: bool = True, scale: float | None = None) -> np.ndarray:
    """Convert an image to float32 :math:`(C, H, W)` in [0, 1].

    uint8 is divided by 255 and uint16 by 65535; float images are taken as [0, 1] unless ``scale``
    is given. ``(H, W)`` becomes one channel; ``(H, W, 3|4)`` (or ``(3|4, H, W)`` with
    ``channels_last=False``) three channels (alpha dropped).
    """
    a = np.asarray(a)
    if scale is None:
        if a.dtype == np.uint8:
            scale = 1 / 255.0
        elif a.dtype == np.uint16:
            scale = 1 / 65535.0
        elif np.issubdtype(a.dtype, np.floating):
            scale = 1.0
        else:
            raise RecordingError(f"{where}: unsupported pixel type {a.dtype} (expected uint8, uint16 or float)")
    img = a.astype(np.float32) * np.float32(scale)
    if img.ndim == 2:
        img = img[None]
    elif img.ndim == 3 and channels_last and img.shape[-1] in (1, 3, 4):
        img = img[..., : 3 if img.shape[-1] >= 3 else 1].transpose(2, 0, 1)
    elif img.ndim == 3 and not channels_last and img.shape[0] in (1, 3, 4):
        img = img[: 3 if img.shape[0] >= 3 else 1]
    else:
        raise RecordingError(f"{where}: unsupported image shape {a.shape} (expected (H, W), (H, W, 3) or (H, W, 4))")
    if not np.isfinite(img).all():
        raise RecordingError(f"{where}: image has NaN or infinite pixels")
    return np.ascontiguousarray(img)


@dataclass
class _StreamState:
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

    Example:
        >>> from evlatcorr.io import open_recording
        >>> rec = open_recording("cradle_lowlight.aedat4", after_us=20_000)  # doctest: +SKIP
        >>> for batch in rec:  # doctest: +SKIP
        ...     print(batch.meta["frame"], len(batch.events))
    """

    format_name = "?"
    #: readers that can find a frame's events without reading the ones before it
    random_access = False

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

    def frame_times(self) -> list[tuple[float, float, int]]:
        """``(exposure_start, exposure_end, segment)`` of every frame, without reading images (cached)."""
        if self._times is None:
            self._times = self._read_frame_times()
        return self._times

    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        return [(f.exposure_start, f.exposure_end, f.segment) for f in self.frames()]

    # windows ------------------------------------------------------------------------------
    def window(self, start: float, end: float) -> tuple[float, float]:
        """The event window ``[lo, hi)`` of a frame with exposure ``[start, end)`` (µs)."""
        after = (end - start) if self.after_us is None else self.after_us
        return start - self.before_us, end + after

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

    # streaming ----------------------------------------------------------------------------
    def _items(self) -> Iterator[FrameInfo | np.ndarray | SegmentEnd]:
        """Frames, event chunks and segment ends merged in one stream.

        The default pulls events lazily: after each frame, only as many chunks as its window
        needs. Frames of a segment come before the :class:`SegmentEnd` that closes it.
        """
        chunks = self._segmented_chunks()
        segment, newest, done = 0, -np.inf, False
        pending_end = False  # a SegmentEnd was pulled from chunks but not yet passed on
        for info in self.frames():
            while info.segment > segment:  # finish the current segment's events
                if not pending_end:
                    for item in chunks:
                        if isinstance(item, SegmentEnd):
                            break
                        yield item
                yield SEGMENT_END
                segment, newest, pending_end = segment + 1, -np.inf, False
            yield info
            _, hi = self.window(info.exposure_start, info.exposure_end)
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

    def _check_chunk(self, chunk: np.ndarray, newest: float, segment: int) -> None:
        t = chunk["t"]
        if not np.isfinite(t).all():
            raise RecordingError(f"{self.path}: event timestamps contain NaN or infinite values")
        if t[0] < newest or (len(t) > 1 and bool(np.any(t[1:] < t[:-1]))):
            raise RecordingError(f"{self.path}: events are not sorted by time (segment {segment}, near "
                                 f"t = {float(t[0]):.0f} us after {newest:.0f} us)")
        h, w = self.sensor_size
        if int(chunk["x"].min()) < 0 or int(chunk["x"].max()) >= w or int(chunk["y"].min()) < 0 \
                or int(chunk["y"].max()) >= h:
            raise RecordingError(
                f"{self.path}: event coordinates x in [{int(chunk['x'].min())}, {int(chunk['x'].max())}], "
                f"y in [{int(chunk['y'].min())}, {int(chunk['y'].max())}] fall outside the sensor (H, W)="
                f"{self.sensor_size} near t = {float(t[0]):.0f} us")

    #: how long after its window starts a frame may still arrive in the file (µs). Readers whose
    #: ``_items`` yields every frame before the events it needs (the default) use 0; interleaved
    #: files (AEDAT4) keep this much of the past events while no frame is waiting.
    _frame_delay_us: float = 0.0

    def __iter__(self) -> Iterator[EventFrames]:
        """Stream the frames: one pass over the events, holding only those a waiting frame may need.

        After a pass, ``peak_buffered_events`` tells the most events held at once.
        """
        self.peak_buffered_events = 0
        s = _StreamState()
        for item in self._items():
            if isinstance(item, SegmentEnd):
                yield from self._close_segment(s)
                s = _StreamState(segment=s.segment + 1)
                continue
            if isinstance(item, FrameInfo):
                self._add_frame(s, item)
                frame_waiting = True
            else:
                if not len(item):
                    continue
                self._check_chunk(item, s.newest, s.segment)
                frame_waiting = bool(s.pending)
                if s.first is None:
                    s.first = float(item["t"][0])
                s.newest = float(item["t"][-1])
                s.buffer.append(item)
                s.buffered += len(item)
                self.peak_buffered_events = max(self.peak_buffered_events, s.buffered)
            while s.pending and s.newest >= s.pending[0][2]:
                info, lo, hi = s.pending.popleft()
                yield self._emit(s, info, lo, hi, exhausted=False)
            self._trim(s, no_frame_waiting=not frame_waiting)
        yield from self._close_segment(s)

    def _add_frame(self, s: _StreamState, info: FrameInfo) -> None:
        if not info.exposure_end > info.exposure_start:
            raise RecordingError(f"{self.path}: frame {info.index} has exposure end {info.exposure_end} us "
                                 f"<= start {info.exposure_start} us")
        if info.exposure_start < s.last_start:
            raise RecordingError(f"{self.path}: frame {info.index} starts its exposure at {info.exposure_start:.0f} "
                                 f"us, before the previous frame ({s.last_start:.0f} us): frames must be in time order")
        lo, hi = self.window(info.exposure_start, info.exposure_end)
        if lo <= s.released:
            raise RecordingError(f"{self.path}: frame {info.index} came {s.newest - lo:.0f} us after its window "
                                 f"start ({lo:.0f} us) in the file, after events it needs were released; "
                                 "raise max_frame_delay_us")
        s.last_start = info.exposure_start
        s.pending.append((info, lo, hi))
        s.later = 0

    def _trim(self, s: _StreamState, no_frame_waiting: bool) -> None:
        """Drop the chunks no present or future frame can need (frames come in time order)."""
        if s.pending:
            cut = s.pending[0][1]
        elif not no_frame_waiting:
            cut = s.last_lo  # a frame was just emitted: later ones start no earlier
        else:
            cut = max(s.last_lo, s.newest - self._frame_delay_us)
        while s.buffer and s.buffer[0]["t"][-1] < cut:
            dropped = s.buffer.popleft()
            s.buffered -= len(dropped)
            if not s.pending and no_frame_waiting:
                s.released = max(s.released, float(dropped["t"][-1]))
                s.later += int((dropped["t"] >= s.last_hi).sum()) if s.last_frame is not None else 0

    def _emit(self, s: _StreamState, info: FrameInfo, lo: float, hi: float, exhausted: bool) -> EventFrames:
        parts = []
        for c in s.buffer:
            if c["t"][-1] < lo:
                continue
            a, b = np.searchsorted(c["t"], [lo, hi], side="left")
            if b > a:
                parts.append(c[a:b])
            if c["t"][-1] >= hi:
                break
        events = np.concatenate(parts) if parts else np.zeros(0, dtype=EVENT_DTYPE)
        self._warn_coverage(info, lo, hi, events, s.first, s.newest, exhausted)
        s.last_frame, s.last_lo, s.last_hi = info, lo, hi
        return self._batch(info, events, lo, hi)

    def _close_segment(self, s: _StreamState) -> Iterator[EventFrames]:
        while s.pending:
            info, lo, hi = s.pending.popleft()
            yield self._emit(s, info, lo, hi, exhausted=True)
        if s.last_frame is not None and s.newest - s.last_hi > s.last_hi - s.last_lo:
            # events go on for longer than a window past the last frame: frames may be missing
            later = s.later + sum(int((c["t"] >= s.last_hi).sum()) for c in s.buffer)
            if later:
                where = f" of segment {s.segment}" if self.num_segments > 1 else ""
                warnings.warn(f"{self.path}: {later} events after the window of the last frame "
                              f"({s.last_frame.index}){where} are not used (they run "
                              f"{s.newest - s.last_hi:.0f} us past its window)", stacklevel=3)
        s.buffer.clear()

    def _warn_coverage(self, info: FrameInfo, lo: float, hi: float, events: np.ndarray, first: float | None,
                       newest: float, exhausted: bool) -> None:
        name = f"{self.path}: frame {info.index}"
        if first is None:
            warnings.warn(f"{name}: no events at all in its segment; its window [{lo:.0f}, {hi:.0f}) us is empty",
                          stacklevel=4)
            return
        if first - lo > 0.1 * (hi - lo):  # a short gap is just a quiet scene; a long one, a missing stream
            warnings.warn(f"{name}: its window starts at {lo:.0f} us, {first - lo:.0f} us before the first event "
                          f"({first:.0f} us); events before that are missing", stacklevel=4)
        if exhausted and newest < hi:
            warnings.warn(f"{name}: events end at {newest:.0f} us, before the end of its window {hi:.0f} us "
                          f"(exposure end + {hi - info.exposure_end:.0f} us); late events are missing", stacklevel=4)
        inside = int(((events["t"] >= info.exposure_start) & (events["t"] < info.exposure_end)).sum())
        if inside == 0:
            warnings.warn(f"{name} has no events inside its exposure [{info.exposure_start:.0f}, "
                          f"{info.exposure_end:.0f}) us", stacklevel=4)

    def _batch(self, info: FrameInfo, events: np.ndarray, lo: float, hi: float) -> EventFrames:
        """Wrap one frame and its events as a batch of 1."""
        image = torch.from_numpy(np.ascontiguousarray(info.image, dtype=np.float32))[None]
        if image.shape[-2:] != self.sensor_size:
            raise RecordingError(f"{self.path}: frame {info.index} is {tuple(image.shape[-2:])} but the sensor "
                                 f"is {self.sensor_size} (H, W)")
        n = len(events)
        # the chunks were validated as they were read (sorted, finite, on the sensor, p = ±1)
        ev = Events._trusted(torch.from_numpy(events["x"].astype(np.int64)),
                             torch.from_numpy(events["y"].astype(np.int64)),
                             torch.from_numpy(events["t"].astype(np.float64)),
                             torch.from_numpy(events["p"].astype(np.int8)),
                             torch.zeros(n, dtype=torch.long), self.sensor_size, 1)
        sharp = None
        if info.sharp is not None:
            sharp = torch.from_numpy(np.ascontiguousarray(info.sharp, dtype=np.float32))[None]
        target_times = target_frames = None
        if info.targets is not None:
            target_times = torch.from_numpy(np.asarray(info.targets[0], dtype=np.float64))[None]
            target_frames = torch.from_numpy(np.ascontiguousarray(info.targets[1], dtype=np.float32))[None]
        meta = {"file": str(self.path), "frame": info.index, "segment": info.segment, "window_us": (lo, hi),
                **info.meta}
        return EventFrames(image, ev, torch.tensor([info.exposure_start], dtype=torch.float64),
                           torch.tensor([info.exposure_end], dtype=torch.float64), sharp=sharp,
                           target_times=target_times, target_frames=target_frames, meta=meta)

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
        raise NotImplementedError

    def events_between(self, t0: float, t1: float, segment: int | None = None) -> Events:
        """Events with ``t0 <= t < t1`` (µs), one sample.

        Readers with an index (HDF5) read only that slice; the others stream the file up to ``t1``.
        Recordings of several segments need ``segment``.
        """
        if not t1 >= t0:
            raise ValueError(f"events_between needs t1 >= t0, got [{t0}, {t1})")
        segment = self._resolve_segment(segment)
        parts, current = [], 0
        for item in self._segmented_chunks():
            if isinstance(item, SegmentEnd):
                current += 1
                if current > segment:
                    break
                continue
            if current != segment or not len(item):
                continue
            a, b = np.searchsorted(item["t"], [t0, t1], side="left")
            if b > a:
                parts.append(item[a:b])
            if item["t"][-1] >= t1:
                break
        events = np.concatenate(parts) if parts else np.zeros(0, dtype=EVENT_DTYPE)
        return Events.from_numpy(events, sensor_size=self.sensor_size)

    def _resolve_segment(self, segment: int | None) -> int:
        n = self.num_segments
        if segment is None:
            if n > 1:
                raise ValueError(f"{self.path} holds {n} independent segments (sequences); pass segment=0..{n - 1}")
            return 0
        if not 0 <= segment < n:
            raise ValueError(f"{self.path}: segment must be in [0, {n}), got {segment}")
        return segment

    # summary --------------------------------------------------------------------------------
    def info(self) -> dict[str, Any]:
        """A summary (format, sensor size, frames, exposures, events and their span), reading no images."""
        times = self.frame_times()
        count, first, last, on = 0, None, None, 0
        for chunk in self.iter_event_chunks():
            if len(chunk):
                count += len(chunk)
                on += int((chunk["p"] > 0).sum())
                first = float(chunk["t"][0]) if first is None else min(first, float(chunk["t"][0]))
                last = float(chunk["t"][-1]) if last is None else max(last, float(chunk["t"][-1]))
        exposures = [e - s for s, e, _ in times]
        return {
            "file": str(self.path),
            "format": self.format_name,
            "sensor_size (H, W)": self.sensor_size,
            "segments": self.num_segments,
            "frames": len(times),
            "exposure_us (min, max)": (min(exposures), max(exposures)) if exposures else None,
            "frame_exposure_start_us (first, last)": (times[0][0], times[-1][0]) if times else None,
            "events": count,
            "on_fraction": on / count if count else None,
            "event_time_us (first, last)": (first, last),
        }

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r}, sensor_size={self.sensor_size})"


def iter_events_as_chunks(events: Events | Iterable[Events | np.ndarray]) -> Iterator[np.ndarray]:
    """Normalise one ``Events`` (a single sample) or an iterable of ``Events``/structured chunks to chunks."""
    items = [events] if isinstance(events, (Events, np.ndarray)) else events
    for item in items:
        if isinstance(item, Events):
            if item.batch_size != 1:
                raise ValueError(f"events to write must be one sample, got batch_size {item.batch_size}; "
                                 "use events.sample(i)")
            yield structured_events(item.x.cpu().numpy(), item.y.cpu().numpy(), item.t.cpu().numpy(),
                                    item.p.cpu().numpy())
        elif isinstance(item, np.ndarray) and item.dtype.names and {"x", "y", "t", "p"} <= set(item.dtype.names):
            yield structured_events(item["x"], item["y"], item["t"], item["p"])
        else:
            raise ValueError(f"expected Events or structured arrays with x, y, t, p; got {type(item).__name__}")
