"""What readers hand over: :class:`FrameInfo`, the :class:`SegmentEnd` marker, our event layout, the error.

These sit below every other module of :mod:`evlatcorr.io` (no imports from the package), so the
conversion, validation and streaming helpers can all share them.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["EVENT_DTYPE", "FrameInfo", "RecordingError", "SEGMENT_END", "SegmentEnd", "no_events", "starts_with"]

#: Our in-memory layout of an event chunk (t in µs; p ±1).
EVENT_DTYPE = np.dtype([("x", np.int32), ("y", np.int32), ("t", np.float64), ("p", np.int8)])


def no_events() -> np.ndarray:
    """An empty chunk in our layout."""
    return np.zeros(0, dtype=EVENT_DTYPE)


def starts_with(path: str | Path, magic: bytes) -> bool:
    """Whether ``path`` is a file whose first bytes are ``magic`` (a format's signature)."""
    path = Path(path)
    if not path.is_file():
        return False
    with open(path, "rb") as f:
        return f.read(len(magic)) == magic


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
