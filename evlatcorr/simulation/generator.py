"""Event generation: per-pixel contrast thresholds and ESIM-style threshold crossings of the log intensity."""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.events import Events

__all__ = ["LOG_EPS", "EventGenerator", "log_intensity", "pixel_thresholds"]

LOG_EPS = 1e-3  # log(Y + eps): dark pixels do not fire on noise-level changes


def log_intensity(lum: Tensor) -> Tensor:
    """``log(Y + LOG_EPS)`` of a luminance (negative values, from interpolation, count as 0)."""
    return torch.log(lum.clamp_min(0) + LOG_EPS)


def pixel_thresholds(height: int, width: int, threshold: float, sigma: float, generator: torch.Generator,
                     device: torch.device) -> Tensor:
    """Contrast thresholds :math:`(H, W)`: ``threshold * (1 + sigma * N(0, 1))`` clipped at ``0.2 * threshold``.

    With ``sigma == 0`` nothing is drawn from ``generator`` (so the noise a seed gives does not move).
    """
    thresholds = torch.full((height, width), float(threshold), dtype=torch.float32)
    if sigma > 0:
        mismatch = 1 + float(sigma) * torch.randn(height, width, generator=generator)
        thresholds = (thresholds * mismatch).clamp_min(0.2 * float(threshold))
    return thresholds.to(device)


class EventGenerator:
    """ESIM-style threshold crossings of a log signal, per pixel, step by step.

    Args:
        log_start: the signal :math:`(H, W)` at the start; it is each pixel's first reference level.
        thresholds: contrast threshold per pixel :math:`(H, W)` (or broadcastable).

    Example:
        >>> gen = EventGenerator(torch.zeros(1, 2), torch.tensor(0.25))
        >>> gen.step(torch.zeros(1, 2), torch.tensor([[0.5, -0.1]]), 0.0, 100.0)  # 2 crossings, then none
        >>> ev = gen.events((1, 2), None)
        >>> ev.t.tolist(), ev.p.tolist()
        ([50.0, 100.0], [1, 1])
    """

    def __init__(self, log_start: Tensor, thresholds: Tensor) -> None:
        self.ref = log_start.clone()
        self.thr = torch.as_tensor(thresholds, dtype=log_start.dtype, device=log_start.device).expand_as(
            log_start).contiguous()
        self.chunks: list[tuple[Tensor, Tensor, Tensor]] = []  # (flat pixel, t, p)

    def step(self, log_prev: Tensor, log_cur: Tensor, t_prev: float, dt: float) -> None:
        """Emit the crossings of a signal going linearly from ``log_prev`` (at ``t_prev``) to ``log_cur`` (``+ dt``)."""
        diff = (log_cur - self.ref).flatten()
        thr = self.thr.flatten()
        count = torch.floor(diff.abs() / thr)
        fired = torch.nonzero(count > 0).flatten()
        if fired.numel() == 0:
            return
        n = count[fired].long()
        sign = torch.sign(diff[fired])
        pix = torch.repeat_interleave(fired, n)
        sgn = torch.repeat_interleave(sign, n)
        first = torch.cumsum(n, 0) - n
        k = torch.arange(pix.numel(), device=n.device) - torch.repeat_interleave(first, n) + 1
        ref = self.ref.view(-1)
        level = ref[pix] + sgn * k * thr[pix]
        lp, lc = log_prev.flatten()[pix], log_cur.flatten()[pix]
        step = lc - lp
        frac = ((level - lp) / step.where(step.abs() > 1e-12, torch.ones_like(step))).clamp(0, 1)
        self.chunks.append((pix, t_prev + frac.double() * dt, sgn.to(torch.int8)))
        ref[fired] += sign * n * thr[fired]

    def events(self, sensor_size: tuple[int, int], extra: tuple[Tensor, Tensor, Tensor] | None) -> Events:
        """All events so far (plus ``extra`` = (flat pixel, t, p) ones) as one time-sorted sample."""
        chunks = self.chunks + ([extra] if extra is not None else [])
        _, width = sensor_size
        device = self.ref.device
        if chunks:
            pix = torch.cat([c[0].to(device) for c in chunks])
            t = torch.cat([c[1].to(device) for c in chunks])
            p = torch.cat([c[2].to(device) for c in chunks])
        else:
            pix = torch.zeros(0, dtype=torch.long, device=device)
            t = torch.zeros(0, dtype=torch.float64, device=device)
            p = torch.zeros(0, dtype=torch.int8, device=device)
        order = torch.argsort(t, stable=True)
        pix, t, p = pix[order], t[order], p[order]
        return Events.from_canonical(pix % width, pix // width, t, p, torch.zeros_like(pix), sensor_size, 1)
