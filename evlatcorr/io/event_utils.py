"""event_utils-style HDF5 (TimoStoff/event_utils; also EFNet's raw-event files).

Layout read: ``/events/xs, ys, ts, ps`` and ``/images/image%09d`` datasets (H, W) or (H, W, 3)
with a ``timestamp`` attribute. Conventions converted once:

- ``ts`` and image timestamps in **seconds** (the event_utils default; ``time_unit="us"`` for
  files in microseconds; ``"auto"`` takes seconds when the largest event time is below 1e5);
- polarity 0/1 (or bool, or ±1) → ±1; images uint8 → [0, 1];
- exposure: the image attributes ``exposure_start`` / ``exposure_end`` (same time unit) when
  present, else ``timestamp`` ± ``exposure_us`` / 2 when the caller gives ``exposure_us``;
  otherwise a :class:`RecordingError` says so.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np

from evlatcorr.events import Events
from evlatcorr.io.base import FrameInfo, Recording, RecordingError, structured_events
from evlatcorr.io.h5 import atomic_path

__all__ = ["EventUtilsRecording", "write_event_utils", "is_event_utils_h5"]


def is_event_utils_h5(path: str | Path) -> bool:
    try:
        with h5py.File(path, "r") as f:
            return "events" in f and "xs" in f["events"] and "ts" in f["events"]
    except OSError:
        return False


class EventUtilsRecording(Recording):
    """Reader of event_utils-style HDF5 files."""

    format_name = "event_utils-h5"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 exposure_us: float | None = None, time_unit: str = "auto", chunk_events: int = 1 << 20) -> None:
        super().__init__(path, before_us, after_us)
        if time_unit not in ("auto", "s", "us"):
            raise ValueError(f"time_unit must be 'auto', 's' or 'us', got {time_unit!r}")
        self.exposure_us, self.chunk_events = exposure_us, chunk_events
        try:
            with h5py.File(self.path, "r") as f:
                if not is_event_utils_h5(self.path):
                    raise RecordingError(f"{self.path}: no /events/xs, ys, ts, ps: not an event_utils HDF5 file")
                ts = f["events/ts"]
                last = float(ts[-1]) if ts.shape[0] else 0.0
                self.scale = (1e6 if last < 1e5 else 1.0) if time_unit == "auto" else (1e6 if time_unit == "s" else 1.0)
                if "sensor_resolution" in f.attrs:
                    self.sensor_size = tuple(int(v) for v in f.attrs["sensor_resolution"])
                else:
                    first = next(iter(f["images"].values()), None) if "images" in f else None
                    if first is None:
                        raise RecordingError(f"{self.path}: no images and no sensor_resolution attribute")
                    self.sensor_size = tuple(int(v) for v in first.shape[:2])
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read as HDF5 ({exc})") from exc

    def frames(self) -> Iterator[FrameInfo]:
        with h5py.File(self.path, "r") as f:
            if "images" not in f:
                raise RecordingError(f"{self.path}: no /images group: latency correction needs frames")
            names = sorted(f["images"].keys())
            for i, name in enumerate(names):
                ds = f["images"][name]
                a = ds.attrs
                if "exposure_start" in a and "exposure_end" in a:
                    start, end = float(a["exposure_start"]) * self.scale, float(a["exposure_end"]) * self.scale
                elif "timestamp" in a and self.exposure_us is not None:
                    mid = float(a["timestamp"]) * self.scale
                    start, end = mid - self.exposure_us / 2, mid + self.exposure_us / 2
                else:
                    raise RecordingError(f"{self.path}: frame {i} ({name}) has no exposure_start/exposure_end "
                                         "attributes; pass exposure_us to centre an exposure on its timestamp")
                img = ds[:]
                img = img.astype(np.float32) / (255.0 if img.dtype == np.uint8 else 65535.0 if img.dtype == np.uint16
                                                 else 1.0)
                img = img[None] if img.ndim == 2 else np.ascontiguousarray(img[..., :3].transpose(2, 0, 1))
                yield FrameInfo(i, start, end, img)

    def iter_event_chunks(self) -> Iterator[np.ndarray]:
        with h5py.File(self.path, "r") as f:
            g = f["events"]
            n = g["ts"].shape[0]
            for i in range(0, n, self.chunk_events):
                j = min(n, i + self.chunk_events)
                yield structured_events(g["xs"][i:j], g["ys"][i:j], g["ts"][i:j] * self.scale, g["ps"][i:j])


def write_event_utils(path: str | Path, events: Events, like: EventUtilsRecording | None = None) -> None:
    """Write events (one sample) in event_utils layout, copying the images of ``like`` (atomic)."""
    scale = like.scale if like is not None else 1e6
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        g = f.create_group("events")
        g.create_dataset("xs", data=events.x.cpu().numpy().astype(np.int16), compression="lzf")
        g.create_dataset("ys", data=events.y.cpu().numpy().astype(np.int16), compression="lzf")
        g.create_dataset("ts", data=events.t.cpu().numpy() / scale, compression="lzf")
        g.create_dataset("ps", data=(events.p.cpu().numpy() > 0).astype(np.uint8), compression="lzf")
        f.attrs["sensor_resolution"] = list(events.sensor_size)
        if like is not None:
            with h5py.File(like.path, "r") as src:
                if "images" in src:
                    src.copy(src["images"], f, "images")
