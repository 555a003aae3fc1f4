"""Kept for compatibility: the restoration trainers now live in :mod:`evlatcorr.lightning`.

``from evlatcorr.train import RestorationModule`` (and every other name below) keeps working, and
``python -m evlatcorr.train ARGS`` runs ``python -m evlatcorr.lightning restore ARGS``.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from evlatcorr.frames import EventFrames
from evlatcorr.lightning.cli import run_command
from evlatcorr.lightning.export import write_checkpoint_readme
from evlatcorr.lightning.networks import MODELS, build_adapter, checkpoint_name
from evlatcorr.lightning.restoration import CorrectedRestorationModule, RestorationModule
from evlatcorr.lightning.restoration_data import RecordingRestorationData, SimulatedRestorationData
from evlatcorr.lightning.targets import has_truth, restoration_pair

__all__ = [
    "MODELS",
    "build_adapter",
    "checkpoint_name",
    "crop_frames",
    "collate_frames",
    "SimulatedRestorationData",
    "RecordingRestorationData",
    "has_truth",
    "restoration_pair",
    "RestorationModule",
    "CorrectedRestorationModule",
    "write_checkpoint_readme",
    "main",
]


def crop_frames(frames: EventFrames, top: int, left: int, height: int, width: int,
                hflip: bool = False) -> EventFrames:
    """:meth:`EventFrames.crop <evlatcorr.frames.EventFrames.crop>` under its former name."""
    return frames.crop(top, left, height, width, hflip=hflip)


def collate_frames(items: Sequence[EventFrames]) -> EventFrames:
    """:meth:`EventFrames.cat <evlatcorr.frames.EventFrames.cat>` under its former name."""
    return EventFrames.cat(items)


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """``python -m evlatcorr.lightning restore``, under the name ``python -m evlatcorr.train``."""
    return run_command("restore", argv, prog="python -m evlatcorr.train")


if __name__ == "__main__":
    main()
