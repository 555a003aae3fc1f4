"""The Event-based Double Integral (EDI, Pan et al.) with latency (paper Eq. 2-9).

A blurry frame is the mean of the latent image over its exposure ``[s, e]``:
``B = I(f) · mean_{u ∈ [s, e]} exp(θ (C(u) − C(f)))`` with ``C`` the integrated event polarity,
so ``I(f) = B / R(f)``. A latency ``l`` (µs, positive = stamped late) reads ``C`` at ``u + l``
(Eq. 7). ``R`` is accumulated in the log domain (log-sum-exp), so thousands of events at a pixel
cannot overflow, and ``I = B · exp(−log R)`` needs no division (a black pixel stays 0).

The exposure is sampled at ``num_bins + 1`` equally spaced times (trapezoidal rule), on a
grid of the same spacing that also covers the latency range and the reference time.

Memory: the grid and the reads take about ``(grid points · 12 + (num_bins + 1) · 28)`` bytes per
pixel and sample (float32, step integral). Over :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES` the
EDI is computed in strips of rows (the same values up to float rounding); when even one row is over it (e.g. a
reference ``time`` far from the exposure), it is refused with a message saying what to change.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Iterator

import kornia
import torch
from torch import Tensor

from evlatcorr.checks import (
    check_batch_vector,
    check_image,
    check_memory,
    check_shape,
    check_threshold,
    resolve_memory_budget,
)
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.event_grid import (
    EventGrid,
    _check_grid_covers,
    _exposure_times,
    _grid_span,
    _span_advice,
    event_grid,
)
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.integral import _cumulative_event_grid, _row_strips, grid_bytes_per_point, sample_grid

__all__ = [
    "EventGrid",
    "event_grid",
    "latency_map",
    "edi_log_ratio",
    "edi_deblur",
    "edi_interpolate",
    "estimate_threshold",
    "trapezoid_log_weights",
    "grid_reads",
    "latent_from_grid_reads",
]

# Bytes per exposure sample and pixel that reading the grid takes (positions, indices, the two
# values read, their blend and the log-sum-exp's work), in units of the computation dtype's size.
_READ_ITEMS = 7
# exposure samples read from the grid at once by the EDI (bounds its working memory)
_SAMPLE_CHUNK = 64


def latency_map(latency: Tensor | float | None, batch_size: int, sensor_size: tuple[int, int],
                device: torch.device, dtype: torch.dtype = torch.float32) -> Tensor:
    """Broadcast ``None``, a scalar, a :math:`(B,)` vector or a :math:`(B,1,H,W)` map to a map, µs."""
    _check_latency_map(latency, batch_size, sensor_size, device)
    return _latency_map(latency, batch_size, sensor_size, device, dtype)


def _check_latency_map(latency: Tensor | float | None, batch_size: int, sensor_size: tuple[int, int],
                       device: torch.device) -> None:
    if latency is None:
        return
    latency = torch.as_tensor(latency, device=device)
    if latency.dim() == 4:
        check_shape(latency, [batch_size, 1, *sensor_size], "latency")
        if latency.is_floating_point() and not bool(torch.isfinite(latency).all()):
            raise ValueError("latency map has NaN or infinite values")
    else:
        check_batch_vector(latency, batch_size, "latency")


def _latency_map(latency: Tensor | float | None, batch_size: int, sensor_size: tuple[int, int],
                 device: torch.device, dtype: torch.dtype) -> Tensor:
    """:func:`latency_map` of a latency already checked (no data read)."""
    height, width = sensor_size
    if latency is None:
        return torch.zeros(batch_size, 1, height, width, device=device, dtype=dtype)
    latency = torch.as_tensor(latency, device=device)
    if not latency.is_floating_point():
        latency = latency.to(dtype)
    if latency.dim() == 4:
        return latency
    if latency.dim() == 0:
        latency = latency.expand(batch_size)
    return latency.view(batch_size, 1, 1, 1).expand(batch_size, 1, height, width)


def trapezoid_log_weights(num_bins: int, device: torch.device, dtype: torch.dtype) -> Tensor:
    """log of the trapezoidal weights of ``num_bins + 1`` samples, summing to 1."""
    w = torch.full((num_bins + 1,), 1.0 / num_bins, device=device, dtype=dtype)
    w[0] = w[-1] = 0.5 / num_bins
    return w.log()










def edi_log_ratio(
    events: Events,
    exposure_start: Tensor,
    exposure_end: Tensor,
    threshold: float | Tensor,
    latency: Tensor | float | None = None,
    num_bins: int = 500,
    time: Tensor | None = None,
    integral: str = "step",
    dtype: torch.dtype = torch.float32,
    grid: EventGrid | None = None,
    memory_budget: int | None = None,
) -> Tensor:
    """``log R`` of Eq. (5)/(7): the log of the mean event-driven brightness ratio over the exposure.

    Args:
        events, exposure_start, exposure_end, latency, num_bins: as :func:`edi_deblur` (the latency
            differentiably).
        threshold: contrast threshold θ (log-intensity step per event), a float or :math:`(B,)`.
        time: reference time per sample :math:`(B,)` (default: mid-exposure); may lie outside.
        integral: ``"step"`` or ``"linear"`` (see :mod:`evlatcorr.integral`), or ``"continuous"``: the step
            integral exact in continuous time (:mod:`evlatcorr.continuous`; ``num_bins`` unused, one latency
            per sample, not differentiable).
        dtype: computation dtype (float64 for gradcheck).
        grid: a prebuilt :func:`event_grid` of these events, exposures and ``num_bins`` covering the
            latencies read (``integral`` is then the grid's); built here when None.
        memory_budget: bytes the grid and its reads may take when the grid is built here; default
            :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`. Over it the EDI runs in strips of rows.

    Returns:
        :math:`(B, 1, H, W)`; the latent image at ``time`` is ``B · exp(−log R)``.

    Raises:
        ValueError: when even one row of the grid is over the memory budget (e.g. a ``time`` far
            from the exposure); the message gives the span and what to narrow.

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([50.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> log_r = edi_log_ratio(ev, torch.tensor([0.0]), torch.tensor([100.0]), 0.2, num_bins=100,
        ...                       time=torch.tensor([0.0]))
        >>> round(log_r.item(), 3)  # about log(0.5 + 0.5 e^0.2) = 0.105 (the trapezoid rule halves the event's sample)
        0.104
    """
    start, end, ref = _exposure_times(events, exposure_start, exposure_end, num_bins, time)
    _check_latency(latency, events, integral)
    theta = check_threshold(threshold, events.batch_size)
    _check_grid(grid, events, start, end, ref, latency, num_bins, dtype)
    return _edi_log_ratio(events, start, end, ref, theta, latency, num_bins, integral, dtype, grid, memory_budget)


def _edi_log_ratio(events: Events, start: Tensor, end: Tensor, ref: Tensor, theta: Tensor,
                   latency: Tensor | float | None, num_bins: int, integral: str, dtype: torch.dtype,
                   grid: EventGrid | None, memory_budget: int | None) -> Tensor:
    """:func:`edi_log_ratio` of checked inputs: float64 :math:`(B,)` times on the events' device, a positive
    :math:`(B,)` threshold, a latency passed by :func:`_check_latency` and a grid by :func:`_check_grid`."""
    b = events.batch_size
    device = events.device
    if integral == "continuous":
        return _continuous_log_ratio(events, start, end, ref, theta, latency, dtype)
    lat = _latency_map(latency, b, events.sensor_size, device, dtype)
    theta = theta.to(device, dtype).view(b, 1, 1, 1)
    if grid is not None:
        return _log_ratio_on_grid(grid.cum.to(dtype), grid.start, grid.width_us, start, ref, lat, theta, num_bins)
    lat_lo = lat.detach().amin(dim=(1, 2, 3)).to(torch.float64)
    lat_hi = lat.detach().amax(dim=(1, 2, 3)).to(torch.float64)
    g0, width_us, m, t_lo, t_hi = _grid_span(start, end, ref, lat_lo, lat_hi, num_bins)
    height, width = events.sensor_size
    limit = resolve_memory_budget(memory_budget)
    itemsize = torch.empty((), dtype=dtype).element_size()
    # bytes per pixel (all samples): the grid while built, and its reads at the exposure samples
    reads = min(num_bins + 1, _SAMPLE_CHUNK)
    per_pixel = b * ((m + 1) * grid_bytes_per_point(integral, dtype) + reads * _READ_ITEMS * itemsize)
    rows = height if per_pixel * height * width <= limit else limit // (per_pixel * width)
    if rows < 1:
        check_memory(per_pixel * width, f"one row of the EDI (its event grid has {m + 1} points x {width} pixels)",
                     _span_advice(t_lo, t_hi, width_us, "the latency range (or the latency map's spread)"), limit)
    strips = [(0, height, events)] if rows >= height else _row_strips(events, rows)
    out = []
    for r0, r1, sub in strips:  # one strip, the whole sensor, unless over the memory budget
        cum = _cumulative_event_grid(sub, g0, width_us, m, integral, dtype)  # sized by `rows` above
        out.append(_log_ratio_on_grid(cum, g0, width_us, start, ref, lat[:, :, r0:r1], theta, num_bins))
    return out[0] if len(out) == 1 else torch.cat(out, dim=2)


def _continuous_log_ratio(events: Events, start: Tensor, end: Tensor, ref: Tensor, theta: Tensor,
                          latency: Tensor | float | None, dtype: torch.dtype) -> Tensor:
    """``log R`` :math:`(B, 1, H, W)` by the exact continuous-time integral (one checked latency per sample)."""
    b = events.batch_size
    lat = torch.as_tensor(0.0 if latency is None else latency, dtype=torch.float64)
    lat = (lat.expand(b) if lat.dim() == 0 else lat).cpu()
    theta = theta.to(torch.float64).cpu()
    start, end, ref = start.cpu(), end.cpu(), ref.cpu()
    out = []
    for i in range(b):
        exposure = float(end[i] - start[i])
        integral = ContinuousIntegral(events.sample(i), float(theta[i]))
        out.append(integral.log_ratio(float(start[i]), float(end[i]), lat[i:i + 1],
                                      reference=float(ref[i] - start[i]) / exposure))
    return torch.cat(out).to(dtype)


def _log_ratio_on_grid(cum: Tensor, g0: Tensor, width_us: Tensor, start: Tensor, ref: Tensor, lat: Tensor,
                       theta: Tensor, num_bins: int) -> Tensor:
    """log R :math:`(B, 1, h, W)` read from a cumulative grid :math:`(B, M + 1, h, W)` (any strip of rows)."""
    return _log_ratio_of_differences(_grid_differences(cum, g0, width_us, start, ref, lat, num_bins), theta, num_bins)


def _grid_differences(cum: Tensor, g0: Tensor, width_us: Tensor, start: Tensor, ref: Tensor, lat: Tensor,
                      num_bins: int) -> Iterator[Tensor]:
    """What log R reads of the grid, which θ does not change: the count at each of the exposure's ``num_bins + 1``
    samples minus the count at the reference, :math:`(B, n, h, W)` chunks of at most ``_SAMPLE_CHUNK`` samples, made
    as they are read (reading all n + 1 at once held several (B, n + 1, H, W) arrays, over a GB at DAVIS346 size)."""
    b, dtype, device = cum.shape[0], cum.dtype, cum.device
    # fractional grid positions: exposure samples (B, n+1, h, W) and the reference (B, 1, h, W)
    offset = ((start - g0) / width_us).to(dtype).view(b, 1, 1, 1) + lat / width_us.to(dtype).view(b, 1, 1, 1)
    ref_pos = offset + ((ref - start) / width_us).to(dtype).view(b, 1, 1, 1)
    c_ref = sample_grid(cum, ref_pos)
    for j0 in range(0, num_bins + 1, _SAMPLE_CHUNK):
        j = torch.arange(j0, min(j0 + _SAMPLE_CHUNK, num_bins + 1), device=device, dtype=dtype).view(1, -1, 1, 1)
        yield sample_grid(cum, offset + j) - c_ref


def _log_ratio_of_differences(differences: Iterable[Tensor], theta: Tensor, num_bins: int) -> Tensor:
    """log R from :func:`_grid_differences`' chunks (a running log-sum-exp over them); ``theta`` :math:`(B, 1, 1, 1)`
    of their dtype."""
    logw = trapezoid_log_weights(num_bins, theta.device, theta.dtype).view(1, -1, 1, 1)
    parts = [torch.logsumexp(theta * chunk + logw[:, j0:j0 + chunk.shape[1]], dim=1, keepdim=True)
             for j0, chunk in zip(range(0, num_bins + 1, _SAMPLE_CHUNK), differences)]
    return parts[0] if len(parts) == 1 else torch.logsumexp(torch.cat(parts, dim=1), dim=1, keepdim=True)


def grid_reads(blurry: Tensor, events: Events, exposure_start: Tensor, exposure_end: Tensor, grid: EventGrid,
               latency: Tensor | float | None = None, num_bins: int = 500, time: Tensor | None = None) -> list[Tensor]:
    """The part of :func:`edi_deblur` from a prebuilt ``grid`` that the threshold does not change, for
    :func:`latent_from_grid_reads` to finish at any number of thresholds (e.g. a search over θ) without reading the
    grid again. Arguments as :func:`edi_deblur`'s; holds :math:`(B, n + 1, H, W)` values.

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([50.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> blurry, start, end = torch.full((1, 1, 1, 1), 0.5), torch.tensor([0.0]), torch.tensor([100.0])
        >>> grid = event_grid(ev, start, end, 100)
        >>> reads = grid_reads(blurry, ev, start, end, grid, num_bins=100)
        >>> torch.equal(latent_from_grid_reads(blurry, reads, 0.3, 100),
        ...             edi_deblur(blurry, ev, start, end, 0.3, num_bins=100, grid=grid))
        True
    """
    check_image(blurry, "blurry")
    _check_events_match(blurry, events)
    start, end, ref = _exposure_times(events, exposure_start, exposure_end, num_bins, time)
    _check_latency(latency, events, "step")
    dtype = _edi_dtype(blurry)
    _check_grid(grid, events, start, end, ref, latency, num_bins, dtype)
    lat = _latency_map(latency, events.batch_size, events.sensor_size, events.device, dtype)
    return list(_grid_differences(grid.cum.to(dtype), grid.start, grid.width_us, start, ref, lat, num_bins))


def latent_from_grid_reads(blurry: Tensor, reads: list[Tensor], threshold: float | Tensor, num_bins: int) -> Tensor:
    """:func:`edi_deblur`'s latent image from :func:`grid_reads` of the same frames at the threshold θ (a number or
    :math:`(B,)`): the same values as :func:`edi_deblur` with that grid.

    Raises:
        ValueError: for a bad threshold, or ``reads`` not made by :func:`grid_reads` for ``blurry`` with
            ``num_bins`` (chunks of its batch and size holding ``num_bins + 1`` samples in all).
    """
    check_image(blurry, "blurry")
    b, _, height, width = blurry.shape
    if (not reads or any(r.dim() != 4 or (r.shape[0], *r.shape[2:]) != (b, height, width) for r in reads)
            or sum(r.shape[1] for r in reads) != num_bins + 1):
        raise ValueError(f"reads must be grid_reads of {b} frame(s) of {height}x{width} with num_bins={num_bins} "
                         f"({num_bins + 1} samples in all), got {[tuple(r.shape) for r in reads]}")
    theta = check_threshold(threshold, b).to(reads[0].device, reads[0].dtype).view(-1, 1, 1, 1)
    return blurry * torch.exp(-_log_ratio_of_differences(reads, theta, num_bins)).to(blurry.dtype)



def _check_latency(latency: Tensor | float | None, events: Events, integral: str) -> None:
    """A latency the EDI can read: a scalar, :math:`(B,)` or a map (not for ``"continuous"``), finite."""
    b = events.batch_size
    if integral not in ("step", "linear", "continuous"):
        raise ValueError(f"integral must be 'step', 'linear' or 'continuous', got {integral!r}")
    if integral != "continuous":
        _check_latency_map(latency, b, events.sensor_size, events.device)
        return
    if isinstance(latency, Tensor) and latency.numel() not in (1, b):
        raise ValueError("integral='continuous' takes one latency per sample (a scalar or (B,)), not a latency map; "
                         "use integral='step' for maps")
    check_batch_vector(0.0 if latency is None else latency, b, "latency")


def _check_grid(grid: EventGrid | None, events: Events, start: Tensor, end: Tensor, ref: Tensor,
                latency: Tensor | float | None, num_bins: int, dtype: torch.dtype) -> None:
    """A prebuilt grid (when given) must cover every time the EDI reads at ``latency``."""
    if grid is None:
        return
    lat = _latency_map(latency, events.batch_size, events.sensor_size, events.device, dtype).detach()
    lat_lo = lat.amin(dim=(1, 2, 3)).to(torch.float64)
    lat_hi = lat.amax(dim=(1, 2, 3)).to(torch.float64)
    _check_grid_covers(grid, start, end, ref, lat_lo, lat_hi, num_bins)



def edi_deblur(
    blurry: Tensor,
    events: Events,
    exposure_start: Tensor,
    exposure_end: Tensor,
    threshold: float | Tensor | str = 0.2,
    latency: Tensor | float | None = None,
    num_bins: int = 500,
    time: Tensor | None = None,
    integral: str = "step",
    grid: EventGrid | None = None,
    memory_budget: int | None = None,
) -> Tensor:
    """Latent sharp image from a blurry frame and its events (EDI deblurring, Eq. 6/9).

    Args:
        blurry: :math:`(B, C, H, W)` in [0, 1].
        events: a batch of ``B`` samples covering ``[start + l, end + l]``.
        exposure_start: :math:`(B,)` µs.
        exposure_end: :math:`(B,)` µs.
        threshold: contrast threshold θ, or ``"auto"`` to estimate it (:func:`estimate_threshold`).
        latency: µs; scalar, :math:`(B,)` or a map :math:`(B,1,H,W)`; events are read ``latency`` late.
        num_bins: sub-intervals of the exposure (paper: 500).
        time: time of the latent image per sample :math:`(B,)`, µs; default mid-exposure.
        integral: ``"step"`` (classic EDI), ``"linear"`` (Eq. 16-18, smooth in the latency) or
            ``"continuous"`` (the step EDI exact in continuous time, no bins; one latency per sample).
        grid: a prebuilt :func:`event_grid` to read instead of building one (e.g. once per
            test-time fit); it must cover the latencies read.
        memory_budget: bytes the EDI may take (see :func:`edi_log_ratio`); default
            :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`.

    Returns:
        latent image :math:`(B, C, H, W)` (not clipped: over-compensation can exceed 1).

    Raises:
        ValueError: for bad input, or when even one row of the EDI is over the memory budget (e.g.
            a ``time`` far from the exposure).

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([50.0]), torch.tensor([1]),
        ...             sensor_size=(1, 1))
        >>> blurry = torch.full((1, 1, 1, 1), 0.5)
        >>> round(edi_deblur(blurry, ev, torch.tensor([0.0]), torch.tensor([100.0]), threshold=0.2,
        ...                  time=torch.tensor([0.0]), num_bins=100).item(), 4)  # I0 · (0.5 + 0.5 e^0.2) ≈ 0.5
        0.4506
    """
    check_image(blurry, "blurry")
    _check_events_match(blurry, events)
    if isinstance(threshold, str) and threshold != "auto":
        raise ValueError(f"threshold must be a positive number or 'auto', got {threshold!r}")
    start, end, ref = _exposure_times(events, exposure_start, exposure_end, num_bins, time)
    _check_latency(latency, events, integral)
    if isinstance(threshold, str):
        _check_threshold_size(blurry)
        theta = _estimate_threshold(blurry, events, start, end, latency, num_bins)
    else:
        theta = check_threshold(threshold, events.batch_size)
    _check_grid(grid, events, start, end, ref, latency, num_bins, _edi_dtype(blurry))
    return _edi_deblur(blurry, events, start, end, ref, theta, latency, num_bins, integral, grid, memory_budget)


def _edi_dtype(blurry: Tensor) -> torch.dtype:
    return blurry.dtype if blurry.dtype in (torch.float32, torch.float64) else torch.float32


def _edi_deblur(blurry: Tensor, events: Events, start: Tensor, end: Tensor, ref: Tensor, theta: Tensor,
                latency: Tensor | float | None, num_bins: int, integral: str = "step", grid: EventGrid | None = None,
                memory_budget: int | None = None) -> Tensor:
    """:func:`edi_deblur` of checked inputs (see :func:`_edi_log_ratio`); ``theta`` is a number, not "auto"."""
    log_r = _edi_log_ratio(events, start, end, ref, theta, latency, num_bins, integral, _edi_dtype(blurry), grid,
                           memory_budget)
    return blurry * torch.exp(-log_r).to(blurry.dtype)


def edi_interpolate(
    frames: EventFrames,
    times: Tensor,
    threshold: float | Tensor = 0.2,
    latency: Tensor | float | None = None,
    latency_next: Tensor | float | None = None,
    num_bins: int = 500,
    integral: str = "step",
) -> Tensor:
    """Frames at arbitrary times between two blurry frames, using both neighbours (EDI interpolation).

    Each blurry frame gives a latent image at the wanted time (the EDI with that time as its
    reference); the two are blended linearly in time, so a time inside an exposure leans on that
    frame and one midway weighs both equally.

    Args:
        frames: with ``blurry_next``, ``exposure_start_next``, ``exposure_end_next`` and events spanning both.
        times: :math:`(B, T)` or :math:`(B,)` µs.
        threshold: contrast threshold θ.
        latency: latency for the first frame (scalar, :math:`(B,)` or map); uses ``frames.latency`` if None.
        latency_next: latency for the second frame; defaults to ``latency``.
        num_bins: sub-intervals of each exposure.
        integral: ``"step"`` or ``"linear"``.

    Returns:
        :math:`(B, T, C, H, W)`.
    """
    if frames.blurry_next is None:
        raise ValueError("edi_interpolate needs frames.blurry_next (and its exposure) for the second frame")
    times = torch.as_tensor(times, dtype=torch.float64, device=frames.device)
    if times.dim() == 1:
        times = times[:, None]
    check_shape(times, [frames.batch_size, "T"], "times")
    if latency is None:
        latency = frames.latency
    if latency_next is None:
        latency_next = latency
    events = frames.corrected if frames.corrected is not None and latency is None else frames.events
    mid0 = (frames.exposure_start + frames.exposure_end) / 2
    mid1 = (frames.exposure_start_next + frames.exposure_end_next) / 2
    out = []
    for k in range(times.shape[1]):
        t = times[:, k]
        i0 = edi_deblur(frames.blurry, events, frames.exposure_start, frames.exposure_end, threshold, latency,
                        num_bins, t, integral)
        i1 = edi_deblur(frames.blurry_next, events, frames.exposure_start_next, frames.exposure_end_next,
                        threshold, latency_next, num_bins, t, integral)
        w1 = ((t - mid0) / (mid1 - mid0)).clamp(0, 1).to(i0.dtype).view(-1, 1, 1, 1)
        out.append((1 - w1) * i0 + w1 * i1)
    return torch.stack(out, dim=1)


def estimate_threshold(
    blurry: Tensor,
    events: Events,
    exposure_start: Tensor,
    exposure_end: Tensor,
    latency: Tensor | float | None = None,
    num_bins: int = 500,
    bounds: tuple[float, float] = (0.02, 1.0),
    iterations: int = 20,
) -> Tensor:
    """Contrast threshold that makes the EDI latent image sharpest, per sample.

    The energy, in the spirit of Pan et al.'s EDI energy, rewards edges of the latent image
    where the events at the reference time are: it is minus the normalised cross-correlation of
    the latent image's gradient magnitude with the (3x3-smoothed) count of events within
    ``±exposure/40`` of mid-exposure. Too small a θ leaves blur (edges smeared away from the
    events), too large a θ paints ghost edges where the exposure's other events were. The energy
    is minimised by golden-section search over ``log θ`` in ``bounds``.

    Returns:
        θ per sample :math:`(B,)`.
    """
    if not 0 < bounds[0] < bounds[1]:
        raise ValueError(f"bounds must satisfy 0 < low < high, got {bounds}")
    check_image(blurry, "blurry")
    _check_threshold_size(blurry)
    _check_events_match(blurry, events)
    start, end, _ = _exposure_times(events, exposure_start, exposure_end, num_bins, None)
    _check_latency(latency, events, "step")
    return _estimate_threshold(blurry, events, start, end, latency, num_bins, bounds, iterations)


def _check_threshold_size(blurry: Tensor) -> None:
    """The θ estimate's 3x3 filters need frames of at least 2x2 pixels."""
    height, width = blurry.shape[-2:]
    if min(height, width) < 2:
        raise ValueError(f"threshold='auto' needs frames of at least 2x2 pixels (its gradient filters reach a pixel "
                         f"either side), got {height}x{width}; give a number")


