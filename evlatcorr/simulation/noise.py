"""Sensor non-idealities shared by both streams: shot noise, leak events, and the refractory period.

Noise events are (flat pixel, t, p) triples of tensors, merged undelayed into the ideal and the
delayed streams alike, so the two streams differ only by the latency.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evlatcorr.events import Events

__all__ = ["NoiseEvents", "apply_refractory", "background_noise", "leak_events", "merge_noise", "shot_noise"]

NoiseEvents = tuple[Tensor, Tensor, Tensor]  # (flat pixel, t µs float64, p int8)

_LEAK_SPREAD = 0.5  # std of log(rate) of the per-pixel leak rates


def shot_noise(height: int, width: int, t_end: float, rate_hz: float, g: torch.Generator) -> NoiseEvents:
    """Shot-noise events in ``[0, t_end)``: a Poisson number at ``rate_hz`` per pixel; uniform pixels, times, signs."""
    mean = torch.tensor(float(rate_hz) * t_end * 1e-6 * height * width, dtype=torch.float64)
    n = int(torch.poisson(mean, generator=g))
    return (torch.randint(0, height * width, (n,), generator=g),
            torch.rand(n, generator=g, dtype=torch.float64) * t_end,
            (torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8))


def leak_events(height: int, width: int, t_end: float, rate_hz: float, g: torch.Generator) -> NoiseEvents:
    """Leak events (flat pixel, t, p = +1) in ``[0, t_end)``: per-pixel periodic at a lognormal rate, random phase."""
    n_pix = height * width
    rates = float(rate_hz) * torch.exp(_LEAK_SPREAD * torch.randn(n_pix, generator=g, dtype=torch.float64)
                                       - _LEAK_SPREAD**2 / 2)  # Hz, mean rate_hz
    period = 1e6 / rates  # µs
    first = torch.rand(n_pix, generator=g, dtype=torch.float64) * period
    count = torch.where(first < t_end, torch.floor((t_end - first) / period) + 1, torch.zeros_like(first)).long()
    pix = torch.repeat_interleave(torch.arange(n_pix), count)
    k = torch.arange(pix.numel()) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    t = first[pix] + k.double() * period[pix]
    t = t.clamp_max(math.nextafter(t_end, 0.0))  # rounding
    return pix, t, torch.ones(pix.numel(), dtype=torch.int8)


def background_noise(height: int, width: int, t_end: float, noise_rate_hz: float, leak_rate_hz: float,
                     g: torch.Generator, device: torch.device) -> NoiseEvents | None:
    """Shot noise then leak events on ``device`` (``None`` when both rates are 0; drawn in this order from ``g``).

    Example:
        >>> noise = background_noise(4, 5, 1e6, 0.0, 1.0, torch.Generator().manual_seed(0), torch.device("cpu"))
        >>> bool((noise[2] == 1).all())
        True
    """
    noise = None
    if noise_rate_hz > 0:
        noise = tuple(v.to(device) for v in shot_noise(height, width, t_end, noise_rate_hz, g))
    if leak_rate_hz > 0:
        leak = tuple(v.to(device) for v in leak_events(height, width, t_end, leak_rate_hz, g))
        noise = leak if noise is None else tuple(torch.cat([a, b]) for a, b in zip(noise, leak))
    return noise


def merge_noise(signal: Events, noise: NoiseEvents | None) -> Events:
    """Signal events plus (flat pixel, t, p) noise events, time-sorted, one sample."""
    if noise is None or noise[0].numel() == 0:
        return signal
    width = signal.sensor_size[1]
    pix = torch.cat([signal.y * width + signal.x, noise[0]])
    t = torch.cat([signal.t, noise[1]])
    p = torch.cat([signal.p, noise[2]])
    order = torch.argsort(t, stable=True)
    pix, t, p = pix[order], t[order], p[order]
    return Events.from_canonical(pix % width, pix // width, t, p, torch.zeros_like(pix), signal.sensor_size, 1)


def apply_refractory(events: Events, refractory_us: float) -> Events:
    """Drop each event whose pixel had an event less than ``refractory_us`` before it (a vectorised dead time).

    The previous event counts whether it was kept or dropped, so this drops at least as many events
    as a true dead time after each *kept* event (a pixel firing steadily faster than 1 /
    ``refractory_us`` keeps only its first event), and kept events of a pixel are always at least
    ``refractory_us`` apart. The change that happens during the dead time is lost, not emitted late.

    Args:
        events: events of one or more samples (pixels are per sample), time-sorted within each.
        refractory_us: dead time, µs (≥ 0; 0 keeps everything).

    Returns:
        the kept events, in their order.

    Example:
        >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([0.0, 50.0, 300.0]), torch.ones(3),
        ...             sensor_size=(1, 1))
        >>> apply_refractory(ev, 100.0).t.tolist()
        [0.0, 300.0]
    """
    refractory_us = float(refractory_us)
    if not (math.isfinite(refractory_us) and refractory_us >= 0):
        raise ValueError(f"refractory_us must be >= 0, got {refractory_us}")
    if refractory_us == 0 or len(events) < 2:
        return events
    pix = events.pixel_index()
    order = torch.argsort(pix, stable=True)  # by pixel, in time order within each pixel
    pix_o, t_o = pix[order], events.t[order]
    close = (pix_o[1:] == pix_o[:-1]) & (t_o[1:] - t_o[:-1] < refractory_us)
    keep = torch.ones_like(pix, dtype=torch.bool)
    keep[order[1:][close]] = False
    return events.select(keep)
