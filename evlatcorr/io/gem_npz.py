"""GEM's NPZ pairs (Zhang et al., ICCV 2023: Ev-REDS, HS-ERGB and MS-RBD as packed by XiangZ-0/GEM).

One ``.npz`` holds two consecutive blurry frames and the events between the first exposure's
start and the second's end. Keys::

    blur1, blur2                 (C, H, W) images, 0..255 (uint8 or float)
    exp_start1, exp_end1,        integers: exposure start/end of each frame
    exp_start2, exp_end2
    events                       a pickled dict with x, y, t, p (t integers, p ±1 or 0/1)
    sharp_imgs                   optional (N, C, H, W) ground truth, 0..255
    sharp_timestamps             optional (N,) their times
    scale_factor                 image resolution / event resolution (MS-RBD, Ev-REDS: 4)

Conventions converted once:

- timestamps: microseconds by default (``time_unit`` = ``"s"``, ``"ms"`` or ``"ns"`` to convert);
- polarity 0/1, bool or ±1 → ±1; images divided by 255 (GEM's own loader does the same);
- ``scale_factor`` > 1 means events at a lower resolution than the frames; latency correction
  needs pixel-aligned events and frames, so such files are refused unless
  ``downsample_frames=True``, which averages the frames over ``scale_factor²`` blocks down to
  the event resolution;
- ground truth: each frame gets as ``sharp`` the sharp image nearest its mid-exposure and as
  targets (``target_times`` / ``target_frames``) all sharp images inside its exposure.

Each file is an independent segment (pairs may overlap or come from different sequences), so a
frame's window only holds that file's events: the second frame's window past its exposure end
is empty (with a warning) because GEM stores no events after it.
"""

from __future__ import annotations

import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.io.base import Recording
from evlatcorr.io.conversions import sorted_by_time, structured_events, time_scale, to_microseconds, to_unit_image
from evlatcorr.io.npz_access import open_npz
from evlatcorr.io.records import FrameInfo, RecordingError, SegmentEnd

__all__ = ["GemNpzRecording", "is_gem_npz"]

_KEYS = {"blur1", "blur2", "exp_start1", "exp_end1", "exp_start2", "exp_end2", "events"}


def _files(path: Path) -> list[Path]:
    return sorted(path.glob("*.npz")) if path.is_dir() else [path]


def is_gem_npz(path: str | Path) -> bool:
    """Whether ``path`` is a GEM pair ``.npz`` (or a folder whose first ``.npz`` is one)."""
    path = Path(path)
    files = _files(path)
    if not files or files[0].suffix != ".npz" or not files[0].is_file():
        return False
    try:
        with np.load(files[0], allow_pickle=True) as z:
            return _KEYS <= set(z.files)
    except (OSError, ValueError, EOFError, zipfile.BadZipFile):
        return False


