"""Train and fine-tune the restoration networks (EFNet, GEM, REFID) with Lightning.

Official weights cannot be downloaded everywhere, so the networks are trained here on the
simulator's training photographs (disjoint from the benchmark's test photographs): random crops,
horizontal flips, L1 loss, PSNR/SSIM validation on held-out sequences of the training photographs.
The same command runs on one CPU or, with ``--devices N --strategy ddp``, on many GPUs (bf16 mixed
precision by default on CUDA); ``--resume last`` continues from the last checkpoint, and the
trained network is exported as fp16 safetensors shards that the adapters load by name.

Command line::

    python -m evlatcorr.train --model efnet --max-steps 2000 --out runs/efnet --export checkpoints
    python -m evlatcorr.train --model efnet --out runs/efnet --resume last     # continue
    python -m evlatcorr.train --model gem --accelerator gpu --devices 4 --strategy ddp
    python -m evlatcorr.train --model refid --refid-layout 4 1                 # REFID 4+1 frames
    python -m evlatcorr.train --model efnet --checkpoint default --finetune spatial   # corrector + EFNet

:class:`CorrectedRestorationModule` puts a latency corrector in front of an adapter and fine-tunes
both end to end on delayed events: the network by the supervised L1 loss when sharp frames exist,
the corrector's polynomial by the self-supervised ETF objective (Eq. 21), which needs no ground
truth (the networks' event representations bin events by hard time thresholds, so no useful
gradient reaches the latency through them).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = [
    "MODELS",
    "build_adapter",
    "checkpoint_name",
    "crop_frames",
    "collate_frames",
    "SimulatedRestorationData",
    "RestorationModule",
    "CorrectedRestorationModule",
    "write_checkpoint_readme",
    "main",
]

#: model name -> task solved ("deblur": one blurry frame; "interpolation": two blurry frames).
MODELS = {"efnet": "deblur", "gem": "deblur", "refid": "interpolation"}


def build_adapter(model: str, checkpoint: str | None = None, clamp: bool = False,
                  refid_layout: tuple[int, int] = (4, 1)) -> nn.Module:
    """The adapter of ``model`` (``"efnet"``, ``"gem"`` or ``"refid"``), unclamped for training by default.

    Example:
        >>> build_adapter("refid", refid_layout=(4, 1)).net.img_chn
        12
    """
    from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter

    if model == "efnet":
        return EFNetAdapter(checkpoint=checkpoint, clamp=clamp)
    if model == "gem":
        return GEMAdapter(checkpoint=checkpoint, clamp=clamp)
    if model == "refid":
        m, n = refid_layout
        return REFIDAdapter(checkpoint=checkpoint, m=m, n=n, clamp=clamp)
    raise ValueError(f"unknown model {model!r}; choose from {sorted(MODELS)}")


def checkpoint_name(model: str, refid_layout: tuple[int, int] = (4, 1)) -> str:
    """The name the adapters look for with ``checkpoint="default"`` (``refid-4-1`` for REFID 4+1)."""
    if model == "refid":
        m, n = refid_layout
        return "refid" if (m, n) == (11, 1) else f"refid-{m}-{n}"
    return model


# --------------------------------------------------------------------------------------------------
# samples
# --------------------------------------------------------------------------------------------------
def crop_frames(frames: EventFrames, top: int, left: int, height: int, width: int,
                hflip: bool = False) -> EventFrames:
    """A spatial crop (optionally mirrored left-right) of every image and of the events.

    Events outside the crop are dropped; the rest keep their times and polarities. Per-pixel fields
    (``latency`` and ``meta["true_latency"]``) are cropped too; other ``meta`` entries are kept.

    Example:
        >>> ev = Events(torch.tensor([1, 3]), torch.tensor([0, 2]), torch.tensor([1.0, 2.0]), torch.ones(2),
        ...             sensor_size=(4, 4))
        >>> fr = EventFrames(torch.rand(1, 1, 4, 4), ev, torch.tensor([0.0]), torch.tensor([5.0]))
        >>> out = crop_frames(fr, 1, 2, 3, 2, hflip=True)
        >>> out.sensor_size, out.events.x.tolist(), out.events.y.tolist()
        ((3, 2), [0], [1])
    """
    h, w = frames.sensor_size
    if not (0 <= top and 0 <= left and height >= 1 and width >= 1 and top + height <= h and left + width <= w):
        raise ValueError(f"crop ({top}, {left}, {height}, {width}) does not fit in (H, W)=({h}, {w})")

    def image(t: Tensor | None) -> Tensor | None:
        if t is None:
            return None
        t = t[..., top:top + height, left:left + width]
        return (t.flip(-1) if hflip else t).contiguous()

    def events(ev: Events | None) -> Events | None:
        if ev is None:
            return None
        keep = (ev.x >= left) & (ev.x < left + width) & (ev.y >= top) & (ev.y < top + height)
        x = ev.x[keep] - left
        x = (width - 1 - x) if hflip else x
        return Events._trusted(x, ev.y[keep] - top, ev.t[keep], ev.p[keep], ev.batch[keep], (height, width),
                               ev.batch_size)

    meta = dict(frames.meta)
    for key in ("true_latency", "true_latency_next"):
        if isinstance(meta.get(key), Tensor):
            meta[key] = image(meta[key])
    return frames.replace(blurry=image(frames.blurry), events=events(frames.events),
                          corrected=events(frames.corrected), latency=image(frames.latency),
                          latent=image(frames.latent), sharp=image(frames.sharp),
                          blurry_next=image(frames.blurry_next), target_frames=image(frames.target_frames),
                          output=image(frames.output), meta=meta)


def _cat(values: list[Any]) -> Any:
    if all(v is None for v in values):
        return None
    if any(v is None for v in values):
        raise ValueError("cannot batch samples where a field is set on some and missing on others")
    return torch.cat(values)


def collate_frames(items: Sequence[EventFrames]) -> EventFrames:
    """Batch ``EventFrames`` samples of one size (every image field, events, exposures, targets).

    ``meta`` entries that are tensors with a batch dimension are concatenated; others are dropped.
    """
    if not items:
        raise ValueError("cannot collate an empty list of EventFrames")
    sizes = {x.sensor_size for x in items}
    if len(sizes) != 1:
        raise ValueError(f"samples must share one (H, W) to be batched, got {sorted(sizes)}; crop them first")
    fields = ("blurry", "exposure_start", "exposure_end", "latency", "latent", "sharp", "blurry_next",
              "exposure_start_next", "exposure_end_next", "target_times", "target_frames")
    kwargs = {f: _cat([getattr(x, f) for x in items]) for f in fields}
    corrected = None if items[0].corrected is None else Events.cat([x.corrected for x in items])
    meta = {}
    for key in ("true_latency", "true_latency_next"):
        if all(isinstance(x.meta.get(key), Tensor) for x in items):
            meta[key] = torch.cat([x.meta[key] for x in items])
    return EventFrames(events=Events.cat([x.events for x in items]), corrected=corrected, meta=meta, **kwargs)


class _Samples(Dataset):
    """Pairs (ideal, delayed) of one-sample batches, served as random crops or whole."""

    def __init__(self, samples: list[tuple[EventFrames, EventFrames]], events: str, crop: tuple[int, int] | None,
                 length: int | None = None) -> None:
        self.samples, self.events, self.crop = samples, events, crop
        self.length = length or len(samples)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> EventFrames:
        ideal, delayed = self.samples[index % len(self.samples)]
        if self.events == "mixed":
            frames = ideal if bool(torch.randint(2, ()).item()) else delayed
        else:
            frames = ideal if self.events == "ideal" else delayed
        if self.crop is None:
            return frames
        h, w = frames.sensor_size
        ch, cw = self.crop
        top = int(torch.randint(h - ch + 1, ()).item())
        left = int(torch.randint(w - cw + 1, ()).item())
        return crop_frames(frames, top, left, ch, cw, hflip=bool(torch.randint(2, ()).item()))


class SimulatedRestorationData(L.LightningDataModule):
    """Training and validation samples simulated from the training photographs.

    Each photograph is simulated ``sequences`` times (different seeds, so different motions, thresholds
    and latencies) with ideal and delayed events; validation uses other seeds of the same photographs,
    so no test photograph (:data:`~evlatcorr.simulate.PHOTOGRAPHS_TEST`) is ever seen. Simulation is
    deterministic by ``seed`` (every DDP rank builds the same samples) and takes seconds.

    Args:
        task: ``"deblur"`` (one sample per frame, target the mid-exposure sharp frame) or
            ``"interpolation"`` (one sample per frame pair, targets at ``target_times``).
        photographs: photograph names to simulate.
        size: simulated (H, W).
        crop: training crop (H, W); validation uses whole frames.
        sequences: sequences per photograph for training.
        val_sequences: sequences per photograph for validation.
        num_frames: frames per sequence.
        exposure_us, interval_us: exposure time and frame interval, µs.
        latency_us: range of the constant latency drawn for each sequence's delayed events, µs.
        events: which events the samples carry: ``"ideal"`` (exact timestamps, as the networks were
            originally trained), ``"delayed"`` or ``"mixed"``.
        target_times: for interpolation, a function ``EventFrames -> (B, T)`` µs of the frames to
            supervise (e.g. REFID's output times); default the gap midpoint.
        batch_size, num_workers: data loading.
        steps_per_epoch: training batches per epoch (samples are drawn with random crops).
        seed: base seed.
    """

    def __init__(self, task: str = "deblur", photographs: Sequence[str] | None = None,
                 size: tuple[int, int] = (128, 160), crop: tuple[int, int] = (64, 64), sequences: int = 2,
                 val_sequences: int = 1, num_frames: int = 3, exposure_us: float = 20000.0,
                 interval_us: float = 25000.0, latency_us: tuple[float, float] = (1000.0, 8000.0),
                 events: str = "ideal", target_times: Any = None, batch_size: int = 4, num_workers: int = 0,
                 steps_per_epoch: int = 200, seed: int = 0) -> None:
        super().__init__()
        from evlatcorr.simulate import PHOTOGRAPHS_TRAIN

        if task not in ("deblur", "interpolation"):
            raise ValueError(f"task must be 'deblur' or 'interpolation', got {task!r}")
        if events not in ("ideal", "delayed", "mixed"):
            raise ValueError(f"events must be 'ideal', 'delayed' or 'mixed', got {events!r}")
        if crop[0] > size[0] or crop[1] > size[1]:
            raise ValueError(f"crop {tuple(crop)} is larger than the simulated size {tuple(size)}")
        if task == "interpolation" and num_frames < 2:
            raise ValueError("interpolation needs num_frames >= 2")
        self.task, self.photographs = task, list(photographs or PHOTOGRAPHS_TRAIN)
        self.size, self.crop = (int(size[0]), int(size[1])), (int(crop[0]), int(crop[1]))
        self.sequences, self.val_sequences, self.num_frames = sequences, val_sequences, num_frames
        self.exposure_us, self.interval_us, self.latency_us = exposure_us, interval_us, latency_us
        self.events, self.target_times = events, target_times
        self.batch_size, self.num_workers, self.steps_per_epoch, self.seed = (
            batch_size, num_workers, steps_per_epoch, seed)
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None

    def simulate(self, seeds: Sequence[int]) -> list[tuple[EventFrames, EventFrames]]:
        """(ideal, delayed) one-sample batches for every photograph and seed."""
        from evlatcorr.simulate import simulate

        samples = []
        for name_index, name in enumerate(self.photographs):
            for seed in seeds:
                g = torch.Generator().manual_seed(10_000 * seed + name_index)
                lo, hi = self.latency_us
                latency = lo + (hi - lo) * float(torch.rand((), generator=g))
                seq = simulate(name, num_frames=self.num_frames, height=self.size[0], width=self.size[1],
                               exposure_us=self.exposure_us, frame_interval_us=self.interval_us,
                               latency="constant", latency_us=latency, seed=10_000 * seed + name_index)
                if self.task == "deblur":
                    both = seq.frames("ideal"), seq.frames("delayed")
                else:
                    both = seq.pairs("ideal"), seq.pairs("delayed")
                    if self.target_times is not None:
                        times = self.target_times(both[0]).to(torch.float64)
                        frames = seq.render(times.flatten()).view(*times.shape, *seq.blurry.shape[1:])
                        both = tuple(b.replace(target_times=times, target_frames=frames) for b in both)
                for i in range(both[0].batch_size):
                    samples.append(tuple(_one(b, i) for b in both))
        return samples

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            base = 1000 * self.seed
            train = self.simulate([base + k for k in range(self.sequences)])
            val = self.simulate([base + 500 + k for k in range(self.val_sequences)])
            self.train_set = _Samples(train, self.events, self.crop, self.steps_per_epoch * self.batch_size)
            self.val_set = _Samples(val, self.events, None)

    def train_dataloader(self) -> DataLoader:
        assert self.train_set is not None, "call setup() first"
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, num_workers=self.num_workers,
                          collate_fn=collate_frames, persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        assert self.val_set is not None, "call setup() first"
        return DataLoader(self.val_set, batch_size=1, shuffle=False, num_workers=self.num_workers,
                          collate_fn=collate_frames)


def _one(frames: EventFrames, i: int) -> EventFrames:
    """Sample ``i`` of a batch as a one-sample batch."""
    def pick(t: Tensor | None) -> Tensor | None:
        return None if t is None else t[i:i + 1].clone()

    meta = {k: pick(v) for k, v in frames.meta.items() if k in ("true_latency", "true_latency_next")}
    return EventFrames(pick(frames.blurry), frames.events.sample(i), pick(frames.exposure_start),
                       pick(frames.exposure_end), sharp=pick(frames.sharp), blurry_next=pick(frames.blurry_next),
                       exposure_start_next=pick(frames.exposure_start_next),
                       exposure_end_next=pick(frames.exposure_end_next), target_times=pick(frames.target_times),
                       target_frames=pick(frames.target_frames), meta=meta)


# --------------------------------------------------------------------------------------------------
# modules
# --------------------------------------------------------------------------------------------------
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


class _RestorationBase(L.LightningModule):
    """Shared optimisation and validation of the restoration modules."""

    def __init__(self, task: str, lr: float, weight_decay: float, warmup_steps: int, max_steps: int) -> None:
        super().__init__()
        if task not in ("deblur", "interpolation"):
            raise ValueError(f"task must be 'deblur' or 'interpolation', got {task!r}")
        if lr <= 0 or warmup_steps < 0 or max_steps < 1:
            raise ValueError("lr must be > 0, warmup_steps >= 0 and max_steps >= 1")
        self.task = task
        self.val_psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.val_ssim = StructuralSimilarityIndexMeasure(data_range=1.0)
        self.val_input_psnr = PeakSignalNoiseRatio(data_range=1.0)

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        return batch.to(device) if isinstance(batch, EventFrames) else super().transfer_batch_to_device(
            batch, device, dataloader_idx)

    def _validate(self, batch: EventFrames, output: EventFrames) -> None:
        pair = restoration_pair(output, self.task)
        if pair is None:
            return
        pred, target = pair
        pred, target = pred.float().clamp(0, 1).flatten(0, -4), target.float().flatten(0, -4)
        self.val_psnr.update(pred, target)
        self.val_ssim.update(pred, target)
        # the blurry frame itself (the left one for interpolation) as a baseline
        blurry = batch.blurry.float()
        if target.shape[0] != blurry.shape[0]:
            blurry = blurry.repeat_interleave(target.shape[0] // blurry.shape[0], 0)
        self.val_input_psnr.update(blurry, target)
        kw = dict(batch_size=batch.batch_size, on_epoch=True, sync_dist=True)
        self.log("val/psnr", self.val_psnr, prog_bar=True, **kw)
        self.log("val/ssim", self.val_ssim, **kw)
        self.log("val/blurry_psnr", self.val_input_psnr, **kw)

    def configure_optimizers(self):
        hp = self.hparams
        optimiser = torch.optim.AdamW(self.param_groups(), lr=hp.lr, weight_decay=hp.weight_decay, betas=(0.9, 0.99))

        def factor(step: int) -> float:  # linear warm-up, then cosine decay to 1 % at max_steps
            if step < hp.warmup_steps:
                return (step + 1) / hp.warmup_steps
            progress = min(1.0, (step - hp.warmup_steps) / max(1, hp.max_steps - hp.warmup_steps))
            return 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * progress))

        scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, factor)
        return {"optimizer": optimiser, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def param_groups(self) -> list[dict[str, Any]]:
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]


class RestorationModule(_RestorationBase):
    """An adapter's network trained with L1 loss on simulated frames.

    Args:
        model: ``"efnet"``, ``"gem"`` or ``"refid"`` (see :data:`MODELS`).
        checkpoint: initial weights (``None``: random; ``"default"``; a path), see the adapters.
        lr: AdamW learning rate (peak, after ``warmup_steps``; cosine decay to 1 % at ``max_steps``).
        weight_decay: AdamW weight decay.
        warmup_steps, max_steps: learning-rate schedule, in optimiser steps.
        refid_layout: REFID's ``(m, n)``: ``m`` sharp frames per exposure, ``n`` in the gap.

    Example:
        >>> module = RestorationModule("efnet")
        >>> module.task, type(module.adapter).__name__
        ('deblur', 'EFNetAdapter')
    """

    def __init__(self, model: str = "efnet", checkpoint: str | None = None, lr: float = 2e-4,
                 weight_decay: float = 1e-4, warmup_steps: int = 100, max_steps: int = 2000,
                 refid_layout: tuple[int, int] = (4, 1)) -> None:
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r}; choose from {sorted(MODELS)}")
        super().__init__(MODELS[model], lr, weight_decay, warmup_steps, max_steps)
        self.save_hyperparameters()
        self.adapter = build_adapter(model, checkpoint, clamp=False, refid_layout=tuple(refid_layout))

    def forward(self, frames: EventFrames) -> EventFrames:
        return self.adapter(frames)

    def training_step(self, batch: EventFrames, batch_idx: int) -> Tensor:
        pair = restoration_pair(self(batch), self.task)
        if pair is None:
            raise ValueError("training batches need ground truth (sharp or target_frames)")
        loss = F.l1_loss(pair[0].float(), pair[1].float())
        self.log("train/l1", loss, prog_bar=True, batch_size=batch.batch_size)
        return loss

    def validation_step(self, batch: EventFrames, batch_idx: int) -> None:
        self._validate(batch, self(batch))


class CorrectedRestorationModule(_RestorationBase):
    """A latency corrector in front of an adapter, fine-tuned end to end on delayed events.

    The corrector is a :class:`~evlatcorr.spatial.PolynomialLatency` of the blurry frame's intensity
    (``"spatial"``, trainable) or the one-pass constant search (``"constant"``, no parameters). Each
    step corrects the batch's events with the current latency map and runs the adapter on them.

    - Supervised (the batch has ``sharp`` or ``target_frames``): the network is trained by L1 loss on
      its output from the corrected events.
    - The polynomial is trained by the self-supervised objective of Eq. (21) (ETF of the
      latency-differentiable EDI, bound, MSE to ``l_const`` and deviation terms), which needs no
      ground truth: on batches without sharp frames this is the only loss ("ETF-only").

    Args:
        adapter: any adapter (``nn.Module`` taking and returning ``EventFrames``).
        task: ``"deblur"`` or ``"interpolation"`` (what the adapter does).
        corrector: ``"spatial"`` or ``"constant"``.
        curve: initial polynomial (path of a saved curve or Lightning checkpoint), spatial only.
        train_corrector: optimise the polynomial.
        train_network: optimise the adapter's parameters.
        corrector_weight: weight of the corrector's objective in the total loss.
        lr, corrector_lr: learning rates of the network and of the polynomial.
        threshold, num_bins: contrast threshold and EDI sub-intervals of the correction.

    Example:
        >>> from evlatcorr.adapters import EFNetAdapter
        >>> module = CorrectedRestorationModule(EFNetAdapter(), "deblur", train_network=False)
        >>> sum(p.requires_grad for p in module.parameters())
        1
    """

    def __init__(self, adapter: nn.Module, task: str, corrector: str = "spatial", curve: str | Path | None = None,
                 train_corrector: bool = True, train_network: bool = True, corrector_weight: float = 1.0,
                 lr: float = 5e-5, corrector_lr: float = 0.02, weight_decay: float = 0.0, warmup_steps: int = 0,
                 max_steps: int = 1000, threshold: float = 0.2, num_bins: int = 100) -> None:
        super().__init__(task, lr, weight_decay, warmup_steps, max_steps)
        from evlatcorr.spatial import LossWeights, PolynomialLatency, load_curve

        if corrector not in ("spatial", "constant"):
            raise ValueError(f"corrector must be 'spatial' or 'constant', got {corrector!r}")
        if corrector == "constant" and train_corrector:
            train_corrector = False  # nothing to train: the constant is searched per frame
        if not (train_corrector or train_network):
            raise ValueError("nothing to train: set train_corrector and/or train_network")
        self.save_hyperparameters(ignore=["adapter"])
        self.adapter = adapter
        self.latency_model = load_curve(curve) if curve is not None else PolynomialLatency()
        self.weights = LossWeights()
        self.adapter.requires_grad_(train_network)
        self.latency_model.requires_grad_(train_corrector)

    def correct(self, frames: EventFrames) -> tuple[EventFrames, Tensor | None]:
        """``frames`` with ``corrected`` events and ``latency``, and the corrector's loss (or None)."""
        from evlatcorr.benchmark import pair_with_latency
        from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
        from evlatcorr.search import search_constant_latency
        from evlatcorr.spatial import constant_reference, spatial_objective

        hp = self.hparams
        first = EventFrames(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end)
        loss = None
        if hp.corrector == "constant":
            latency = search_constant_latency(first.blurry, first.events, first.exposure_start, first.exposure_end,
                                              hp.threshold, hp.num_bins).latency
            latency = latency.to(frames.blurry).view(-1, 1, 1, 1).expand(-1, 1, *frames.sensor_size).contiguous()
            latency_next = latency
        else:
            high = frames.exposure_time.to(frames.blurry).view(-1, 1, 1, 1)
            if hp.train_corrector:
                with torch.enable_grad():
                    l_const, etf_const = constant_reference(first, hp.threshold, hp.num_bins, None, 100,
                                                            DEFAULT_EPSILON, DEFAULT_WINDOW, DEFAULT_SIGMA_US)
                    terms = spatial_objective(self.latency_model, first, l_const, first.exposure_time, etf_const,
                                              hp.threshold, hp.num_bins, self.weights)
                loss = terms["total"]
            latency = torch.minimum(self.latency_model(frames.blurry).clamp_min(0.0), high).detach()
            latency_next = latency if frames.blurry_next is None else torch.minimum(
                self.latency_model(frames.blurry_next).clamp_min(0.0), high).detach()
        if self.task == "interpolation":
            corrected = pair_with_latency(frames, latency.double(), latency_next.double())
            return corrected.replace(latency=latency), loss
        return frames.replace(corrected=frames.events.shift(latency.double()), latency=latency), loss

    def forward(self, frames: EventFrames) -> EventFrames:
        corrected, _ = self.correct(frames)
        return self.adapter(corrected)

    def training_step(self, batch: EventFrames, batch_idx: int) -> Tensor:
        corrected, corrector_loss = self.correct(batch)
        total = torch.zeros((), device=batch.device)
        if self.hparams.train_network:
            pair = restoration_pair(self.adapter(corrected), self.task)
            if pair is not None:
                l1 = F.l1_loss(pair[0].float(), pair[1].float())
                self.log("train/l1", l1, prog_bar=True, batch_size=batch.batch_size)
                total = total + l1
        if corrector_loss is not None:
            self.log("train/corrector", corrector_loss, batch_size=batch.batch_size)
            total = total + self.hparams.corrector_weight * corrector_loss
        if not total.requires_grad:  # e.g. network-only training on a batch without ground truth
            total = sum(p.sum() * 0.0 for p in self.parameters() if p.requires_grad)
        return total

    def validation_step(self, batch: EventFrames, batch_idx: int) -> None:
        corrected, _ = self.correct(batch)
        self._validate(batch, self.adapter(corrected))

    def param_groups(self) -> list[dict[str, Any]]:
        # the polynomial's 6 coefficients (ms) take a much larger step than the network's weights
        network = [p for p in self.adapter.parameters() if p.requires_grad]
        poly = [p for p in self.latency_model.parameters() if p.requires_grad]
        groups = [{"params": network}] if network else []
        if poly:
            groups.append({"params": poly, "lr": self.hparams.corrector_lr, "weight_decay": 0.0})
        return groups


# --------------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------------
def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m evlatcorr.train", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", choices=sorted(MODELS), required=True)
    p.add_argument("--checkpoint", help="initial weights: 'default' (shipped) or a path; default random")
    p.add_argument("--finetune", choices=("none", "constant", "spatial"), default="none",
                   help="put a corrector in front and fine-tune on delayed events (CorrectedRestorationModule)")
    p.add_argument("--freeze-network", action="store_true", help="with --finetune spatial: train the polynomial only")
    p.add_argument("--events", choices=("ideal", "delayed", "mixed"), default=None,
                   help="events of the training samples (default: ideal; delayed with --finetune)")
    p.add_argument("--max-steps", type=int, default=2000)
    p.add_argument("--max-time", default=None, help="stop after this wall time, DD:HH:MM:SS")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--crop", type=int, nargs=2, default=(64, 64), metavar=("H", "W"))
    p.add_argument("--size", type=int, nargs=2, default=(128, 160), metavar=("H", "W"), help="simulated size")
    p.add_argument("--photographs", nargs="+", default=None, help="training photographs (default: the training "
                   "split, disjoint from the benchmark's test photographs)")
    p.add_argument("--allow-test-photographs", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--sequences", type=int, default=2, help="training sequences per photograph")
    p.add_argument("--num-frames", type=int, default=3, help="frames per simulated sequence")
    p.add_argument("--lr", type=float, default=None, help="default 2e-4 (5e-5 when fine-tuning)")
    p.add_argument("--warmup-steps", type=int, default=100)
    p.add_argument("--gradient-clip", type=float, default=None, help="clip the gradient norm (REFID: 0.5)")
    p.add_argument("--refid-layout", type=int, nargs=2, default=(4, 1), metavar=("M", "N"),
                   help="REFID sharp frames per exposure and in the gap (4 1 fits 20 ms exposures 25 ms apart)")
    p.add_argument("--val-every", type=int, default=200, help="validate every N training steps")
    p.add_argument("--accelerator", default="auto")
    p.add_argument("--devices", default="1")
    p.add_argument("--strategy", default="auto")
    p.add_argument("--precision", default=None, help="default bf16-mixed on GPU, 32-true on CPU")
    p.add_argument("--num-workers", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/train"))
    p.add_argument("--resume", default=None, help="'last' or a .ckpt path")
    p.add_argument("--export", type=Path, default=None, help="folder for the fp16 safetensors of the network")
    p.add_argument("--data", type=Path, default=None,
                   help="fine-tune on this recording (any format evlatcorr.io reads) instead of simulated data: "
                        "without sharp frames the network stays frozen and the latency polynomial trains by the "
                        "self-supervised objective (Eq. 21), see evlatcorr.training")
    args = p.parse_args(argv)
    if args.max_steps < 1 or args.batch_size < 1:
        p.error("--max-steps and --batch-size must be >= 1")
    from evlatcorr.simulate import PHOTOGRAPHS_TEST

    leaked = sorted(set(args.photographs or ()) & set(PHOTOGRAPHS_TEST))
    if leaked and not args.allow_test_photographs:
        p.error(f"{leaked} belong to the benchmark's test split; training on them would inflate its scores")
    if args.freeze_network and args.finetune != "spatial":
        p.error("--freeze-network needs --finetune spatial (otherwise nothing is trained)")
    return args


def write_checkpoint_readme(folder: str | Path) -> Path:
    """Render the JSON cards of a checkpoint folder (written by ``--export``) as its ``README.md``."""
    folder = Path(folder)
    cards = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json")) if not p.name.endswith(".index.json")]
    lines = [
        "# Shipped weights",
        "",
        "Trained here by `python -m evlatcorr.train` on the simulator's training photographs "
        "(`evlatcorr.simulate.PHOTOGRAPHS_TRAIN`, disjoint from the benchmark's test photographs), ideal events, "
        "L1 loss; validated on other simulated sequences of the same training photographs. fp16 safetensors, "
        "sharded at 15 MB; the adapters load them with `checkpoint=\"default\"` "
        "(REFID: `REFIDAdapter(checkpoint=\"default\", m=4, n=1)`). Each `<name>.json` holds every detail.",
        "",
        "Each card lists the SHA-256 of its weight files under `sha256`; every load checks them (a corrupt or "
        "modified file raises a ValueError naming it). `pip install .` installs this folder as "
        "`evlatcorr/checkpoints/`, where `checkpoint=\"default\"` finds it.",
        "",
        "| name | model | steps | train time | device | val PSNR (blurry input) | val SSIM | files |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in cards:
        lines.append(f"| {c['name']} | {c['model']} | {c['steps']} | {c['train_seconds'] / 60:.0f} min | "
                     f"{c['device']} | {c['val_psnr']:.2f} dB ({c['val_blurry_psnr']:.2f} dB) | {c['val_ssim']:.3f} | "
                     f"{len(c.get('files', []))} |")
    # Data settings shared by every card once, then what differs per checkpoint.
    shared = {k: v for k, v in cards[0]["data"].items() if all(c["data"].get(k) == v for c in cards)} if cards else {}
    lines += ["", "Data: " + ", ".join(f"{k}={v}" for k, v in shared.items()), ""]
    for c in cards:
        own = {k: v for k, v in c["data"].items() if k not in shared}
        if own:
            lines.append(f"- {c['name']}: " + ", ".join(f"{k}={v}" for k, v in own.items()))
        if c.get("note"):
            lines.append(f"- {c['name']}: {c['note']}")
    lines += ["", "Commands, in order (run from the repository root):", ""]
    for c in cards:
        for command in c.get("commands", [c["command"]]):
            lines.append(f"    {command}")
    path = folder / "README.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _precision(args: argparse.Namespace) -> str:
    if args.precision is not None:
        return args.precision
    gpu = args.accelerator in ("gpu", "cuda") or (args.accelerator == "auto" and torch.cuda.is_available())
    return "bf16-mixed" if gpu else "32-true"


def _finetune_on_recording(args: argparse.Namespace) -> dict[str, Any]:
    """``--data``: a recording without ground truth trains the latency polynomial, the network frozen."""
    from evlatcorr.io import open_recording
    from evlatcorr.training import main as train_curve

    try:
        rec = open_recording(args.data)
        has_sharp = any(info.sharp is not None for info in itertools.islice(rec.frames(), 3))
    except (ValueError, OSError) as exc:
        print(f"evlatcorr.train: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if has_sharp:
        print(f"evlatcorr.train: error: {args.data} has sharp frames; fine-tuning {args.model} on recorded ground "
              "truth is not supported yet (--data trains the latency polynomial on recordings without it)",
              file=sys.stderr)
        raise SystemExit(2)
    print(f"{args.data}: no sharp frames, so {args.model} stays frozen (its weights are not changed) and the latency "
          "polynomial trains by the self-supervised objective (Eq. 21)")
    crop = [str(v) for v in args.crop]
    curve_args = ["--data", str(args.data), "--crop", *crop, "--out", str(args.out), "--seed", str(args.seed),
                  "--accelerator", args.accelerator, "--devices", str(args.devices), "--strategy", args.strategy,
                  "--max-steps", str(args.max_steps), "--epochs", "1000"]
    train_curve(curve_args)
    return {"model": args.model, "data": str(args.data), "network": "frozen", "curve": str(args.out / "curve.pt")}


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the command line; returns the exported card (validation metrics, steps, configuration)."""
    from lightning.pytorch.callbacks import ModelCheckpoint

    args = parse_args(argv)
    if args.data is not None:
        return _finetune_on_recording(args)
    L.seed_everything(args.seed, workers=True)
    task = MODELS[args.model]
    layout = tuple(args.refid_layout)
    target_times = None
    if args.model == "refid":
        from evlatcorr.adapters.refid import refid_output_times

        def target_times(frames: EventFrames) -> Tensor:  # supervise every REFID output frame
            return refid_output_times(frames, layout[0], layout[1])
    finetune = args.finetune != "none"
    events = args.events or ("delayed" if finetune else "ideal")
    data = SimulatedRestorationData(task, photographs=args.photographs, size=tuple(args.size), crop=tuple(args.crop),
                                    sequences=args.sequences,
                                    num_frames=args.num_frames, events=events, target_times=target_times,
                                    batch_size=args.batch_size, num_workers=args.num_workers,
                                    steps_per_epoch=args.val_every, seed=args.seed)
    if finetune:
        adapter = build_adapter(args.model, args.checkpoint, clamp=False, refid_layout=layout)
        module: L.LightningModule = CorrectedRestorationModule(
            adapter, task, corrector=args.finetune, train_network=not args.freeze_network,
            lr=args.lr or 5e-5, warmup_steps=min(args.warmup_steps, args.max_steps - 1), max_steps=args.max_steps)
    else:
        module = RestorationModule(args.model, args.checkpoint, lr=args.lr or 2e-4,
                                   warmup_steps=min(args.warmup_steps, args.max_steps - 1),
                                   max_steps=args.max_steps, refid_layout=layout)
    devices: int | str = int(args.devices) if str(args.devices).isdigit() else args.devices
    checkpointing = ModelCheckpoint(dirpath=args.out / "checkpoints", save_last=True, monitor="val/psnr",
                                    mode="max", save_top_k=1, filename="best-{step}")
    trainer = L.Trainer(max_steps=args.max_steps, max_time=args.max_time, max_epochs=-1,
                        accelerator=args.accelerator, devices=devices, strategy=args.strategy,
                        precision=_precision(args), default_root_dir=args.out, callbacks=[checkpointing],
                        gradient_clip_val=args.gradient_clip,
                        log_every_n_steps=10, enable_model_summary=False, num_sanity_val_steps=0)
    resume = None
    if args.resume == "last":
        resume = args.out / "checkpoints" / "last.ckpt"
        if not resume.is_file():
            raise SystemExit(f"evlatcorr.train: error: --resume last, but {resume} does not exist")
    elif args.resume:
        resume = Path(args.resume)
        if not resume.is_file():
            raise SystemExit(f"evlatcorr.train: error: checkpoint {resume} not found")
    start = time.perf_counter()
    trainer.fit(module, data, ckpt_path=resume)
    seconds = time.perf_counter() - start
    final = trainer.validate(module, data, verbose=False)[0]
    card = {
        "model": args.model, "name": checkpoint_name(args.model, layout), "task": task,
        "command": "python -m evlatcorr.train " + " ".join(sys.argv[1:] if argv is None else argv),
        "steps": int(trainer.global_step), "train_seconds": round(seconds, 1),
        "val_psnr": round(float(final["val/psnr"]), 3), "val_ssim": round(float(final["val/ssim"]), 4),
        "val_blurry_psnr": round(float(final["val/blurry_psnr"]), 3), "events": events,
        "data": {"photographs": data.photographs, "size": list(data.size), "crop": list(data.crop),
                 "sequences": data.sequences, "num_frames": data.num_frames, "exposure_us": data.exposure_us,
                 "interval_us": data.interval_us, "latency_us": list(data.latency_us), "seed": args.seed},
        "world_size": trainer.world_size, "precision": str(trainer.precision),
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() and trainer.on_gpu else
        f"CPU, {torch.get_num_threads()} threads", "torch": torch.__version__,
    }
    if args.model == "refid":
        card["refid_layout"] = list(layout)
    if trainer.is_global_zero:
        if args.export is not None:
            from evlatcorr.adapters.checkpoint import card_sha256, save_weights

            previous = args.export / f"{card['name']}.json"
            # a resumed run, or one continuing the shipped weights of this name, extends their history
            continued = resume is not None or args.checkpoint == "default"
            if continued and previous.is_file():
                old = json.loads(previous.read_text())
                card["commands"] = old.get("commands", [old["command"]]) + [card["command"]]
                card["train_seconds"] = round(card["train_seconds"] + old["train_seconds"], 1)
                if "note" in old:
                    card["note"] = old["note"]
                if resume is None:  # the step count restarted on top of the shipped weights
                    card["steps"] += int(old["steps"])

            adapter = module.adapter
            files = save_weights(adapter.net, args.export / f"{card['name']}.safetensors")
            card["files"] = [f.name for f in files]
            card["sha256"] = card_sha256(files)  # checked at every load
            (args.export / f"{card['name']}.json").write_text(json.dumps(card, indent=2) + "\n")
            write_checkpoint_readme(args.export)
        print(json.dumps(card, indent=2))
    return card


if __name__ == "__main__":
    main()
