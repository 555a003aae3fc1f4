"""Datasets and data loaders of ``EventFrames`` samples: lists, seeded random crops, the generic data module."""

from __future__ import annotations

from collections.abc import Sequence

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset, get_worker_info

from evlatcorr.frames import EventFrames

__all__ = ["FramesDataset", "RandomCrops", "EventFramesDataModule", "collate_event_frames", "frames_loader",
           "seed_worker"]


class FramesDataset(Dataset):
    """A map-style dataset over a list of ``EventFrames``."""

    def __init__(self, items: Sequence[EventFrames]) -> None:
        self.items = list(items)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> EventFrames:
        return self.items[index]


class RandomCrops(Dataset):
    """Random crops, mirrored left-right at random, of whole-frame samples, drawn from a seeded generator.

    Args:
        samples: each sample is a tuple of alternatives (e.g. one frame with ideal and with delayed
            events); each item draws one of them at random (no draw for a single alternative).
        crop: ``(H, W)`` of the crops; None serves whole frames (only the alternative is drawn).
        length: items per epoch (the samples are reused in turn); default one per sample.
        seed: seed of the generator. Data-loader workers reseed it from their own seed
            (:func:`seed_worker`), so that they do not draw the same crops.
        require_events: draw a crop again, up to ``tries`` times, while it has no events in its
            exposure and latency-search window (dark or static tiles of a real scene).
        tries: the most crops drawn per item with ``require_events``.

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0, 3]), torch.tensor([0, 3]), torch.tensor([1.0, 2.0]), torch.ones(2),
        ...             sensor_size=(4, 4))
        >>> frame = EventFrames(torch.rand(1, 1, 4, 4), ev, torch.zeros(1), torch.full((1,), 10.0))
        >>> crops = RandomCrops([(frame,)], (2, 2), length=3, seed=0)
        >>> len(crops), crops[0].sensor_size
        (3, (2, 2))
    """

    def __init__(self, samples: Sequence[tuple[EventFrames, ...]], crop: tuple[int, int] | None,
                 length: int | None = None, seed: int = 0, require_events: bool = False, tries: int = 10) -> None:
        self.samples, self.crop, self.length = list(samples), crop, length or len(samples)
        self.require_events, self.tries = require_events, tries
        self.generator = torch.Generator().manual_seed(seed)

    def reseed(self, seed: int) -> None:
        self.generator.manual_seed(seed)

    def __len__(self) -> int:
        return self.length

    def _draw(self, high: int) -> int:
        return int(torch.randint(high, (), generator=self.generator))

    def __getitem__(self, index: int) -> EventFrames:
        from evlatcorr.restore import has_events

        alternatives = self.samples[index % len(self.samples)]
        frames = alternatives[self._draw(len(alternatives))] if len(alternatives) > 1 else alternatives[0]
        if self.crop is None:
            return frames
        h, w = frames.sensor_size
        ch, cw = self.crop
        for _ in range(self.tries if self.require_events else 1):
            top, left = self._draw(h - ch + 1), self._draw(w - cw + 1)
            out = frames.crop(top, left, ch, cw, hflip=bool(self._draw(2)))
            if not self.require_events or has_events(out):
                break
        return out


def seed_worker(worker_id: int) -> None:
    """``worker_init_fn`` of the loaders: reseed a dataset's generator from the worker's own seed.

    The worker's seed comes from the loader's seeded generator (a new one each epoch for
    non-persistent workers), so runs are reproducible and workers draw different crops.
    """
    info = get_worker_info()
    if info is not None and hasattr(info.dataset, "reseed"):
        info.dataset.reseed(info.seed)


def frames_loader(dataset: Dataset, batch_size: int, shuffle: bool, num_workers: int, seed: int = 0,
                  persistent_workers: bool = False) -> DataLoader:
    """A ``DataLoader`` batching ``EventFrames`` by :meth:`EventFrames.cat`; its shuffling and worker seeds are
    drawn from a generator seeded by ``seed`` (not from the global random state)."""
    return DataLoader(dataset, batch_size=batch_size, shuffle=shuffle, num_workers=num_workers,
                      collate_fn=EventFrames.cat, generator=torch.Generator().manual_seed(seed),
                      worker_init_fn=seed_worker, persistent_workers=persistent_workers and num_workers > 0)


def collate_event_frames(items: Sequence[EventFrames]) -> EventFrames:
    """Batch ``EventFrames`` keeping only blurry frames, events, exposures and (when all have it) ``sharp``.

    Kept for the callers that rely on the other fields being left out (e.g. target times, at which
    the deblurring adapters would otherwise restore); :meth:`EventFrames.cat` keeps every field.

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([1.0]), torch.ones(1), sensor_size=(1, 1))
        >>> item = EventFrames(torch.zeros(1, 1, 1, 1), ev, torch.zeros(1), torch.ones(1), target_times=[0.5])
        >>> batch = collate_event_frames([item, item])
        >>> batch.batch_size, batch.target_times
        (2, None)
    """
    if not items:
        raise ValueError("cannot collate an empty list of EventFrames")
    sharp = all(x.sharp is not None for x in items)
    return EventFrames.cat([EventFrames(x.blurry, x.events, x.exposure_start, x.exposure_end,
                                        sharp=x.sharp if sharp else None) for x in items])


class EventFramesDataModule(L.LightningDataModule):
    """A ``LightningDataModule`` over any ``EventFrames`` dataset (typically one frame per item).

    Args:
        train: training frames: a sequence of ``EventFrames`` or a map-style ``Dataset`` yielding
            them (read lazily, e.g. from files).
        val: optional validation frames, same kinds.
        batch_size: frames per step (paper: 1); items are batched by :meth:`EventFrames.cat`.
        num_workers: data-loader workers.
        seed: seed of the training loader's shuffling.

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0, 1]), torch.tensor([0, 2]), torch.tensor([10.0, 150.0]),
        ...             torch.tensor([1, -1]), sensor_size=(4, 4))
        >>> item = EventFrames(torch.rand(1, 1, 4, 4), ev, torch.zeros(1), torch.full((1,), 100.0))
        >>> batch = next(iter(EventFramesDataModule([item, item], batch_size=2).train_dataloader()))
        >>> batch.batch_size, batch.events.batch_size
        (2, 2)
    """

    def __init__(self, train: Sequence[EventFrames] | Dataset, val: Sequence[EventFrames] | Dataset | None = None,
                 batch_size: int = 1, num_workers: int = 0, seed: int = 0) -> None:
        super().__init__()
        if len(train) == 0:
            raise ValueError("the training dataset is empty: give at least one EventFrames")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.train_set, self.val_set = _as_dataset(train), _as_dataset(val if val is not None else [])
        self.batch_size, self.num_workers, self.seed = batch_size, num_workers, seed

    def train_dataloader(self) -> DataLoader:
        return frames_loader(self.train_set, self.batch_size, True, self.num_workers, self.seed)

    def val_dataloader(self) -> DataLoader:
        return frames_loader(self.val_set, self.batch_size, False, self.num_workers, self.seed)


def _as_dataset(items: Sequence[EventFrames] | Dataset) -> Dataset:
    return items if isinstance(items, Dataset) else FramesDataset(items)
