"""event_utils-style HDF5 (TimoStoff/event_utils ``hdf5_packager``; also EFNet's raw-event files).

Layout read::

    /events/xs, ys          int16 (N,)       column, row
    /events/ts              float64 (N,)     seconds (the event_utils convention) or µs
    /events/ps              bool/uint8 (N,)  1 = ON (0/1, bool or ±1 accepted)
    /images/image%09d       uint8 (H, W), (H, W, 3) or (3, H, W); attrs: timestamp, type, size, event_idx
    /sharp_images/image%09d optional ground truth (EFNet), same layout
    root attrs              sensor_resolution (H, W), num_events, num_pos, num_neg, t0, tk, num_imgs, ...

Conventions converted once:

- time unit: ``time_unit="auto"`` takes the root attribute ``time_unit`` when there is one (our
  writer sets it); otherwise seconds when ``ts`` holds fractional values below 1e5, else µs.
  ``"s"``, ``"ms"``, ``"us"``, ``"ns"`` force it. Everything is converted to µs (rounded to the
  nanosecond when converted, so whole-µs stamps stored in seconds come back exact);
- polarity 0/1 (or bool, or ±1) → ±1; images uint8 → [0, 1]; an image with ``type="color_bgr"``
  (event_utils writes OpenCV's BGR order) is flipped to RGB;
- sensor size: ``sensor_resolution`` is ``(H, W)`` in event_utils; when it disagrees with the
  images, the images win (with a warning);
- exposure: event_utils stores one ``timestamp`` per image, not an exposure. The image attributes
  ``exposure_start`` / ``exposure_end`` (same time unit; our writer adds them) are used when
  present; otherwise, when the caller gives ``exposure_us``, an exposure of that length placed by
  ``timestamp_is`` (``"middle"`` by default, ``"start"`` or ``"end"``); otherwise a
  :class:`RecordingError` names the file and the frame.
"""

from __future__ import annotations

import re
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path

import h5py
import numpy as np

from evlatcorr.events import Events
from evlatcorr.io.base import Recording
from evlatcorr.io.conversions import (
    TIME_UNITS,
    iter_events_as_chunks,
    structured_events,
    time_scale,
    to_microseconds,
    to_unit_image,
)
from evlatcorr.io.h5 import atomic_path
from evlatcorr.io.hdf5_access import IndexedH5Recording, bisect_sorted, check_columns, is_hdf5_with, open_h5
from evlatcorr.io.records import EVENT_DTYPE, FrameInfo, RecordingError, SegmentEnd
from evlatcorr.sample_warnings import user_stacklevel

__all__ = ["EventUtilsRecording", "is_event_utils_h5", "write_event_utils"]

_UNITS = TIME_UNITS


