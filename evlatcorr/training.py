"""Self-supervised training of the latency polynomial with Lightning (paper Sec. 3.4).

No ground truth is used: each step finds the frame's constant latency ``l_const`` by the one-pass
search and minimises Eq. (21) through the latency-differentiable EDI. The same module runs on one
CPU or on many GPUs with ``Trainer(accelerator="auto", devices=N, strategy="ddp")``.

Command line (simulated training scenes, a checkpoint and the curve under ``--out``)::

    python -m evlatcorr.training --epochs 5 --out runs/curve
    python -m evlatcorr.training --devices 2 --strategy ddp --accelerator cpu --epochs 1 --size 32 40
    python -m evlatcorr.training --data my_camera.aedat4 --crop 96 128 --out runs/my_curve   # your recording

With ``--data`` the frames of any recording ``evlatcorr.io`` reads are the training data (no ground
truth needed): frames with events, cut into ``--crop`` tiles, every ``--val-every``-th frame held out
for validation, and the recording's contrast threshold estimated (``--threshold auto``, two-frame
consistency) unless given.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.spatial import LossWeights, PolynomialLatency, constant_reference, save_curve, spatial_objective

__all__ = ["split_frames", "collate_event_frames", "EventFramesDataModule", "LatencyCorrectionModule",
           "simulated_training_frames"]


def split_frames(frames: EventFrames) -> list[EventFrames]:
    """One single-frame ``EventFrames`` per sample of a batch."""
    out = []
    for i in range(frames.batch_size):
        out.append(EventFrames(frames.blurry[i:i + 1], frames.events.sample(i), frames.exposure_start[i:i + 1],
                               frames.exposure_end[i:i + 1],
                               sharp=None if frames.sharp is None else frames.sharp[i:i + 1],
                               meta={"index": i}))
    return out


def collate_event_frames(items: Sequence[EventFrames]) -> EventFrames:
    """Batch single- or multi-frame ``EventFrames`` (events via :meth:`Events.cat`)."""
    if not items:
        raise ValueError("cannot collate an empty list of EventFrames")
    sharp = None if any(x.sharp is None for x in items) else torch.cat([x.sharp for x in items])
    return EventFrames(torch.cat([x.blurry for x in items]), Events.cat([x.events for x in items]),
                       torch.cat([x.exposure_start for x in items]), torch.cat([x.exposure_end for x in items]),
                       sharp=sharp)


def _as_dataset(items: Sequence[EventFrames] | Dataset) -> Dataset:
    return items if isinstance(items, Dataset) else _ListDataset(items)


class _ListDataset(Dataset):
    def __init__(self, items: Sequence[EventFrames]) -> None:
        self.items = list(items)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, index: int) -> EventFrames:
        return self.items[index]


class EventFramesDataModule(L.LightningDataModule):
    """A ``LightningDataModule`` over any ``EventFrames`` dataset (typically one frame per item).

    Args:
        train: training frames: a sequence of ``EventFrames`` or a map-style ``Dataset`` yielding
            them (read lazily, e.g. from files).
        val: optional validation frames, same kinds.
        batch_size: frames per step (paper: 1); items are batched by :func:`collate_event_frames`.
        num_workers: data-loader workers.

    Example:
        >>> ev = Events(torch.tensor([0, 1]), torch.tensor([0, 2]), torch.tensor([10.0, 150.0]),
        ...             torch.tensor([1, -1]), sensor_size=(4, 4))
        >>> item = EventFrames(torch.rand(1, 1, 4, 4), ev, torch.zeros(1), torch.full((1,), 100.0))
        >>> batch = next(iter(EventFramesDataModule([item, item], batch_size=2).train_dataloader()))
        >>> batch.batch_size, batch.events.batch_size
        (2, 2)
    """

    def __init__(self, train: Sequence[EventFrames] | Dataset, val: Sequence[EventFrames] | Dataset | None = None,
                 batch_size: int = 1, num_workers: int = 0) -> None:
        super().__init__()
        if len(train) == 0:
            raise ValueError("the training dataset is empty: give at least one EventFrames")
        if batch_size < 1:
            raise ValueError(f"batch_size must be >= 1, got {batch_size}")
        self.train_set, self.val_set = _as_dataset(train), _as_dataset(val if val is not None else [])
        self.batch_size, self.num_workers = batch_size, num_workers

    def train_dataloader(self) -> DataLoader:
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, num_workers=self.num_workers,
                          collate_fn=collate_event_frames)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(self.val_set, batch_size=self.batch_size, num_workers=self.num_workers,
                          collate_fn=collate_event_frames)


class LatencyCorrectionModule(L.LightningModule):
    """Trains :class:`~evlatcorr.spatial.PolynomialLatency` self-supervised (Eq. 19-21).

    Args:
        order: polynomial order K.
        eps: ε of the intensity map f.
        scale_us: µs per polynomial unit.
        lr: Adam learning rate.
        constant_epochs: epochs at constant learning rate (paper: 2).
        decay_epochs: epochs of linear decay to 0 afterwards (paper: 3).
        threshold: contrast threshold θ.
        num_bins: EDI sub-intervals during training.
        search_range: latency range (µs) of ``l_const`` and of the bound; default 0 to the exposure.
        num_candidates: candidates of the ``l_const`` search.
        alpha, beta, eta, zeta: loss weights of Eq. (21).

    Example:
        >>> module = LatencyCorrectionModule(order=3)
        >>> module.latency_model.coefficients.shape
        torch.Size([4])
    """

    def __init__(self, order: int = 5, eps: float = 0.01, scale_us: float = 1000.0, lr: float = 0.02,
                 constant_epochs: int = 2, decay_epochs: int = 3, threshold: float = 0.2, num_bins: int = 100,
                 search_range: tuple[float, float] | None = None, num_candidates: int = 100, alpha: float = 1.0,
                 beta: float = 1.0, eta: float = 20.0, zeta: float = 0.1, epsilon: float = DEFAULT_EPSILON,
                 window: int = DEFAULT_WINDOW, sigma_us: float = DEFAULT_SIGMA_US) -> None:
        super().__init__()
        if constant_epochs < 0 or decay_epochs < 0:
            raise ValueError("constant_epochs and decay_epochs must be >= 0")
        if lr <= 0 or threshold <= 0:
            raise ValueError("lr and threshold must be positive")
        self.save_hyperparameters()
        self.latency_model = PolynomialLatency(order, eps, scale_us)
        self.weights = LossWeights(alpha, beta, eta, zeta)

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        return batch.to(device) if isinstance(batch, EventFrames) else super().transfer_batch_to_device(
            batch, device, dataloader_idx)

    def _step(self, batch: EventFrames, stage: str) -> torch.Tensor:
        hp = self.hparams
        if bool((batch.exposure_time <= 0).any()):
            raise ValueError("every frame needs an exposure of positive length")
        l_const, etf_const = constant_reference(batch, hp.threshold, hp.num_bins, hp.search_range,
                                                hp.num_candidates, hp.epsilon, hp.window, hp.sigma_us)
        l_max = batch.exposure_time if hp.search_range is None else torch.full_like(batch.exposure_time,
                                                                                   hp.search_range[1])
        terms = spatial_objective(self.latency_model, batch, l_const, l_max, etf_const, hp.threshold, hp.num_bins,
                                  self.weights, hp.epsilon, hp.window, hp.sigma_us)
        for name, value in terms.items():
            self.log(f"{stage}/{name}", value, batch_size=batch.batch_size, sync_dist=stage != "train",
                     prog_bar=name == "total")
        return terms["total"]

    def training_step(self, batch: EventFrames, batch_idx: int) -> torch.Tensor:
        return self._step(batch, "train")

    def validation_step(self, batch: EventFrames, batch_idx: int) -> None:
        with torch.enable_grad():  # the EDI is cheap either way; keep one code path
            self._step(batch, "val")

    def configure_optimizers(self):
        hp = self.hparams
        optimiser = torch.optim.Adam(self.parameters(), lr=hp.lr)

        def factor(epoch: int) -> float:
            if epoch < hp.constant_epochs:
                return 1.0
            if hp.decay_epochs == 0:
                return 0.0
            return max(0.0, 1.0 - (epoch - hp.constant_epochs + 1) / (hp.decay_epochs + 1))

        scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, factor)
        return {"optimizer": optimiser, "lr_scheduler": {"scheduler": scheduler, "interval": "epoch"}}


def simulated_training_frames(names: Sequence[str], size: tuple[int, int], seed: int = 0,
                              latency: str = "intensity_delay", **kwargs: Any) -> list[EventFrames]:
    """Single-frame training samples from the simulator's training photographs."""
    from evlatcorr.simulate import simulate

    frames: list[EventFrames] = []
    for i, name in enumerate(names):
        seq = simulate(name, num_frames=2, height=size[0], width=size[1], latency=latency, seed=seed + i, **kwargs)
        frames.extend(split_frames(seq.frames("delayed")))
    return frames