def _estimate_threshold(blurry: Tensor, events: Events, start: Tensor, end: Tensor, latency: Tensor | float | None,
                        num_bins: int, bounds: tuple[float, float] = (0.02, 1.0), iterations: int = 20) -> Tensor:
    """:func:`estimate_threshold` of checked inputs: float64 :math:`(B,)` exposure times on the events' device."""
    b = blurry.shape[0]
    corrected = events if latency is None else events.shift(
        latency if torch.as_tensor(latency).dim() != 4 else torch.as_tensor(latency).to(torch.float64))
    mid, half = (start + end) / 2, (end - start) / 40
    near = corrected.window(mid - half, mid + half)
    height, width = events.sensor_size
    activity = torch.zeros(b * height * width, dtype=torch.float32, device=events.device)
    activity.index_add_(0, near.pixel_index(), torch.ones(len(near), device=events.device))
    activity = kornia.filters.box_blur(activity.view(b, 1, height, width), (3, 3))
    activity = activity - activity.mean(dim=(1, 2, 3), keepdim=True)

    def energy(log_theta: Tensor) -> Tensor:
        latent = _edi_deblur(blurry, events, start, end, mid, log_theta.exp(), latency, num_bins)
        grey = kornia.color.rgb_to_grayscale(latent) if latent.shape[1] == 3 else latent
        grad = kornia.filters.spatial_gradient(grey.float(), mode="diff").pow(2).sum(2).sqrt()
        grad = grad - grad.mean(dim=(1, 2, 3), keepdim=True)
        ncc = (grad * activity).sum(dim=(1, 2, 3)) / (grad.flatten(1).norm(dim=1) * activity.flatten(1).norm(dim=1)
                                                      + 1e-12)
        return -ncc.to(torch.float64).cpu()

    dtype = torch.float64
    lo = torch.full((b,), math.log(bounds[0]), dtype=dtype)
    hi = torch.full((b,), math.log(bounds[1]), dtype=dtype)
    ratio = (math.sqrt(5) - 1) / 2
    x1 = hi - ratio * (hi - lo)
    x2 = lo + ratio * (hi - lo)
    f1, f2 = energy(x1), energy(x2)
    for _ in range(iterations):
        left = f1 < f2  # the minimum lies in [lo, x2]: drop (x2, hi]; else drop [lo, x1)
        hi = torch.where(left, x2, hi)
        lo = torch.where(left, lo, x1)
        new_x1 = torch.where(left, hi - ratio * (hi - lo), x2)
        new_x2 = torch.where(left, x1, lo + ratio * (hi - lo))
        f_probe = energy(torch.where(left, new_x1, new_x2))
        f1, f2 = torch.where(left, f_probe, f2), torch.where(left, f1, f_probe)
        x1, x2 = new_x1, new_x2
    return ((lo + hi) / 2).exp().to(blurry.device)


def _check_events_match(blurry: Tensor, events: Events) -> None:
    if not isinstance(events, Events):
        raise ValueError(f"events must be evlatcorr.Events, got {type(events).__name__}")
    if events.batch_size != blurry.shape[0]:
        raise ValueError(f"events have batch_size {events.batch_size} but blurry has {blurry.shape[0]} frames")
    if events.sensor_size != tuple(blurry.shape[-2:]):
        raise ValueError(f"events sensor_size {events.sensor_size} does not match blurry (H, W)="
                         f"{tuple(blurry.shape[-2:])}")
