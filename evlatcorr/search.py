"""Constant-latency search in one pass over the events (paper Sec. 3.3, ``l_const``).

For a latency ``l = dΔ`` that is a whole number ``d`` of sub-intervals ``Δ = T / n`` the EDI
reads the stamped events' cumulative sum ``C`` at grid points ``d .. d + n`` (Eq. 7), so

    R_d = mean_j exp(θ (C[d + j] − C[d + n/2]))  =  (P[d + n + 1] − P[d] − ½(Y_d + Y_{d+n})) / n / Y_{d+n/2}

with ``Y = exp(θC − max θC)`` and ``P`` its prefix sum (trapezoidal rule, log domain). One
histogram of the events and one cumulative sum serve every candidate in O(1) per pixel, and the
ETF of all candidates is one batched call. The best candidate is refined at every sub-interval
around it, then to below a sub-interval by a parabola through the three best ETF values.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import kornia
import torch
from torch import Tensor

from evlatcorr.checks import check_batch_vector, check_exposure, check_image
from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW, etf_loss
from evlatcorr.events import Events
from evlatcorr.integral import cumulative_event_grid

__all__ = ["ConstantSearchResult", "search_constant_latency", "default_search_range"]

# Memory bound of one strip of the prefix-sum table (float64), in elements.
_STRIP_ELEMENTS = 4_000_000


@dataclass
class ConstantSearchResult:
    """Result of :func:`search_constant_latency`.

    Attributes:
        latency: best constant latency per sample :math:`(B,)`, µs.
        candidates: coarse candidate latencies :math:`(B, K)`, µs.
        etf: ETF of the coarse candidates :math:`(B, K)` (the paper's Fig. 2b curve).
        fine_candidates: list per sample of the refined candidates, µs.
        fine_etf: list per sample of their ETF values.
    """

    latency: Tensor
    candidates: Tensor
    etf: Tensor
    fine_candidates: list[Tensor]
    fine_etf: list[Tensor]


def default_search_range(exposure_time: Tensor) -> tuple[Tensor, Tensor]:
    """Default latency search range per sample: 0 to the exposure time, µs."""
    return torch.zeros_like(exposure_time), exposure_time.clone()


def search_constant_latency(
    blurry: Tensor,
    events: Events,
    exposure_start: Tensor,
    exposure_end: Tensor,
    threshold: float | Tensor = 0.2,
    num_bins: int = 500,
    search_range: tuple[float, float] | None = None,
    num_candidates: int = 100,
    refine: bool = True,
    previous_latency: Tensor | None = None,
    epsilon: float = DEFAULT_EPSILON,
    window: int = DEFAULT_WINDOW,
    sigma_us: float = DEFAULT_SIGMA_US,
    integral: str = "step",
) -> ConstantSearchResult:
    """Find the constant latency per sample that minimises the ETF of the EDI latent image.

    Args:
        blurry: :math:`(B, C, H, W)` in [0, 1].
        events: events of each sample; they must reach ``exposure_end + search_range[1]``.
        exposure_start: :math:`(B,)` µs.
        exposure_end: :math:`(B,)` µs.
        threshold: contrast threshold θ, float or :math:`(B,)`.
        num_bins: sub-intervals of the exposure ``n`` (paper: 500); candidates are whole sub-intervals.
        search_range: ``(low, high)`` µs; default ``(0, exposure time)`` per sample.
        num_candidates: number of coarse candidates over the range (default 100).
        refine: search every sub-interval around the best candidate, then fit a parabola.
        previous_latency: ``l'`` :math:`(B,)` µs for the temporal term ``g``; None drops it.
        epsilon: ETF edge amplifier.
        window: ETF contrast window.
        sigma_us: σ of the temporal prior, µs.
        integral: ``"step"`` (impulse events) or ``"linear"`` (each event spread since the previous one
            at its pixel, Eq. 16-18; see :mod:`evlatcorr.integral`).

    Returns:
        a :class:`ConstantSearchResult`.
    """
    check_image(blurry, "blurry")
    b = blurry.shape[0]
    if events.batch_size != b:
        raise ValueError(f"events have batch_size {events.batch_size} but blurry has {b} frames")
    if events.sensor_size != tuple(blurry.shape[-2:]):
        raise ValueError(f"events sensor_size {events.sensor_size} does not match blurry {tuple(blurry.shape[-2:])}")
    start = check_batch_vector(exposure_start, b, "exposure_start").to(events.device, torch.float64)
    end = check_batch_vector(exposure_end, b, "exposure_end").to(events.device, torch.float64)
    check_exposure(start, end)
    if num_candidates < 2:
        raise ValueError(f"num_candidates must be >= 2, got {num_candidates}")
    if num_bins < 2:
        raise ValueError(f"num_bins must be >= 2, got {num_bins}")
    theta = check_batch_vector(threshold, b, "threshold").to(torch.float64)
    if bool((theta <= 0).any()):
        raise ValueError(f"threshold must be positive, got {theta.min().item()}")
    if search_range is None:
        lows, highs = default_search_range(end - start)
    else:
        lo, hi = float(search_range[0]), float(search_range[1])
        if not hi > lo:
            raise ValueError(f"search_range must be (low, high) with high > low, got {search_range}")
        lows, highs = torch.full_like(start, lo), torch.full_like(start, hi)
    prev = None if previous_latency is None else check_batch_vector(previous_latency, b, "previous_latency")

    grey = kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry
    results = []
    for i in range(b):
        ev = events.sample(i)
        results.append(_search_one(
            grey[i:i + 1], ev, float(start[i]), float(end[i]), float(theta[i]), num_bins,
            float(lows[i]), float(highs[i]), num_candidates, refine,
            None if prev is None else prev[i:i + 1], epsilon, window, sigma_us, integral,
        ))
    return ConstantSearchResult(
        latency=torch.tensor([r[0] for r in results], dtype=torch.float64, device=blurry.device),
        candidates=torch.stack([r[1] for r in results]).to(blurry.device),
        etf=torch.stack([r[2] for r in results]).to(blurry.device),
        fine_candidates=[r[3] for r in results],
        fine_etf=[r[4] for r in results],
    )


def _search_one(grey: Tensor, events: Events, start: float, end: float, theta: float, n: int,
                low: float, high: float, num_candidates: int, refine: bool, prev: Tensor | None,
                epsilon: float, window: int, sigma_us: float,
                integral: str) -> tuple[float, Tensor, Tensor, Tensor, Tensor]:
    """Search for one sample; ``grey`` is :math:`(1, 1, H, W)`."""
    width_us = (end - start) / n
    step = max(1, round((high - low) / (num_candidates - 1) / width_us))  # candidate spacing in sub-intervals
    first = math.floor(low / width_us)
    num = max(2, math.ceil((high - low) / (step * width_us) - 1e-9) + 1)
    span = (num - 1) * step  # shifts 0..span (in sub-intervals, from the first candidate)
    grid_start = start + first * width_us
    table = _ShiftTable(events, grid_start, width_us, n, span, theta, integral)

    def etf_of(shifts: Tensor) -> Tensor:
        lat = (first + shifts).to(torch.float64) * width_us
        log_r = table.log_ratio(shifts)  # (K, 1, H, W), latent at mid-exposure
        latent = grey.to(log_r.dtype) * torch.exp(-log_r)
        return etf_loss(latent.float(), lat.float(), None if prev is None else prev.expand(len(shifts)).float(),
                        epsilon, window, sigma_us).double().cpu()

    coarse = torch.arange(num, device=events.device) * step
    coarse_etf = etf_of(coarse)
    best = int(coarse[int(torch.argmin(coarse_etf))])
    fine, fine_etf = coarse, coarse_etf
    offset = 0.0
    if refine:
        fine = torch.arange(max(0, best - step), min(span, best + step) + 1, device=events.device)
        fine_etf = etf_of(fine)
        k = int(torch.argmin(fine_etf))
        best = int(fine[k])
        if 0 < k < len(fine) - 1:
            f_m, f_0, f_p = (float(v) for v in fine_etf[k - 1:k + 2])
            curvature = f_m - 2 * f_0 + f_p
            if curvature > 0:
                offset = max(-0.5, min(0.5, 0.5 * (f_m - f_p) / curvature))
    latency = (first + best + offset) * width_us
    to_us = lambda s: (first + s).to(torch.float64).cpu() * width_us  # noqa: E731
    return latency, to_us(coarse), coarse_etf, to_us(fine), fine_etf


class _ShiftTable:
    """log R for whole-sub-interval shifts, from one prefix-sum table per strip of rows."""

    def __init__(self, events: Events, grid_start: float, width_us: float, n: int, span: int, theta: float,
                 integral: str = "step"):
        self.n, self.theta = n, theta
        height, width = events.sensor_size
        num_bins = n + span
        budget = _STRIP_ELEMENTS * (16 if events.device.type == "cuda" else 1)
        rows = max(1, min(height, budget // ((num_bins + 2) * width)))
        self.strips = []
        # events ordered by row once, so each strip is a contiguous slice (not a mask over all events)
        order = torch.argsort(events.y, stable=True)
        ys = events.y[order]
        bounds = torch.searchsorted(ys, torch.arange(0, height + rows, rows, device=ys.device).clamp_(max=height))
        for k, r0 in enumerate(range(0, height, rows)):
            r1 = min(height, r0 + rows)
            idx = order[int(bounds[k]):int(bounds[k + 1])]
            sub = Events._trusted(events.x[idx], events.y[idx] - r0, events.t[idx], events.p[idx],
                                  events.batch[idx], (r1 - r0, width), 1)
            cum = cumulative_event_grid(sub, grid_start, width_us, num_bins, integral)[0]  # (M+1, h, W)
            x = theta * cum.double()
            peak = x.amax(0, keepdim=True)
            y = torch.exp(x - peak)
            prefix = torch.cat([torch.zeros_like(y[:1]), y.cumsum(0)])
            self.strips.append((x, peak, y, prefix))

    def log_ratio(self, shifts: Tensor, reference: float = 0.5) -> Tensor:
        """log R for each shift, latent at ``start + reference * exposure`` (0.5 = mid-exposure)."""
        n = self.n
        r_lo, r_hi = math.floor(reference * n), math.ceil(reference * n)
        w_hi = reference * n - r_lo
        out = []
        for x, peak, y, prefix in self.strips:
            total = prefix[shifts + n + 1] - prefix[shifts] - 0.5 * (y[shifts] + y[shifts + n])
            total = total.clamp_min(1e-300) / n
            ref = (1 - w_hi) * x[shifts + r_lo] + w_hi * x[shifts + r_hi]
            out.append(torch.log(total) + peak - ref)
        return torch.cat(out, dim=1)[:, None]  # (K, 1, H, W)
