"""Kept for compatibility: the latency-curve trainer now lives in :mod:`evlatcorr.lightning`.

``from evlatcorr.training import LatencyCorrectionModule`` (and every other name below) keeps
working, and ``python -m evlatcorr.training ARGS`` runs ``python -m evlatcorr.lightning latency ARGS``.
"""

from __future__ import annotations

from collections.abc import Sequence

from evlatcorr.frames import EventFrames
from evlatcorr.lightning.cli import run_command
from evlatcorr.lightning.data import EventFramesDataModule, collate_event_frames
from evlatcorr.lightning.latency import LatencyCorrectionModule
from evlatcorr.lightning.latency_data import recording_training_frames, simulated_training_frames

__all__ = ["split_frames", "collate_event_frames", "EventFramesDataModule", "LatencyCorrectionModule",
           "simulated_training_frames", "recording_training_frames", "main"]


def split_frames(frames: EventFrames) -> list[EventFrames]:
    """:meth:`EventFrames.split <evlatcorr.frames.EventFrames.split>` under its former name."""
    return frames.split()


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m evlatcorr.lightning latency``, under the name ``python -m evlatcorr.training``."""
    run_command("latency", argv, prog="python -m evlatcorr.training")


if __name__ == "__main__":
    main()
