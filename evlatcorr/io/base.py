"""The reader interface: recordings yield ``EventFrames`` frame by frame with bounded memory."""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = ["FrameInfo", "Recording", "RecordingError", "frame_batch"]


class RecordingError(ValueError):
    """A recording that cannot be read as asked (names the file and, where it applies, the frame)."""


@dataclass
class FrameInfo:
    """One frame of a recording: exposure in µs and the image as float (C, H, W) in [0, 1]."""

    index: int
    exposure_start: float
    exposure_end: float
    image: np.ndarray


def frame_batch(info: FrameInfo, events: Events, meta: dict[str, Any]) -> EventFrames:
    """Wrap one frame and its events as a batch of 1."""
    return EventFrames(torch.from_numpy(np.ascontiguousarray(info.image))[None].float(), events,
                       torch.tensor([info.exposure_start], dtype=torch.float64),
                       torch.tensor([info.exposure_end], dtype=torch.float64), meta=meta)


class Recording:
    """Base class of readers.

    Iterating yields one :class:`~evlatcorr.EventFrames` per frame, whose events cover
    ``[exposure_start - before_us, exposure_end + after_us)``; ``after_us`` defaults to the
    exposure time, the corrector's default latency search range.

    Subclasses implement :meth:`frames` (frame metadata and images, in order) and
    :meth:`iter_event_chunks` (events in time order, as numpy structured chunks).
    """

    format_name = "?"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None) -> None:
        self.path = Path(path)
        if not self.path.exists():
            raise FileNotFoundError(f"{self.path}: no such file or directory")
        self.before_us, self.after_us = before_us, after_us
        self.sensor_size: tuple[int, int] = (0, 0)

    # to implement -------------------------------------------------------------------------
    def frames(self) -> Iterator[FrameInfo]:
        raise NotImplementedError

    def iter_event_chunks(self) -> Iterator[np.ndarray]:
        """Event chunks (structured arrays with x, y, t (µs), p (±1)) in time order."""
        raise NotImplementedError

    # shared -------------------------------------------------------------------------------
    def __iter__(self) -> Iterator[EventFrames]:
        """Stream frames: one pass over the events, holding only those still needed."""
        chunks = self.iter_event_chunks()
        buffer: list[np.ndarray] = []
        newest = -np.inf
        exhausted = False
        last_index, last_hi = -1, -np.inf
        for info in self.frames():
            after = (info.exposure_end - info.exposure_start) if self.after_us is None else self.after_us
            lo, hi = info.exposure_start - self.before_us, info.exposure_end + after
            while newest < hi and not exhausted:
                try:
                    chunk = next(chunks)
                except StopIteration:
                    exhausted = True
                    break
                if len(chunk):
                    buffer.append(chunk)
                    newest = float(chunk["t"][-1])
            # drop what no later frame can need (frames come in time order)
            buffer = [c for c in buffer if len(c) and c["t"][-1] >= lo]
            events = np.concatenate(buffer) if buffer else np.zeros(0, dtype=_EVENT_DTYPE)
            inside = events[(events["t"] >= lo) & (events["t"] < hi)]
            if exhausted and newest < hi:
                warnings.warn(f"{self.path}: frame {info.index}: events end at {newest:.0f} us, before the end of its "
                              f"window {hi:.0f} us (exposure end + {after:.0f} us); late events are missing",
                              stacklevel=2)
            n_exposure = int(((inside["t"] >= info.exposure_start) & (inside["t"] < info.exposure_end)).sum())
            if n_exposure == 0:
                warnings.warn(f"{self.path}: frame {info.index} has no events inside its exposure", stacklevel=2)
            ev = Events.from_numpy(inside, sensor_size=self.sensor_size)
            last_index, last_hi = info.index, hi
            yield frame_batch(info, ev, {"file": str(self.path), "frame": info.index})
        if not exhausted:
            later = sum(int((c["t"] >= last_hi).sum()) for c in buffer) + sum(len(c) for c in chunks)
            if later:
                warnings.warn(f"{self.path}: {later} events after the window of the last frame "
                              f"({last_index}) are not used", stacklevel=2)

    def __len__(self) -> int:
        return sum(1 for _ in self.frames())

    def frame(self, index: int) -> EventFrames:
        """One frame (streams up to it)."""
        for i, batch in enumerate(self):
            if i == index:
                return batch
        raise RecordingError(f"{self.path}: frame {index} out of range ({len(self)} frames)")

    def info(self) -> dict[str, Any]:
        """A summary: format, sensor size, frames, exposures, events and their time span."""
        frames = list(self.frames())
        count, first, last, on = 0, None, None, 0
        for chunk in self.iter_event_chunks():
            if len(chunk):
                count += len(chunk)
                on += int((chunk["p"] > 0).sum())
                first = float(chunk["t"][0]) if first is None else first
                last = float(chunk["t"][-1])
        exposures = [f.exposure_end - f.exposure_start for f in frames]
        return {
            "file": str(self.path), "format": self.format_name, "sensor_size (H, W)": self.sensor_size,
            "frames": len(frames), "channels": int(frames[0].image.shape[0]) if frames else 0,
            "exposure_us (min, max)": (min(exposures), max(exposures)) if exposures else None,
            "events": count, "on_fraction": on / count if count else None,
            "event_time_us (first, last)": (first, last),
            "frame_exposure_start_us (first, last)": (frames[0].exposure_start, frames[-1].exposure_start)
            if frames else None,
        }


_EVENT_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.float64), ("p", np.int8)])


def structured_events(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Pack columns into our structured layout (t float64 µs, p ±1)."""
    out = np.empty(len(t), dtype=_EVENT_DTYPE)
    out["x"], out["y"], out["t"] = x, y, t
    p = np.asarray(p)
    out["p"] = np.where(p.astype(bool) if p.dtype == bool or set(np.unique(p)) <= {0, 1} else p > 0, 1, -1)
    return out
