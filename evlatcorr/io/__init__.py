"""Readers and writers of event recordings; every reader yields ``EventFrames`` frame by frame.

Example:
    >>> from evlatcorr.io import open_recording
    >>> for batch in open_recording("recording.aedat4"):  # doctest: +SKIP
    ...     out = EventLatencyCorrector()(batch)
"""

from __future__ import annotations

from pathlib import Path

from evlatcorr.io.aedat4 import AedatRecording, is_aedat4
from evlatcorr.io.base import FrameInfo, Recording, RecordingError
from evlatcorr.io.event_utils import EventUtilsRecording, is_event_utils_h5, write_event_utils
from evlatcorr.io.gem_npz import GemNpzRecording, is_gem_npz
from evlatcorr.io.h5 import EventWriter, H5Recording, is_evlatcorr_h5, read_sequence, write_sequence
from evlatcorr.io.highrev import HighREVRecording, is_highrev

__all__ = [
    "AedatRecording",
    "EventUtilsRecording",
    "EventWriter",
    "GemNpzRecording",
    "HighREVRecording",
    "FrameInfo",
    "H5Recording",
    "Recording",
    "RecordingError",
    "open_recording",
    "read_sequence",
    "write_event_utils",
    "write_sequence",
]


def open_recording(path: str | Path, **kwargs) -> Recording:
    """Open a recording, recognising its format by content (AEDAT4 header, HDF5 layout)."""
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file or directory")
    if path.is_file() and is_aedat4(path):
        return AedatRecording(path, **kwargs)
    if path.is_file() and is_evlatcorr_h5(path):
        return H5Recording(path, **kwargs)
    if path.is_file() and is_event_utils_h5(path):
        return EventUtilsRecording(path, **kwargs)
    if is_highrev(path):
        return HighREVRecording(path, **kwargs)
    if is_gem_npz(path):
        return GemNpzRecording(path, **kwargs)
    raise RecordingError(f"{path}: unknown format (supported: AEDAT4, evlatcorr HDF5, event_utils HDF5, GEM npz, "
                         "HighREV video folder)")
