"""The self-supervised Lightning module of the latency polynomial (paper Sec. 3.4, Eq. 19-21).

No ground truth is used: each step finds the frame's constant latency ``l_const`` by the one-pass
search and minimises Eq. (21) through the latency-differentiable EDI. The same module runs on one
CPU or on many GPUs with ``Trainer(accelerator="auto", devices=N, strategy="ddp")``.
"""

from __future__ import annotations

import torch

from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
from evlatcorr.frames import EventFrames
from evlatcorr.lightning.base import EventFramesModule
from evlatcorr.spatial import LossWeights, PolynomialLatency, constant_reference, spatial_objective

__all__ = ["LatencyCorrectionModule"]


class LatencyCorrectionModule(EventFramesModule):
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