def recording_training_frames(path: str | Path, crop: tuple[int, int] | None = None, threshold: float | str = "auto",
                              search_high_us: float | None = None, val_every: int = 5
                              ) -> tuple[list[EventFrames], list[EventFrames], float]:
    """Training and validation samples from a recording (any format ``evlatcorr.io`` reads), no ground truth.

    Every frame with events in its exposure and search window becomes one sample, cut into
    non-overlapping ``crop`` tiles (None: whole frames); every ``val_every``-th frame is held out.

    Args:
        path: the recording.
        crop: ``(H, W)`` of the tiles.
        threshold: θ, or ``"auto"`` for one θ of the recording (:func:`~evlatcorr.restore.recording_threshold`).
        search_high_us: the largest latency searched (default: the exposure time); events are read
            that far past each exposure.
        val_every: every this-many-th frame goes to validation (0: none).

    Returns:
        ``(train, val, θ)``.

    Raises:
        ValueError: when the recording has no frame with events, or ``crop`` is larger than the sensor.
    """
    from evlatcorr.io import open_recording
    from evlatcorr.restore import has_events, recording_threshold

    rec = open_recording(path, after_us=search_high_us)
    if isinstance(threshold, str):
        found = recording_threshold(rec, None if search_high_us is None else (0.0, search_high_us))
        theta = found if found is not None else 0.2
    else:
        theta = float(threshold)
    height, width = rec.sensor_size
    ch, cw = crop if crop is not None else (height, width)
    if not (0 < ch <= height and 0 < cw <= width):
        raise ValueError(f"crop {crop} must fit the sensor {rec.sensor_size} (H, W)")
    train, val, used = [], [], 0
    for batch in rec:
        if not has_events(batch):
            continue
        tiles = [_crop(batch, y, x, ch, cw) for y in range(0, height - ch + 1, ch)
                 for x in range(0, width - cw + 1, cw)]
        tiles = [t for t in tiles if has_events(t)]
        (val if val_every and used % val_every == val_every - 1 else train).extend(tiles)
        used += 1
    if not train:
        raise ValueError(f"{path}: no frame with events in its exposure and search window to train on")
    return train, val, theta


