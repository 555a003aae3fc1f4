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

import math

import torch
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.integral import cumsum_

__all__ = ["ContinuousIntegral"]

# Bytes per candidate latency and pixel that :meth:`ContinuousIntegral.inverse_ratio` returns (float32), plus the
# float32 latent image its caller makes of it.
BYTES_PER_CANDIDATE = 8
# Bytes per event kept between calls (time, pixel, level before and after, rise, the pixel-order permutation),
# and at the peak of a call.
BYTES_PER_EVENT_KEPT = 48
BYTES_PER_EVENT = 112
# Bytes per time point and pixel of the tables one strip of rows is evaluated in (S and the level, float64, and
# the gathers that read them), and the most one strip may take.
BYTES_PER_POINT = 40
STRIP_BYTES = 64 * 2**20
# Window ends are rounded to 1/_LATTICE µs (exact in binary) so equal times computed two ways coincide.
_LATTICE = 1024.0


class ContinuousIntegral:
    """Exact step-EDI integrals of one sample's events over any windows.

    Args:
        events: events of one sample (``batch_size == 1``), sorted by time.
        threshold: contrast threshold θ.
        max_log_range: pixels whose level θC spans more than this over the events (a hot pixel firing one
            polarity: no scene's log intensity spans e^15) are read as if they had no events (``ignored``: their
            mask :math:`(H·W,)`); None: every pixel is read.

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

    def __init__(self, events: Events, threshold: float, max_log_range: float | None = None) -> None:
        if events.batch_size != 1:
            raise ValueError(f"ContinuousIntegral takes one sample, got batch_size {events.batch_size}")
        if not threshold > 0:
            raise ValueError(f"threshold must be positive, got {threshold}")
        if max_log_range is not None and not max_log_range > 0:
            raise ValueError(f"max_log_range must be positive or None, got {max_log_range}")
        height, width = events.sensor_size
        self.num_pixels = height * width
        self.sensor_size = events.sensor_size
        self.theta = float(threshold)
        self.device = events.device
        # events in pixel order (each pixel's in time order: a stable sort), so a strip of rows is a slice
        pixel = events.pixel_index()
        # int32 keys sort twice as fast as int64 (the same stable order); the sort returns the sorted keys, and
        # index_select gathers about twice as fast as advanced indexing on a CPU
        keys, order = torch.sort(pixel.to(torch.int32) if self.num_pixels < 2**31 else pixel, stable=True)
        # the events in time order (the input's own times, no copy) and where each pixel-order event came from: an
        # event's slot among sorted times is then a count over the time-ordered stream, not a binary search each
        self.time_ordered = events.t
        self.order = order.to(torch.int32) if len(order) < 2**31 else order
        self.pixel, self.t = keys.to(torch.int64), events.t.to(torch.float64).index_select(0, order)
        polarity = events.p.index_select(0, order).to(torch.int64)
        counts = torch.bincount(self.pixel, minlength=self.num_pixels)
        self.run_start = torch.cumsum(counts, 0) - counts
        self._levels(polarity)
        # pixels whose events span more log intensity than any scene can (hot pixels firing one polarity) would
        # dominate every latent image: they are read as if they had no events
        self.ignored = torch.zeros(self.num_pixels, dtype=torch.bool, device=self.device)
        if max_log_range is not None and len(polarity):
            low = torch.zeros_like(self.peak).scatter_reduce(0, self.pixel, self.level_after, reduce="amin")
            hot = self.peak - low > max_log_range
            if bool(hot.any()):
                self.ignored = hot
                self._levels(polarity * (~hot).index_select(0, self.pixel))
        # first event of each row (and the end): strips of rows are contiguous
        row_starts = torch.arange(height + 1, device=self.device) * width
        self.row_bounds = torch.searchsorted(self.pixel, row_starts).tolist()

    def _levels(self, polarity: Tensor) -> None:
        """Each event's level θC before and after it at its pixel, each pixel's peak, and each event's rise."""
        # each event's level C after it at its pixel: a cumulative sum within the pixel's run
        running = torch.cumsum(polarity, 0)
        # the running sum before each pixel's run (no copy of the sums)
        run_start = self.run_start
        before_run = torch.where(run_start > 0, running.index_select(0, (run_start - 1).clamp(min=0)), 0)
        self.level_after = self.theta * (running - before_run.index_select(0, self.pixel)).to(torch.float64)
        self.level_before = self.level_after - self.theta * polarity.to(torch.float64)
        # levels are read relative to each pixel's highest level over the whole stream (0 before its first
        # event), so each event's rise of exp(θC − peak) is computed once here, not once per read
        zeros = torch.zeros(self.num_pixels, dtype=torch.float64, device=self.device)
        self.peak = zeros.scatter_reduce(0, self.pixel, self.level_after, reduce="amax", include_self=True)
        top = self.peak.index_select(0, self.pixel)
        # exp(after − top) − exp(before − top) = exp(after − top)·(1 − exp(−θp)): one exponential per event, the
        # factor one of three constants (p = −1, 0 for an ignored pixel's event, +1)
        factor = torch.tensor([1.0 - math.exp(self.theta), 0.0, 1.0 - math.exp(-self.theta)], dtype=torch.float64,
                              device=self.device)
        self.rise = torch.exp(self.level_after - top).mul_(factor.index_select(0, polarity + 1))

    def at(self, times: Tensor) -> tuple[Tensor, Tensor]:
        """``S`` and ``exp(θC − peak)`` of every pixel at sorted times.

        Args:
            times: strictly increasing times :math:`(G,)`, µs (float64).

        Returns:
            ``(S, level)``, each :math:`(G, H, W)` float64: ``S(g_j) = ∫_{g_0}^{g_j} exp(θC − peak)``
            (0 at ``g_0``) and ``exp(θC(g_j) − peak)`` with ``C(g)`` counting the events before ``g``; ``peak``
            is each pixel's highest ``θC`` over its events (0 before the first), so the levels are at most 1.
        """
        times = times.to(self.device, torch.float64)
        height, width = self.sensor_size
        work = torch.empty(2 * len(times) * height * width, dtype=torch.float64, device=self.device)
        return self._tables(times, 0, height, work, self._slots(times))

    def _slots(self, g: Tensor) -> Tensor:
        """How many of the sorted times ``g`` each event (pixel order) is at or after: ``searchsorted(g, t,
        right=True)``, from one count over the time-ordered stream."""
        n = len(self.time_ordered)
        first = torch.searchsorted(self.time_ordered, g)  # the first event at or after each time
        marks = torch.zeros(n + 1, dtype=torch.int32, device=self.device).index_add_(
            0, first, torch.ones_like(first, dtype=torch.int32))
        return torch.cumsum(marks[:n], 0, dtype=torch.int32).index_select(0, self.order)

    def _tables(self, g: Tensor, r0: int, r1: int, work: Tensor, slots: Tensor) -> tuple[Tensor, Tensor]:
        """:meth:`at` for the rows ``[r0, r1)``: :math:`(G, r1 − r0, W)` each, written into ``work`` (float64, at
        least ``2·G·(r1 − r0)·W`` elements, overwritten); ``slots``: :meth:`_slots` of ``g``."""
        width = self.sensor_size[1]
        num, p = len(g), (r1 - r0) * width
        lo, hi = self.row_bounds[r0], self.row_bounds[r1]
        t, pixel = self.t[lo:hi], self.pixel[lo:hi] - r0 * width
        after, before = self.level_after[lo:hi], self.level_before[lo:hi]
        # events before the grid set the start level, those inside it the steps; masks as weights, not
        # compaction, so nothing waits on the device for a count
        slot = slots[lo:hi]
        ahead = slot == 0
        inside = ~ahead & (slot < num)
        peak = self.peak[r0 * width:r1 * width]
        # θC at g_0 (exact, in the log domain), relative to the pixel's peak
        start_level = torch.zeros(p, dtype=torch.float64, device=self.device).index_add_(
            0, pixel, torch.where(ahead, after - before, 0.0))
        slot = slot.clamp(max=num - 1).to(torch.int64)  # g[slot - 1] <= t < g[slot] inside
        # exp(level) is piecewise constant: its value at g_j is the start value plus the rises of the events
        # before g_j, and its integral from g_0 is (g_j − g_0)·level(g_j) − Σ rise·(t − g_0) over those events
        rise = torch.where(inside, self.rise[lo:hi], 0.0)
        flat = slot * p + pixel
        level = work[:num * p].zero_().index_add_(0, flat, rise)
        held = work[num * p:2 * num * p].zero_().index_add_(0, flat, rise * (t - g[0]))
        level = cumsum_(level.view(num, p), 0).add_(torch.exp(start_level - peak))
        held = cumsum_(held.view(num, p), 0)
        s_total = held.neg_().addcmul_(level, (g - g[0])[:, None])
        return s_total.view(num, r1 - r0, width), level.view(num, r1 - r0, width)

    def log_ratio(self, start: float, end: float, latencies: Tensor, reference: float = 0.5,
                  out: Tensor | None = None) -> Tensor:
        """``log R`` of the windows ``[start + l, end + l]`` read at ``start + l + reference·(end − start)``.

        Args:
            start: exposure start, µs.
            end: exposure end, µs (``> start``).
            latencies: :math:`(K,)` µs.
            reference: where in the exposure the latent image is (0.5 = mid-exposure).
            out: optional float64 :math:`(K, 1, H, W)` to write into (e.g. a slice of a larger batch).

        Returns:
            :math:`(K, 1, H, W)` float64; the latent image is ``blurry · exp(−log R)``.
        """
        return self._read(start, end, latencies, reference, out, torch.float64)

    def inverse_ratio(self, start: float, end: float, latencies: Tensor, reference: float = 0.5,
                      out: Tensor | None = None, change_out: Tensor | None = None) -> Tensor:
        """``1 / R`` of the same windows as :meth:`log_ratio`, float32: the latent image is ``blurry / R``.

        What a search that scores latent images needs, without a logarithm and an exponential per pixel and
        candidate. ``out``: optional float32 :math:`(K, 1, H, W)`. ``change_out``: optional float32
        :math:`(K, 1, H, W)` that also receives :meth:`log_change` of the windows, from the same tables (the log
        of the level ratio at the window's ends: no second pass over the events).
        """
        return self._read(start, end, latencies, reference, out, torch.float32, change_out)

    def _read(self, start: float, end: float, latencies: Tensor, reference: float, out: Tensor | None,
              dtype: torch.dtype, change_out: Tensor | None = None) -> Tensor:
        """log R (float64) or 1 / R (float32) of every window, a strip of rows at a time (and the windows' event
        change into ``change_out``)."""
        lat = latencies.to(self.device, torch.float64).reshape(-1)
        mid = start + reference * (end - start)
        times, (a, b, r) = _distinct_times(torch.stack([start + lat, end + lat, mid + lat]))
        height, width = self.sensor_size
        # a strip of rows at a time: the tables of all the times stay within STRIP_BYTES
        rows = max(1, min(height, STRIP_BYTES // (len(times) * width * BYTES_PER_POINT)))
        if out is None:
            out = torch.empty((len(lat), 1, height, width), dtype=dtype, device=self.device)
        elif out.shape != (len(lat), 1, height, width) or out.dtype != dtype:
            raise ValueError(f"out must be {dtype} {(len(lat), 1, height, width)}, got {out.dtype} {tuple(out.shape)}")
        if change_out is not None and (change_out.shape != out.shape or change_out.dtype != torch.float32):
            raise ValueError(f"change_out must be float32 {tuple(out.shape)}, got {change_out.dtype} "
                             f"{tuple(change_out.shape)}")
        # one work buffer for every strip's tables: fresh tables each strip would cost their page faults again
        work = torch.empty(2 * len(times) * rows * width, dtype=torch.float64, device=self.device)
        slots = self._slots(times)
        # evenly spaced candidates read evenly spaced times: rows of the tables as views, not gathered copies
        a, b, r = (_as_rows(index) for index in (a, b, r))
        for r0 in range(0, height, rows):
            r1 = min(height, r0 + rows)
            s_total, level = self._tables(times, r0, r1, work, slots)
            if change_out is not None:  # θC(end) − θC(start) = log of the ratio of exp(θC − peak) at the two
                ratio = torch.div(level[b], level[a].clamp_min(1e-300))
                torch.log(ratio, out=change_out[:, 0, r0:r1])
            mean = torch.sub(s_total[b], s_total[a]).clamp_min_(1e-300)
            if dtype == torch.float64:
                mean.div_(level[r]).div_(end - start)
                torch.log(mean, out=out[:, 0, r0:r1])
            else:
                torch.div(level[r], mean, out=out[:, 0, r0:r1]).mul_(end - start)
        return out

    def log_change(self, start: float, end: float, latencies: Tensor) -> Tensor:
        """``θ (C(end + l) − C(start + l))``: the log-intensity change the events of each window make.

        Args:
            start: exposure start, µs.
            end: exposure end, µs.
            latencies: :math:`(K,)` µs.

        Returns:
            :math:`(K, 1, H, W)` float32: θ times each pixel's net signed events in ``[start + l, end + l)``.
        """
        lat = latencies.to(self.device, torch.float64).reshape(-1)
        times, (a, b) = _distinct_times(torch.stack([start + lat, end + lat]))
        # C(g) counts the events before g: an event counts from the first time after it on (slot G: never)
        slot = torch.searchsorted(times, self.t, right=True)
        p = self.num_pixels
        table = torch.zeros((len(times) + 1) * p, dtype=torch.float32, device=self.device).index_add_(
            0, slot * p + self.pixel, (self.level_after - self.level_before).to(torch.float32))
        table = cumsum_(table.view(len(times) + 1, p)[:len(times)], 0)  # event counts: the same sums
        change = table.index_select(0, b).sub_(table.index_select(0, a))
        return change.view(len(lat), 1, *self.sensor_size)


def _as_rows(index: Tensor) -> slice | Tensor:
    """``index`` as a slice where it counts up by one (then ``table[index]`` is a view), else as it is."""
    if len(index) and bool((index.diff() == 1).all()):
        first = int(index[0])
        return slice(first, first + len(index))
    return index


def _distinct_times(points: Tensor) -> tuple[Tensor, Tensor]:
    """The sorted distinct times of ``points`` :math:`(M, K)` and where each point lies among them :math:`(M, K)`.

    Times are rounded to a 1/1024 µs lattice first, so window ends that meet other windows' starts (or
    references) computed two ways are one point.
    """
    points = torch.round(points * _LATTICE) / _LATTICE
    times, index = torch.unique(points.reshape(-1), sorted=True, return_inverse=True)
    return times, index.view(points.shape)
