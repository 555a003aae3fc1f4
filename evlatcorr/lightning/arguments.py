"""Command-line pieces the training subcommands share: one-line errors, ``--devices``, ``--threshold``."""

from __future__ import annotations

import argparse
import math
import sys
from typing import NoReturn

__all__ = ["CommandParser", "parse_devices", "threshold_argument", "exit_bad_input"]


class CommandParser(argparse.ArgumentParser):
    """Bad arguments: one line on stderr and exit code 2 (the usage is long; ``--help`` shows it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def parse_devices(text: str) -> int | str:
    """``--devices``: a count (``"2"`` -> 2) or anything Lightning takes as is (``"auto"``, ``"0,1"``).

    Example:
        >>> parse_devices("2"), parse_devices("auto")
        (2, 'auto')
    """
    return int(text) if str(text).isdigit() else text


def threshold_argument(text: str) -> float | str:
    """``--threshold``: ``auto`` or a positive number.

    Example:
        >>> threshold_argument("0.25"), threshold_argument("auto")
        (0.25, 'auto')
    """
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number or 'auto', got {text!r}")
    return value


def exit_bad_input(label: str, exc: BaseException) -> NoReturn:
    """Bad input (a missing or unreadable file, too few frames, ...): one line on stderr and exit code 2,
    like bad arguments, instead of a traceback."""
    print(f"{label}: error: {exc}", file=sys.stderr)
    raise SystemExit(2) from None
