"""Wrapping one frame and its window's events as an :class:`~evlatcorr.EventFrames` batch of 1."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.io.records import FrameInfo, RecordingError

__all__ = ["frame_batch"]


def frame_batch(info: FrameInfo, events: np.ndarray, lo: float, hi: float, sensor_size: tuple[int, int],
                path: Path) -> EventFrames:
    """One frame with the (already validated) events of its window ``[lo, hi)`` as a batch of 1.

    Raises:
        RecordingError: the frame's ``(H, W)`` is not the sensor's.
    """
    image = _tensor(info.image)
    if image.shape[-2:] != sensor_size:
        raise RecordingError(f"{path}: frame {info.index} is {tuple(image.shape[-2:])} but the sensor "
                             f"is {sensor_size} (H, W)")
    target_times = target_frames = None
    if info.targets is not None:
        target_times = torch.from_numpy(np.asarray(info.targets[0], dtype=np.float64))[None]
        target_frames = _tensor(info.targets[1])
    meta = {"file": str(path), "frame": info.index, "segment": info.segment, "window_us": (lo, hi), **info.meta}
    return EventFrames(image, _trusted_events(events, sensor_size),
                       torch.tensor([info.exposure_start], dtype=torch.float64),
                       torch.tensor([info.exposure_end], dtype=torch.float64),
                       sharp=None if info.sharp is None else _tensor(info.sharp),
                       target_times=target_times, target_frames=target_frames, meta=meta)


def _tensor(image: np.ndarray) -> torch.Tensor:
    """A float32 image (or stack) with a leading batch dimension of 1."""
    return torch.from_numpy(np.ascontiguousarray(image, dtype=np.float32))[None]


def _trusted_events(events: np.ndarray, sensor_size: tuple[int, int]) -> Events:
    # the chunks were validated as they were read (sorted, finite, on the sensor, p = ±1)
    return Events.from_canonical(torch.from_numpy(events["x"].astype(np.int64)),
                                 torch.from_numpy(events["y"].astype(np.int64)),
                                 torch.from_numpy(events["t"].astype(np.float64)),
                                 torch.from_numpy(events["p"].astype(np.int8)),
                                 torch.zeros(len(events), dtype=torch.long), sensor_size, 1)
