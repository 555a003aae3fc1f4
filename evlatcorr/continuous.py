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

That is how a GPU reads them (tables of every pixel at every time, in eager PyTorch). A CPU, where those tables'
memory traffic bounds the search, prepares the events with a compiled counting sort
(:mod:`~evlatcorr.compiled.event_runs`) and reads the windows by a compiled walk over each pixel's events
(:mod:`~evlatcorr.compiled.window_reads`), with the same results to float32 rounding; ``EVLATCORR_COMPILED=0`` (or
``evlatcorr.compiled.ENABLED`` False) takes the tables there too.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
from torch import Tensor

from evlatcorr import compiled
from evlatcorr.compiled.event_runs import sort_into_runs
from evlatcorr.compiled.window_reads import read_windows
from evlatcorr.events import Events
from evlatcorr.integral import cumsum_

__all__ = ["ContinuousIntegral"]

# Bytes per candidate latency and pixel that :meth:`ContinuousIntegral.inverse_ratio` returns (float32), plus the
# float32 latent image its caller makes of it.
BYTES_PER_CANDIDATE = 8
# Bytes per event kept between calls (time, pixel, step, rise, the pixel-order permutation and, where few pixels have
# events, its place among them), and at the peak of a call.
BYTES_PER_EVENT_KEPT = 40
BYTES_PER_EVENT = 112
# The most the tables of one strip of rows may take (each pixel's event count, level and interval integrals at
# every time, and the windows' sums read from them) on a CPU, where strips that fit its caches and reuse freed
# pages are faster; and elsewhere (a GPU), where each strip costs two dozen kernel launches and a DAVIS346 frame's
# 200 times take about 400 MB in one strip.
STRIP_BYTES = 64 * 2**20
DEVICE_STRIP_BYTES = 2**30
# Where at most this share of the pixels has events (a dim or still scene: a DAVIS346 low-light frame has events at
# 14 % of its pixels), a CPU reads the windows at those pixels alone: every other pixel's ratio is exactly 1.
SPARSE_SHARE = 0.5
# where in the window, besides its ends and reference, the peak log rise (``peak_out``) is read
PEAK_FRACTIONS = (0.25, 0.75)
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
        time_sorted: the events are sorted by time (one sample's). False: only each pixel's events are (e.g.
            several frames' events side by side as one tall image, each frame's times from its own exposure start);
            each read then finds its events' slots by a binary search each (cheap on a GPU, slower on a CPU).

    Levels are kept relative to each pixel's highest level (``θC − peak ≤ 0``) so ``exp`` never
    overflows; the ratio ``R`` does not depend on that scale. A window's integral is summed from the
    integrals over the intervals between the times read, which are never negative, in blocks as long as the
    shortest window (no difference of two large running sums): :meth:`inverse_ratio` keeps its tables in
    float32, :meth:`log_ratio` in float64.

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

    def __init__(self, events: Events, threshold: float, max_log_range: float | None = None,
                 time_sorted: bool = True) -> None:
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
        small = self.num_pixels < 2**31 and len(events) < 2**31
        # the events in time order (the input's own times, no copy) and where each pixel-order event came from: an
        # event's slot among sorted times is then a count over the time-ordered stream, not a binary search each
        self.time_ordered = events.t if time_sorted else None
        if self._compiled and len(events):  # a counting sort and one pass over each pixel's run, compiled
            runs = sort_into_runs(events.x, events.y, events.t.to(torch.float64), events.p, events.sensor_size,
                                  self.theta, max_log_range)
            self.pixel, self.t, self.step, self.run_start = runs.pixel, runs.t, runs.step, runs.run_start
            self.peak_count, self.ignored, self._bounds = runs.peak_count, runs.ignored, runs.bounds
            self._after, self._rise = runs.after, None
            self.order = runs.order if time_sorted else None
            counts = runs.bounds.diff()
        else:
            counts = self._eager_runs(events, width, small, time_sorted, max_log_range)
        # first event of each row (and the end): strips of rows are contiguous
        row_starts = torch.arange(height + 1, device=self.device, dtype=self.pixel.dtype) * width
        self.row_bounds = torch.searchsorted(self.pixel, row_starts).tolist()
        # the pixels with events, where few have any: each event's place among them, and the first event of each
        # (on a CPU: on a GPU, whose search is bound by launches and waits more than arithmetic, it is unmeasured)
        self.active = self.local = self.active_bounds = None
        active = torch.nonzero(counts).flatten() if self.device.type == "cpu" else None
        if active is not None and len(active) <= SPARSE_SHARE * self.num_pixels:
            self.active = active
            self.local = torch.repeat_interleave(torch.arange(len(active), device=self.device),
                                                 counts.index_select(0, active), output_size=len(self.pixel))
            self.active_bounds = torch.cat([self.run_start.index_select(0, active),
                                            self.run_start.new_tensor([len(self.pixel)])]).cpu()

    def _eager_runs(self, events: Events, width: int, small: bool, time_sorted: bool,
                    max_log_range: float | None) -> Tensor:
        """:func:`~evlatcorr.compiled.event_runs.sort_into_runs` in eager PyTorch (a GPU's way); returns each pixel's
        count of events."""
        # int32 keys sort twice as fast as int64 (the same stable order); the sort returns the sorted keys, and
        # index_select gathers about twice as fast as advanced indexing on a CPU (one sample: the pixel is y·W + x).
        # The sorted pixels are kept as int64: the tables' flat indices are computed from them
        pixel = torch.empty(len(events), dtype=torch.int32 if small else torch.int64, device=self.device)
        keys, order = torch.sort(torch.add(events.x, events.y, alpha=width, out=pixel), stable=True)
        self.order = (order.to(torch.int32) if small else order) if time_sorted else None
        self.pixel, self.t = keys.to(torch.int64), events.t.to(torch.float64).index_select(0, order)
        step = events.p.index_select(0, order)
        counts = torch.bincount(self.pixel, minlength=self.num_pixels)
        self.run_start = torch.cumsum(counts, 0) - counts
        self._bounds = None
        count_after = self._levels(step)
        # pixels whose events span more log intensity than any scene can (hot pixels firing one polarity) would
        # dominate every latent image: they are read as if they had no events
        self.ignored = torch.zeros(self.num_pixels, dtype=torch.bool, device=self.device)
        if max_log_range is not None and len(step):
            low = torch.zeros_like(self.peak_count).scatter_reduce(0, self.pixel, count_after, reduce="amin")
            hot = self.theta * (self.peak_count - low) > max_log_range
            if bool(hot.any()):
                self.ignored = hot
                self._levels(step * (~hot).index_select(0, self.pixel))
        return counts

    def _levels(self, step: Tensor) -> Tensor:
        """Each event's step (±1, 0 for an ignored pixel's) and each pixel's peak count; returns each event's count
        after it at its pixel (kept for :attr:`rise`).

        Few event-sized tensors are made (each fresh one costs its page faults) and counts are int32.
        """
        self.step = step.to(torch.int8)
        # each event's count C after it at its pixel: a running sum within the pixel's run
        after = torch.cumsum(step, 0, dtype=torch.int32 if len(step) < 2**31 else torch.int64)
        run_start = self.run_start
        before_run = (torch.where(run_start > 0, after.index_select(0, (run_start - 1).clamp(min=0)), 0) if len(after)
                      else torch.zeros_like(run_start))  # no events: nothing to index
        after.sub_(before_run.to(after.dtype).index_select(0, self.pixel))
        # levels are read relative to each pixel's highest level over the whole stream (0 before its first event)
        self.peak_count = torch.zeros(self.num_pixels, dtype=after.dtype, device=self.device).scatter_reduce(
            0, self.pixel, after, reduce="amax", include_self=True)
        self._after, self._rise = after, None
        return after

    @property
    def rise(self) -> Tensor:
        """Each event's rise of ``exp(θC − peak)`` at its pixel :math:`(N,)` float64, pixel order: made on first use
        (a CPU's compiled reads never need it)."""
        if self._rise is None:
            # exp(θ·after − peak) − exp(θ·before − peak) = step·(1 − e^−θ)·exp(θ·max(before, after) − peak): one
            # exponential per event, of the higher of its two levels (after, or after + 1 for a −1 step)
            higher = self.peak_count.index_select(0, self.pixel)
            torch.sub(self._after, higher, out=higher).add_(self.step < 0)
            self._rise = higher.to(torch.float64).mul_(self.theta).exp_().mul_(self.step).mul_(
                1.0 - math.exp(-self.theta))
        return self._rise

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
        num, p = len(times), self.num_pixels
        count = torch.empty((num + 1, p), dtype=torch.float32, device=self.device)
        level = torch.empty((num, p), dtype=torch.float64, device=self.device)
        interval = torch.empty((num + 1, p), dtype=torch.float64, device=self.device)
        self._tables(times, 0, len(self.pixel), self.pixel, 0, self.peak_count, self._slots(times), count, level,
                     interval)
        s_total = torch.zeros_like(level)
        torch.cumsum(interval[1:num], 0, out=s_total[1:])
        return s_total.view(num, height, width), level.view(num, height, width)

    def _slots(self, g: Tensor) -> Tensor:
        """How many of the sorted times ``g`` each event (pixel order) is at or after: ``searchsorted(g, t,
        right=True)``, from one count over the time-ordered stream."""
        if self.time_ordered is None:  # times sorted within each pixel only
            return torch.searchsorted(g, self.t, right=True, out_int32=True)
        n = len(self.time_ordered)
        first = torch.searchsorted(self.time_ordered, g)  # the first event at or after each time
        marks = torch.zeros(n + 1, dtype=torch.int32, device=self.device).index_add_(
            0, first, torch.ones_like(first, dtype=torch.int32))
        return torch.cumsum(marks[:n], 0, dtype=torch.int32).index_select(0, self.order)

    def _tables(self, g: Tensor, lo: int, hi: int, pixels: Tensor, base: int, peak: Tensor, slots: Tensor,
                count: Tensor, level: Tensor, interval: Tensor) -> None:
        """Fill the tables of ``p`` pixels at the sorted times ``g`` (:math:`G`) from the events ``[lo, hi)`` (pixel
        order), the ``p`` pixels that ``pixels[lo:hi] − base`` numbers 0 to ``p − 1`` (``peak``: their peak counts).

        Row ``j`` of ``count`` :math:`(G + 1, p)` float32 gets ``C(g_j) − peak / θ`` (a whole number), row ``j``
        of ``level`` :math:`(G, p)` ``exp(θC(g_j) − peak)``, and row ``j + 1`` of ``interval`` (at least
        :math:`G + 1` rows) the integral of ``exp(θC − peak)`` over ``[g_j, g_{j+1}]``. An event lands in row
        ``slot`` of both (:meth:`_slots`): rows ``G`` (events after the last time) and ``interval``'s row 0
        (events before the first) take what no window reads, so no event is masked.
        """
        num, p = len(g), len(peak)
        slot = slots[lo:hi]
        flat = torch.add(pixels[lo:hi], slot, alpha=p).sub_(base)  # int64: the pixels' type
        # an event counts from the first time after it on; row 0 starts from minus the pixel's peak
        count.zero_()[0].sub_(peak.to(count.dtype))
        # scatter_add_ rather than index_add_: the same sums, a little faster on a CPU (`speed.py --part against
        # --against` the index_add_ revision: 181 against 183 ms per DAVIS346 default search)
        count.view(-1).scatter_add_(0, flat, self.step[lo:hi].to(count.dtype))
        cumsum_(count[:num], 0)
        if level.dtype == count.dtype:
            torch.mul(count[:num], self.theta, out=level)
        else:  # θ times the count in float64, not rounded to float32 first
            level.copy_(count[:num]).mul_(self.theta)
        level.exp_()
        # between g_j and g_{j+1} the level of g_j is held, and each event in between adds its rise from its time on
        end = torch.cat([g, g[-1:]]).index_select(0, slot)
        held = end.sub_(self.t[lo:hi]).mul_(self.rise[lo:hi])
        torch.mul(level[:num - 1], (g[1:] - g[:-1]).to(level.dtype)[:, None], out=interval[1:num])
        interval[0].zero_()  # rows no window reads (events before the first time, after the last, padding)
        interval[num:].zero_()
        interval.view(-1).scatter_add_(0, flat, held.to(interval.dtype))

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
        if (latencies.numel() == 1 and self.time_ordered is not None and out is None
                and not (self._compiled and self.active is None)):
            return self._one_window(start, end, float(latencies.reshape(-1)[0]), reference)
        return self._read(start, end, latencies, reference, out, torch.float64)

    def _counts_where(self, mask: Tensor) -> Tensor:
        """Each pixel's net signed events where ``mask`` (pixel order) holds, float64 :math:`(H·W,)`: a running sum
        over the pixel-ordered events read at each pixel's run (whole numbers: exact)."""
        running = torch.empty(len(mask) + 1, dtype=torch.int32 if len(mask) < 2**31 else torch.int64,
                              device=self.device)
        running[0] = 0
        torch.cumsum(torch.mul(self.step, mask), 0, out=running[1:])
        ends = torch.cat([self.run_start[1:], self.run_start.new_tensor([len(mask)])])
        return (running.index_select(0, ends) - running.index_select(0, self.run_start)).to(torch.float64)

    def _one_window(self, start: float, end: float, latency: float, reference: float) -> Tensor:
        """:meth:`log_ratio` of one window (e.g. the latent at a search's estimate), from per-pixel sums instead of
        tables: each pixel's count before the window's start and before its reference time, and its events' rises
        held until the window's end. An event is before a time when its place in the time-ordered stream is (the
        tables' rule); the sums run over events in pixel order, so they are sequential."""
        lat = torch.tensor([latency], dtype=torch.float64)
        mid = start + reference * (end - start)
        times, index = _distinct_times(torch.stack([start + lat, mid + lat, end + lat]))
        a, r, b = times[index[:, 0]].tolist()  # rounded as the tables' times are
        # the first event at or after each time, left on the device (no wait for it on a GPU)
        first_a, first_r, first_b = torch.searchsorted(
            self.time_ordered, torch.tensor([a, r, b], dtype=torch.float64, device=self.device)).to(self.order.dtype)
        before_a, before_r = self.order < first_a, self.order < first_r
        count_a, count_r = self._counts_where(before_a), self._counts_where(before_r)
        # the level at the window's start held throughout, and each event inside it adding its rise from its time on
        held = torch.sub(b, self.t).mul_(self.rise).mul_((self.order < first_b).logical_and_(before_a.logical_not()))
        window = torch.zeros(self.num_pixels, dtype=torch.float64, device=self.device).scatter_add_(
            0, self.pixel, held)
        peak = self.peak_count.to(torch.float64)
        window += torch.exp((count_a - peak) * self.theta) * (b - a)
        log_ratio = window.clamp_min_(torch.finfo(torch.float64).tiny).div_(end - start).log_()
        log_ratio -= (count_r - peak) * self.theta
        return log_ratio.view(1, 1, *self.sensor_size)

    def inverse_ratio(self, start: float, end: float, latencies: Tensor, reference: float = 0.5,
                      out: Tensor | None = None, change_out: Tensor | None = None,
                      peak_out: Tensor | None = None, peak_stride: int = 1,
                      peak_frame_height: int | None = None) -> Tensor:
        """``1 / R`` of the same windows as :meth:`log_ratio`, float32: the latent image is ``blurry / R``.

        What a search that scores latent images needs: its tables are float32 (half the memory traffic of
        :meth:`log_ratio`'s) and it takes no logarithm. ``out``: optional float32 :math:`(K, 1, H, W)`.
        ``change_out``: optional float32 :math:`(K, 1, H, W)` that also receives :meth:`log_change` of the windows,
        from the same tables (the count at the window's ends: no second pass over the events).
        ``peak_out``: optional float32 :math:`(K, 1, H, W)` that receives, from the same tables, how far each
        pixel's log latent rises above its value at the reference over the window:
        ``θ (max C − C(reference))``, the maximum over the window's start, its quarters, its reference and its end
        (what :func:`evlatcorr.overshoot.overshoot` reads); with ``peak_stride`` s, only every s-th row and column's,
        :math:`(K, 1, ⌈H/s⌉, ⌈W/s⌉)`. ``peak_frame_height`` h: the sensor's rows are ``H / h`` frames of h rows
        stacked (several frames read in one pass), and every s-th row of each frame is read, frame after frame:
        :math:`(K, 1, (H/h)·⌈h/s⌉, ⌈W/s⌉)`.

        Raises:
            ValueError: for an output of the wrong shape or dtype, a ``peak_stride`` below 1, or a
                ``peak_frame_height`` that does not divide the sensor's height.
        """
        return self._read(start, end, latencies, reference, out, torch.float32, change_out, peak_out, peak_stride,
                          peak_frame_height)

    def _read(self, start: float, end: float, latencies: Tensor, reference: float, out: Tensor | None,
              dtype: torch.dtype, change_out: Tensor | None = None, peak_out: Tensor | None = None,
              peak_stride: int = 1, peak_frame_height: int | None = None) -> Tensor:
        """log R (float64) or 1 / R (float32) of every window, a strip of rows at a time (and the windows' event
        change into ``change_out``, their peak log rise into ``peak_out``)."""
        # the plan (a few hundred times and where each window lies among them) is made on the CPU: on a GPU its
        # small steps would each cost a kernel launch, and its decisions a wait for the device
        lat = latencies.detach().to("cpu", torch.float64).reshape(-1)
        mid = start + reference * (end - start)
        points = [start + lat, end + lat, mid + lat]
        if peak_out is not None:  # the quarters: with candidates spaced by exposure / 100, times already read
            points += [start + f * (end - start) + lat for f in PEAK_FRACTIONS]
        times, (a, b, r, *quarters) = _distinct_times(torch.stack(points))
        height, width = self.sensor_size
        if out is None:
            out = torch.empty((len(lat), 1, height, width), dtype=dtype, device=self.device)
        elif out.shape != (len(lat), 1, height, width) or out.dtype != dtype:
            raise ValueError(f"out must be {dtype} {(len(lat), 1, height, width)}, got {out.dtype} {tuple(out.shape)}")
        if change_out is not None and (change_out.shape != out.shape or change_out.dtype != torch.float32):
            raise ValueError(f"change_out must be float32 {tuple(out.shape)}, got {change_out.dtype} "
                             f"{tuple(change_out.shape)}")
        if isinstance(peak_stride, bool) or not isinstance(peak_stride, int) or peak_stride < 1:
            raise ValueError(f"peak_stride must be a whole number >= 1, got {peak_stride!r}")
        frame_height = height if peak_frame_height is None else peak_frame_height
        if (isinstance(frame_height, bool) or not isinstance(frame_height, int) or frame_height < 1
                or height % frame_height):
            raise ValueError(f"peak_frame_height must divide the sensor's height {height}, got {peak_frame_height!r}")
        peak_shape = (len(lat), 1, height // frame_height * -(-frame_height // peak_stride), -(-width // peak_stride))
        if peak_out is not None and (peak_out.shape != peak_shape or peak_out.dtype != torch.float32):
            raise ValueError(f"peak_out must be float32 {peak_shape}, got {peak_out.dtype} {tuple(peak_out.shape)}")
        if self._compiled and self.active is None:  # one compiled pass per pixel, no tables
            k = len(lat)
            read_windows(self.t, self.step, self._run_bounds(), self.peak_count, self.theta, times, a, b, r, quarters,
                         end - start, width, out.view(k, -1), None if change_out is None else change_out.view(k, -1),
                         None if peak_out is None else peak_out.view(k, -1), peak_stride, frame_height)
            return out
        windows = _Windows(a, b, len(times), self.device)
        num, padded, size = len(times), windows.rows, out.element_size()
        extended = 1 + max(padded, num)  # interval rows: before the first time, the blocks, after the last time
        # a strip of rows (or of the pixels with events) at a time: its tables and the windows' sums stay within
        # STRIP_BYTES (on a CPU)
        pixel_bytes = (num + 1) * 4 + num * size + (extended + padded) * size + 3 * len(lat) * size
        strip_bytes = STRIP_BYTES if self.device.type == "cpu" else DEVICE_STRIP_BYTES
        rows = max(1, min(height, strip_bytes // (pixel_bytes * width)))
        strip_pixels = rows * width if self.active is None else max(1, min(len(self.active),
                                                                             strip_bytes // pixel_bytes))
        # one set of work buffers for every strip: fresh tables each strip would cost their page faults again
        count = torch.empty((num + 1) * strip_pixels, dtype=torch.float32, device=self.device)
        level = torch.empty(num * strip_pixels, dtype=dtype, device=self.device)
        interval = torch.empty(extended * strip_pixels, dtype=dtype, device=self.device)
        backward = torch.empty(padded * strip_pixels, dtype=dtype, device=self.device)
        times = times.to(self.device)
        slots = self._slots(times)
        # evenly spaced candidates read evenly spaced times: rows of the tables as views, not gathered copies
        a, b, r, *quarters = (_as_rows(index, self.device) for index in (a, b, r, *quarters))

        def strip_sums(lo: int, hi: int, pixels: Tensor, base: int, peak: Tensor) -> tuple[Tensor, Tensor, Tensor]:
            """The tables of one strip's ``len(peak)`` pixels and each window's integral there."""
            p = len(peak)
            strip_count, strip_level = count[:(num + 1) * p].view(num + 1, p), level[:num * p].view(num, p)
            strip_interval = interval[:extended * p].view(extended, p)
            self._tables(times, lo, hi, pixels, base, peak, slots, strip_count, strip_level, strip_interval)
            window = windows.sums(strip_interval[1:1 + padded], backward[:padded * p].view(padded, p))
            return strip_count, strip_level, window.clamp_min_(torch.finfo(dtype).tiny)

        if self.active is not None:
            self._read_active(strip_pixels, strip_sums, (a, b, r, quarters), end - start, out, change_out, peak_out,
                              peak_stride, frame_height)
            return out
        for r0 in range(0, height, rows):
            r1 = min(height, r0 + rows)
            p = (r1 - r0) * width
            strip_count, strip_level, window = strip_sums(self.row_bounds[r0], self.row_bounds[r1], self.pixel,
                                                          r0 * width, self.peak_count[r0 * width:r1 * width])
            window = window.view(len(lat), r1 - r0, width)
            if change_out is not None:  # θ (C(end) − C(start)): whole numbers of events
                torch.sub(strip_count[b], strip_count[a], out=change_out[:, 0, r0:r1].view(len(lat), p))
                change_out[:, 0, r0:r1].mul_(self.theta)
            sampled, placed = _sampled_rows(r0, r1, frame_height, peak_stride, self.device)
            if peak_out is not None and placed is not None:
                # θ (max C − C(reference)) over the window's start, quarters, reference and end, at the sampled pixels
                counts = [_sampled(strip_count[rows_read], r1 - r0, sampled, peak_stride) for rows_read in (a, b, r)]
                peak = peak_out[:, 0, placed]
                torch.maximum(counts[0], counts[1], out=peak)
                for rows_read in quarters:
                    torch.maximum(peak, _sampled(strip_count[rows_read], r1 - r0, sampled, peak_stride), out=peak)
                torch.maximum(peak, counts[2], out=peak).sub_(counts[2]).mul_(self.theta)
            if dtype == torch.float64:  # log of the mean level over the window, relative to the level read
                torch.sub(window.div_(end - start).log_(), strip_count[r].view(len(lat), r1 - r0, width),
                          alpha=self.theta, out=out[:, 0, r0:r1])
            else:
                torch.div(strip_level[r].view(len(lat), r1 - r0, width), window, out=out[:, 0, r0:r1])
                out[:, 0, r0:r1].mul_(end - start)
        return out

    @property
    def _compiled(self) -> bool:
        """Whether the events are prepared by compiled passes (:mod:`~evlatcorr.compiled.event_runs`) and, where more
        than :data:`SPARSE_SHARE` of the pixels have events, read by one (:mod:`~evlatcorr.compiled.window_reads`): on
        a CPU, unless ``evlatcorr.compiled.ENABLED`` is off. Where fewer have events the tables at those pixels alone
        are faster."""
        return self.device.type == "cpu" and compiled.ENABLED

    def _run_bounds(self) -> Tensor:
        """Where each pixel's events start, and the end of the last :math:`(H·W + 1,)`."""
        if self._bounds is None:
            self._bounds = torch.cat([self.run_start, self.run_start.new_tensor([len(self.pixel)])])
        return self._bounds

    def _read_active(self, strip_pixels: int, strip_sums: Callable, rows_read: tuple, duration: float, out: Tensor,
                     change_out: Tensor | None, peak_out: Tensor | None, peak_stride: int, frame_height: int) -> None:
        """:meth:`_read`'s strips over the pixels with events alone (:data:`SPARSE_SHARE`): every other pixel's
        ratio is 1 (log ratio 0), its change and peak rise 0; each strip's results are scattered into place."""
        a, b, r, quarters = rows_read
        k, width = out.shape[0], self.sensor_size[1]
        flat_out = out.view(k, -1).fill_(0.0 if out.dtype == torch.float64 else 1.0)
        flat_change = None if change_out is None else change_out.view(k, -1).zero_()
        sampled_place = None
        if peak_out is not None:  # where each sampled pixel with events lies in peak_out (-1: not sampled)
            peak_out.zero_()
            y, x = self.active // width, self.active % width
            frame, y = y // frame_height, y % frame_height
            sampled = (y % peak_stride == 0) & (x % peak_stride == 0)
            row = frame * -(-frame_height // peak_stride) + y // peak_stride
            sampled_place = torch.where(sampled, row * peak_out.shape[-1] + x // peak_stride, -1)
        for c0 in range(0, len(self.active), strip_pixels):
            c1 = min(len(self.active), c0 + strip_pixels)
            pixels = self.active[c0:c1]
            strip_count, strip_level, window = strip_sums(int(self.active_bounds[c0]), int(self.active_bounds[c1]),
                                                          self.local, c0, self.peak_count.index_select(0, pixels))
            if flat_change is not None:
                flat_change.index_copy_(1, pixels, (strip_count[b] - strip_count[a]).mul_(self.theta))
            if sampled_place is not None:
                place = sampled_place[c0:c1]
                keep = torch.nonzero(place >= 0).flatten()
                if len(keep):
                    reference = strip_count[r].index_select(1, keep)
                    peak = torch.maximum(strip_count[a].index_select(1, keep), strip_count[b].index_select(1, keep))
                    for rows in quarters:
                        torch.maximum(peak, strip_count[rows].index_select(1, keep), out=peak)
                    torch.maximum(peak, reference, out=peak).sub_(reference).mul_(self.theta)
                    peak_out.view(k, -1).index_copy_(1, place.index_select(0, keep), peak)
            if out.dtype == torch.float64:
                ratio = window.div_(duration).log_().sub_(strip_count[r], alpha=self.theta)
            else:
                ratio = torch.div(strip_level[r], window).mul_(duration)
            flat_out.index_copy_(1, pixels, ratio)

    def log_change(self, start: float, end: float, latencies: Tensor) -> Tensor:
        """``θ (C(end + l) − C(start + l))``: the log-intensity change the events of each window make.

        Args:
            start: exposure start, µs.
            end: exposure end, µs.
            latencies: :math:`(K,)` µs.

        Returns:
            :math:`(K, 1, H, W)` float32: θ times each pixel's net signed events in ``[start + l, end + l)``.
        """
        lat = latencies.detach().to("cpu", torch.float64).reshape(-1)  # the plan on the CPU, as in _read
        times, (a, b) = _distinct_times(torch.stack([start + lat, end + lat]))
        times, a, b = times.to(self.device), a.to(self.device), b.to(self.device)
        # C(g) counts the events before g: an event counts from the first time after it on (slot G: never)
        slot = self._slots(times).to(torch.int64)
        p = self.num_pixels
        table = torch.zeros((len(times) + 1) * p, dtype=torch.float32, device=self.device).index_add_(
            0, slot * p + self.pixel, self.step.to(torch.float32))
        table = cumsum_(table.view(len(times) + 1, p)[:len(times)], 0)  # event counts: the same sums
        change = table.index_select(0, b).sub_(table.index_select(0, a)).mul_(self.theta)
        return change.view(len(lat), 1, *self.sensor_size)


class _Windows:
    """Sums of interval integrals over windows of sorted times, without the cancellation of a running sum.

    Window ``k`` covers the intervals ``a_k .. b_k − 1``. The intervals are cut into blocks of the shortest
    window's length ``L``, and each block summed forwards and backwards in place; a window is then the backward
    sum from its first interval to the end of that block, plus the forward sum of the block of its last interval
    up to it, plus (rarely) the totals of whole blocks in between. Every sum is of non-negative terms, so
    float32 tables keep float32's relative precision whatever the level's range (a difference of two running
    sums from the first time loses it where the level before the window is much higher than inside it).
    """

    def __init__(self, a: Tensor, b: Tensor, num_times: int, device: torch.device) -> None:
        """``a``, ``b``: the windows' first and end intervals :math:`(K,)` on the CPU; the indices the sums
        take are kept on ``device``, the tables' own."""
        self.block = max(1, int((b - a).min()))
        self.num_blocks = max(1, -(-(num_times - 1) // self.block))
        self.rows = self.num_blocks * self.block
        last = b - 1
        first_block, last_block = a // self.block, last // self.block
        # a window exactly one block long is that block's total: its backward sum at its first interval, or its
        # forward sum at its last; the others need the backward sums of their first blocks and the forward sums of
        # their last. Only those blocks are summed (evenly spaced candidates: half of each)
        whole = first_block == last_block
        parts = ~whole
        backward_blocks = first_block[parts].tolist() if bool(parts.any()) else []
        forward_blocks = last_block[parts].tolist() if backward_blocks else []
        self.backward_range = _block_range(backward_blocks)
        self.forward_range = _block_range(forward_blocks)
        self.whole_forward = self.whole_backward = None
        if bool(whole.any()):
            rows, blocks = torch.nonzero(whole).flatten(), first_block[whole]
            low, high = self.forward_range
            by_forward = (blocks >= low) & (blocks < high)
            if not bool(by_forward.all()):
                self.backward_range = _block_range(backward_blocks + blocks[~by_forward].tolist())
                self.whole_backward = rows[~by_forward].to(device)
            if bool(by_forward.any()):
                self.whole_forward = rows[by_forward].to(device)
        # whole blocks strictly inside window k: first_block + 1 .. last_block − 1 (none for the others)
        inner = first_block + 1
        self.between = ((inner.to(device), torch.maximum(last_block, inner).to(device))
                        if bool((last_block > inner).any()) else None)
        self.first, self.last = _as_rows(a, device), _as_rows(last, device)

    def sums(self, interval: Tensor, backward: Tensor) -> Tensor:
        """Each window's sum :math:`(K, p)` of ``interval`` :math:`(rows, p)`, overwriting it and ``backward``
        (the same shape) with the blocks' forward and backward running sums where they are read."""
        blocks = (self.num_blocks, self.block, -1)
        forward, backward_blocks = interval.view(blocks), backward.view(blocks)
        totals = None
        if self.between is not None:  # whole blocks inside a window: the blocks' totals, summed in float64
            totals = forward.sum(1, dtype=torch.float64)
        low, high = self.backward_range
        if high > low:
            cumsum_(forward[low:high], 1, reverse=True, out=backward_blocks[low:high])
        low, high = self.forward_range
        if high > low:
            cumsum_(forward[low:high], 1)
        # rows of blocks that were not summed hold other values: they are read only where overwritten below
        total = torch.add(backward[self.first], interval[self.last])
        if self.whole_backward is not None:
            total[self.whole_backward] = backward[self.first][self.whole_backward]
        if self.whole_forward is not None:
            total[self.whole_forward] = interval[self.last][self.whole_forward]
        if totals is not None:
            running = torch.cat([torch.zeros_like(totals[:1]), torch.cumsum(totals, 0)])
            lo, hi = self.between
            total += (running[hi] - running[lo]).to(total.dtype)
        return total


def _sampled_rows(r0: int, r1: int, frame_height: int, stride: int, device: torch.device
                  ) -> tuple[slice | Tensor, slice | None]:
    """The rows of a strip ``[r0, r1)`` of frames of ``frame_height`` rows stacked that the peak is read at (every
    ``stride``-th row of each frame), counted from ``r0``: a slice where they are evenly spaced (one frame, or frames
    whose height ``stride`` divides), else their indices on ``device``; and the rows of the peak they fill (a slice;
    None where the strip has none)."""
    local: list[int] = []
    for frame in range(r0 // frame_height, -(-r1 // frame_height)):
        lo, hi = max(r0, frame * frame_height), min(r1, (frame + 1) * frame_height)
        local.extend(range(lo + (frame * frame_height - lo) % stride - r0, hi - r0, stride))
    if not local:
        return slice(0, 0), None
    per_frame = -(-frame_height // stride)

    def place(row: int) -> int:
        return (row // frame_height) * per_frame + (row % frame_height) // stride

    placed = slice(place(r0 + local[0]), place(r0 + local[-1]) + 1)  # consecutive: each frame's follow the last's
    if all(b - a == stride for a, b in zip(local, local[1:])):
        return slice(local[0], local[-1] + 1, stride), placed
    return torch.tensor(local, device=device), placed


def _sampled(rows: Tensor, height: int, sampled: slice | Tensor, stride: int) -> Tensor:
    """The ``sampled`` rows (:func:`_sampled_rows`) and every ``stride``-th column of table rows
    :math:`(K, height·W)`: a view where they are a slice."""
    table = rows.view(rows.shape[0], height, -1)
    return (table[:, sampled] if isinstance(sampled, slice) else table.index_select(1, sampled))[..., ::stride]


def _block_range(blocks: list[int]) -> tuple[int, int]:
    """The blocks ``[low, high)`` from the least to the greatest of ``blocks`` (empty: ``(0, 0)``)."""
    return (min(blocks), max(blocks) + 1) if blocks else (0, 0)


def _as_rows(index: Tensor, device: torch.device) -> slice | Tensor:
    """``index`` (on the CPU) as a slice where it counts up by one (then ``table[index]`` is a view), else as it
    is, on ``device``."""
    if len(index) and bool((index.diff() == 1).all()):
        first = int(index[0])
        return slice(first, first + len(index))
    return index.to(device)


def _distinct_times(points: Tensor) -> tuple[Tensor, Tensor]:
    """The sorted distinct times of ``points`` :math:`(M, K)` and where each point lies among them :math:`(M, K)`.

    Times are rounded to a 1/1024 µs lattice first, so window ends that meet other windows' starts (or
    references) computed two ways are one point.
    """
    points = torch.round(points * _LATTICE) / _LATTICE
    times, index = torch.unique(points.reshape(-1), sorted=True, return_inverse=True)
    return times, index.view(points.shape)
