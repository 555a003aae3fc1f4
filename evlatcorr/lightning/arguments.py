"""Command-line pieces the training subcommands share: one-line errors, ``--devices``, ``--threshold``."""

from __future__ import annotations

import argparse
import logging
import math
import re
import sys
import warnings
from collections.abc import Callable
from typing import Any, NoReturn

__all__ = ["CommandParser", "parse_devices", "threshold_argument", "exit_bad_input", "trainer_or_exit",
           "quiet_lightning", "MIN_FRAME_SIZE"]

#: the smallest simulated frame or --data crop the commands that train the latency curve take (the latency command,
#: and run.py, whose spatial rows train one): the search and the ETF filter 7x7 boxes
MIN_FRAME_SIZE = 8

#: Lightning's messages that tell a user of these commands nothing they can act on: adverts for its cloud services,
#: a note that without TensorBoard its default logger writes CSV files (under --out, where the commands write their
#: runs), and a deprecation inside Lightning's own code
_LIGHTNING_NOISE = ("💡 Tip:", "Starting from v1.9.0, `tensorboardX` has been removed",
                    "`isinstance(treespec, LeafSpec)` is deprecated")


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


def trainer_or_exit(label: str, make: Callable[[], Any]) -> Any:
    """``make()``, a Lightning ``Trainer``; a setting Lightning refuses (``--devices 0``, ``--accelerator gpu`` on a
    machine without one, an unknown ``--strategy``) is bad input: one line and exit code 2, not a traceback."""
    from lightning.fabric.utilities.exceptions import MisconfigurationException

    quiet_lightning()
    try:
        return make()
    except (MisconfigurationException, ValueError) as exc:  # an unknown strategy name is a ValueError
        exit_bad_input(label, exc)


class _DropLightningNoise(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith(_LIGHTNING_NOISE)


def quiet_lightning() -> None:
    """Leave out :data:`_LIGHTNING_NOISE` from a training command's output; Lightning's other messages and warnings
    (devices found, a loader with too few workers, ...) stay. Calling it again adds nothing."""
    for text in _LIGHTNING_NOISE[1:]:
        warnings.filterwarnings("ignore", message=f".*{re.escape(text)}")
    log = logging.getLogger("lightning.pytorch.utilities.rank_zero")  # where rank_zero_info logs
    if not any(isinstance(f, _DropLightningNoise) for f in log.filters):
        log.addFilter(_DropLightningNoise())
