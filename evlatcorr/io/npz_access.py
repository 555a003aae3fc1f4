"""Reading ``.npz`` files, shared by the GEM and HighREV readers: required keys, errors that name the file."""

from __future__ import annotations

import zipfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.io.records import RecordingError

__all__ = ["open_npz"]


@contextmanager
def open_npz(file: Path, keys: Iterable[str], kind: str, allow_pickle: bool = False) -> Iterator[Any]:
    """``file`` opened with :func:`numpy.load`, after checking it holds ``keys``.

    A missing key, and any error reading the file inside the block (truncated or corrupt
    archive), becomes a :class:`RecordingError` that names the file; ``kind`` says what the file
    should have been (``"a GEM npz pair"``).

    Example:
        >>> import tempfile, os
        >>> path = Path(tempfile.mkdtemp()) / "a.npz"
        >>> np.savez(path, x=np.arange(3))
        >>> with open_npz(path, {"x"}, "an event file") as z:
        ...     z["x"].tolist()
        [0, 1, 2]
        >>> try:
        ...     with open_npz(path, {"x", "y"}, "an event file") as z:
        ...         pass
        ... except RecordingError as exc:
        ...     print(str(exc).split(": ", 1)[1])
        not an event file, missing keys ['y']
    """
    try:
        with np.load(file, allow_pickle=allow_pickle) as z:
            missing = set(keys) - set(z.files)
            if missing:
                raise RecordingError(f"{file}: not {kind}, missing keys {sorted(missing)}")
            yield z
    except RecordingError:
        raise
    except (OSError, ValueError, EOFError, KeyError, zipfile.BadZipFile) as exc:
        raise RecordingError(f"{file}: cannot read npz (truncated or corrupt?): {exc}") from exc
