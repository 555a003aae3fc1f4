"""The restoration Lightning modules: an adapter's network by L1, or a latency corrector and the network end to end.

:class:`CorrectedRestorationModule` puts a latency corrector in front of an adapter and fine-tunes
both on delayed events: the network by the supervised L1 loss when sharp frames exist, the
corrector's polynomial by the self-supervised ETF objective (Eq. 21), which needs no ground truth
(the networks' event representations bin events by hard time thresholds, so no useful gradient
reaches the latency through them).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from evlatcorr.frames import EventFrames
from evlatcorr.lightning.base import EventFramesModule
from evlatcorr.lightning.networks import MODELS, build_adapter
from evlatcorr.lightning.targets import has_truth, restoration_pair

__all__ = ["RestorationModule", "CorrectedRestorationModule"]


class _RestorationBase(EventFramesModule):
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

    def _validate(self, batch: EventFrames, output: EventFrames) -> None:
        pair = restoration_pair(output, self.task)
        if pair is None:
            return
        pred, target = pair
        pred, target = pred.float().clamp(0, 1).flatten(0, -4), target.float().flatten(0, -4)
        # in float32 also under bf16 mixed precision, whose autocast would run SSIM's convolutions in bf16
        with torch.autocast(self.device.type, enabled=False):
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
        frame_gamma: the batches' frames are encoded as ``linear ** (1 / frame_gamma)`` (2.2: encoded for display);
            the corrector reads them made linear, as EDI needs them, and the network as they are (default 1).

    Example:
        >>> from evlatcorr.adapters import EFNetAdapter
        >>> module = CorrectedRestorationModule(EFNetAdapter(), "deblur", train_network=False)
        >>> sum(p.requires_grad for p in module.parameters())
        1
    """

    def __init__(self, adapter: nn.Module, task: str, corrector: str = "spatial", curve: str | Path | None = None,
                 train_corrector: bool = True, train_network: bool = True, corrector_weight: float = 1.0,
                 lr: float = 5e-5, corrector_lr: float = 0.02, weight_decay: float = 0.0, warmup_steps: int = 0,
                 max_steps: int = 1000, threshold: float = 0.2, num_bins: int = 100, frame_gamma: float = 1.0) -> None:
        super().__init__(task, lr, weight_decay, warmup_steps, max_steps)
        from evlatcorr.gamma import check_frame_gamma
        from evlatcorr.spatial import LossWeights, PolynomialLatency, load_curve

        check_frame_gamma(frame_gamma)

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
        from evlatcorr.gamma import linear_frames
        from evlatcorr.search import search_constant_latency
        from evlatcorr.spatial import constant_reference, spatial_objective

        hp = self.hparams
        linear = linear_frames(frames, hp.frame_gamma)  # what EDI and the polynomial read
        first = EventFrames(linear.blurry, frames.events, frames.exposure_start, frames.exposure_end)
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
            latency = torch.minimum(self.latency_model(linear.blurry).clamp_min(0.0), high).detach()
            latency_next = latency if frames.blurry_next is None else torch.minimum(
                self.latency_model(linear.blurry_next).clamp_min(0.0), high).detach()
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
        corrected, corrector_loss = self.correct(batch)
        if corrector_loss is not None:  # the self-supervised objective (Eq. 21) on held-out frames
            self.log("val/corrector", corrector_loss, batch_size=batch.batch_size, on_epoch=True, sync_dist=True,
                     prog_bar=True)
        if has_truth(batch, self.task):  # without ground truth the network's output has nothing to be scored on
            self._validate(batch, self.adapter(corrected))

    def param_groups(self) -> list[dict[str, Any]]:
        # the polynomial's 6 coefficients (ms) take a much larger step than the network's weights
        network = [p for p in self.adapter.parameters() if p.requires_grad]
        poly = [p for p in self.latency_model.parameters() if p.requires_grad]
        groups = [{"params": network}] if network else []
        if poly:
            groups.append({"params": poly, "lr": self.hparams.corrector_lr, "weight_decay": 0.0})
        return groups
