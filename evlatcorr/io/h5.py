"""Our HDF5 dataset format: written by the simulator, the benchmark cache and ``evlatcorr correct``.

## The evlatcorr HDF5 format (version 1)

Units and conventions: times in **microseconds**, polarity **±1**, sensor size **(H, W)**,
images **(F, C, H, W)** linear intensity in [0, 1].

A *sequence group* holds one continuous recording:

```
<group>/                   attrs: sensor_size=[H, W]; optional threshold, seed, config (JSON text)
<group>/events/x, y        uint16 (N,)           column, row of each event
<group>/events/t           float64 (N,)          µs, sorted (float keeps the simulator's sub-µs times)
<group>/events/p           int8 (N,)             ±1
<group>/frames/blurry      (F, C, H, W)          float32 by default (see "image storage")
<group>/frames/exposure_start, exposure_end     float64 (F,) µs
<group>/frames/sharp       (F, C, H, W)          optional ground truth at mid-exposure
<group>/frames/latency     float32 (F, 1, H, W)  optional true latency map (µs)
<group>/frames/estimated_latency       float32 (F,)          optional, written by `evlatcorr correct`
<group>/frames/estimated_latency_map   float32 (F, 1, H, W)  optional latency maps (µs; `correct --mode spatial`)
<group>/ideal_events/x, y, t, p                  optional events without latency (same layout)
<group>/targets/times      float64 (T,)          optional times of ground-truth frames (µs)
<group>/targets/frames     (T, C, H, W)          optional ground-truth frames at those times
```

A file is either one sequence (the root group is the sequence group) or a dataset of several:
`/sequences/0000`, `/sequences/0001`, ... each a sequence group. The root always carries
`format="evlatcorr"`, `version=1`, `time_unit="us"`, `creator`, and `sensor_size` (of the
first sequence); a dataset also `num_sequences`.

Storage: event columns are chunked (65,536 events) and compressed (LZF by default; `"gzip"`,
or `"zstd"`/`"blosc"`/`"lz4"` when the optional `hdf5plugin` package is installed; `None` for
none). Images are chunked one frame per chunk. Image storage: `float32` (default, exact),
`float16`, or `uint8`/`uint16` with an attribute `scale` (value = stored × scale). The readers
(:mod:`evlatcorr.io.h5_read`) find a frame's events by binary search on `t`, reading O(log N)
chunks, so memory stays bounded by one frame's window. Writers write to a temporary file in the
same folder and rename it at the end, so a failed write leaves nothing behind.
"""

from __future__ import annotations

import json
import os
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import h5py
import numpy as np
import torch

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.io.base import Recording
from evlatcorr.io.conversions import iter_events_as_chunks, structured_events
from evlatcorr.io.hdf5_access import (
    is_hdf5_with,
    load_plugins,
)
from evlatcorr.io.outputs import default_file_mode

__all__ = [
    "EventWriter",
    "atomic_path",
    "is_evlatcorr_h5",
    "write_dataset",
    "write_h5_events",
    "write_header",
    "write_sequence",
]

FORMAT, VERSION = "evlatcorr", 1
_CHUNK = 65536  # elements per HDF5 chunk of an event column
_PLUGIN_FILTERS = ("zstd", "blosc", "lz4")


def _creator() -> str:
    try:
        from evlatcorr import __version__
    except ImportError:  # pragma: no cover
        __version__ = "?"
    return f"evlatcorr {__version__}"


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path next to ``path``, renamed to ``path`` only if the block succeeds.

    Example:
        >>> with atomic_path("out.h5") as tmp:  # doctest: +SKIP
        ...     write_something(tmp)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.chmod(tmp, default_file_mode())  # mkstemp makes it 0o600; a plain open() would honour the umask
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise


def _compression(compression: str | None) -> dict[str, Any]:
    if compression is None or compression == "none":
        return {}
    if compression == "lzf":
        return {"compression": "lzf"}
    if compression == "gzip":
        return {"compression": "gzip", "compression_opts": 4}
    if compression in _PLUGIN_FILTERS:
        if not load_plugins():
            raise ValueError(f"compression={compression!r} needs the optional package hdf5plugin "
                             "(pip install hdf5plugin); use 'lzf' or 'gzip' without it")
        import hdf5plugin

        return dict({"zstd": hdf5plugin.Zstd(), "blosc": hdf5plugin.Blosc(), "lz4": hdf5plugin.LZ4()}[compression])
    raise ValueError(f"compression must be None, 'lzf', 'gzip', 'zstd', 'blosc' or 'lz4', got {compression!r}")


