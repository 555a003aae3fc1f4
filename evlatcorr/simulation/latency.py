"""Latency models: constant shift, per-pixel intensity-dependent delay, and the low-pass photoreceptor.

``τ = clip(bright / I, bright, dim)`` is the time constant of a pixel of linear intensity ``I``:
``"intensity"`` filters the log intensity with it (the delayed events are the filtered signal's
crossings), ``"intensity_delay"`` shifts each ideal event by it; both report it, from the blurry
frame's luminance, as the true latency.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.simulation.photographs import luminance

__all__ = ["LATENCY_MODELS", "MAX_LATENCY_US", "Photoreceptor", "delay_events", "largest_latency",
           "time_constant", "true_latency_map"]

LATENCY_MODELS = ("none", "constant", "intensity", "intensity_delay")
# Largest latency simulated, µs: the sequence runs this much past its last exposure (memory grows with it).
MAX_LATENCY_US = 1_000_000.0


def largest_latency(model: str, latency_us: float, dim_us: float) -> float:
    """The largest latency ``model`` can give, µs: how long the events must run past the last exposure."""
    return {"none": 0.0, "constant": float(latency_us), "intensity": dim_us, "intensity_delay": dim_us}[model]


def time_constant(lum: Tensor, bright_us: float, dim_us: float) -> Tensor:
    """Photoreceptor time constant ``clip(bright_us / lum, bright_us, dim_us)`` µs of a linear luminance.

    Example:
        >>> time_constant(torch.tensor([1.0, 0.1, 0.0]), 500.0, 10_000.0).tolist()
        [500.0, 5000.0, 10000.0]
    """
    return (bright_us / lum.clamp_min(1e-12)).clamp(bright_us, dim_us)


class Photoreceptor:
    """A first-order low-pass filter of the log intensity whose time constant follows the intensity (v2e, IEBCS).

    Args:
        log_start: the filter's initial level :math:`(H, W)` (its steady state for a still input).
        bright_us: time constant at intensity 1, µs.
        dim_us: longest time constant, µs.
    """

    def __init__(self, log_start: Tensor, bright_us: float, dim_us: float) -> None:
        self.level = log_start.clone()
        self.bright_us, self.dim_us = bright_us, dim_us

    def advance(self, log_prev: Tensor, log_cur: Tensor, lum_prev: Tensor, lum_cur: Tensor, step: float) -> Tensor:
        """Filter an input going linearly from ``log_prev`` to ``log_cur`` over ``step`` µs; returns the new level.

        The update is exact for a linear input; τ is taken at the step's mean luminance.
        """
        tau = time_constant(0.5 * (lum_cur + lum_prev), self.bright_us, self.dim_us)
        slope_tau = (log_cur - log_prev) / step * tau
        self.level = log_cur - slope_tau + (self.level - log_prev + slope_tau) * torch.exp(-step / tau)
        return self.level


def true_latency_map(model: str, blurry: Tensor, latency_us: float, bright_us: float, dim_us: float) -> Tensor:
    """The latency reported as ground truth :math:`(F, 1, H, W)` µs for blurry frames :math:`(F, 3, H, W)`.

    The intensity models report ``τ`` at the luminance averaged over the exposure: the quantity a
    method can estimate from the blurry frame.
    """
    if model in ("intensity", "intensity_delay"):
        return time_constant(luminance(blurry), bright_us, dim_us)
    lat = float(latency_us) if model == "constant" else 0.0
    return torch.full((blurry.shape[0], 1, blurry.shape[-2], blurry.shape[-1]), lat, device=blurry.device)


def delay_events(model: str, signal: Events, true_latency: Tensor, mids: Tensor, latency_us: float) -> Events:
    """The ideal ``signal`` events (one sample, time-sorted) delayed by a non-filtering ``model``.

    Args:
        model: ``"none"``, ``"constant"`` or ``"intensity_delay"`` (``"intensity"`` filters the signal
            itself, see :class:`Photoreceptor`).
        signal: ideal events, without noise.
        true_latency: :math:`(F, 1, H, W)` µs from :func:`true_latency_map`.
        mids: :math:`(F,)` mid-exposure times µs; an event takes the latency of the nearest frame.
        latency_us: the constant latency.
    """
    if model == "intensity_delay":
        return _delay_by_map(signal, true_latency, mids)
    lat = float(latency_us) if model == "constant" else 0.0
    return Events.from_canonical(signal.x, signal.y, signal.t + lat, signal.p, signal.batch, signal.sensor_size, 1)


def _delay_by_map(signal: Events, true_latency: Tensor, mids: Tensor) -> Events:
    """Each event delayed by the latency at its pixel in the frame whose mid-exposure is nearest, re-sorted."""
    sensor = signal.sensor_size
    nearest = torch.searchsorted((mids[1:] + mids[:-1]) / 2, signal.t)
    delay = true_latency[:, 0].flatten(1)[nearest, signal.y * sensor[1] + signal.x].double()
    shifted = Events.from_canonical(signal.x, signal.y, signal.t + delay, signal.p, signal.batch, sensor, 1)
    order = torch.argsort(shifted.t, stable=True)
    return Events.from_canonical(shifted.x[order], shifted.y[order], shifted.t[order], shifted.p[order],
                                 shifted.batch, sensor, 1)
