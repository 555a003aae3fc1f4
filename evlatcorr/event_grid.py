"""The cumulative event grid an EDI reads: built once over a span of latencies, read by every EDI inside it.

:func:`event_grid` integrates a batch's events on a grid aligned to each exposure's sub-intervals (spacing: the
exposure time / ``num_bins``), wide enough for every time an EDI reads (its exposure and reference time, shifted by
the latencies of ``latency_range``), with spare bins on each side. :mod:`evlatcorr.edi` builds one per call, or reads
one given to it: a test-time fit (:mod:`evlatcorr.spatial`) reads the same grid at every step. The grid's size is
checked against the memory budget before it is allocated, and refused with what to narrow.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from evlatcorr.checks import check_batch_vector, check_exposure, check_memory, resolve_memory_budget
from evlatcorr.events import Events
from evlatcorr.integral import _cumulative_event_grid, grid_bytes_per_point

__all__ = ["EventGrid", "event_grid"]


@dataclass(frozen=True)
class EventGrid:
    """The cumulative event integral of a batch on a grid aligned to each exposure's sub-intervals.

    Built once by :func:`event_grid`, it serves every EDI whose reads (exposure and reference time,
    shifted by the latency) fall inside its span: a test-time fit reads the same grid at every step.

    Attributes:
        cum: :math:`(B, M + 1, H, W)` cumulative polarity at the grid boundaries.
        start: time of boundary 0 per sample :math:`(B,)`, µs (float64).
        width_us: grid spacing per sample :math:`(B,)`, µs: the exposure time / ``num_bins``.
        num_bins: sub-intervals of the exposure the grid was built for.
        integral: ``"step"`` or ``"linear"``.
    """

    cum: Tensor
    start: Tensor
    width_us: Tensor
    num_bins: int
    integral: str

    @property
    def end(self) -> Tensor:
        """Time of the last boundary per sample :math:`(B,)`, µs."""
        return self.start + (self.cum.shape[1] - 1) * self.width_us


def event_grid(
    events: Events,
    exposure_start: Tensor,
    exposure_end: Tensor,
    num_bins: int = 500,
    latency_range: tuple[Tensor | float, Tensor | float] = (0.0, 0.0),
    time: Tensor | None = None,
    integral: str = "step",
    dtype: torch.dtype = torch.float32,
    memory_budget: int | None = None,
) -> EventGrid:
    """The cumulative event grid an EDI reads, for any latency in ``latency_range``.

    Args:
        events: a batch of ``B`` samples.
        exposure_start: :math:`(B,)` µs.
        exposure_end: :math:`(B,)` µs.
        num_bins: sub-intervals of the exposure; the grid spacing is the exposure time / ``num_bins``.
        latency_range: lowest and highest latency to be read, µs, scalars or :math:`(B,)`.
        time: reference time per sample :math:`(B,)` (default: mid-exposure).
        integral: ``"step"`` or ``"linear"`` (see :mod:`evlatcorr.integral`).
        dtype: dtype of ``cum``.
        memory_budget: bytes the grid may take while built; default
            :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`.

    Returns:
        the grid, with spare bins on each side of the span read.

    Raises:
        ValueError: when the grid would exceed the memory budget (checked from sizes before allocating);
            the message gives the span and what to narrow.

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([50.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> grid = event_grid(ev, torch.tensor([0.0]), torch.tensor([100.0]), num_bins=10,
        ...                   latency_range=(0.0, 30.0))
        >>> grid.start.item(), grid.end.item()
        (-10.0, 150.0)
    """
    if integral not in ("step", "linear"):
        raise ValueError(f"integral must be 'step' or 'linear', got {integral!r}")
    times = _grid_times(events, exposure_start, exposure_end, num_bins, latency_range, time)
    return _event_grid(events, *times, num_bins, integral, dtype, memory_budget)


def _grid_times(events: Events, exposure_start: Tensor, exposure_end: Tensor, num_bins: int,
                latency_range: tuple[Tensor | float, Tensor | float], time: Tensor | None
                ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Checked float64 :math:`(B,)` exposure start, end, reference time and latency bounds on the events' device."""
    b, device = events.batch_size, events.device
    start, end, ref = _exposure_times(events, exposure_start, exposure_end, num_bins, time)
    lat_lo = check_batch_vector(latency_range[0], b, "latency_range[0]").to(device, torch.float64)
    lat_hi = check_batch_vector(latency_range[1], b, "latency_range[1]").to(device, torch.float64)
    if bool((lat_hi < lat_lo).any()):
        raise ValueError(f"latency_range must be (low, high) with low <= high, got {latency_range}")
    return start, end, ref, lat_lo, lat_hi


def _event_grid(events: Events, start: Tensor, end: Tensor, ref: Tensor, lat_lo: Tensor, lat_hi: Tensor,
                num_bins: int, integral: str, dtype: torch.dtype, memory_budget: int | None) -> EventGrid:
    """:func:`event_grid` of checked float64 :math:`(B,)` times and latency bounds on the events' device."""
    b = events.batch_size
    g0, width_us, m, t_lo, t_hi = _grid_span(start, end, ref, lat_lo, lat_hi, num_bins)
    height, width = events.sensor_size
    limit = resolve_memory_budget(memory_budget)
    need = _grid_bytes(b, m, events.sensor_size, integral, dtype)
    if need > limit:
        check_memory(need, f"the event grid ({b}, {m + 1}, {height}, {width})",
                     _span_advice(t_lo, t_hi, width_us, "latency_range"), limit)
    cum = _cumulative_event_grid(events, g0, width_us, m, integral, dtype)
    return EventGrid(cum, g0, width_us, num_bins, integral)


def _event_grid_bytes(events: Events, start: Tensor, end: Tensor, ref: Tensor, lat_lo: Tensor, lat_hi: Tensor,
                      num_bins: int, integral: str, dtype: torch.dtype) -> int:
    """Estimated peak bytes of :func:`_event_grid` with these checked inputs (nothing is allocated)."""
    m = _grid_span(start, end, ref, lat_lo, lat_hi, num_bins)[2]
    return _grid_bytes(events.batch_size, m, events.sensor_size, integral, dtype)


def _grid_bytes(batch_size: int, num_bins: int, sensor_size: tuple[int, int], integral: str,
                dtype: torch.dtype) -> int:
    return batch_size * (num_bins + 1) * sensor_size[0] * sensor_size[1] * grid_bytes_per_point(integral, dtype)


def _grid_span(start: Tensor, end: Tensor, ref: Tensor, lat_lo: Tensor, lat_hi: Tensor,
               num_bins: int) -> tuple[Tensor, Tensor, int, Tensor, Tensor]:
    """``(g0, width_us, M, t_lo, t_hi)``: the grid aligned to the exposure that spans every time read."""
    width_us = (end - start) / num_bins
    t_lo = torch.minimum(start, ref) + lat_lo
    t_hi = torch.maximum(end, ref) + lat_hi
    # Aligned to the exposure start (not to the latencies), so moving a latency does not move the grid.
    g0 = start + (torch.floor((t_lo - start) / width_us) - 1) * width_us
    m = int(torch.ceil((t_hi - g0) / width_us).max().item()) + 2
    return g0, width_us, m, t_lo, t_hi


def _span_advice(t_lo: Tensor, t_hi: Tensor, width_us: Tensor, latency_name: str) -> str:
    """What to change when a grid over ``[t_lo, t_hi]`` is too large (read only on that error path)."""
    return (f"it spans [{float(t_lo.min()):.0f}, {float(t_hi.max()):.0f}] us (the exposure, the reference time "
            f"and the latencies read) in steps of {float(width_us.min()):.4g} us (exposure time / num_bins): bring "
            f"`time` closer to the exposure, narrow {latency_name}, or use fewer num_bins")


def _exposure_times(events: Events, exposure_start: Tensor, exposure_end: Tensor, num_bins: int,
                    time: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
    """Validated exposure start, end and reference time (default mid-exposure), float64 :math:`(B,)`."""
    b, device = events.batch_size, events.device
    start = check_batch_vector(exposure_start, b, "exposure_start").to(device, torch.float64)
    end = check_batch_vector(exposure_end, b, "exposure_end").to(device, torch.float64)
    check_exposure(start, end)
    if num_bins < 1:
        raise ValueError(f"num_bins must be >= 1, got {num_bins}")
    ref = (start + end) / 2 if time is None else check_batch_vector(time, b, "time").to(device, torch.float64)
    return start, end, ref


def _check_grid_covers(grid: EventGrid, start: Tensor, end: Tensor, ref: Tensor, lat_lo: Tensor, lat_hi: Tensor,
                       num_bins: int) -> None:
    """A prebuilt grid must match the exposure's sub-intervals and span every time read."""
    if grid.num_bins != num_bins or not torch.allclose(grid.width_us, (end - start) / num_bins):
        raise ValueError(f"grid was built for num_bins={grid.num_bins} and other exposures; this EDI needs "
                         f"num_bins={num_bins}")
    t_lo = torch.minimum(start, ref) + lat_lo
    t_hi = torch.maximum(end, ref) + lat_hi
    if bool((t_lo < grid.start).any()) or bool((t_hi > grid.end).any()):
        raise ValueError(f"grid spans [{grid.start.min().item():.1f}, {grid.end.max().item():.1f}] us but this EDI "
                         f"reads [{t_lo.min().item():.1f}, {t_hi.max().item():.1f}] us: build it with a wider "
                         "latency_range")
