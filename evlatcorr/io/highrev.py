"""HighREV (Sun et al., CVPR 2023): blur/sharp PNGs and one event NPZ per sharp-frame interval.

Layout read (one video)::

    <root>/<split>/<video>/blur/*.png          blurry frames, in name order
    <root>/<split>/<video>/gt/*.png            sharp frames (optional)
    <root>/<split>_event/<video>/*.npz         keys x, y, timestamp, polarity; one per interval

Pass the video's ``blur`` folder's parent (``<root>/<split>/<video>``); the event folder is found
beside it (or give ``event_dir``). Blurry frame ``k`` averages ``m`` sharp frames, and ``n`` sharp
frames are skipped before the next one (REFID's 11+1 setting by default), so its events are the NPZ
files ``k·(m+n) .. k·(m+n)+m−2`` (the ``m−1`` intervals between its sharp frames).

Conventions converted once: HighREV stores **no exposure times**, so a frame's exposure is taken
as the span of its own event files' timestamps (first to last event); the NPZ ``x`` and ``y`` are
swapped with respect to the images (``swap_xy=True``, as the dataset notes); timestamps are taken
as microseconds (``time_unit="s"`` multiplies by 1e6); polarity 0/1 → ±1.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evlatcorr.io.base import FrameInfo, Recording, RecordingError, structured_events

__all__ = ["HighREVRecording", "is_highrev"]


def _event_dir(video: Path) -> Path:
    split = video.parent
    return split.parent / f"{split.name}_event" / video.name


def is_highrev(path: str | Path) -> bool:
    path = Path(path)
    return path.is_dir() and (path / "blur").is_dir() and _event_dir(path).is_dir()


class HighREVRecording(Recording):
    """Reader of one HighREV video (see the module docstring for the layout and conventions)."""

    format_name = "highrev"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None, m: int = 11,
                 n: int = 1, event_dir: str | Path | None = None, swap_xy: bool = True,
                 time_unit: str = "us") -> None:
        super().__init__(path, before_us, after_us)
        if m < 2 or n < 0:
            raise ValueError(f"need m >= 2 sharp frames per blurry frame and n >= 0, got m={m}, n={n}")
        if time_unit not in ("us", "s"):
            raise ValueError(f"time_unit must be 'us' or 's', got {time_unit!r}")
        self.m, self.n, self.swap_xy, self.scale = m, n, swap_xy, 1e6 if time_unit == "s" else 1.0
        self.blur_files = sorted((self.path / "blur").glob("*.png"))
        self.event_dir = Path(event_dir) if event_dir is not None else _event_dir(self.path)
        self.event_files = sorted(self.event_dir.glob("*.npz"))
        if not self.blur_files:
            raise RecordingError(f"{self.path}: no blur/*.png frames")
        if not self.event_files:
            raise RecordingError(f"{self.event_dir}: no event .npz files")
        from PIL import Image

        with Image.open(self.blur_files[0]) as im:
            self.sensor_size = (im.height, im.width)

    def _load(self, file: Path) -> np.ndarray:
        try:
            with np.load(file) as z:
                missing = {"x", "y", "timestamp", "polarity"} - set(z.files)
                if missing:
                    raise RecordingError(f"{file}: not a HighREV event file, missing keys {sorted(missing)}")
                x, y = (z["y"], z["x"]) if self.swap_xy else (z["x"], z["y"])
                ev = structured_events(x, y, z["timestamp"].astype(np.float64) * self.scale, z["polarity"])
        except (OSError, ValueError, EOFError) as exc:
            raise RecordingError(f"{file}: cannot read npz ({exc})") from exc
        return ev[np.argsort(ev["t"], kind="stable")]

    def frames(self) -> Iterator[FrameInfo]:
        from PIL import Image

        for k, blur in enumerate(self.blur_files):
            first = k * (self.m + self.n)
            files = self.event_files[first:first + self.m - 1]
            if len(files) < self.m - 1:
                raise RecordingError(f"{self.path}: frame {k} ({blur.name}) needs event files {first}..."
                                     f"{first + self.m - 2}, but there are only {len(self.event_files)}")
            times = [self._load(f)["t"] for f in files]
            times = [t for t in times if len(t)]
            if not times:
                raise RecordingError(f"{self.path}: frame {k} ({blur.name}) has no events: its exposure "
                                     "(taken from the event timestamps) is unknown")
            start, end = float(times[0][0]), float(times[-1][-1])
            with Image.open(blur) as im:
                img = np.asarray(im.convert("RGB"), dtype=np.float32) / 255.0
            if img.shape[:2] != self.sensor_size:
                raise RecordingError(f"{blur}: frame {k} is {img.shape[:2]}, expected {self.sensor_size}")
            yield FrameInfo(k, start, max(end, start + 1.0), np.ascontiguousarray(img.transpose(2, 0, 1)))

    def iter_event_chunks(self) -> Iterator[np.ndarray]:
        for file in self.event_files:
            chunk = self._load(file)
            if len(chunk):
                yield chunk
