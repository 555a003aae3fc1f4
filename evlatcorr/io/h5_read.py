"""Reading our HDF5 format (:mod:`evlatcorr.io.h5` describes it and writes it): whole sequences with their ground
truth (:func:`read_sequence`), and recordings frame by frame (:class:`H5Recording`), each frame's events found by
binary search so that memory stays bounded by one frame's window."""

from __future__ import annotations

import json
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

import h5py
import numpy as np
import torch

from evlatcorr.events import Events
from evlatcorr.io.conversions import structured_events
from evlatcorr.io.h5 import FORMAT, VERSION
from evlatcorr.io.hdf5_access import IndexedH5Recording, bisect_sorted, check_columns, open_h5
from evlatcorr.io.records import EVENT_DTYPE, FrameInfo, RecordingError, SegmentEnd

__all__ = ["H5Recording", "is_sequence_file", "num_sequences", "read_sequence", "read_sequences"]


def _read_images(ds: h5py.Dataset, index: Any = slice(None)) -> np.ndarray:
    a = ds[index]
    scale = ds.attrs.get("scale")
    a = a.astype(np.float32)
    return a * np.float32(scale) if scale is not None else a


def _sequence_groups(f: h5py.File, path: Any) -> list[str]:
    if f.attrs.get("format") != FORMAT:
        raise RecordingError(f"{path}: not an evlatcorr HDF5 file (attribute format={f.attrs.get('format')!r})")
    version = int(f.attrs.get("version", 0))
    if version > VERSION:
        raise RecordingError(f"{path}: format version {version} is newer than this reader ({VERSION})")
    if "frames" in f or "events" in f:
        return ["/"]
    if "sequences" in f:
        names = sorted(f["sequences"].keys())
        if names:
            return [f"sequences/{n}" for n in names]
    raise RecordingError(f"{path}: no sequence in this file (neither /frames nor /sequences/NNNN)")


def _require(g: h5py.Group, names: Iterable[str], path: Any, group: str) -> None:
    for name in names:
        if name not in g:
            where = "" if group == "/" else f" in /{group}"
            raise RecordingError(f"{path}: missing dataset /{name}{where}")


def _dataset_name(group: str, name: str) -> str:
    return f"/{name}" if group == "/" else f"/{group.strip('/')}/{name}"


def _check_event_columns(g: h5py.Group, path: Any, group: str, events: str) -> None:
    """``<events>/x, y, t, p`` must be 1-D (or ``(N, 1)``) columns of one length."""
    check_columns(g[events], ("x", "y", "t", "p"), f"{path}: {_dataset_name(group, events)}")


def _check_frame_arrays(g: h5py.Group, path: Any, group: str) -> None:
    """Every per-frame dataset under ``frames/`` (exposures, sharp, latency, ...) has one entry per frame."""
    blurry = g["frames/blurry"]
    if blurry.ndim != 4:
        raise RecordingError(f"{path}: {_dataset_name(group, 'frames/blurry')} must be (F, C, H, W), got shape "
                             f"{blurry.shape}")
    count = blurry.shape[0]
    for name, ds in g["frames"].items():
        if isinstance(ds, h5py.Dataset) and ds.ndim >= 1 and ds.shape[0] != count:
            raise RecordingError(f"{path}: {_dataset_name(group, f'frames/{name}')} has {ds.shape[0]} entries but "
                                 f"{_dataset_name(group, 'frames/blurry')} has {count} frames")
        if isinstance(ds, h5py.Dataset) and ds.ndim == 0:
            raise RecordingError(f"{path}: {_dataset_name(group, f'frames/{name}')} is a scalar, expected one "
                                 f"entry per frame ({count})")


def is_sequence_file(path: str | Path) -> bool:
    """Whether ``path`` is one of our HDF5 files holding sequences with ideal and delayed events
    (written by :func:`write_sequence` / :func:`write_dataset`), as opposed to events alone."""
    try:
        with h5py.File(path, "r") as f:
            return all("ideal_events" in f[g] for g in _sequence_groups(f, path))
    except (OSError, RecordingError):
        return False


def num_sequences(path: str | Path) -> int:
    """Number of sequences in one of our files (1 for a single-sequence file)."""
    with open_h5(path) as f:
        return len(_sequence_groups(f, path))