def is_evlatcorr_h5(path: str | Path) -> bool:
    """Whether ``path`` is an HDF5 file with ``format="evlatcorr"``."""
    return is_hdf5_with(path, lambda f: f.attrs.get("format") == FORMAT)


class EventWriter:
    """Appends time-sorted event chunks to ``<group>/{x,y,t,p}`` of an open HDF5 file.

    Args:
        f: an HDF5 file or group open for writing.
        group: name of the group to create.
        compression: see the module docstring.

    Example:
        >>> with h5py.File("ev.h5", "w") as f:  # doctest: +SKIP
        ...     w = EventWriter(f)
        ...     w.append_events(events)
    """

    def __init__(self, f: h5py.Group, group: str = "events", compression: str | None = "lzf") -> None:
        g = f.require_group(group)
        kw = dict(maxshape=(None,), chunks=(_CHUNK,), **_compression(compression))
        self.ds = {name: g.create_dataset(name, shape=(0,), dtype=dtype, **kw)
                   for name, dtype in (("x", np.uint16), ("y", np.uint16), ("t", np.float64), ("p", np.int8))}
        self.last = -np.inf
        self.count = 0

    def append(self, x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray) -> None:
        """Append columns of one length (t in µs, sorted and not before the previous chunk; p 0/1, ±1 or bool)."""
        x, y, t = np.asarray(x).reshape(-1), np.asarray(y).reshape(-1), np.asarray(t, dtype=np.float64).reshape(-1)
        p = structured_events(x, y, t, p)["p"]  # one length, integer coordinates, polarity 0/1, ±1 or bool
        if len(t) == 0:
            return
        if t[0] < self.last or np.any(np.diff(t) < 0):
            raise ValueError("EventWriter.append needs events sorted by time, continuing the previous chunk")
        if x.min() < 0 or y.min() < 0 or x.max() > 65535 or y.max() > 65535:
            raise ValueError("event coordinates must be in [0, 65535] to be stored as uint16")
        n = self.count
        for name, values in (("x", x), ("y", y), ("t", t), ("p", p)):
            self.ds[name].resize((n + len(t),))
            self.ds[name][n:] = values
        self.last, self.count = float(t[-1]), n + len(t)

    def append_events(self, events: Events | np.ndarray) -> None:
        """Append one sample of :class:`Events` (or a structured chunk)."""
        for chunk in iter_events_as_chunks(events):
            self.append(chunk["x"], chunk["y"], chunk["t"], chunk["p"])


def write_header(f: h5py.File, sensor_size: tuple[int, int], **attrs: Any) -> None:
    """Root attributes of our format (``sensor_size`` as (H, W))."""
    f.attrs["format"], f.attrs["version"] = FORMAT, VERSION
    f.attrs["sensor_size"] = [int(v) for v in sensor_size]
    f.attrs["time_unit"] = "us"
    f.attrs["creator"] = _creator()
    for k, v in attrs.items():
        f.attrs[k] = v


def _numpy(a: Any) -> np.ndarray:
    return a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a)


def _write_images(g: h5py.Group, name: str, array: Any, dtype: str = "float32",
                  compression: str | None = "lzf") -> None:
    a = _numpy(array).astype(np.float32)
    if a.ndim != 4:
        raise ValueError(f"{name} must be (F, C, H, W), got shape {a.shape}")
    kw = dict(chunks=(1, *a.shape[1:]) if a.shape[0] else None, **_compression(compression))
    if dtype in ("float32", "float16"):
        g.create_dataset(name, data=a.astype(dtype), **kw)
    elif dtype in ("uint8", "uint16"):
        top = float(np.iinfo(dtype).max)
        ds = g.create_dataset(name, data=np.round(np.clip(a, 0, 1) * top).astype(dtype), **kw)
        ds.attrs["scale"] = 1.0 / top
    else:
        raise ValueError(f"frames_dtype must be float32, float16, uint8 or uint16, got {dtype!r}")


def _json(config: Any) -> str:
    try:
        return json.dumps(config, sort_keys=True, default=lambda o: o.tolist() if hasattr(o, "tolist") else repr(o))
    except (TypeError, ValueError):
        return json.dumps({"repr": repr(config)})


