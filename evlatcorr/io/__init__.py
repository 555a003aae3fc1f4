"""Readers and writers of event recordings; every reader yields ``EventFrames`` frame by frame.

Formats read (each reader states its file's conventions and converts them once to ours: µs,
polarity ±1, sensor size (H, W), frames (C, H, W) float in [0, 1]):

| format | reader | recognised by |
| --- | --- | --- |
| AEDAT4 (DAVIS, iniVation) | :class:`AedatRecording` | magic ``#!AER-DAT4.0`` |
| our HDF5 (see :mod:`evlatcorr.io.h5`) | :class:`H5Recording` | HDF5 with ``format="evlatcorr"`` |
| event_utils / EFNet HDF5 | :class:`EventUtilsRecording` | HDF5 with ``/events/xs, ys, ts, ps`` |
| GEM NPZ pairs | :class:`GemNpzRecording` | ``.npz`` (or a folder of them) with ``blur1``, ``exp_start1``, ... |
| HighREV | :class:`HighREVRecording` | a folder with ``blur/`` and ``event/`` NPZs |
| ROS1 bag (``rpg_dvs_ros``) | :class:`RosbagRecording` | magic ``#ROSBAG V2.0`` |

Formats written: our HDF5 (:func:`write_sequence`, :func:`write_dataset`, :func:`write_h5_events`)
and event_utils HDF5 (:func:`write_event_utils`); :func:`write_events` picks the input's format
where we can write it, else ours.

Example:
    >>> from evlatcorr.io import open_recording
    >>> rec = open_recording("recording.aedat4", after_us=20_000)  # doctest: +SKIP
    >>> for batch in rec:  # doctest: +SKIP
    ...     out = EventLatencyCorrector()(batch)
"""

from __future__ import annotations

import inspect
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from evlatcorr.events import Events
from evlatcorr.gamma import check_frame_gamma, linear_frames
from evlatcorr.io.aedat4 import AedatRecording
from evlatcorr.io.base import FrameInfo, Recording, RecordingError
from evlatcorr.io.event_utils import EventUtilsRecording, is_event_utils_h5, write_event_utils
from evlatcorr.io.gem_npz import GemNpzRecording, is_gem_npz
from evlatcorr.io.h5 import EventWriter, is_evlatcorr_h5, write_dataset, write_h5_events, write_sequence
from evlatcorr.io.h5_read import H5Recording, is_sequence_file, num_sequences, read_sequence, read_sequences
from evlatcorr.io.highrev import HighREVRecording, is_highrev
from evlatcorr.io.rosbag import RosbagRecording

__all__ = [
    "AedatRecording",
    "EventUtilsRecording",
    "EventWriter",
    "FrameInfo",
    "GemNpzRecording",
    "H5Recording",
    "HighREVRecording",
    "Recording",
    "RecordingError",
    "RosbagRecording",
    "is_sequence_file",
    "linear_frames",
    "num_sequences",
    "open_recording",
    "read_sequence",
    "read_sequences",
    "recording_class",
    "write_dataset",
    "write_event_utils",
    "write_events",
    "write_h5_events",
    "write_sequence",
]

_HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_ZIP_MAGIC = b"PK\x03\x04"


def _make(cls: type[Recording], path: Path, kwargs: dict[str, Any]) -> Recording:
    kwargs = dict(kwargs)
    gamma = check_frame_gamma(kwargs.pop("frame_gamma", 1.0))  # every reader's: set on the recording it makes
    accepted = set(inspect.signature(cls.__init__).parameters) - {"self", "path"}
    unknown = sorted(set(kwargs) - accepted)
    if unknown:
        raise TypeError(f"{path} is read by {cls.__name__}, which does not take {unknown}; it takes "
                        f"{sorted(accepted | {'frame_gamma'})}")
    recording = cls(path, **kwargs)
    recording.frame_gamma = gamma
    return recording


