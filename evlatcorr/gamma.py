"""Frames encoded for display (``linear ** (1 / gamma)``: PNG exports, video frames, sRGB) made linear, as EDI needs
them, and linear images encoded back."""

from __future__ import annotations

import argparse
import math

from torch import Tensor

from evlatcorr.frames import EventFrames

__all__ = ["check_frame_gamma", "frame_gamma_argument", "linear_frames", "display_image"]


def check_frame_gamma(gamma: object) -> float:
    """``frame_gamma`` as a float, refused unless finite and positive.

    Example:
        >>> check_frame_gamma(2.2)
        2.2
    """
    if isinstance(gamma, bool) or not isinstance(gamma, (int, float)) or not math.isfinite(gamma) or gamma <= 0:
        raise ValueError(f"frame_gamma must be a finite number > 0 (1: frames kept as read, 2.2: display-encoded "
                         f"frames made linear), got {gamma!r}")
    return float(gamma)


def frame_gamma_argument(text: str) -> float:
    """``--frame-gamma`` on a command line: the number, refused by argparse unless finite and positive.

    Example:
        >>> frame_gamma_argument("2.2")
        2.2
    """
    try:
        return check_frame_gamma(float(text))
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text!r}") from None


def linear_frames(batch: EventFrames, gamma: float) -> EventFrames:
    """``batch`` with its images (the blurry frame, the next one, a sharp one and target frames where present)
    raised to ``gamma``: display-encoded images made linear, as EDI needs them (``gamma = 1``: the batch itself;
    ``1 / gamma`` encodes linear ones back).

    Example:
        >>> import torch
        >>> from evlatcorr import EventFrames, Events
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5.0]), torch.tensor([1]),
        ...             sensor_size=(1, 2))
        >>> batch = EventFrames(torch.tensor([[[[0.5, 1.0]]]]), ev, torch.tensor([0.0]), torch.tensor([10.0]))
        >>> linear_frames(batch, 2.0).blurry.flatten().tolist()
        [0.25, 1.0]
    """
    if check_frame_gamma(gamma) == 1:
        return batch
    images = ("blurry", "blurry_next", "sharp", "target_frames")
    changes = {name: getattr(batch, name).clamp(0, 1) ** gamma for name in images if getattr(batch, name) is not None}
    return batch.replace(**changes)


def display_image(image: Tensor, gamma: float) -> Tensor:
    """A linear ``image`` (any shape, in [0, 1]) encoded back as its file had it: raised to ``1 / gamma``, the
    inverse of :func:`linear_frames` (``gamma = 1``: the image itself).

    Example:
        >>> import torch
        >>> display_image(torch.tensor([0.25, 1.0]), 2.0).tolist()
        [0.5, 1.0]
    """
    return image if check_frame_gamma(gamma) == 1 else image.clamp(0, 1) ** (1 / gamma)
