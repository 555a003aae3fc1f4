"""Output files that never destroy what they did not create.

Every writer of the command line goes through these helpers:

- :func:`check_outputs` refuses, before any work, an output that is an input, two outputs with one
  name, an output that is a directory, and a folder that cannot be written;
- :func:`check_hdf5_name` refuses an HDF5 output named as another format (``events.txt``);
- :func:`atomic_dir` builds a folder under a hidden temporary name and renames it only when the
  block succeeds (on any exception, KeyboardInterrupt and SIGTERM included, it is removed);
- :func:`default_file_mode` is the mode a plain ``open()`` would give (``0o666`` less the umask):
  temporary files are made ``0o600`` and must be widened before they are renamed into place.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = ["check_outputs", "check_hdf5_name", "check_writable_folder", "atomic_dir", "default_file_mode"]

# names an HDF5 file goes by
HDF5_SUFFIXES = (".h5", ".hdf5", ".hdf", ".he5")


def _umask() -> int:
    mask = os.umask(0)  # the only portable way to read it is to set it and put it back
    os.umask(mask)
    return mask


def default_file_mode() -> int:
    """``0o666`` less the process umask: the mode ``open(path, "w")`` creates files with.

    Example:
        >>> oct(default_file_mode())  # doctest: +SKIP
        '0o644'
    """
    return 0o666 & ~_umask()


def _same(a: Path, b: Path) -> bool:
    if a.exists() and b.exists():
        return os.path.samefile(a, b)
    return a.resolve() == b.resolve()


def _writable_folder(path: Path) -> Path:
    """The nearest existing ancestor of ``path`` (the folder a new file or folder would go into)."""
    parent = path.parent
    while not parent.exists():
        parent = parent.parent
    return parent


def check_hdf5_name(path: str | Path) -> None:
    """Refuse an HDF5 output whose name says it is something else (``events.txt`` would hold HDF5, and a user who
    asked for a text file would find out only when reading it).

    Raises:
        ValueError: naming the path and the suffixes taken.

    Example:
        >>> check_hdf5_name("corrected.h5")
        >>> check_hdf5_name("corrected.txt")
        Traceback (most recent call last):
        ...
        ValueError: output corrected.txt: this command writes HDF5; name it .h5 (or .hdf5, .hdf, .he5)
    """
    if Path(path).suffix.lower() not in HDF5_SUFFIXES:
        raise ValueError(f"output {path}: this command writes HDF5; name it {HDF5_SUFFIXES[0]} (or "
                         f"{', '.join(HDF5_SUFFIXES[1:])})")


def check_outputs(inputs: Iterable[str | Path], files: Iterable[str | Path] = (), folders: Iterable[str | Path] = (),
                  overwrite_folders: bool = False) -> None:
    """Refuse outputs that would destroy an input or each other, or that cannot be written.

    Args:
        inputs: paths read (files or folders).
        files: output files; each may exist as a file (it is replaced), not as a folder.
        folders: output folders; each may be missing or empty, or anything with ``overwrite_folders``.
        overwrite_folders: allow replacing a non-empty output folder.

    Raises:
        ValueError: naming the path and what to change.

    Example:
        >>> check_outputs(["in.h5"], files=["in.h5"])
        Traceback (most recent call last):
        ...
        ValueError: output in.h5 is the input in.h5: write the result to another file
    """
    inputs = [Path(p) for p in inputs]
    files, folders = [Path(p) for p in files], [Path(p) for p in folders]
    outputs = files + folders
    for i, out in enumerate(outputs):
        for src in inputs:
            if _same(out, src) or (src.exists() and src.resolve().is_relative_to(out.resolve())):
                raise ValueError(f"output {out} is the input {src}: write the result to another "
                                 f"{'file' if out in files else 'folder'}")
        for other in outputs[i + 1:]:
            if _same(out, other):
                raise ValueError(f"two outputs have the same name {out}: choose another output name")
    for out in files:
        if out.is_dir():
            raise ValueError(f"output {out} is a directory: pass a file name")
        if out.exists() and not os.access(out, os.W_OK):
            raise ValueError(f"output {out} exists and is not writable")
    for out in folders:
        if out.exists() and not out.is_dir():
            raise ValueError(f"output folder {out} exists and is a file: pass a folder name")
        if out.is_dir() and any(out.iterdir()) and not overwrite_folders:
            raise ValueError(f"output folder {out} exists and is not empty: choose another folder or pass "
                             "--overwrite")
    for out in outputs:
        folder = _writable_folder(out)
        if not folder.is_dir():
            raise ValueError(f"cannot write {out}: {folder} is not a folder")
        if not os.access(folder, os.W_OK | os.X_OK):
            raise ValueError(f"cannot write {out}: the folder {folder} is not writable")


def check_writable_folder(path: str | Path) -> None:
    """Make the folder ``path`` (a run would make it anyway) and write and remove a scratch file in it: for a long run
    that writes there only at its end, checked before it starts, so that a typo in a path does not lose it. Unlike a
    permission check this also holds for root and for file systems that refuse writes.

    Raises:
        ValueError: naming the path and why it cannot be written.

    Example:
        >>> check_writable_folder("/proc/no/such/folder")
        Traceback (most recent call last):
        ...
        ValueError: /proc/no/such/folder cannot be written: No such file or directory
    """
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as exc:
        raise ValueError(f"{path} cannot be written: {exc.strerror or exc}") from None


@contextmanager
def atomic_dir(path: str | Path, overwrite: bool = False) -> Iterator[Path]:
    """A temporary folder next to ``path``, renamed to ``path`` only if the block succeeds.

    An existing empty ``path`` is replaced; a non-empty one only with ``overwrite`` (it is removed
    after the new folder is in place). On failure the temporary folder is removed and ``path`` is
    left as it was.

    Example:
        >>> with atomic_dir("frames") as tmp:  # doctest: +SKIP
        ...     (tmp / "a.png").write_bytes(data)
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_umask())  # mkdtemp makes it 0o700; a plain mkdir would honour the umask
        old = None
        if path.exists():
            if path.is_dir() and not any(path.iterdir()):
                path.rmdir()
            elif overwrite and path.is_dir():
                old = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".old", dir=path.parent))
                os.replace(path, old / path.name)
            else:
                raise ValueError(f"output folder {path} exists and is not empty: choose another folder or pass "
                                 "--overwrite")
        os.replace(tmp, path)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
