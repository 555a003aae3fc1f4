"""GEM's NPZ pairs (Zhang et al., ICCV 2023; Ev-REDS / MS-RBD layout).

One ``.npz`` holds two consecutive blurry frames and their events. Keys read: ``blur1``, ``blur2``
(C, H, W; uint8 or float), ``exp_start1``, ``exp_end1``, ``exp_start2``, ``exp_end2`` (integers),
``events`` (a pickled dict with ``x``, ``y``, ``t``, ``p``), optional ``sharp_imgs`` (N, C, H, W) with
``sharp_timestamps`` (N,), and ``scale_factor``. Conventions converted once:

- timestamps: microseconds by default (``time_unit="us"``); ``"s"`` multiplies by 1e6;
- polarity 0/1, bool or ±1 → ±1;
- ``scale_factor`` > 1 means events at a lower resolution than the frames (Ev-REDS: 4); latency
  correction needs pixel-aligned events and frames, so such files are refused with a clear message.

A directory of ``.npz`` files is read in name order, two frames per file.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evlatcorr.io.base import FrameInfo, Recording, RecordingError, structured_events

__all__ = ["GemNpzRecording", "is_gem_npz"]

_KEYS = {"blur1", "blur2", "exp_start1", "exp_end1", "exp_start2", "exp_end2", "events"}


def is_gem_npz(path: str | Path) -> bool:
    path = Path(path)
    files = sorted(path.glob("*.npz")) if path.is_dir() else [path]
    if not files or files[0].suffix != ".npz":
        return False
    try:
        with np.load(files[0], allow_pickle=True) as z:
            return _KEYS <= set(z.files)
    except (OSError, ValueError):
        return False


class GemNpzRecording(Recording):
    """Reader of GEM's NPZ pairs (a file or a directory of them)."""

    format_name = "gem-npz"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 time_unit: str = "us") -> None:
        super().__init__(path, before_us, after_us)
        if time_unit not in ("us", "s"):
            raise ValueError(f"time_unit must be 'us' or 's', got {time_unit!r}")
        self.scale = 1e6 if time_unit == "s" else 1.0
        self.files = sorted(self.path.glob("*.npz")) if self.path.is_dir() else [self.path]
        if not self.files:
            raise RecordingError(f"{self.path}: no .npz files")
        first = self._load(self.files[0])
        self.sensor_size = tuple(int(v) for v in np.asarray(first["blur1"]).shape[-2:])

    def _load(self, file: Path) -> dict:
        try:
            with np.load(file, allow_pickle=True) as z:
                missing = _KEYS - set(z.files)
                if missing:
                    raise RecordingError(f"{file}: not a GEM npz pair, missing keys {sorted(missing)}")
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError) as exc:
            raise RecordingError(f"{file}: cannot read npz ({exc})") from exc
        scale_factor = int(np.asarray(data.get("scale_factor", 1)))
        if scale_factor != 1:
            raise RecordingError(f"{file}: events are {scale_factor}x lower resolution than the frames "
                                 "(scale_factor); latency correction needs pixel-aligned events")
        events = data["events"]
        data["events"] = events.item() if isinstance(events, np.ndarray) and events.dtype == object else events
        return data

    @staticmethod
    def _image(blur: np.ndarray) -> np.ndarray:
        blur = np.asarray(blur)
        img = blur.astype(np.float32) / (255.0 if blur.dtype == np.uint8 else 1.0)
        return img[None] if img.ndim == 2 else img

    def frames(self) -> Iterator[FrameInfo]:
        index = 0
        for file in self.files:
            data = self._load(file)
            for k in (1, 2):
                start, end = float(data[f"exp_start{k}"]) * self.scale, float(data[f"exp_end{k}"]) * self.scale
                if not end > start:
                    raise RecordingError(f"{file}: frame {index} (blur{k}) has exposure end {end} <= start {start}")
                yield FrameInfo(index, start, end, self._image(data[f"blur{k}"]))
                index += 1

    def iter_event_chunks(self) -> Iterator[np.ndarray]:
        last = -np.inf
        for file in self.files:
            ev = self._load(file)["events"]
            chunk = structured_events(np.asarray(ev["x"]), np.asarray(ev["y"]),
                                      np.asarray(ev["t"], dtype=np.float64) * self.scale, np.asarray(ev["p"]))
            chunk = chunk[np.argsort(chunk["t"], kind="stable")]
            if len(chunk) and chunk["t"][0] <= last:  # overlapping pairs repeat events already yielded
                chunk = chunk[chunk["t"] > last]
            if len(chunk):
                last = float(chunk["t"][-1])
                yield chunk
