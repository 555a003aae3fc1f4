"""Where shipped weights are found (the adapters' checkpoints and the learned curve reader's).

Example:
    >>> any(d.name == "checkpoints" for d in checkpoint_dirs())
    True
"""

from __future__ import annotations

import os
from pathlib import Path

__all__ = ["checkpoint_dirs"]


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