def _read_events(g: h5py.Group, size: tuple[int, int], where: str = "") -> Events:
    chunk = structured_events(g["x"][:], g["y"][:], g["t"][:], g["p"][:], where=where or g.name)
    try:
        return Events.from_numpy(chunk, sensor_size=size)
    except ValueError as exc:
        raise RecordingError(f"{where or g.name}: {exc}") from exc


def _read_sequence_group(f: h5py.File, name: str, path: Any) -> Any:
    from evlatcorr.simulate import SimulatedSequence

    g = f[name]
    needed = ("events/t", "ideal_events/t", "frames/blurry", "frames/sharp", "frames/exposure_start",
              "frames/exposure_end", "frames/latency", "targets/times", "targets/frames")
    missing = [n for n in needed if n not in g]
    if missing:
        raise RecordingError(f"{path}: /{name.strip('/')} is not a simulated sequence (missing {missing})")
    for events in ("events", "ideal_events"):
        _check_event_columns(g, path, name, events)
    _check_frame_arrays(g, path, name)
    if g["targets/times"].shape[:1] != g["targets/frames"].shape[:1]:
        raise RecordingError(f"{path}: {_dataset_name(name, 'targets/times')} has {g['targets/times'].shape[:1]} "
                             f"entries but {_dataset_name(name, 'targets/frames')} {g['targets/frames'].shape[:1]}")
    size = tuple(int(v) for v in g.attrs.get("sensor_size", f.attrs["sensor_size"]))
    try:
        config = json.loads(g.attrs.get("config", "{}"))
    except (TypeError, ValueError):
        config = {"source": str(g.attrs.get("config"))}
    start, end = g["frames/exposure_start"][:], g["frames/exposure_end"][:]
    if isinstance(config, dict) and "exposure_us" not in config and len(start):
        config["exposure_us"] = float(end[0] - start[0])
    t = lambda n: torch.from_numpy(_read_images(g[n]) if n.endswith(("blurry", "sharp", "frames")) else g[n][:])  # noqa: E731
    return SimulatedSequence(
        blurry=t("frames/blurry"), sharp=t("frames/sharp"), exposure_start=torch.from_numpy(start),
        exposure_end=torch.from_numpy(end),
        ideal_events=_read_events(g["ideal_events"], size, f"{path}: {_dataset_name(name, 'ideal_events')}"),
        delayed_events=_read_events(g["events"], size, f"{path}: {_dataset_name(name, 'events')}"),
        true_latency=t("frames/latency"),
        target_times=t("targets/times"), target_frames=t("targets/frames"),
        threshold=float(g.attrs.get("threshold", 0.2)), seed=int(g.attrs.get("seed", 0)), config=config,
    )


def read_sequence(path: str | Path, index: int = 0) -> Any:
    """Read back a sequence written by :func:`write_sequence` / :func:`write_dataset` as a ``SimulatedSequence``.

    Args:
        path: the file.
        index: which sequence of a dataset file (0 for a single-sequence file).
    """
    with open_h5(path) as f:
        groups = _sequence_groups(f, path)
        if not -len(groups) <= index < len(groups):
            raise IndexError(f"{path}: sequence {index} out of range ({len(groups)} sequences)")
        return _read_sequence_group(f, groups[index], path)


def read_sequences(path: str | Path) -> Iterator[Any]:
    """Every sequence of a file, one at a time (``SimulatedSequence`` objects)."""
    for i in range(num_sequences(path)):
        yield read_sequence(path, i)


