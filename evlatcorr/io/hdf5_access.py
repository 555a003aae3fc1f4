"""HDF5 reading shared by our reader and the event_utils one: opening, column checks, bisection, their base.

Recognising and opening files (the optional compression plugins registered, errors that name the
file), checking that event columns are columns of one length, a bisection over a sorted dataset
that reads O(log N) chunks instead of the whole column, and :class:`IndexedH5Recording`, the base
of the readers that use it to read only a frame's window.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

import h5py
import numpy as np

from evlatcorr.io.base import Recording
from evlatcorr.io.records import RecordingError

__all__ = ["IndexedH5Recording", "bisect_sorted", "check_columns", "is_hdf5_with", "load_plugins", "open_h5"]

# Elements of a dataset read at once once the bisection has narrowed it down.
_CHUNK = 65536


def load_plugins() -> bool:
    """Register the optional hdf5plugin filters (for files compressed with zstd/blosc/lz4)."""
    try:
        import hdf5plugin  # noqa: F401
    except ImportError:
        return False
    return True


def is_hdf5_with(path: str | Path, test: Callable[[h5py.File], bool]) -> bool:
    """Whether ``path`` is a readable HDF5 file for which ``test(file)`` holds (never raises for other files)."""
    path = Path(path)
    if not path.is_file() or not h5py.is_hdf5(path):
        return False
    try:
        with h5py.File(path, "r") as f:
            return test(f)
    except OSError:
        return False


def open_h5(path: str | Path) -> h5py.File:
    """``path`` opened read-only, or a :class:`RecordingError` that names it."""
    load_plugins()
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read as HDF5 (truncated or corrupt?): {exc}") from exc


def check_columns(group: h5py.Group, names: Sequence[str], where: str) -> None:
    """The datasets ``names`` of ``group`` must be columns, ``(N,)`` or ``(N, 1)``, of one length.

    Args:
        group: the group holding them.
        names: their names, in the order the message lists them.
        where: the file and the group's path, to start messages with (``"a.h5: /events"``).
    """
    lengths = {}
    for name in names:
        shape = group[name].shape
        if len(shape) not in (1, 2) or (len(shape) == 2 and shape[1] != 1):
            raise RecordingError(f"{where}/{name} must be a column (N,), got shape {shape}")
        lengths[name] = shape[0]
    if len(set(lengths.values())) > 1:
        raise RecordingError(f"{where}/{', '.join(names)} differ in length: "
                             + ", ".join(f"{c} {n}" for c, n in lengths.items()))


def bisect_sorted(ds: h5py.Dataset, value: float, lo: int = 0, hi: int | None = None) -> int:
    """First index with ``ds[i] >= value`` in a sorted 1-D dataset, reading O(log N) chunks.

    Example:
        >>> import tempfile, os
        >>> path = os.path.join(tempfile.mkdtemp(), "t.h5")
        >>> with h5py.File(path, "w") as f:
        ...     _ = f.create_dataset("t", data=np.arange(10.0))
        >>> with open_h5(path) as f:
        ...     bisect_sorted(f["t"], 3.5)
        4
    """
    hi = ds.shape[0] if hi is None else hi
    while hi - lo > _CHUNK:
        mid = (lo + hi) // 2
        if ds[mid] < value:
            lo = mid + 1
        else:
            hi = mid
    return lo + int(np.searchsorted(ds[lo:hi], value, side="left"))


class IndexedH5Recording(Recording):
    """Base of the HDF5 readers: events streamed ``chunk_events`` at a time, a window read by bisection.

    Subclasses implement ``_slice(f, segment, t0, t1)``, the events of ``[t0, t1)`` of a segment of the
    open file ``f``, and call :meth:`_set_chunk_events` from ``__init__``.
    """

    random_access = True
    chunk_events = 1 << 20

    def _set_chunk_events(self, chunk_events: int) -> None:
        if chunk_events < 1:
            raise ValueError(f"chunk_events must be >= 1, got {chunk_events}")
        self.chunk_events = int(chunk_events)

    def _chunk_ranges(self, n: int) -> Iterator[tuple[int, int]]:
        """``[i, j)`` index ranges of ``chunk_events`` events covering ``n`` events."""
        for i in range(0, n, self.chunk_events):
            yield i, min(n, i + self.chunk_events)

    def _slice(self, f: h5py.File, segment: int, t0: float, t1: float) -> np.ndarray:
        raise NotImplementedError

    def _read_events_between(self, segment: int, t0: float, t1: float) -> np.ndarray:
        with open_h5(self.path) as f:
            return self._slice(f, segment, t0, t1)
