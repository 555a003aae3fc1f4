"""Wrapping one frame and its window's events as an :class:`~evlatcorr.EventFrames` batch of 1; frames encoded for
display made linear as read (``frame_gamma``), and encoded back for writing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.io.records import FrameInfo, RecordingError

__all__ = ["frame_batch", "linear_frames", "display_image", "check_frame_gamma"]


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


def check_frame_gamma(gamma: object) -> float:
    """``frame_gamma`` as a float, refused unless finite and positive.

    Example:
        >>> check_frame_gamma(2.2)
        2.2
    """
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not np.isfinite(gamma) or gamma <= 0:
        raise ValueError(f"frame_gamma must be a finite number > 0 (1: frames kept as read, 2.2: display-encoded "
                         f"frames made linear), got {gamma!r}")
    return float(gamma)


def linear_frames(batch: EventFrames, gamma: float) -> EventFrames:
    """``batch`` with its images (the blurry frame, the next one, a sharp one and target frames where present)
    raised to ``gamma``: display-encoded images made linear, as EDI needs them (``gamma = 1``: the batch itself;
    ``1 / gamma`` encodes linear ones back).

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5.0]), torch.tensor([1]),
        ...             sensor_size=(1, 2))
        >>> batch = EventFrames(torch.tensor([[[[0.5, 1.0]]]]), ev, torch.tensor([0.0]), torch.tensor([10.0]))
        >>> linear_frames(batch, 2.0).blurry.flatten().tolist()
        [0.25, 1.0]
    """
    if gamma == 1:
        return batch
    images = ("blurry", "blurry_next", "sharp", "target_frames")
    changes = {name: getattr(batch, name).clamp(0, 1) ** gamma for name in images if getattr(batch, name) is not None}
    return batch.replace(**changes)


def display_image(image: Tensor, gamma: float) -> Tensor:
    """A linear ``image`` (any shape, in [0, 1]) encoded back as its file had it: raised to ``1 / gamma``, the
    inverse of :func:`linear_frames` (``gamma = 1``: the image itself).

    Example:
        >>> display_image(torch.tensor([0.25, 1.0]), 2.0).tolist()
        [0.5, 1.0]
    """
    return image if gamma == 1 else image.clamp(0, 1) ** (1 / gamma)