class H5Recording(IndexedH5Recording):
    """Reader of our HDF5 format (see the module docstring for the layout).

    Frames and events are read lazily: a frame's events by binary search on ``t``, so
    :meth:`frame` and :meth:`events_between` read only what they return.

    Args:
        path: the ``.h5`` file.
        before_us: events to include before exposure start (µs).
        after_us: events to include after exposure end (µs); ``None``: the exposure time.
        sequence: which sequence of a dataset file; ``None``: all of them, as segments.
        chunk_events: events per read when streaming.
        group: the event group to read, ``"events"`` (default) or ``"ideal_events"``.

    Example:
        >>> rec = H5Recording("seq.h5", after_us=20_000)  # doctest: +SKIP
        >>> batch = rec.frame(1)  # doctest: +SKIP
    """

    format_name = "evlatcorr-h5"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 sequence: int | None = None, chunk_events: int = 1 << 20, group: str = "events") -> None:
        super().__init__(path, before_us, after_us)
        self._set_chunk_events(chunk_events)
        self.event_group = group
        with open_h5(self.path) as f:
            groups = _sequence_groups(f, self.path)
            if sequence is not None:
                if not -len(groups) <= sequence < len(groups):
                    raise RecordingError(f"{self.path}: sequence {sequence} out of range ({len(groups)} sequences)")
                groups = [groups[sequence]]
            sizes = set()
            for name in groups:
                g = f[name]
                _require(g, (f"{group}/t", f"{group}/x", f"{group}/y", f"{group}/p", "frames/blurry",
                             "frames/exposure_start", "frames/exposure_end"), self.path, name)
                _check_event_columns(g, self.path, name, group)
                _check_frame_arrays(g, self.path, name)
                sizes.add(tuple(int(v) for v in g.attrs.get("sensor_size", f.attrs.get("sensor_size", (0, 0)))))
            if len(sizes) != 1:
                raise RecordingError(f"{self.path}: sequences of different sensor sizes {sorted(sizes)}; "
                                     "open one at a time with sequence=")
            self.sensor_size = sizes.pop()
        self.groups = groups
        self.segment_names = [] if len(groups) == 1 else list(groups)

    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        times = []
        with open_h5(self.path) as f:
            for seg, name in enumerate(self.groups):
                start, end = f[name]["frames/exposure_start"][:], f[name]["frames/exposure_end"][:]
                times.extend((float(a), float(b), seg) for a, b in zip(start, end))
        return times

    def _locate(self, index: int) -> tuple[int, int]:
        """(segment, index inside the segment) of a recording-wide frame index."""
        times = self.frame_times()
        seg = times[index][2]
        first = next(i for i, (_, _, s) in enumerate(times) if s == seg)
        return seg, index - first

    def _frame_info(self, f: h5py.File, seg: int, local: int, index: int) -> FrameInfo:
        g = f[self.groups[seg]]
        start, end = float(g["frames/exposure_start"][local]), float(g["frames/exposure_end"][local])
        image = _read_images(g["frames/blurry"], local)
        sharp = _read_images(g["frames/sharp"], local) if "frames/sharp" in g else None
        meta = {"sequence": self.groups[seg]} if len(self.groups) > 1 else {}
        if "frames/latency" in g:
            meta["true_latency"] = torch.from_numpy(g["frames/latency"][local].astype(np.float32))[None]
        return FrameInfo(index, start, end, image, sharp=sharp, segment=seg, meta=meta)

    def frames(self) -> Iterator[FrameInfo]:
        with open_h5(self.path) as f:
            index = 0
            for seg, name in enumerate(self.groups):
                for local in range(f[name]["frames/exposure_start"].shape[0]):
                    yield self._frame_info(f, seg, local, index)
                    index += 1

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        with open_h5(self.path) as f:
            for seg, name in enumerate(self.groups):
                if seg:
                    yield SegmentEnd()
                g = f[name][self.event_group]
                n = g["t"].shape[0]
                where = f"{self.path}: {_dataset_name(name, self.event_group)}"
                for i, j in self._chunk_ranges(n):
                    yield structured_events(g["x"][i:j], g["y"][i:j], g["t"][i:j], g["p"][i:j], where=where)

    def _slice(self, f: h5py.File, seg: int, t0: float, t1: float) -> np.ndarray:
        g = f[self.groups[seg]][self.event_group]
        i = bisect_sorted(g["t"], t0)
        j = bisect_sorted(g["t"], t1, lo=i)
        if j == i:
            return np.zeros(0, dtype=EVENT_DTYPE)
        where = f"{self.path}: {_dataset_name(self.groups[seg], self.event_group)}"
        return structured_events(g["x"][i:j], g["y"][i:j], g["t"][i:j], g["p"][i:j], where=where)

    def _read_frame_window(self, index: int) -> tuple[FrameInfo, np.ndarray, tuple[float | None, float]]:
        seg, local = self._locate(index)
        with open_h5(self.path) as f:
            info = self._frame_info(f, seg, local, index)
            events = self._slice(f, seg, *self.window(info.exposure_start, info.exposure_end))
            t = f[self.groups[seg]][self.event_group]["t"]
            return info, events, ((float(t[0]), float(t[-1])) if t.shape[0] else (None, -np.inf))
