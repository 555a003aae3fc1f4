"""The ``evlatcorr`` command and ``python -m evlatcorr``: large CPU pages asked for, then the command line."""

from __future__ import annotations

import sys
from collections.abc import Sequence

from evlatcorr.pages import prefer_large_pages


def main(argv: Sequence[str] | None = None) -> int:
    """Run :func:`evlatcorr.cli.main` with 2 MB CPU pages (``THP_MEM_ALLOC_ENABLE=0`` opts out)."""
    prefer_large_pages()  # before the command line's imports make the process's first tensor
    from evlatcorr.cli import main as command_line

    return command_line(argv)


if __name__ == "__main__":
    sys.exit(main())
