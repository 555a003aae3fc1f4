"""The LightningModule base of every trainer here: its batches are :class:`~evlatcorr.frames.EventFrames`."""

from __future__ import annotations

import lightning as L

__all__ = ["EventFramesModule"]


class EventFramesModule(L.LightningModule):
    """A ``LightningModule`` whose batches are :class:`~evlatcorr.frames.EventFrames`.

    Lightning's own batch transfer moves them: it calls the ``to`` of any object that has one, and
    :meth:`EventFrames.to <evlatcorr.frames.EventFrames.to>` moves the images and the events. No hook is
    overridden, so a ``LightningDataModule`` beside it draws no warning.

    Example:
        >>> import torch
        >>> from evlatcorr.events import Events
        >>> from evlatcorr.frames import EventFrames
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([1.0]), torch.ones(1), sensor_size=(1, 1))
        >>> batch = EventFrames(torch.zeros(1, 1, 1, 1), ev, torch.zeros(1), torch.ones(1))
        >>> EventFramesModule().transfer_batch_to_device(batch, torch.device("cpu"), 0).device
        device(type='cpu')
    """
