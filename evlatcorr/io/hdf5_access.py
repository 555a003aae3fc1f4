"""Reading HDF5 files, shared by the readers of our format and of event_utils' format.

Opening with the optional compression plugins registered and an error that names the file, and a
bisection over a sorted dataset that reads O(log N) chunks instead of the whole column.
"""

from __future__ import annotations

from pathlib import Path

import h5py
import numpy as np

from evlatcorr.io.base import RecordingError

__all__ = ["load_plugins", "open_h5", "bisect_sorted"]

# Elements of a dataset read at once once the bisection has narrowed it down.
_CHUNK = 65536


def load_plugins() -> bool:
    """Register the optional hdf5plugin filters (for files compressed with zstd/blosc/lz4)."""
    try:
        import hdf5plugin  # noqa: F401
    except ImportError:
        return False
    return True


def open_h5(path: str | Path) -> h5py.File:
    """``path`` opened read-only, or a :class:`RecordingError` that names it."""
    load_plugins()
    try:
        return h5py.File(path, "r")
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read as HDF5 (truncated or corrupt?): {exc}") from exc


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
