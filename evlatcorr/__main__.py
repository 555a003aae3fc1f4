"""The ``evlatcorr`` command and ``python -m evlatcorr``: CPU memory settings asked for, then the command line."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from evlatcorr.pages import prefer_fast_memory


def main(argv: Sequence[str] | None = None) -> int:
    """Run :func:`evlatcorr.cli.main` with 2 MB CPU pages and freed memory kept for reuse (:mod:`evlatcorr.pages`)."""
    prefer_fast_memory()  # before the command line's imports make the process's first tensor
    from evlatcorr.cli import main as command_line

    return command_line(argv)


if __name__ == "__main__":
    sys.exit(main())
