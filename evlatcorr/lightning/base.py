"""The LightningModule base of every trainer here: moves :class:`~evlatcorr.frames.EventFrames` batches to devices."""

from __future__ import annotations

from typing import Any

import lightning as L
import torch

from evlatcorr.frames import EventFrames

__all__ = ["EventFramesModule"]


class EventFramesModule(L.LightningModule):
    """A ``LightningModule`` whose batches are :class:`~evlatcorr.frames.EventFrames`.

    Lightning moves only tensors and standard containers; an ``EventFrames`` (tensors and
    :class:`~evlatcorr.events.Events`) is moved by its own ``to``.

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([1.0]), torch.ones(1), sensor_size=(1, 1))
        >>> batch = EventFrames(torch.zeros(1, 1, 1, 1), ev, torch.zeros(1), torch.ones(1))
        >>> EventFramesModule().transfer_batch_to_device(batch, torch.device("cpu"), 0).device
        device(type='cpu')
    """

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        if isinstance(batch, EventFrames):
            return batch.to(device)
        return super().transfer_batch_to_device(batch, device, dataloader_idx)
