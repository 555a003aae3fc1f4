"""The step EDI's double integral in continuous time, exact, for any set of windows (no temporal bins).

At a pixel the stamped events make ``θC(t)`` a step function, so ``exp(θC(t))`` is piecewise constant and
its integral ``S(t) = ∫ exp(θC)`` is piecewise linear with a kink at each event. The EDI ratio of a
window ``[a, b]`` read at ``r`` (Eq. 7) is then exact:

    R = (S(b) − S(a)) / (b − a) / exp(θC(r))

which is what the binned EDI tends to as its number of bins grows. :class:`ContinuousIntegral` prepares
the events once (each event's level before and after it at its pixel), then evaluates ``S`` and ``θC`` at
any sorted set of times with one scatter of the events: an event in ``[g_{j−1}, g_j)`` that raises the level
from ``e⁻`` to ``e⁺`` adds ``(e⁺ − e⁻)(g_j − t)`` to the integral over that interval, on top of the level at
``g_{j−1}`` held for the whole interval. The cost is one pass over the events plus a few operations per
time and pixel; the constant-latency search reads all its candidates' windows this way
(:func:`evlatcorr.search.search_constant_latency`).
"""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.events import Events

__all__ = ["ContinuousIntegral"]

# Peak bytes per candidate latency and pixel of :meth:`ContinuousIntegral.log_ratio`: up to three time points
# of the integral and level tables (float64 each) and the gathers that combine them.
BYTES_PER_CANDIDATE = 80
# Bytes per event kept between calls (time, pixel, level before and after), and at the peak of a call.
BYTES_PER_EVENT_KEPT = 32
BYTES_PER_EVENT = 112
# Window ends are rounded to 1/_LATTICE µs (exact in binary) so equal times computed two ways coincide.
_LATTICE = 1024.0


