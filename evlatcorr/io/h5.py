"""Our HDF5 dataset format (written by the simulator, the benchmark cache and ``evlatcorr correct``).

Layout (all times in microseconds, polarity ±1, sensor size (H, W)):

```
/                       attrs: format="evlatcorr", version=1, sensor_size=[H, W], time_unit="us"
/events/x, y            uint16 (N,)     column, row
/events/t               float64 (N,)    sorted, µs (float keeps the simulator's sub-µs times)
/events/p               int8 (N,)       ±1
/frames/blurry          float32 (F, C, H, W) in [0, 1], one chunk per frame
/frames/exposure_start  float64 (F,)
/frames/exposure_end    float64 (F,)
/frames/sharp           float32 (F, C, H, W)   optional ground truth at mid-exposure
/frames/latency         float32 (F, 1, H, W)   optional true latency (µs)
/frames/estimated_latency float32 (F,)        optional, written by `evlatcorr correct`
/ideal_events/x, y, t, p                        optional events without latency
/targets/times          float64 (T,)           optional times of ground-truth frames
/targets/frames         float32 (T, C, H, W)
```

Event datasets are chunked (64 Ki events) and LZF-compressed; readers find a frame's events by
binary search on ``t``, so memory stays bounded by one frame's window. Writers write to a
temporary file in the same folder and rename it, so a failed write leaves nothing behind.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from evlatcorr.events import Events
from evlatcorr.io.base import FrameInfo, Recording, RecordingError, structured_events

__all__ = ["H5Recording", "write_sequence", "read_sequence", "EventWriter", "atomic_path", "is_evlatcorr_h5"]

FORMAT, VERSION = "evlatcorr", 1
_CHUNK = 65536


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path next to ``path``, renamed to it only if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def is_evlatcorr_h5(path: str | Path) -> bool:
    try:
        with h5py.File(path, "r") as f:
            return f.attrs.get("format") == FORMAT
    except OSError:
        return False


class EventWriter:
    """Appends sorted event chunks to ``/<group>/{x,y,t,p}`` of an open HDF5 file."""

    def __init__(self, f: h5py.File, group: str = "events") -> None:
        g = f.require_group(group)
        kw = dict(maxshape=(None,), chunks=(_CHUNK,), compression="lzf")
        self.ds = {name: g.create_dataset(name, shape=(0,), dtype=dtype, **kw)
                   for name, dtype in (("x", np.uint16), ("y", np.uint16), ("t", np.float64), ("p", np.int8))}
        self.last = -np.inf

    def append(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        if len(t) == 0:
            return
        if t[0] < self.last or np.any(np.diff(t) < 0):
            raise ValueError("EventWriter.append needs events sorted by time, continuing the previous chunk")
        n = self.ds["t"].shape[0]
        for name, values in (("x", x), ("y", y), ("t", t), ("p", p)):
            self.ds[name].resize((n + len(t),))
            self.ds[name][n:] = values
        self.last = float(t[-1])

    def append_events(self, events: Events) -> None:
        self.append(events.x.cpu().numpy(), events.y.cpu().numpy(), events.t.cpu().numpy(),
                    events.p.cpu().numpy())


def _write_header(f: h5py.File, sensor_size: tuple[int, int], **attrs: Any) -> None:
    f.attrs["format"], f.attrs["version"] = FORMAT, VERSION
    f.attrs["sensor_size"] = list(sensor_size)
    f.attrs["time_unit"] = "us"
    for k, v in attrs.items():
        f.attrs[k] = v


def _write_frames(f: h5py.File, name: str, array: torch.Tensor) -> None:
    a = array.detach().cpu().float().numpy()
    f.create_dataset(f"frames/{name}", data=a, chunks=(1, *a.shape[1:]), compression="lzf")


def write_sequence(path: str | Path, seq: Any) -> None:
    """Write a simulated sequence (any object with the fields of ``SimulatedSequence``)."""
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        _write_header(f, seq.ideal_events.sensor_size, threshold=float(seq.threshold), seed=int(seq.seed),
                      config=repr(seq.config))
        EventWriter(f, "events").append_events(seq.delayed_events)
        EventWriter(f, "ideal_events").append_events(seq.ideal_events)
        _write_frames(f, "blurry", seq.blurry)
        _write_frames(f, "sharp", seq.sharp)
        _write_frames(f, "latency", seq.true_latency)
        f["frames/exposure_start"] = seq.exposure_start.cpu().numpy()
        f["frames/exposure_end"] = seq.exposure_end.cpu().numpy()
        f["targets/times"] = seq.target_times.cpu().numpy()
        f.create_dataset("targets/frames", data=seq.target_frames.cpu().float().numpy(), compression="lzf")


def read_sequence(path: str | Path):
    """Read back what :func:`write_sequence` wrote, as a ``SimulatedSequence``."""
    from evlatcorr.simulate import SimulatedSequence

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT or "ideal_events" not in f:
            raise RecordingError(f"{path}: not an evlatcorr simulated sequence")
        size = tuple(int(v) for v in f.attrs["sensor_size"])

        def events(group: str) -> Events:
            g = f[group]
            return Events(g["x"][:].astype(np.int64), g["y"][:].astype(np.int64), g["t"][:], g["p"][:],
                          sensor_size=size)

        t = lambda name: torch.from_numpy(f[name][:])  # noqa: E731
        return SimulatedSequence(
            blurry=t("frames/blurry"), sharp=t("frames/sharp"), exposure_start=t("frames/exposure_start"),
            exposure_end=t("frames/exposure_end"), ideal_events=events("ideal_events"),
            delayed_events=events("events"), true_latency=t("frames/latency"), target_times=t("targets/times"),
            target_frames=t("targets/frames"), threshold=float(f.attrs["threshold"]), seed=int(f.attrs["seed"]),
            config={"exposure_us": float(f["frames/exposure_end"][0] - f["frames/exposure_start"][0]),
                    "source": str(f.attrs.get("config", ""))},
        )


def _bisect(ds: h5py.Dataset, value: float) -> int:
    """First index with ``ds[i] >= value`` in a sorted 1-D dataset, reading O(log N) chunks."""
    lo, hi = 0, ds.shape[0]
    while hi - lo > _CHUNK:
        mid = (lo + hi) // 2
        if ds[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    block = ds[lo:hi]
    return lo + int(np.searchsorted(block, value, side="left"))


class H5Recording(Recording):
    """Reader of our HDF5 format (see the module docstring for the layout)."""

    format_name = "evlatcorr-h5"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 chunk_events: int = 1 << 20) -> None:
        super().__init__(path, before_us, after_us)
        self.chunk_events = chunk_events
        try:
            with h5py.File(self.path, "r") as f:
                if f.attrs.get("format") != FORMAT:
                    raise RecordingError(f"{self.path}: not an evlatcorr HDF5 file (attribute format="
                                         f"{f.attrs.get('format')!r})")
                self.sensor_size = tuple(int(v) for v in f.attrs["sensor_size"])
                for name in ("events/t", "frames/blurry", "frames/exposure_start", "frames/exposure_end"):
                    if name not in f:
                        raise RecordingError(f"{self.path}: missing dataset /{name}")
        except OSError as exc:
            raise RecordingError(f"{self.path}: cannot read as HDF5 ({exc})") from exc

    def frames(self) -> Iterator[FrameInfo]:
        with h5py.File(self.path, "r") as f:
            start, end = f["frames/exposure_start"][:], f["frames/exposure_end"][:]
            for i in range(len(start)):
                if not end[i] > start[i]:
                    raise RecordingError(f"{self.path}: frame {i} has exposure end {end[i]} <= start {start[i]}")
                yield FrameInfo(i, float(start[i]), float(end[i]), f["frames/blurry"][i])

    def iter_event_chunks(self, group: str = "events") -> Iterator[np.ndarray]:
        with h5py.File(self.path, "r") as f:
            g = f[group]
            n = g["t"].shape[0]
            for i in range(0, n, self.chunk_events):
                j = min(n, i + self.chunk_events)
                yield structured_events(g["x"][i:j], g["y"][i:j], g["t"][i:j], g["p"][i:j])

    def events_between(self, t0: float, t1: float, group: str = "events") -> Events:
        """Events with ``t0 <= t < t1`` (binary search, reads only that slice)."""
        with h5py.File(self.path, "r") as f:
            g = f[group]
            i, j = _bisect(g["t"], t0), _bisect(g["t"], t1)
            arr = structured_events(g["x"][i:j], g["y"][i:j], g["t"][i:j], g["p"][i:j])
        return Events.from_numpy(arr, sensor_size=self.sensor_size)
