"""What a restoration batch is scored against: its ground truth (``sharp`` or ``target_frames``)."""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.frames import EventFrames

__all__ = ["has_truth", "restoration_pair"]


def has_truth(frames: EventFrames, task: str) -> bool:
    """Whether a batch carries the ground truth of ``task``: ``sharp`` (deblur) or ``target_frames``.

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([1.0]), torch.ones(1), sensor_size=(2, 2))
        >>> fr = EventFrames(torch.rand(1, 1, 2, 2), ev, torch.tensor([0.0]), torch.tensor([5.0]))
        >>> has_truth(fr, "deblur"), has_truth(fr.replace(sharp=fr.blurry), "deblur")
        (False, True)
    """
    if task == "deblur":
        return frames.sharp is not None
    return frames.target_frames is not None and frames.target_times is not None


def restoration_pair(output: EventFrames, task: str) -> tuple[Tensor, Tensor] | None:
    """(prediction, target) of an adapter's output, or None when the batch has no ground truth.

    Deblurring compares ``output`` with ``sharp``. Interpolation compares with ``target_frames``: an
    output with one frame per target time is compared frame by frame; an output with its own times
    (``meta["output_times"]``, REFID) is compared at the output frame nearest each target time.
    """
    pred = output.output
    if pred is None:
        raise ValueError("the model did not fill frames.output")
    if task == "deblur":
        return None if output.sharp is None else (pred, output.sharp)
    if output.target_frames is None or output.target_times is None:
        return None
    if pred.dim() == 5 and pred.shape[1] != output.target_times.shape[1]:
        times = output.meta["output_times"].to(output.target_times)
        index = (times[:, None, :] - output.target_times[:, :, None]).abs().argmin(-1)
        pred = torch.stack([pred[b, index[b]] for b in range(pred.shape[0])])
    return pred, output.target_frames