def _crop(frames: EventFrames, y0: int, x0: int, h: int, w: int) -> EventFrames:
    ev = frames.events
    keep = (ev.y >= y0) & (ev.y < y0 + h) & (ev.x >= x0) & (ev.x < x0 + w)
    events = Events._trusted(ev.x[keep] - x0, ev.y[keep] - y0, ev.t[keep], ev.p[keep], ev.batch[keep], (h, w),
                             ev.batch_size)
    return EventFrames(frames.blurry[..., y0:y0 + h, x0:x0 + w].contiguous(), events, frames.exposure_start,
                       frames.exposure_end, meta={"frame": frames.meta.get("frame"), "tile": (y0, x0)})


def main(argv: Sequence[str] | None = None) -> None:
    from evlatcorr.simulate import PHOTOGRAPHS_TRAIN

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scenes", nargs="+", default=list(PHOTOGRAPHS_TRAIN))
    p.add_argument("--size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"))
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--constant-epochs", type=int, default=2)
    p.add_argument("--order", type=int, default=5)
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--num-bins", type=int, default=100)
    p.add_argument("--accelerator", default="auto")
    p.add_argument("--devices", default="1")
    p.add_argument("--strategy", default="auto")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/latency_curve"))
    p.add_argument("--data", type=Path, help="train on this recording (any format evlatcorr.io reads) instead of "
                                             "simulated scenes")
    p.add_argument("--crop", type=int, nargs=2, metavar=("H", "W"), help="--data: tiles of this size (default: "
                                                                          "whole frames)")
    p.add_argument("--threshold", default="auto", help="--data: contrast threshold, or 'auto' (default): one θ "
                                                       "for the recording")
    p.add_argument("--val-every", type=int, default=5, help="--data: every N-th frame is held out (0: none)")
    p.add_argument("--max-steps", type=int, default=-1, help="stop after this many steps (default: --epochs only)")
    args = p.parse_args(argv)

    L.seed_everything(args.seed, workers=True)
    val: list[EventFrames] = []
    theta = 0.2
    if args.data is not None:
        try:
            threshold = args.threshold if args.threshold == "auto" else float(args.threshold)
            frames, val, theta = recording_training_frames(args.data, tuple(args.crop) if args.crop else None,
                                                           threshold, val_every=args.val_every)
        except (ValueError, OSError) as exc:  # bad input: one line and exit code 2, as the evlatcorr command
            print(f"evlatcorr.training: error: {exc}", file=sys.stderr)
            raise SystemExit(2) from None
        print(f"{args.data}: {len(frames)} training and {len(val)} validation samples, threshold {theta:.3f}")
    else:
        frames = simulated_training_frames(args.scenes, tuple(args.size), args.seed)
    module = LatencyCorrectionModule(order=args.order, lr=args.lr, num_bins=args.num_bins, threshold=theta,
                                     constant_epochs=args.constant_epochs,
                                     decay_epochs=max(0, args.epochs - args.constant_epochs))
    devices: int | str = int(args.devices) if args.devices.isdigit() else args.devices
    trainer = L.Trainer(max_epochs=args.epochs, max_steps=args.max_steps, accelerator=args.accelerator, devices=devices,
                        strategy=args.strategy, default_root_dir=args.out, log_every_n_steps=1,
                        enable_model_summary=False)
    trainer.fit(module, EventFramesDataModule(frames, val or None))
    args.out.mkdir(parents=True, exist_ok=True)
    trainer.save_checkpoint(args.out / "last.ckpt")  # every rank: it synchronises
    if trainer.is_global_zero:
        save_curve(module.latency_model, args.out / "curve.pt", world_size=trainer.world_size,
                   scenes=[str(args.data)] if args.data is not None else list(args.scenes), threshold=theta)
        print(f"world_size={trainer.world_size} coefficients={module.latency_model.coefficients.tolist()} "
              f"saved {args.out / 'curve.pt'}")


if __name__ == "__main__":
    main()
