"""Every pixel's EDI ratio tabulated over evenly spaced latencies, read back differentiably in the latency.

The spatial test-time fit evaluates the EDI at a new per-pixel latency map at every optimiser step. A
pixel's ``log R`` depends on its own latency only, so it can be computed once for a set of latencies (the
exact continuous-time integral, :mod:`evlatcorr.continuous`) and read at any latency by linear
interpolation between the two nearest ones: two gathers per pixel per step instead of re-integrating the
events, with a gradient in the latency (the table's slope) as the linear integral of Eq. 16-18 gives.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.events import Events
from evlatcorr.integral import sample_grid

__all__ = ["LatencyTable"]


@dataclass
class LatencyTable:
    """``log R`` :math:`(B, K, H, W)` at latencies ``low + k · step`` (k = 0..K-1), latent at mid-exposure.

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([50.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> table = LatencyTable.build(ev, torch.tensor([0.0]), torch.tensor([100.0]), 0.2, 0.0, 100.0, 5)
        >>> table.log_ratio.shape
        torch.Size([1, 5, 1, 1])
        >>> latency = torch.tensor([[[[10.0]]]], requires_grad=True)
        >>> table.read(latency).requires_grad
        True
    """

    log_ratio: Tensor
    low: float
    step: float

    @classmethod
    def build(cls, events: Events, exposure_start: Tensor, exposure_end: Tensor, threshold: float | Tensor,
              low: float, high: float, num: int) -> LatencyTable:
        """Tabulate ``num >= 2`` latencies from ``low`` to ``high`` µs for each sample (one read of its events)."""
        if num < 2 or not high > low:
            raise ValueError(f"need num >= 2 latencies over high > low, got {num} over [{low}, {high}]")
        b = events.batch_size
        theta = torch.as_tensor(threshold, dtype=torch.float64).expand(b).cpu()
        latencies = torch.linspace(low, high, num, dtype=torch.float64)
        rows = []
        for i in range(b):
            integral = ContinuousIntegral(events.sample(i), float(theta[i]))
            rows.append(integral.log_ratio(float(exposure_start[i]), float(exposure_end[i]), latencies)[:, 0])
        return cls(torch.stack(rows).float(), float(low), (high - low) / (num - 1))

    def read(self, latency: Tensor) -> Tensor:
        """``log R`` at a latency map :math:`(B, 1, H, W)` µs (clamped to the table's span), differentiable."""
        position = (latency - self.low) / self.step
        return sample_grid(self.log_ratio.to(latency), position)
