"""Event binning and the cumulative event integral on a regular time grid.

Everything downstream (EDI, the constant-latency search, the spatial training) reads events
through one object: the cumulative polarity sum ``C`` of each pixel sampled at the boundaries
``g_i = grid_start + i * bin_width`` (i = 0..M) of a regular grid. A latency ``l`` shifts the
times at which ``C`` is read (Eq. 7: the window ``[τ - l, t - l]`` of corrected events is the
window ``[τ, t]`` of stamped events read ``l`` later), so one grid serves every latency.

Two integrals are offered:

- ``"step"``: each event is an impulse at its timestamp (Eq. 3). This is the classic EDI.
- ``"linear"``: each event's polarity is spread uniformly over the interval since the previous
  event at its pixel (Eq. 16-18), so ``C`` is continuous and piecewise linear in time and the
  EDI is differentiable in the latency. For an event with no earlier event at its pixel the
  interval starts at the grid start.

Between grid points ``C`` is read by linear interpolation, which is exact for ``"linear"``
between events and makes both integrals differentiable in ``l`` almost everywhere.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evlatcorr.checks import check_batch_vector, check_memory
from evlatcorr.events import Events

__all__ = ["event_histogram", "cumulative_event_grid", "sample_grid", "grid_bytes_per_point", "cumsum_"]

# Smallest interval (µs) over which the linear integral spreads an event: two events at the same
# pixel and timestamp become (almost) a step instead of a division by zero.
_MIN_SPREAD_US = 1e-3


def cumsum_(table: Tensor, dim: int, reverse: bool = False, out: Tensor | None = None) -> Tensor:
    """Cumulative sum of ``table`` along ``dim``, in place (what :func:`torch.cumsum` gives; with ``reverse``, the
    sums from each slice to the last), or into ``out`` (of ``table``'s shape), leaving ``table`` as it is.

    On a CPU, ``torch.cumsum`` along any dim but the last walks each line with a stride of everything after
    ``dim``; adding each slice to the next is much faster there (over EDI's 500 time bins it took
    ``python benchmarks/run.py``'s EDI stages from 37 s to 21 s). The slices are added in the same order, so the
    sums are the same: bit for bit in float64, and for integer values (event counts) in float32
    (``torch.cumsum`` accumulates float32 in float64, which can round differently on fractional values). The
    loop runs over the slices along ``dim`` (time bins or time points, a few hundred), not over events or
    pixels; elsewhere ``torch.cumsum`` is one kernel.

    Args:
        table: a tensor of at least one dimension.
        dim: the dimension to sum along (negative counts from the end).
        reverse: sum from the last slice towards the first.
        out: where to write the sums (``None``: into ``table``).

    Returns:
        ``out`` (or ``table``), holding the cumulative sum.

    Raises:
        ValueError: when ``table`` is not a tensor with a dimension ``dim``.

    Example:
        >>> cumsum_(torch.tensor([[1.0, 2.0], [3.0, 4.0], [5.0, 6.0]]), 0)
        tensor([[ 1.,  2.],
                [ 4.,  6.],
                [ 9., 12.]])
        >>> cumsum_(torch.tensor([1.0, 2.0, 3.0]), 0, reverse=True)
        tensor([6., 5., 3.])
        >>> table, sums = torch.tensor([1.0, 2.0, 3.0]), torch.empty(3)
        >>> cumsum_(table, 0, out=sums), table
        (tensor([1., 3., 6.]), tensor([1., 2., 3.]))
    """
    if not isinstance(table, Tensor) or table.dim() == 0:
        raise ValueError(f"table must be a tensor of at least one dimension, got "
                         f"{tuple(table.shape) if isinstance(table, Tensor) else type(table).__name__}")
    if not isinstance(dim, int) or not -table.dim() <= dim < table.dim():
        raise ValueError(f"dim must be an int in [{-table.dim()}, {table.dim() - 1}] for a table of shape "
                         f"{tuple(table.shape)}, got {dim!r}")
    if out is None:
        out = table
    elif not isinstance(out, Tensor) or out.shape != table.shape:
        raise ValueError(f"out must be a tensor of table's shape {tuple(table.shape)}, got "
                         f"{tuple(out.shape) if isinstance(out, Tensor) else type(out).__name__}")
    if table.device.type != "cpu":
        if reverse:
            return out.copy_(torch.cumsum(table.flip(dim), dim).flip(dim))
        return out.copy_(torch.cumsum(table, dim))
    slices, sums = table.unbind(dim), out.unbind(dim)
    if reverse:
        slices, sums = slices[::-1], sums[::-1]
    if out is not table:
        sums[0].copy_(slices[0])
    for total, before, after in zip(sums[1:], sums[:-1], slices[1:]):
        torch.add(after, before, out=total)
    return out


def grid_bytes_per_point(integral: str = "step", dtype: torch.dtype = torch.float32) -> int:
    """Approximate peak bytes per grid point and pixel of :func:`cumulative_event_grid`.

    ``"step"``: the histogram, its cumulative sum and the output (3 values of ``dtype``);
    ``"linear"``: four float64 work arrays and the output.

    Example:
        >>> grid_bytes_per_point("step"), grid_bytes_per_point("linear", torch.float64)
        (12, 40)
    """
    itemsize = torch.empty((), dtype=dtype).element_size()
    return 3 * itemsize if integral == "step" else 32 + itemsize


def event_histogram(
    events: Events, start: Tensor | float, end: Tensor | float, num_bins: int = 500, dtype: torch.dtype = torch.float32,
    memory_budget: int | None = None,
) -> Tensor:
    """Sum of polarities per pixel in ``num_bins`` equal temporal bins over ``[start, end)``.

    Args:
        events: a batch of ``B`` samples.
        start: window start per sample :math:`(B,)` or scalar, µs.
        end: window end per sample :math:`(B,)` or scalar, µs.
        num_bins: number of temporal bins (the paper uses 500).
        dtype: output dtype.
        memory_budget: bytes the output may take; default :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`.

    Returns:
        signed event counts :math:`(B, N, H, W)`; events outside the window are dropped.

    Raises:
        ValueError: when the output would exceed the memory budget (checked before allocating).

    Example:
        >>> ev = Events(torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([1.0, 9.0]),
        ...             torch.tensor([1, 0]), sensor_size=(1, 2))
        >>> event_histogram(ev, 0.0, 10.0, num_bins=2)[0, :, 0].tolist()
        [[1.0, 0.0], [0.0, -1.0]]
    """
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    b = events.batch_size
    start = check_batch_vector(start, b, "start").to(events.device, torch.float64)
    end = check_batch_vector(end, b, "end").to(events.device, torch.float64)
    if bool((end <= start).any()):
        raise ValueError("histogram window end must be after its start")
    height, width = events.sensor_size
    itemsize = torch.empty((), dtype=dtype).element_size()
    check_memory(b * num_bins * height * width * itemsize,
                 f"the event histogram ({b}, {num_bins}, {height}, {width})", "use fewer num_bins", memory_budget)
    return _event_histogram(events, start, end, num_bins, dtype)


def _event_histogram(events: Events, start: Tensor, end: Tensor, num_bins: int, dtype: torch.dtype) -> Tensor:
    """:func:`event_histogram` without its checks: ``start`` < ``end`` float64 :math:`(B,)` on the events' device."""
    b = events.batch_size
    height, width = events.sensor_size
    out = torch.zeros(b * num_bins * height * width, dtype=dtype, device=events.device)
    if len(events) == 0:
        return out.view(b, num_bins, height, width)
    s, e = start[events.batch], end[events.batch]
    inside = (events.t >= s) & (events.t < e)
    pos = (events.t - s) / (e - s) * num_bins
    index = pos.floor().long().clamp_(0, num_bins - 1)
    flat = ((events.batch * num_bins + index) * height + events.y) * width + events.x
    out.index_add_(0, flat[inside], events.p[inside].to(dtype))
    return out.view(b, num_bins, height, width)


def cumulative_event_grid(
    events: Events,
    grid_start: Tensor | float,
    bin_width: Tensor | float,
    num_bins: int,
    integral: str = "step",
    dtype: torch.dtype = torch.float32,
    memory_budget: int | None = None,
    max_spread_us: float | None = None,
    next_spread_factor: float | None = None,
) -> Tensor:
    """Cumulative polarity sum of every pixel at the boundaries of a regular time grid.

    Args:
        events: a batch of ``B`` samples (sorted by time within each sample).
        grid_start: time of the first boundary ``g_0`` per sample :math:`(B,)`, µs.
        bin_width: grid spacing per sample :math:`(B,)`, µs, positive.
        num_bins: number of bins ``M``; the grid has ``M + 1`` boundaries.
        integral: ``"step"`` (impulse events, Eq. 3) or ``"linear"`` (Eq. 16-18).
        dtype: output dtype (accumulation is done in float64 for ``"linear"``).
        memory_budget: bytes the computation may take (estimated with :func:`grid_bytes_per_point`);
            default :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`.
        max_spread_us: ``"linear"`` only: the longest interval an event is spread over, µs (None: back to the
            previous event at its pixel, however long ago). An event after a long quiet is where an edge's change
            first crossed the threshold, not the end of a change that lasted since the pixel's last event.
        next_spread_factor: ``"linear"`` only: an event is also spread over no longer than this many times the
            interval to its pixel's next event (None: no such limit). The first event of an edge's burst then
            spreads over about the burst's own interval between events, not over ``max_spread_us``: the change that
            led up to it took about as long as the ones after it.

    Returns:
        :math:`(B, M + 1, H, W)` with ``C[:, 0] = 0``: the polarity integrated from ``g_0`` to ``g_i``.

    Raises:
        ValueError: when the grid would exceed the memory budget (checked before allocating).

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([4.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> cumulative_event_grid(ev, 0.0, 2.0, 4, integral="step")[0, :, 0, 0].tolist()
        [0.0, 0.0, 0.0, 1.0, 1.0]
        >>> cumulative_event_grid(ev, 0.0, 2.0, 4, integral="linear")[0, :, 0, 0].tolist()
        [0.0, 0.5, 1.0, 1.0, 1.0]
        >>> cumulative_event_grid(ev, 0.0, 2.0, 4, integral="linear", max_spread_us=2.0)[0, :, 0, 0].tolist()
        [0.0, 0.0, 1.0, 1.0, 1.0]
    """
    if integral not in ("step", "linear"):
        raise ValueError(f"integral must be 'step' or 'linear', got {integral!r}")
    if max_spread_us is not None and (integral != "linear" or not max_spread_us > 0):
        raise ValueError(f"max_spread_us is a positive interval of the 'linear' integral, got {max_spread_us!r} with "
                         f"integral={integral!r}")
    if next_spread_factor is not None and (integral != "linear" or not next_spread_factor > 0):
        raise ValueError(f"next_spread_factor is a positive factor of the 'linear' integral, got "
                         f"{next_spread_factor!r} with integral={integral!r}")
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    b = events.batch_size
    g0 = check_batch_vector(grid_start, b, "grid_start").to(events.device, torch.float64)
    width_us = check_batch_vector(bin_width, b, "bin_width").to(events.device, torch.float64)
    if bool((width_us <= 0).any()):
        raise ValueError(f"bin_width must be positive, got {width_us.min().item()}")
    height, width = events.sensor_size
    check_memory(b * (num_bins + 1) * height * width * grid_bytes_per_point(integral, dtype),
                 f"the cumulative event grid ({b}, {num_bins + 1}, {height}, {width})",
                 "use fewer num_bins or a shorter time span (num_bins x bin_width)", memory_budget)
    return _cumulative_event_grid(events, g0, width_us, num_bins, integral, dtype, max_spread_us, next_spread_factor)


def _cumulative_event_grid(events: Events, g0: Tensor, width_us: Tensor, num_bins: int, integral: str,
                           dtype: torch.dtype, max_spread_us: float | None = None,
                           next_spread_factor: float | None = None) -> Tensor:
    """:func:`cumulative_event_grid` without its checks (nor the memory budget's: the caller sized the grid).

    ``g0`` and ``width_us`` (positive) are float64 :math:`(B,)` on the events' device.
    """
    if integral == "step":
        # the histogram is a third of the grid's bytes: within the budget the grid was checked against
        hist = _event_histogram(events, g0, g0 + num_bins * width_us, num_bins, dtype)
        b, _, height, width = hist.shape
        cum = hist.new_zeros((b, num_bins + 1, height, width))
        cum[:, 1:] = hist  # summed in its place: two grid-sized arrays at a time, not three
        del hist
        cumsum_(cum[:, 1:], 1)
        return cum
    return _linear_grid(events, g0, width_us, num_bins, max_spread_us, next_spread_factor).to(dtype)


def _linear_grid(events: Events, g0: Tensor, width_us: Tensor, num_bins: int,
                 max_spread_us: float | None = None, next_spread_factor: float | None = None) -> Tensor:
    """Piecewise-linear integral at grid points, exactly, via slope breakpoints.

    Event k spreads ``σ_k`` over ``(a_k, t_k]`` with slope ``c_k = σ_k / (t_k - a_k)``; the
    integral is ``C(g) = Σ_{breakpoints q < g} c_q (g - q)`` with ``+c_k`` at ``a_k`` and ``-c_k`` at
    ``t_k``. Two scatter-adds of ``c`` and ``c·q`` into the grid slots and two cumulative sums give
    ``C`` at every boundary in O(N + M·H·W).
    """
    b = events.batch_size
    height, width = events.sensor_size
    m1 = num_bins + 1
    device = events.device
    s1 = torch.zeros(b * m1 * height * width, dtype=torch.float64, device=device)
    s2 = torch.zeros_like(s1)
    if len(events):
        pix = events.pixel_index()
        # previous event at the same pixel: sort by pixel (stable keeps time order inside a pixel)
        order = torch.argsort(pix, stable=True)
        pix_sorted = pix[order]
        t_rel = (events.t - g0[events.batch]) / width_us[events.batch]  # in bins, relative to g_0
        t_sorted = t_rel[order]
        prev = torch.zeros_like(t_sorted)  # grid start for the first event of a pixel
        same = pix_sorted[1:] == pix_sorted[:-1]
        prev[1:] = torch.where(same, t_sorted[:-1], prev[1:])
        first = torch.ones_like(t_sorted, dtype=torch.bool)
        first[1:] = ~same
        # an event before the grid start with no predecessor becomes a step at its timestamp
        prev = torch.where(first & (t_sorted <= 0), t_sorted - _MIN_SPREAD_US / width_us[events.batch[order]], prev)
        min_spread = _MIN_SPREAD_US / width_us[events.batch[order]]
        if max_spread_us is not None:
            prev = torch.maximum(prev, t_sorted - max_spread_us / width_us[events.batch[order]])
        if next_spread_factor is not None:  # a few times the interval to the pixel's next event (none after its last)
            after = torch.full_like(t_sorted, math.inf)
            after[:-1] = torch.where(same, t_sorted[1:] - t_sorted[:-1], math.inf)
            prev = torch.maximum(prev, t_sorted - next_spread_factor * after)
        prev = torch.minimum(prev, t_sorted - min_spread)
        slope = events.p[order].to(torch.float64) / (t_sorted - prev)
        # breakpoints: +slope at prev, -slope at t
        q = torch.cat([prev, t_sorted])
        c = torch.cat([slope, -slope])
        pix2 = torch.cat([pix_sorted, pix_sorted])
        slot = (q.floor() + 1).clamp_(min=0)
        keep = slot <= num_bins
        slot = slot.long()
        bidx = pix2 // (height * width)
        flat = (bidx * m1 + slot) * (height * width) + pix2 % (height * width)
        s1.index_add_(0, flat[keep], c[keep])
        s2.index_add_(0, flat[keep], (c * q)[keep])
    s1 = cumsum_(s1.view(b, m1, height, width), 1)
    s2 = cumsum_(s2.view(b, m1, height, width), 1)
    grid = torch.arange(m1, dtype=torch.float64, device=device).view(1, m1, 1, 1)
    cum = s1.mul_(grid).sub_(s2)  # in place: no third grid-sized array
    del s2
    return cum.sub_(cum[:, :1].clone())


def _row_strips(events: Events, rows: int) -> list[tuple[int, int, Events]]:
    """The events split into strips of ``rows`` sensor rows: ``(first row, end row, events)`` per strip.

    Each strip's events keep their sample index and are in the strip's own coordinates (``y - first
    row``); within a pixel they keep their order. One sort by row, then contiguous slices.
    """
    height, width = events.sensor_size
    order = torch.argsort(events.y, stable=True)
    ys = events.y[order]
    bounds = torch.searchsorted(ys, torch.arange(0, height + rows, rows, device=ys.device).clamp_(max=height)).tolist()
    strips = []
    for k, r0 in enumerate(range(0, height, rows)):
        r1 = min(height, r0 + rows)
        idx = order[bounds[k]:bounds[k + 1]]
        strips.append((r0, r1, Events.from_canonical(events.x[idx], events.y[idx] - r0, events.t[idx], events.p[idx],
                                                     events.batch[idx], (r1 - r0, width), events.batch_size)))
    return strips


def sample_grid(cum: Tensor, position: Tensor) -> Tensor:
    """Read a cumulative grid at fractional positions, linearly interpolated (differentiable).

    Args:
        cum: grid values :math:`(B, M + 1, H, W)`.
        position: fractional grid indices :math:`(B, K, H, W)` (or broadcastable), clamped to [0, M].

    Returns:
        values :math:`(B, K, H, W)`.
    """
    m = cum.shape[1] - 1
    position = position.clamp(0, m)
    lo = position.detach().floor().clamp_(max=max(m - 1, 0))
    frac = position - lo
    lo = lo.long()
    shape = (cum.shape[0], position.shape[1], cum.shape[2], cum.shape[3])
    lo = lo.expand(shape)
    frac = frac.expand(shape)
    v0 = torch.gather(cum, 1, lo)
    if m == 0:
        return v0
    v1 = torch.gather(cum, 1, lo + 1)
    return v0 + frac * (v1 - v0)
