"""The constant-latency search's binned candidates (``method="binned"``): one prefix-sum table for all of them.

For a latency ``l = dΔ`` that is a whole number ``d`` of sub-intervals ``Δ = T / n`` the EDI reads the cumulative
sum ``C`` at grid points ``d .. d + n``, so

    R_d = mean_j exp(θ (C[d + j] − C[d + n/2]))  =  (P[d + n + 1] − P[d] − ½(Y_d + Y_{d+n})) / n / Y_{d+n/2}

with ``Y = exp(θC − max θC)`` and ``P`` its prefix sum (trapezoidal rule, log domain): one table of
``(n + span) × H × W`` serves every candidate. Needed for the ``"linear"`` integral; the default search reads its
candidates in continuous time instead (:mod:`evlatcorr.search_candidates`), about 16x faster at DAVIS346 size.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evlatcorr import continuous
from evlatcorr.checks import check_memory, resolve_memory_budget
from evlatcorr.config import SearchConfig
from evlatcorr.events import Events
from evlatcorr.integral import _row_strips, cumsum_, cumulative_event_grid
from evlatcorr.overshoot import overshoot_stride
from evlatcorr.search_candidates import _CandidateReader, _Window

# Memory bound of one strip of the prefix-sum table (float64), in elements.
_STRIP_ELEMENTS = 4_000_000
# Bytes per grid point and pixel that the search table keeps: the cumulative event sum (float32) and the
# prefix sum of exp(θC − peak) (float64).
_TABLE_BYTES = 4 + 8
# The largest search table kept between reads (larger ones are rebuilt per read, in strips).
_KEEP_TABLE_BYTES = 512 * 2**20
# Peak bytes per grid point and pixel while one strip of the table is built (the integral's work
# arrays, θC in float64, its exponential and prefix sum).
_BUILD_BYTES = 64


def _binned_reader(events: Events, span: _Window, theta: float, config: SearchConfig, integral: str,
                   budget: int | None) -> _CandidateReader:
    """Candidates that are whole sub-intervals ``exposure / n`` of one prefix-sum table; the grid may overhang
    the range by up to one, and the latency is clamped into ``[low, high]``."""
    start, end, low, high, reach, n = span.start, span.end, span.low, span.high, span.reach, config.num_bins
    width_us = (end - start) / n
    stride = overshoot_stride(*events.sensor_size)  # the overshoot's pixels
    step = max(1, round((high - low) / (config.num_candidates - 1) / width_us))  # in sub-intervals
    first = math.floor(low / width_us)
    num = max(2, math.ceil((high - low) / (step * width_us) - 1e-9) + 1)
    span_steps = (num - 1) * step  # shifts 0..span_steps (in sub-intervals, from the first candidate)
    # shifts whose window stays inside the events (a bin of slack: the last event is in the last bin)
    top = min(span_steps, math.floor(reach / width_us) + 1 - first) if math.isfinite(reach) else -1
    table = None
    if top >= 0:
        advice = (f"the table spans num_bins={n} sub-intervals of {width_us:.4g} us for the exposure plus "
                  f"{min(span_steps, top)} for the latencies searched (search_range [{low:.0f}, {high:.0f}] us, "
                  f"events up to {reach:.0f} us past exposure_end): narrow search_range, use fewer num_bins, or "
                  "pass only the events up to exposure_end + search_range[1]")
        table = _ShiftTable(events, start + first * width_us, width_us, n, min(span_steps, top), theta, integral,
                            budget, advice)

    def fine_of(best: float) -> Tensor:
        best = int(best)
        return torch.arange(max(0, best - step), min(span_steps, top, best + step) + 1, device=events.device)

    return _CandidateReader(torch.arange(num, device=events.device) * step, top, 0,
                            lambda v: (first + v).to(torch.float64) * width_us,
                            lambda shifts: torch.exp(-table.log_ratio(shifts)).float(), fine_of, lambda latency: None,
                            lambda shifts: table.log_change(shifts),
                            log_peak=lambda shifts: table.log_peak(shifts, stride))


class _ShiftTable:
    """log R for whole-sub-interval shifts, from one prefix-sum table per strip of rows.

    The table keeps about ``_TABLE_BYTES`` per grid point and pixel. When the whole table is over the
    memory budget, its strips are not kept but rebuilt at each :meth:`log_ratio` call (the same values,
    more time); when even one row of it is over the budget the search is refused with ``advice``.
    """

    def __init__(self, events: Events, grid_start: float, width_us: float, n: int, span: int, theta: float,
                 integral: str = "step", budget: int | None = None, advice: str = "narrow the search range"):
        self.n, self.theta = n, theta
        self.grid_start, self.width_us, self.integral = grid_start, width_us, integral
        height, width = events.sensor_size
        self.num_bins = num_bins = n + span
        limit = resolve_memory_budget(budget)
        elements = _STRIP_ELEMENTS * (16 if events.device.type == "cuda" else 1)
        rows = max(1, min(height, elements // ((num_bins + 2) * width)))
        # sizes from Python ints only: nothing is read from the device to decide
        # a table over _KEEP_TABLE_BYTES is rebuilt strip by strip at each read: at DAVIS346 size that takes
        # no longer than building and keeping it (page faults of a GB-sized table), at a third of the memory
        self.keep = (num_bins + 2) * height * width * _TABLE_BYTES <= min(limit, _KEEP_TABLE_BYTES)
        if not self.keep:
            row_bytes = (num_bins + 2) * width * _BUILD_BYTES
            check_memory(row_bytes, f"one row of the latency search table ({num_bins + 1} grid points x {width} "
                         "pixels)", advice, limit)
            rows = max(1, min(rows, limit // row_bytes))
        # a strip is bounded by _STRIP_ELEMENTS (kept table) or by the budget (streamed): let it through
        self.strip_budget = max(limit, rows * (num_bins + 2) * width * _BUILD_BYTES)
        # events ordered by row once, so each strip is a contiguous slice (not a mask over all events)
        self.strips: list[Events | tuple[Tensor, Tensor, Tensor]] = [
            self._build(sub) if self.keep else sub for _, _, sub in _row_strips(events, rows)]

    def _build(self, sub: Events) -> tuple[Tensor, Tensor, Tensor]:
        """(C float32, peak of θC, prefix sum of exp(θC − peak)) of one strip.

        exp(θC − peak) itself is not kept: :meth:`log_ratio` recomputes it on the two slices it reads
        (the same float64 values), which saves 8 bytes per grid point and pixel.
        """
        cum = cumulative_event_grid(sub, self.grid_start, self.width_us, self.num_bins, self.integral,
                                    memory_budget=self.strip_budget)[0]  # (M+1, h, W)
        x = self.theta * cum.double()
        peak = x.amax(0, keepdim=True)
        prefix = torch.zeros((x.shape[0] + 1, *x.shape[1:]), dtype=x.dtype, device=x.device)
        prefix[1:] = torch.exp_(x.sub_(peak))  # summed in place: one float64 copy at a time
        del x
        cumsum_(prefix[1:], 0)
        return cum, peak, prefix

    def log_change(self, shifts: Tensor) -> Tensor:
        """θ times each pixel's net events in each shift's window :math:`(K, 1, H, W)` float32 (the ghost cue's)."""
        out = []
        for strip in self.strips:
            cum = (strip if isinstance(strip, tuple) else self._build(strip))[0]
            out.append(self.theta * (cum[shifts + self.n] - cum[shifts]))
        return torch.cat(out, dim=1)[:, None].float()

    def log_peak(self, shifts: Tensor, stride: int = 1) -> Tensor:
        """θ (max C − C(mid-exposure)) over each shift's window :math:`(K, 1, ⌈H/s⌉, ⌈W/s⌉)` float32 at every
        ``stride``-th row and column, the maximum over the window's start, quarters, middle and end bin edges (the
        overshoot cue's; the continuous integral's ``peak_out`` on the bins' edges)."""
        n, out = self.n, []
        offsets = [round(f * n) for f in (0.0, *continuous.PEAK_FRACTIONS, 1.0)]
        for strip in self.strips:
            cum = (strip if isinstance(strip, tuple) else self._build(strip))[0]
            middle = cum[shifts + round(0.5 * n)]
            peak = middle.clone()
            for offset in offsets:
                torch.maximum(peak, cum[shifts + offset], out=peak)
            out.append(self.theta * (peak - middle))
        return torch.cat(out, dim=1)[:, None, ::stride, ::stride].float()

    def log_ratio(self, shifts: Tensor, reference: float = 0.5) -> Tensor:
        """log R for each shift, latent at ``start + reference * exposure`` (0.5 = mid-exposure)."""
        n = self.n
        r_lo, r_hi = math.floor(reference * n), math.ceil(reference * n)
        w_hi = reference * n - r_lo
        out = []
        for strip in self.strips:
            cum, peak, prefix = strip if isinstance(strip, tuple) else self._build(strip)
            y_lo = torch.exp(self.theta * cum[shifts].double() - peak)
            y_hi = torch.exp(self.theta * cum[shifts + n].double() - peak)
            total = prefix[shifts + n + 1] - prefix[shifts] - 0.5 * (y_lo + y_hi)
            total = total.clamp_min(1e-300) / n
            # θC from the float32 sum, as when the table was built (the same float64 values)
            x_lo, x_hi = self.theta * cum[shifts + r_lo].double(), self.theta * cum[shifts + r_hi].double()
            ref = (1 - w_hi) * x_lo + w_hi * x_hi
            out.append(torch.log(total) + peak - ref)
        return torch.cat(out, dim=1)[:, None]  # (K, 1, H, W)
