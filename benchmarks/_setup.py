"""What every script in ``benchmarks/`` does before it imports torch: the repository on ``sys.path``, the CPU
memory settings (2 MB pages, freed memory kept for reuse).

Each script imports it first (``import _setup``: the script's own folder is on ``sys.path``), so the memory
settings (:func:`evlatcorr.pages.prefer_fast_memory`) come before the process's first tensor.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evlatcorr.pages import prefer_fast_memory  # noqa: E402

prefer_fast_memory()


def passive_openmp() -> None:
    """Let idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE`` unless set): call before torch loads.

    While another process keeps a core busy, OpenMP's busy-waiting threads made the simulator's small-tensor
    steps 3-20x slower on a 2-core VM; passive waiting costs little otherwise. The suite scripts ask for it;
    the timing scripts do not, so their figures keep torch's default.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def add_case_options(parser: argparse.ArgumentParser, default_split: str, splits: tuple[str, ...] = ("test", "dev"),
                     num_help: str = "first N cases of each split") -> None:
    """``--split``, ``--num`` and ``--size``: which of the accuracy suite's cases a script runs."""
    from evlatcorr.benchmark.accuracy import DEFAULT_SIZE

    parser.add_argument("--split", choices=splits, default=default_split)
    parser.add_argument("--num", type=int, default=None, help=num_help)
    parser.add_argument("--size", type=int, nargs=2, default=DEFAULT_SIZE, metavar=("H", "W"))