def _sniff_file(path: Path) -> type[Recording]:
    with open(path, "rb") as f:
        head = f.read(16)
    if head.startswith(b"#!AER-DAT4"):
        return AedatRecording
    if head.startswith(b"#ROSBAG V2"):
        return RosbagRecording
    if head.startswith(b"#ROSBAG"):
        version = head.split(b"\n")[0].decode(errors="replace")
        raise RecordingError(f"{path}: a ROS bag of an old version ({version}); only version 2.0 is read ('rosbag "
                             "fix' converts older bags)")
    if head.startswith(b"#!AER-DAT"):
        version = head[len(b"#!AER-DAT"):].split(b"\r")[0].split(b"\n")[0].decode(errors="replace")
        raise RecordingError(f"{path}: AEDAT {version} is not supported (only AEDAT4; convert the file with "
                             "DV or dv-processing)")
    if head.startswith(_HDF5_MAGIC) or h5py.is_hdf5(path):
        if is_evlatcorr_h5(path):
            return H5Recording
        if is_event_utils_h5(path):
            return EventUtilsRecording
        try:
            with h5py.File(path, "r") as f:
                keys = sorted(f.keys())[:10]
        except OSError as exc:
            raise RecordingError(f"{path}: cannot read as HDF5 (truncated or corrupt?): {exc}") from exc
        raise RecordingError(f"{path}: unknown format: an HDF5 file with top-level {keys}; expected our format "
                             "(attribute format='evlatcorr') or event_utils (/events/xs, ys, ts, ps)")
    if head.startswith(_ZIP_MAGIC) or path.suffix == ".npz":
        if is_gem_npz(path):
            return GemNpzRecording
        try:
            with np.load(path, allow_pickle=False) as z:
                keys = sorted(z.files)[:10]
        except Exception as exc:  # noqa: BLE001 - any failure here means "not a readable npz"
            raise RecordingError(f"{path}: cannot read as npz (truncated or corrupt?): {exc}") from exc
        raise RecordingError(f"{path}: unknown format: an npz with keys {keys}; expected a GEM pair (blur1, blur2, "
                             "exp_start1, exp_end1, exp_start2, exp_end2, events)")
    if path.suffix.lower() in (".aedat4", ".aedat"):
        raise RecordingError(f"{path}: named like AEDAT but does not start with '#!AER-DAT4.0' (wrong format or "
                             "corrupt header)")
    if path.suffix.lower() in (".h5", ".hdf5"):
        raise RecordingError(f"{path}: named like HDF5 but has no HDF5 signature (wrong format or truncated)")
    if path.suffix.lower() in (".db3", ".mcap"):
        raise RecordingError(f"{path}: a ROS2 bag; only ROS1 bags (rpg_dvs_ros's dvs_msgs) are read")
    raise RecordingError(f"{path}: unknown format (supported: AEDAT4, ROS1 bag, evlatcorr HDF5, event_utils HDF5, "
                         "GEM npz, HighREV folder)")


def open_recording(path: str | Path, **kwargs: Any) -> Recording:
    """Open a recording, recognising its format by content (magic bytes, HDF5 layout, folder layout).

    Args:
        path: a file (AEDAT4, ROS1 bag, HDF5, npz) or a folder (HighREV, folder of GEM npz).
        **kwargs: passed to the reader: ``before_us``, ``after_us`` and ``frame_gamma`` (the frames' images raised
            to it as they are read: 2.2 makes display-encoded frames linear, as EDI needs them; default 1) for all,
            and the reader's own options (e.g. ``exposure_us`` for event_utils and bags, ``events_topic`` for bags,
            ``sequence`` for our HDF5 and HighREV).

    Returns:
        A :class:`Recording`.

    Raises:
        FileNotFoundError: ``path`` does not exist.
        RecordingError: the format is not recognised, or the file is corrupt (the message says which).

    Example:
        >>> rec = open_recording("cradle_lowlight.aedat4")  # doctest: +SKIP
        >>> rec.format_name, rec.sensor_size, len(rec)  # doctest: +SKIP
        ('aedat4', (260, 346), 13)
    """
    return _make(recording_class(path), Path(path), kwargs)


def recording_class(path: str | Path) -> type[Recording]:
    """The reader of ``path``'s format (recognised as :func:`open_recording` does), without opening it.

    Example:
        >>> recording_class("cradle_lowlight.aedat4").__name__  # doctest: +SKIP
        'AedatRecording'
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    if path.is_file():
        return _sniff_file(path)
    if is_highrev(path):
        return HighREVRecording
    if is_gem_npz(path):
        return GemNpzRecording
    if (path / "metadata.yaml").is_file():
        raise RecordingError(f"{path}: a ROS2 bag; only ROS1 bags (rpg_dvs_ros's dvs_msgs) are read")
    inner = [p.name for p in sorted(path.iterdir()) if p.is_dir() and is_highrev(p)][:5]
    hint = f"; its subfolders {inner} are HighREV folders: open one of them" if inner else ""
    raise RecordingError(f"{path}: unknown format: a folder that is neither HighREV blur/ + event/, or GEM .npz files)"
                         f"{hint}")


def write_events(path: str | Path, events: Events | Iterable[Events | np.ndarray], like: Recording | None = None,
                 format: str | None = None, **kwargs: Any) -> str:
    """Write events in the format of the recording they came from where we can write it, else ours.

    Args:
        path: output file (written atomically).
        events: one sample of :class:`Events`, or an iterable of time-sorted chunks.
        like: the input recording; its frames are written too.
        format: ``"evlatcorr"`` or ``"event_utils"``; default: event_utils for an event_utils input,
            our HDF5 for every other input (AEDAT4, HighREV and GEM are not written).
        **kwargs: passed to :func:`write_h5_events` or :func:`write_event_utils`.

    Returns:
        The format written.

    Example:
        >>> rec = open_recording("input.h5")  # doctest: +SKIP
        >>> write_events("corrected.h5", corrected, like=rec)  # doctest: +SKIP
        'event_utils'
    """
    if format is None:
        format = "event_utils" if isinstance(like, EventUtilsRecording) else "evlatcorr"
    if format == "event_utils":
        write_event_utils(path, events, like=like, **kwargs)
    elif format == "evlatcorr":
        write_h5_events(path, events, like=like, **kwargs)
    else:
        raise ValueError(f"format must be 'evlatcorr' or 'event_utils', got {format!r}")
    return format