class GemNpzRecording(Recording):
    """Reader of GEM's NPZ pairs (a file or a folder of them, read in name order).

    Args:
        path: an ``.npz`` file or a folder of them.
        before_us: events to include before exposure start (µs).
        after_us: events to include after exposure end (µs); ``None``: the exposure time.
        time_unit: unit of the file's timestamps: ``"us"`` (default), ``"ms"``, ``"s"`` or ``"ns"``.
        downsample_frames: for files with ``scale_factor`` > 1, average the frames down to the
            events' resolution instead of refusing the file.

    Example:
        >>> rec = GemNpzRecording("MS-RBD/test", downsample_frames=True)  # doctest: +SKIP
        >>> rec.sensor_size  # doctest: +SKIP
        (192, 288)
    """

    format_name = "gem-npz"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 time_unit: str = "us", downsample_frames: bool = False) -> None:
        super().__init__(path, before_us, after_us)
        self.scale, self.downsample_frames = time_scale(time_unit), downsample_frames
        self.files = _files(self.path)
        if not self.files:
            raise RecordingError(f"{self.path}: no .npz files")
        self._cache: tuple[Path, dict[str, Any]] | None = None
        first = self._load(self.files[0])
        self.sensor_size = tuple(int(v) for v in self._image(first["blur1"], first["scale_factor"],
                                                             f"{self.files[0]}: blur1").shape[-2:])
        self.segment_names = [f.name for f in self.files] if len(self.files) > 1 else []

    def _load(self, file: Path) -> dict[str, Any]:
        if self._cache is not None and self._cache[0] == file:
            return self._cache[1]
        with open_npz(file, _KEYS, "a GEM npz pair", allow_pickle=True) as z:
            data = {k: z[k] for k in z.files}
        data["scale_factor"] = int(np.asarray(data.get("scale_factor", 1)))
        if data["scale_factor"] < 1:
            raise RecordingError(f"{file}: scale_factor must be >= 1, got {data['scale_factor']}")
        if data["scale_factor"] > 1 and not self.downsample_frames:
            raise RecordingError(f"{file}: events are {data['scale_factor']}x lower resolution than the frames "
                                 "(scale_factor); latency correction needs pixel-aligned events: pass "
                                 "downsample_frames=True to average the frames down to the events' resolution")
        events = data["events"]
        if isinstance(events, np.ndarray) and events.dtype == object:
            events = events.item()
        if not isinstance(events, dict) or not {"x", "y", "t", "p"} <= set(events):
            raise RecordingError(f"{file}: 'events' must be a dict with x, y, t, p")
        lengths = {k: np.asarray(events[k]).size for k in ("x", "y", "t", "p")}
        if len(set(lengths.values())) > 1:
            raise RecordingError(f"{file}: events x, y, t, p differ in length: "
                                 + ", ".join(f"{k} {n}" for k, n in lengths.items()))
        if "sharp_imgs" in data and "sharp_timestamps" in data:
            images, stamps = len(np.asarray(data["sharp_imgs"])), np.asarray(data["sharp_timestamps"]).size
            if images != stamps:
                raise RecordingError(f"{file}: sharp_imgs holds {images} images but sharp_timestamps {stamps} times")
        data["events"] = events
        self._cache = (file, data)
        return data

    def _image(self, a: np.ndarray, scale_factor: int, where: str) -> np.ndarray:
        img = to_unit_image(a, where, channels_last=False, scale=1 / 255.0)
        if scale_factor > 1:
            c, h, w = img.shape
            if h % scale_factor or w % scale_factor:
                raise RecordingError(f"{where}: frame size {(h, w)} is not a multiple of scale_factor {scale_factor}")
            img = img.reshape(c, h // scale_factor, scale_factor, w // scale_factor, scale_factor).mean((2, 4))
        return np.ascontiguousarray(img, dtype=np.float32)

    def _exposures(self, data: dict[str, Any], file: Path, index: int) -> list[tuple[float, float]]:
        out = []
        for k in (1, 2):
            start = float(to_microseconds(data[f"exp_start{k}"], self.scale))
            end = float(to_microseconds(data[f"exp_end{k}"], self.scale))
            if not end > start:
                raise RecordingError(f"{file}: frame {index + k - 1} (blur{k}) has exposure end {end} us <= start "
                                     f"{start} us")
            out.append((start, end))
        return out

    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        times = []
        for seg, file in enumerate(self.files):
            times.extend((s, e, seg) for s, e in self._exposures(self._load(file), file, len(times)))
        return times

    def frames(self) -> Iterator[FrameInfo]:
        index = 0
        for seg, file in enumerate(self.files):
            data = self._load(file)
            sf = data["scale_factor"]
            stamps = sharp = None
            if "sharp_imgs" in data and "sharp_timestamps" in data:
                stamps = to_microseconds(data["sharp_timestamps"], self.scale).reshape(-1)
                sharp = np.asarray(data["sharp_imgs"])
            for k, (start, end) in enumerate(self._exposures(data, file, index), start=1):
                where = f"{file}: frame {index} (blur{k})"
                image = self._image(data[f"blur{k}"], sf, where)
                if image.shape[-2:] != self.sensor_size:
                    raise RecordingError(f"{where} is {image.shape[-2:]}, expected {self.sensor_size}")
                info = FrameInfo(index, start, end, image, segment=seg, meta={"source": file.name, "pair": k})
                if stamps is not None and len(stamps):
                    mid = (start + end) / 2
                    nearest = int(np.argmin(np.abs(stamps - mid)))
                    info.sharp = self._image(sharp[nearest], sf, where + " sharp")
                    inside = np.nonzero((stamps >= start) & (stamps <= end))[0]
                    if len(inside):
                        info.targets = (stamps[inside],
                                        np.stack([self._image(sharp[i], sf, where + " sharp") for i in inside]))
                yield info
                index += 1

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        for seg, file in enumerate(self.files):
            if seg:
                yield SegmentEnd()
            ev = self._load(file)["events"]
            chunk = structured_events(np.asarray(ev["x"]), np.asarray(ev["y"]), to_microseconds(ev["t"], self.scale),
                                      np.asarray(ev["p"]), where=f"{file}: events")
            chunk = sorted_by_time(chunk)
            if len(chunk):
                yield chunk