def _sequence_fields(seq: Any) -> SimpleNamespace:
    """Duck-typed read of a sequence-like object (``SimulatedSequence`` or similar)."""
    def get(*names: str) -> Any:
        for n in names:
            v = getattr(seq, n, None)
            if v is not None:
                return v
        return None

    out = SimpleNamespace(
        blurry=get("blurry"), exposure_start=get("exposure_start"), exposure_end=get("exposure_end"),
        events=get("delayed_events", "events"), ideal_events=get("ideal_events"), sharp=get("sharp"),
        latency=get("true_latency"), target_times=get("target_times"), target_frames=get("target_frames"),
        threshold=get("threshold"), seed=get("seed"), config=get("config"),
    )
    missing = [n for n in ("blurry", "exposure_start", "exposure_end", "events") if getattr(out, n) is None]
    if missing:
        raise ValueError(f"write_sequence needs an object with blurry, exposure_start, exposure_end and "
                         f"delayed_events (or events); {type(seq).__name__} lacks {missing}")
    return out


def _write_sequence_group(g: h5py.Group, seq: Any, compression: str | None, frames_dtype: str) -> None:
    s = _sequence_fields(seq)
    blurry = _numpy(s.blurry)
    if blurry.ndim != 4:
        raise ValueError(f"blurry must be (F, C, H, W), got shape {blurry.shape}")
    size = tuple(int(v) for v in blurry.shape[-2:])
    if isinstance(s.events, Events) and s.events.sensor_size != size:
        raise ValueError(f"events sensor_size {s.events.sensor_size} differs from the frames' (H, W)={size}")
    g.attrs["sensor_size"] = list(size)
    if s.threshold is not None:
        g.attrs["threshold"] = float(s.threshold)
    if s.seed is not None:
        g.attrs["seed"] = int(s.seed)
    if s.config is not None:
        g.attrs["config"] = _json(s.config)
    EventWriter(g, "events", compression).append_events(s.events)
    if s.ideal_events is not None:
        EventWriter(g, "ideal_events", compression).append_events(s.ideal_events)
    _write_images(g, "frames/blurry", blurry, frames_dtype, compression)
    start, end = _numpy(s.exposure_start).astype(np.float64), _numpy(s.exposure_end).astype(np.float64)
    if start.shape != (blurry.shape[0],) or end.shape != start.shape:
        raise ValueError(f"exposure_start/end must be ({blurry.shape[0]},), got {start.shape} and {end.shape}")
    g["frames/exposure_start"], g["frames/exposure_end"] = start, end
    if s.sharp is not None:
        _write_images(g, "frames/sharp", s.sharp, frames_dtype, compression)
    if s.latency is not None:
        g.create_dataset("frames/latency", data=_numpy(s.latency).astype(np.float32), **_compression(compression))
    est = getattr(seq, "estimated_latency_map", None)
    if est is not None:
        g.create_dataset("frames/estimated_latency_map", data=_numpy(est).astype(np.float32),
                         **_compression(compression))
    if s.target_times is not None:
        g["targets/times"] = _numpy(s.target_times).astype(np.float64).reshape(-1)
        if s.target_frames is not None:
            _write_images(g, "targets/frames", _numpy(s.target_frames).reshape(-1, *blurry.shape[1:]),
                          frames_dtype, compression)


def write_sequence(path_or_group: str | Path | h5py.Group, seq: Any, compression: str | None = "lzf",
                   frames_dtype: str = "float32") -> None:
    """Write one sequence: a ``SimulatedSequence`` or any object with its fields.

    Fields read (duck typing): ``blurry`` (F, C, H, W), ``exposure_start``/``exposure_end`` (F,) µs,
    ``delayed_events`` (or ``events``; one sample), and optionally ``ideal_events``, ``sharp``,
    ``true_latency`` (F, 1, H, W), ``target_times`` (T,), ``target_frames`` (T, C, H, W),
    ``threshold``, ``seed``, ``config`` (stored as JSON).

    Args:
        path_or_group: a file path (written atomically; the root is the sequence) or an open
            ``h5py.Group`` to write into.
        seq: the sequence.
        compression: ``"lzf"`` (default), ``"gzip"``, ``None``, or a hdf5plugin filter name.
        frames_dtype: image storage, ``"float32"`` (default, lossless), ``"float16"``, ``"uint8"``, ``"uint16"``.

    Example:
        >>> from evlatcorr.simulate import simulate  # doctest: +SKIP
        >>> write_sequence("seq.h5", simulate("camera", num_frames=3))  # doctest: +SKIP
        >>> read_sequence("seq.h5").num_frames  # doctest: +SKIP
        3
    """
    if isinstance(path_or_group, h5py.Group):
        _write_sequence_group(path_or_group, seq, compression, frames_dtype)
        return
    with atomic_path(path_or_group) as tmp, h5py.File(tmp, "w") as f:
        _write_sequence_group(f, seq, compression, frames_dtype)
        write_header(f, tuple(f.attrs["sensor_size"]))