def is_event_utils_h5(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 file with ``/events/xs``, ``ys``, ``ts``, ``ps``."""
    return is_hdf5_with(path, lambda f: "events" in f and all(k in f["events"] for k in ("xs", "ys", "ts", "ps")))


def _image_names(group: h5py.Group) -> list[str]:
    def key(name: str) -> tuple[int, str]:
        m = re.search(r"(\d+)$", name)
        return (int(m.group(1)) if m else -1, name)

    return sorted(group.keys(), key=key)


def _image(ds: h5py.Dataset, where: str) -> np.ndarray:
    a = ds[()]
    channels_last = not (a.ndim == 3 and a.shape[0] in (1, 3) and a.shape[-1] not in (1, 3, 4))
    img = to_unit_image(a, where, channels_last=channels_last)
    kind = ds.attrs.get("type", "")
    kind = kind.decode() if isinstance(kind, bytes) else str(kind)
    if img.shape[0] == 3 and "bgr" in kind.lower():
        img = np.ascontiguousarray(img[::-1])
    return img


class EventUtilsRecording(IndexedH5Recording):
    """Reader of event_utils-style HDF5 files (see the module docstring for conventions).

    Args:
        path: the ``.h5`` file.
        before_us: events to include before exposure start (µs).
        after_us: events to include after exposure end (µs); ``None``: the exposure time.
        exposure_us: exposure length for files whose images only carry a ``timestamp``.
        timestamp_is: where ``timestamp`` lies in that exposure: ``"middle"``, ``"start"`` or ``"end"``.
        time_unit: ``"auto"``, ``"s"``, ``"ms"``, ``"us"`` or ``"ns"`` (of ``ts`` and image attributes).
        chunk_events: events per read when streaming.

    Example:
        >>> rec = EventUtilsRecording("esim.h5", exposure_us=10_000)  # doctest: +SKIP
        >>> batch = rec.frame(0)  # doctest: +SKIP
    """

    format_name = "event_utils-h5"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 exposure_us: float | None = None, time_unit: str = "auto", chunk_events: int = 1 << 20,
                 timestamp_is: str = "middle") -> None:
        super().__init__(path, before_us, after_us)
        if time_unit != "auto" and time_unit not in _UNITS:
            raise ValueError(f"time_unit must be 'auto' or one of {sorted(_UNITS)}, got {time_unit!r}")
        if timestamp_is not in ("middle", "start", "end"):
            raise ValueError(f"timestamp_is must be 'middle', 'start' or 'end', got {timestamp_is!r}")
        if exposure_us is not None and not exposure_us > 0:
            raise ValueError(f"exposure_us must be positive, got {exposure_us}")
        self._set_chunk_events(chunk_events)
        self.exposure_us, self.timestamp_is = exposure_us, timestamp_is
        if not is_event_utils_h5(self.path):
            with open_h5(self.path):  # a RecordingError for files that are not HDF5 at all
                pass
            raise RecordingError(f"{self.path}: no /events/xs, ys, ts, ps: not an event_utils HDF5 file")
        with open_h5(self.path) as f:
            ts = f["events/ts"]
            self._check_columns(f["events"])
            self.time_unit = self._detect_unit(f, ts) if time_unit == "auto" else time_unit
            self.scale = _UNITS[self.time_unit]
            self.sensor_size = self._sensor_size(f)

    def _check_columns(self, g: h5py.Group) -> None:
        """``/events/xs, ys, ts, ps`` must be columns of one length (checked from their shapes)."""
        check_columns(g, ("xs", "ys", "ts", "ps"), f"{self.path}: /events")

    def _detect_unit(self, f: h5py.File, ts: h5py.Dataset) -> str:
        unit = f.attrs.get("time_unit")
        if unit is not None:
            unit = unit.decode() if isinstance(unit, bytes) else str(unit)
            if unit not in _UNITS:
                raise RecordingError(f"{self.path}: unknown time_unit attribute {unit!r}")
            return unit
        if ts.shape[0] == 0 or not np.issubdtype(ts.dtype, np.floating):
            return "us"
        head = ts[: min(ts.shape[0], 4096)]
        fractional = bool(np.any(head != np.round(head)))
        return "s" if fractional and abs(float(ts[-1])) < 1e5 else "us"

    def _sensor_size(self, f: h5py.File) -> tuple[int, int]:
        from_images = None
        if "images" in f and len(f["images"]):
            first = f["images"][_image_names(f["images"])[0]]
            shape = first.shape
            from_images = tuple(int(v) for v in (shape[1:] if len(shape) == 3 and shape[0] in (1, 3)
                                                 and shape[-1] not in (1, 3, 4) else shape[:2]))
        if "sensor_resolution" in f.attrs:
            res = tuple(int(v) for v in np.asarray(f.attrs["sensor_resolution"]).reshape(-1)[:2])
            if from_images is not None and res != from_images:
                warnings.warn(f"{self.path}: sensor_resolution {res} disagrees with the images {from_images} "
                              "(H, W); using the images'", stacklevel=user_stacklevel())
                return from_images
            return res
        if from_images is None:
            raise RecordingError(f"{self.path}: no images and no sensor_resolution attribute")
        return from_images

    # frames -------------------------------------------------------------------------------
    def _exposure(self, ds: h5py.Dataset, index: int, name: str) -> tuple[float, float]:
        a = ds.attrs
        if "exposure_start" in a and "exposure_end" in a:
            if self.exposure_us is not None:  # one message for the file (warnings show each once)
                warnings.warn(f"{self.path}: images with their own exposure_start/exposure_end keep them; "
                              f"exposure_us={self.exposure_us:g} is used only for images with a timestamp alone",
                              stacklevel=user_stacklevel())
            return float(self._us(float(a["exposure_start"]))), float(self._us(float(a["exposure_end"])))
        if "timestamp" in a and self.exposure_us is not None:
            t = float(self._us(float(a["timestamp"])))
            offset = {"middle": self.exposure_us / 2, "start": 0.0, "end": self.exposure_us}[self.timestamp_is]
            return t - offset, t - offset + self.exposure_us
        raise RecordingError(f"{self.path}: frame {index} ({name}) has no exposure_start/exposure_end attributes; "
                             "pass exposure_us (and timestamp_is) to place an exposure around its timestamp")

    def _images_group(self, f: h5py.File) -> h5py.Group:
        if "images" not in f or not len(f["images"]):
            raise RecordingError(f"{self.path}: no /images: latency correction needs frames")
        return f["images"]

    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        with open_h5(self.path) as f:
            g = self._images_group(f)
            return [(*self._exposure(g[n], i, n), 0) for i, n in enumerate(_image_names(g))]

    def _frame_info(self, f: h5py.File, index: int, name: str) -> FrameInfo:
        ds = self._images_group(f)[name]
        start, end = self._exposure(ds, index, name)
        image = _image(ds, f"{self.path}: frame {index} ({name})")
        sharp = None
        if "sharp_images" in f and name in f["sharp_images"]:
            sharp = _image(f["sharp_images"][name], f"{self.path}: sharp frame {index} ({name})")
        return FrameInfo(index, start, end, image, sharp=sharp, meta={"image": name})

    def frames(self) -> Iterator[FrameInfo]:
        with open_h5(self.path) as f:
            for i, name in enumerate(_image_names(self._images_group(f))):
                yield self._frame_info(f, i, name)

    # events -------------------------------------------------------------------------------
    def _us(self, t: np.ndarray | float) -> np.ndarray:
        return to_microseconds(t, self.scale)

    def _columns(self, g: h5py.Group, i: int, j: int) -> np.ndarray:
        return structured_events(g["xs"][i:j], g["ys"][i:j], self._us(g["ts"][i:j].astype(np.float64)), g["ps"][i:j],
                                 where=f"{self.path}: /events (events {i}..{j - 1})")

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        with open_h5(self.path) as f:
            g = f["events"]
            n = g["ts"].shape[0]
            for i, j in self._chunk_ranges(n):
                yield self._columns(g, i, j)

    def _slice(self, f: h5py.File, segment: int, t0: float, t1: float) -> np.ndarray:
        g = f["events"]
        # search a hair wider in file units (the unit conversion rounds), then cut exactly in µs
        a, b = t0 / self.scale, t1 / self.scale
        i = bisect_sorted(g["ts"], a - abs(a) * 1e-12 - 1e-300)
        j = bisect_sorted(g["ts"], b + abs(b) * 1e-12 + 1e-300, lo=i)
        ev = self._columns(g, i, j) if j > i else np.zeros(0, dtype=EVENT_DTYPE)
        # the unit conversion can move a boundary event across t0/t1 by rounding: filter in µs
        return ev[(ev["t"] >= t0) & (ev["t"] < t1)]

    def _read_frame_window(self, index: int) -> tuple[FrameInfo, np.ndarray, tuple[float | None, float]]:
        with open_h5(self.path) as f:
            name = _image_names(self._images_group(f))[index]
            info = self._frame_info(f, index, name)
            events = self._slice(f, 0, *self.window(info.exposure_start, info.exposure_end))
            ts = f["events/ts"]
            return info, events, ((float(self._us(ts[0])), float(self._us(ts[-1]))) if ts.shape[0] else (None, -np.inf))


def write_event_utils(path: str | Path, events: Events | Iterable[Events | np.ndarray],
                      like: Recording | None = None, time_unit: str | None = None,
                      sensor_size: tuple[int, int] | None = None) -> None:
    """Write events in event_utils layout (atomic), with the frames of ``like``.

    Args:
        path: output file.
        events: one sample of :class:`Events`, or an iterable of time-sorted chunks (``Events`` or
            structured arrays) for outputs larger than memory.
        like: a recording whose frames are written too: an :class:`EventUtilsRecording`'s image
            groups are copied as they are; other recordings' frames are written as uint8 images
            (lossy: use our HDF5 format to keep float frames) with ``timestamp`` at mid-exposure
            and ``exposure_start`` / ``exposure_end`` attributes.
        time_unit: unit of ``ts``; defaults to ``like``'s for an event_utils input, else seconds.
        sensor_size: ``(H, W)``; defaults to ``like``'s or the events'.

    Example:
        >>> write_event_utils("corrected.h5", corrected_events, like=recording)  # doctest: +SKIP
    """
    if time_unit is None:
        time_unit = like.time_unit if isinstance(like, EventUtilsRecording) else "s"
    scale = time_scale(time_unit)
    if sensor_size is None:
        sensor_size = like.sensor_size if like is not None else getattr(events, "sensor_size", None)
        if sensor_size is None:
            raise ValueError("write_event_utils needs sensor_size (or like=) when given chunks")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        kw = dict(shape=(0,), maxshape=(None,), chunks=(65536,), compression="lzf")
        ds = {"xs": f.create_dataset("events/xs", dtype=np.int16, **kw),
              "ys": f.create_dataset("events/ys", dtype=np.int16, **kw),
              "ts": f.create_dataset("events/ts", dtype=np.float64, **kw),
              "ps": f.create_dataset("events/ps", dtype=np.bool_, **kw)}
        n, pos, t_first, t_last = 0, 0, None, None
        for chunk in iter_events_as_chunks(events):
            if not len(chunk):
                continue
            if t_last is not None and chunk["t"][0] < t_last:
                raise ValueError("write_event_utils needs event chunks sorted by time")
            m = n + len(chunk)
            for name, values in (("xs", chunk["x"]), ("ys", chunk["y"]), ("ts", chunk["t"] / scale),
                                 ("ps", chunk["p"] > 0)):
                ds[name].resize((m,))
                ds[name][n:] = values
            pos += int((chunk["p"] > 0).sum())
            t_first = float(chunk["t"][0]) if t_first is None else t_first
            t_last, n = float(chunk["t"][-1]), m
        num_imgs = 0
        if isinstance(like, EventUtilsRecording):
            with open_h5(like.path) as src:
                for group in ("images", "sharp_images"):
                    if group in src:
                        src.copy(src[group], f, group)
                num_imgs = len(src["images"]) if "images" in src else 0
        elif like is not None:
            for info in like.frames():
                img = np.round(np.clip(info.image, 0, 1) * 255).astype(np.uint8)
                img = img[0] if img.shape[0] == 1 else np.ascontiguousarray(img[::-1].transpose(1, 2, 0))  # BGR
                d = f.create_dataset(f"images/image{info.index:09d}", data=img)
                d.attrs["size"] = img.shape
                d.attrs["timestamp"] = (info.exposure_start + info.exposure_end) / 2 / scale
                d.attrs["exposure_start"] = info.exposure_start / scale
                d.attrs["exposure_end"] = info.exposure_end / scale
                d.attrs["type"] = "greyscale" if img.ndim == 2 else "color_bgr"
                num_imgs += 1
        if "images" in f:
            ts = ds["ts"]
            for name in _image_names(f["images"]):
                stamp = f["images"][name].attrs.get("timestamp")
                if stamp is not None:
                    f["images"][name].attrs["event_idx"] = max(0, bisect_sorted(ts, float(stamp)) - 1) if n else 0
        f.attrs.update({"num_events": n, "num_pos": pos, "num_neg": n - pos, "num_imgs": num_imgs, "num_flow": 0,
                        "t0": (t_first or 0.0) / scale, "tk": (t_last or 0.0) / scale,
                        "duration": ((t_last or 0.0) - (t_first or 0.0)) / scale,
                        "sensor_resolution": [int(v) for v in sensor_size], "time_unit": time_unit})