class ContinuousIntegral:
    """Exact step-EDI integrals of one sample's events over any windows.

    Args:
        events: events of one sample (``batch_size == 1``), sorted by time.
        threshold: contrast threshold θ.

    Levels are kept relative to each pixel's highest level (``θC − peak ≤ 0``) so ``exp`` never
    overflows; the ratio ``R`` does not depend on that scale.

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> ci = ContinuousIntegral(ev, threshold=0.5)
        >>> # window [0, 10] read at 10: half the time at e^-0.5 relative to the end level
        >>> round(float(ci.log_ratio(0.0, 10.0, torch.tensor([0.0]), reference=1.0)), 6)
        -0.21907
        >>> round(float(torch.log((0.5 + 0.5 * torch.exp(torch.tensor(-0.5))))), 6)
        -0.21907
    """

    def __init__(self, events: Events, threshold: float) -> None:
        if events.batch_size != 1:
            raise ValueError(f"ContinuousIntegral takes one sample, got batch_size {events.batch_size}")
        if not threshold > 0:
            raise ValueError(f"threshold must be positive, got {threshold}")
        height, width = events.sensor_size
        self.num_pixels = height * width
        self.sensor_size = events.sensor_size
        self.theta = float(threshold)
        self.device = events.device
        self.t = events.t.to(torch.float64)
        self.pixel = events.pixel_index()
        polarity = events.p.to(torch.int64)
        # each event's level C after it at its pixel: a cumulative sum within runs of one pixel (a stable
        # sort by pixel keeps each pixel's events in time order)
        order = torch.argsort(self.pixel, stable=True)
        running = torch.cumsum(polarity[order], 0)
        counts = torch.bincount(self.pixel, minlength=self.num_pixels)
        run_start = torch.cumsum(counts, 0) - counts
        before_run = torch.cat([running.new_zeros(1), running])[run_start]
        level_after = torch.empty_like(running)
        level_after[order] = running - before_run[self.pixel[order]]
        level_after = self.theta * level_after.to(torch.float64)
        self.level_after = level_after
        self.level_before = level_after - self.theta * polarity.to(torch.float64)
        self._work = torch.empty(0, dtype=torch.float64, device=self.device)

    def at(self, times: Tensor) -> tuple[Tensor, Tensor]:
        """``S`` and ``exp(θC − peak)`` of every pixel at sorted times.

        Args:
            times: strictly increasing times :math:`(G,)`, µs (float64).

        Returns:
            ``(S, level)``, each :math:`(G, H, W)` float64: ``S(g_j) = ∫_{g_0}^{g_j} exp(θC − peak)``
            (0 at ``g_0``) and ``exp(θC(g_j) − peak)`` with ``C(g)`` counting the events before ``g``; ``peak``
            is each pixel's highest ``θC`` over ``[g_0, g_{G−1}]``, so the levels are at most 1.
        """
        s_total, level = self._tables(times)
        return s_total.clone(), level.clone()

    def _tables(self, times: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`at` in a work buffer that the next call overwrites (fresh GB-sized arrays cost page faults)."""
        g = times.to(self.device, torch.float64)
        num, p = len(g), self.num_pixels
        if self._work.numel() < 2 * num * p:
            self._work = torch.empty(2 * num * p, dtype=torch.float64, device=self.device)
        # the events are in time order: those before the grid, then those inside it (slices, not masks)
        first, last = torch.searchsorted(self.t, g[[0, -1]]).tolist()
        t, pixel, after = self.t[first:last], self.pixel[first:last], self.level_after[first:last]
        slot = torch.searchsorted(g, t, right=True)  # g[slot - 1] <= t < g[slot]
        # θC at g_0 (the events before the grid) and each pixel's highest level from there to the last point
        start_level = torch.zeros(p, dtype=torch.float64, device=self.device).index_add_(
            0, self.pixel[:first], self.level_after[:first] - self.level_before[:first])
        peak = start_level.clone().scatter_reduce_(0, pixel, after, reduce="amax", include_self=True)
        # exp(level) is piecewise constant: its value at g_j is the start value plus the rises of the events
        # before g_j, and its integral from g_0 is (g_j − g_0)·level(g_j) − Σ rise·(t − g_0) over those events
        rise = torch.exp(after - peak[pixel]) - torch.exp(self.level_before[first:last] - peak[pixel])
        flat = slot * p + pixel
        level = self._work[:num * p].zero_().index_add_(0, flat, rise)
        held = self._work[num * p:2 * num * p].zero_().index_add_(0, flat, rise * (t - g[0]))
        level = torch.cumsum(level.view(num, p), 0, out=level.view(num, p)).add_(torch.exp(start_level - peak))
        held = torch.cumsum(held.view(num, p), 0, out=held.view(num, p))
        s_total = held.neg_().addcmul_(level, (g - g[0])[:, None])
        h, w = self.sensor_size
        return s_total.view(num, h, w), level.view(num, h, w)

    def log_ratio(self, start: float, end: float, latencies: Tensor, reference: float = 0.5) -> Tensor:
        """``log R`` of the windows ``[start + l, end + l]`` read at ``start + l + reference·(end − start)``.

        Args:
            start: exposure start, µs.
            end: exposure end, µs (``> start``).
            latencies: :math:`(K,)` µs.
            reference: where in the exposure the latent image is (0.5 = mid-exposure).

        Returns:
            :math:`(K, 1, H, W)` float64; the latent image is ``blurry · exp(−log R)``.
        """
        lat = latencies.to(self.device, torch.float64).reshape(-1)
        points = torch.stack([start + lat, end + lat, start + reference * (end - start) + lat])  # (3, K)
        # on a 1/1024 µs lattice, so window ends that meet other windows' starts (or references) are one point
        points = torch.round(points * _LATTICE) / _LATTICE
        times, index = torch.unique(points.reshape(-1), sorted=True, return_inverse=True)
        s_total, level = self._tables(times)
        a, b, r = index.view(3, -1)
        mean = (s_total[b] - s_total[a]).clamp_min_(1e-300).div_(level[r]).div_(end - start)
        return torch.log_(mean)[:, None]
