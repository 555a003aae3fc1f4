"""Where shipped weights are found (the adapters' checkpoints and the learned curve and tile readers').

Example:
    >>> any(d.name == "checkpoints" for d in checkpoint_dirs())
    True
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["checkpoint_dirs", "shipped_weights"]


def checkpoint_dirs() -> list[Path]:
    """Folders searched for ``"default"`` checkpoints, in order: ``$EVLATCORR_CHECKPOINT_DIR``, the
    repository's ``checkpoints/`` (source checkout) and the installed package's ``checkpoints/``."""
    dirs = []
    if os.environ.get("EVLATCORR_CHECKPOINT_DIR"):
        dirs.append(Path(os.environ["EVLATCORR_CHECKPOINT_DIR"]).expanduser())
    package = Path(__file__).resolve().parent
    dirs.append(package.parent / "checkpoints")  # evlatcorr/.. = the repository root in a source checkout
    dirs.append(package / "checkpoints")  # installed package data
    out: list[Path] = []
    for d in dirs:
        if d not in out:
            out.append(d)
    return out


def shipped_weights(file_name: str, path: str | Path | None, what: str, how_to_make: str) -> str:
    """``path`` if given (it must exist), else the first ``file_name`` in :func:`checkpoint_dirs`.

    Raises:
        FileNotFoundError: naming ``what`` and where it looked, and saying ``how_to_make`` them.
    """
    if path is not None:
        if not Path(path).is_file():
            raise FileNotFoundError(f"no {what} weights at {path}")
        return str(path)
    found = next((d / file_name for d in checkpoint_dirs() if (d / file_name).is_file()), None)
    if found is None:
        raise FileNotFoundError(f"no {file_name} in {[str(d) for d in checkpoint_dirs()]}: {how_to_make}")
    return str(found)