def _frames_as_sequences(frames: EventFrames) -> Iterator[SimpleNamespace]:
    """Each sample of an ``EventFrames`` batch as a one-frame sequence."""
    for i in range(frames.batch_size):
        yield SimpleNamespace(
            blurry=frames.blurry[i:i + 1], exposure_start=frames.exposure_start[i:i + 1],
            exposure_end=frames.exposure_end[i:i + 1], events=frames.events.sample(i),
            sharp=None if frames.sharp is None else frames.sharp[i:i + 1],
            estimated_latency_map=None if frames.latency is None else frames.latency[i:i + 1],
            target_times=None if frames.target_times is None else frames.target_times[i],
            target_frames=None if frames.target_frames is None else frames.target_frames[i],
            config={k: v for k, v in frames.meta.items() if isinstance(v, (str, int, float, bool))},
        )


def write_dataset(path: str | Path, items: Any, compression: str | None = "lzf",
                  frames_dtype: str = "float32", **attrs: Any) -> int:
    """Write several sequences to one file, as ``/sequences/0000``, ``/sequences/0001``, ...

    Args:
        path: output file (written atomically).
        items: sequence-like objects (see :func:`write_sequence`), :class:`EventFrames` batches
            (each sample becomes a one-frame sequence with its window's events), or one of either.
        compression: see :func:`write_sequence`.
        frames_dtype: see :func:`write_sequence`.
        **attrs: extra root attributes (str, numbers).

    Returns:
        The number of sequences written.

    Example:
        >>> write_dataset("test_set.h5", [seq_a, seq_b])  # doctest: +SKIP
        2
        >>> [s.num_frames for s in read_sequences("test_set.h5")]  # doctest: +SKIP
    """
    if isinstance(items, EventFrames) or hasattr(items, "blurry"):
        items = [items]
    count, size = 0, None
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        for item in items:
            for seq in (_frames_as_sequences(item) if isinstance(item, EventFrames) else [item]):
                g = f.create_group(f"sequences/{count:04d}")
                _write_sequence_group(g, seq, compression, frames_dtype)
                size = size or tuple(g.attrs["sensor_size"])
                count += 1
        if count == 0:
            raise ValueError("write_dataset needs at least one sequence")
        write_header(f, size, num_sequences=count, **attrs)
    return count


def write_h5_events(path: str | Path, events: Events | Iterable[Events | np.ndarray],
                    like: Recording | None = None, sensor_size: tuple[int, int] | None = None,
                    compression: str | None = "lzf", **attrs: Any) -> None:
    """Write events (e.g. latency-corrected ones) in our format, with the frames of ``like``.

    Args:
        path: output file (written atomically).
        events: one sample of :class:`Events`, or an iterable of time-sorted chunks (``Events``
            or structured arrays) for outputs larger than memory.
        like: a recording whose frames (images and exposures, streamed) are copied.
        sensor_size: ``(H, W)``; defaults to ``like``'s or the events'.
        compression: see :func:`write_sequence`.
        **attrs: extra root attributes.
    """
    if sensor_size is None:
        if like is not None:
            sensor_size = like.sensor_size
        elif isinstance(events, Events):
            sensor_size = events.sensor_size
        else:
            raise ValueError("write_h5_events needs sensor_size (or like=) when given chunks")
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as f:
        write_header(f, sensor_size, **attrs)
        writer = EventWriter(f, "events", compression)
        for chunk in iter_events_as_chunks(events):
            writer.append(chunk["x"], chunk["y"], chunk["t"], chunk["p"])
        if like is not None:
            _copy_frames(f, like, compression)


def _copy_frames(f: h5py.File, rec: Recording, compression: str | None) -> None:
    starts, ends, ds, sharp = [], [], None, None
    for info in rec.frames():
        img = np.asarray(info.image, dtype=np.float32)
        if ds is None:
            ds = f.create_dataset("frames/blurry", shape=(0, *img.shape), maxshape=(None, *img.shape),
                                  dtype=np.float32, chunks=(1, *img.shape), **_compression(compression))
            if info.sharp is not None:
                sharp = f.create_dataset("frames/sharp", shape=(0, *img.shape), maxshape=(None, *img.shape),
                                         dtype=np.float32, chunks=(1, *img.shape), **_compression(compression))
        n = ds.shape[0]
        ds.resize((n + 1, *img.shape))
        ds[n] = img
        if sharp is not None and info.sharp is not None:
            sharp.resize((n + 1, *img.shape))
            sharp[n] = info.sharp
        starts.append(info.exposure_start)
        ends.append(info.exposure_end)
    f["frames/exposure_start"] = np.asarray(starts, dtype=np.float64)
    f["frames/exposure_end"] = np.asarray(ends, dtype=np.float64)
