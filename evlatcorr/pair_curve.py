"""A latency that grows as pixels dim, fitted to two frames' agreement: ``ψ(L) = a + b · f(L)``.

Spatial mode's sharpness scores do not prefer the true latency map (``docs/accuracy.md``, "Constant or spatial?").
Two consecutive frames' agreement does, pixel by pixel: a pixel's EDI latent depends on its own events alone, so
its disagreement between the two frames at a latency (:func:`evlatcorr.pair_evidence.pair_disagreement_maps`) is
its own, and a map's disagreement is the mean over the pixels of each one's at its latency. Here the map is the
paper's polynomial of intensity cut to its first order, ``ψ(L) = a + b · f(L)`` (``f`` of
:class:`~evlatcorr.spatial.PolynomialLatency`: 0 for white, 1 for black), with ``b ≥ 0`` (dim pixels later), and
``(a, b)`` the grid point whose map the pairs agree on best. Two numbers, not a latency per region: fitted freely,
brightness bands wandered by milliseconds on dark scenes (``docs/estimator.md``). Unless the best slope lowers the
disagreement by ``min_gain`` (relative) below the best single latency, the slope is 0.

The result is a :class:`~evlatcorr.spatial.PolynomialLatency` of order 1: save it with
:func:`~evlatcorr.spatial.save_curve` and ``EventLatencyCorrector(mode="spatial", curve=path)`` applies it to every
frame. ``python benchmarks/pair_curve.py`` measures it on the accuracy suite.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch
from torch import Tensor

from evlatcorr.blank_frames import blank_pairs
from evlatcorr.checks import check_threshold
from evlatcorr.frames import EventFrames
from evlatcorr.pair_evidence import DEFAULT_RAMP_NEXT_FACTOR, DEFAULT_RAMP_US, pair_disagreement_maps
from evlatcorr.spatial import PolynomialLatency

__all__ = ["DEFAULT_MIN_GAIN", "DEFAULT_THRESHOLD_SCALES", "PairCurve", "fit_pair_curve", "pair_curve_table"]

#: the least relative drop of the pairs' mean disagreement, below the best single latency, that a slope must earn
#: (chosen on the accuracy suite's tuning cases, ``docs/estimator.md``: with no bar a slope was taken on 15 of 79
#: constant-latency cases, at 0.2 % on 2, one of them costing 2 dB at 0.54 %; at 1 % on none, and on 7 of the 40
#: per-pixel delay cases)
DEFAULT_MIN_GAIN = 0.01
#: multiples of the given θ at which a slope must hold too, where the pairs agree better there without one
#: (:func:`fit_pair_curve`): the recording's θ estimate is off by more than 30 % on about a tenth of the suite's
#: recordings where θ matters (``docs/threshold.md``)
DEFAULT_THRESHOLD_SCALES = (1 / 1.4, 1 / 1.2, 1.2, 1.4)
_STEPS = 80  # candidate offsets over the latency range (250 µs at a 20 ms exposure)


@dataclass
class PairCurve:
    """What :func:`fit_pair_curve` found.

    Attributes:
        curve: ``ψ(L) = offset_us + slope_us · f(L)`` as a :class:`~evlatcorr.spatial.PolynomialLatency` of order 1.
        offset_us: ``a``, the latency of white pixels, µs.
        slope_us: ``b``, how much later black pixels are, µs (0: one latency for all).
        gain: the relative drop of the pairs' mean disagreement (geometric mean over the pairs) at the best slope,
            below the best single latency; the slope is kept only above ``min_gain``.
        pairs_used: pairs that told something (not blank, events past the second exposure).
        single_latency_us: the best single latency on the same grid (the pairs' agreement alone, as
            :func:`~evlatcorr.pair_evidence.pair_log_odds` reads it), what ``offset_us`` is without a slope.
    """

    curve: PolynomialLatency
    offset_us: float
    slope_us: float
    gain: float
    pairs_used: int
    single_latency_us: float

    def departure(self, blurry: Tensor) -> Tensor:
        """Each pixel's latency less the single latency, µs :math:`(B, 1, H, W)`: what to add to a frame's constant
        latency (the corrector's, which also reads the frame's sharpness) for the curve's spread over intensities."""
        f = self.curve.transform(PolynomialLatency.intensity(blurry.detach()))  # exactly 0 without a slope
        return (self.offset_us - self.single_latency_us) + self.slope_us * f


def pair_curve_table(pair: EventFrames, threshold: float, offsets: Tensor, slopes: Tensor,
                     max_spread_us: float = DEFAULT_RAMP_US,
                     next_spread_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> Tensor:
    """The pair's mean disagreement under the map ``offsets[k] + slopes[s] · f(L)`` of the first frame's intensity:
    :math:`(S, K)` float64, ``inf`` where a pixel's latency would need events past the pair's last one.

    Each pixel's disagreement is read between the candidate offsets linearly (:func:`pair_disagreement_maps` at
    ``offsets``, which must be evenly spaced from 0).

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pair = simulate("camera", num_frames=2, height=24, width=32, latency_us=3000.0, seed=0).pairs()
        >>> table = pair_curve_table(pair, 0.2, torch.arange(0.0, 8001.0, 500.0), torch.tensor([0.0, 2000.0]))
        >>> table.shape, int(table[0].argmin()) * 500
        (torch.Size([2, 17]), 3000)
    """
    _check_grid(offsets, "offsets")
    _check_grid(slopes, "slopes")
    if pair.batch_size != 1 or pair.blurry_next is None:
        raise ValueError("pair_curve_table reads one pair of frames (B = 1, with blurry_next)")
    offsets = offsets.detach().to("cpu", torch.float64)
    slopes = slopes.detach().to("cpu", torch.float64)
    out = torch.full((len(slopes), len(offsets)), math.inf, dtype=torch.float64)
    if len(pair.events) == 0:
        return out
    reach = float(pair.events.t.max() - pair.exposure_end_next[0])  # a window never runs past the last event
    readable = int((offsets <= reach).sum())
    if readable < 2:
        return out
    maps = pair_disagreement_maps(pair, threshold, offsets[:readable], max_spread_us,
                                  next_spread_factor=next_spread_factor).flatten(1).double().cpu()
    f = PolynomialLatency(order=1).transform(PolynomialLatency.intensity(pair.blurry)).flatten().double().cpu()
    varying = maps.amax(0) > maps.amin(0)  # a pixel without events has one disagreement at every latency
    still = float(maps[0, ~varying].sum())
    maps, f, pixels = maps[:, varying], f[varying], maps.shape[1]
    step = float(offsets[1] - offsets[0]) if len(offsets) > 1 else 1.0
    start = torch.arange(readable, dtype=torch.float64)[:, None]
    for s, slope in enumerate(slopes.tolist()):
        position = start + (slope / step) * f[None]  # (K, n) each pixel's latency in candidate steps
        low = position.floor().long().clamp_(0, readable - 1)
        frac = position - low
        high = (low + 1).clamp_(max=readable - 1)
        value = maps.gather(0, low) * (1 - frac) + maps.gather(0, high) * frac
        fits = (position <= readable - 1 + 1e-9).all(1) if len(f) else torch.ones(readable, dtype=torch.bool)
        out[s, :readable] = torch.where(fits, (value.sum(1) + still) / pixels, math.inf)
    return out


def fit_pair_curve(pairs: EventFrames, threshold: float, max_latency_us: float | None = None,
                   max_slope_us: float | None = None, min_gain: float = DEFAULT_MIN_GAIN,
                   threshold_scales: Sequence[float] = DEFAULT_THRESHOLD_SCALES,
                   max_spread_us: float = DEFAULT_RAMP_US,
                   next_spread_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> PairCurve:
    """Fit ``ψ(L) = a + b · f(L)`` to the agreement of one or more pairs of frames (the module's docstring).

    The pairs' evidence adds up: each pair's log mean disagreement over the grid of ``(a, b)`` is summed, over the
    grid points every pair can read. Offsets run over 0 to ``max_latency_us`` in 80 steps, slopes over 0 to
    ``max_slope_us`` in the same steps.

    Args:
        pairs: frames with the next one (``blurry_next`` set), each sample one pair (``EventFrames.pairs()``), their
            events past the next exposure by the latencies to be read.
        threshold: contrast threshold θ.
        max_latency_us: the largest offset ``a``; default the first pair's exposure time (the constant search's
            default range).
        max_slope_us: the largest slope ``b``; default half of ``max_latency_us``.
        min_gain: the relative drop of the disagreement a slope must earn (:data:`DEFAULT_MIN_GAIN`).
        threshold_scales: a slope is also a wrong θ in disguise (a θ too high made the disagreement grow with
            intensity and a slope took it up: on the tuning cases at 1.4x θ, 9 of 79 constant-latency cases, up to
            5 dB lost); where the pairs agree better without a slope at one of these multiples of ``threshold``, the
            slope must earn ``min_gain`` there too (:data:`DEFAULT_THRESHOLD_SCALES`; ``()``: no such check).
        max_spread_us, next_spread_factor: the ramps of :func:`evlatcorr.pair_evidence.pair_disagreement_curve`.

    Raises:
        ValueError: for arguments out of range, frames without ``blurry_next``, or when no pair tells anything (each
            blank, or without events past its second exposure).

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pairs = simulate("camera", num_frames=3, height=24, width=32, latency_us=3000.0, seed=0).pairs()
        >>> fit = fit_pair_curve(pairs, 0.2)
        >>> fit.pairs_used, round(fit.offset_us), fit.slope_us
        (2, 3000, 0.0)
    """
    if pairs.blurry_next is None or pairs.exposure_start_next is None:
        raise ValueError("fit_pair_curve reads pairs of frames (blurry_next set: EventFrames.pairs())")
    theta = float(check_threshold(threshold, 1)[0])
    exposure = float(pairs.exposure_end[0] - pairs.exposure_start[0])
    high = exposure if max_latency_us is None else max_latency_us
    if not (math.isfinite(high) and high > 0):
        raise ValueError(f"max_latency_us must be a positive number of µs, got {max_latency_us}")
    slope_high = high / 2 if max_slope_us is None else max_slope_us
    if not (math.isfinite(slope_high) and slope_high >= 0):
        raise ValueError(f"max_slope_us must be a non-negative number of µs, got {max_slope_us}")
    if not (math.isfinite(min_gain) and min_gain >= 0):
        raise ValueError(f"min_gain must be a non-negative number, got {min_gain}")
    if not all(math.isfinite(x) and x > 0 for x in threshold_scales):
        raise ValueError(f"threshold_scales must be positive numbers, got {threshold_scales}")
    step = high / _STEPS
    offsets = torch.arange(_STEPS + 1, dtype=torch.float64) * step
    slopes = torch.arange(int(slope_high / step + 1e-9) + 1, dtype=torch.float64) * step
    readable = [pair for pair, blank in zip(pairs.split(), blank_pairs(pairs.blurry, pairs.blurry_next).tolist())
                if not blank]
    spread = (max_spread_us, next_spread_factor)
    total, used = _summed_table(readable, theta, offsets, slopes, *spread)
    if used == 0 or not bool(torch.isfinite(total[0]).any()):
        raise ValueError("no pair tells a latency: each is blank (black, saturated or flat) or has no events past "
                         "its second exposure")
    one = int(total[0].argmin())
    s, k, gain = _best_slope(total, used)
    if s > 0 and gain > min_gain and threshold_scales:
        # the θ the pairs agree on best without a slope: where it is not the given one, the slope must hold there too
        # (one that vanishes was θ's error)
        lowest = {1.0: float(total[0, one]) / used}
        for x in threshold_scales:
            flat, n = _summed_table(readable, theta * x, offsets, slopes[:1], *spread)
            if n:
                lowest[x] = float(flat[0].min()) / n
        preferred = min(lowest, key=lowest.get)
        if preferred != 1.0:
            again, n = _summed_table(readable, theta * preferred, offsets, slopes, *spread)
            gain = min(gain, _best_slope(again, n)[2] if n else 0.0)
    if s == 0 or gain <= min_gain:
        s, k = 0, one
    curve = PolynomialLatency(order=1)
    with torch.no_grad():
        curve.coefficients.copy_(torch.tensor([float(offsets[k]), float(slopes[s])]) / curve.scale_us)
    return PairCurve(curve, float(offsets[k]), float(slopes[s]), gain, used, float(offsets[one]))


def _summed_table(pairs: list[EventFrames], theta: float, offsets: Tensor, slopes: Tensor, max_spread_us: float,
                  next_spread_factor: float | None) -> tuple[Tensor, int]:
    """The pairs' log mean disagreement over the grid, summed (inf where any pair cannot read a grid point), and how
    many pairs could be read."""
    total, used = torch.zeros(len(slopes), len(offsets), dtype=torch.float64), 0
    for pair in pairs:
        table = pair_curve_table(pair, theta, offsets, slopes, max_spread_us, next_spread_factor)
        if bool(torch.isfinite(table[0]).any()):
            total += table.log()
            used += 1
    return total, used


def _best_slope(total: Tensor, used: int) -> tuple[int, int, float]:
    """The grid point of least summed disagreement (slope index, offset index) and its gain over the best single
    latency: the relative drop of the geometric mean disagreement per pair."""
    s, k = divmod(int(total.argmin()), total.shape[1])
    return s, k, math.exp((float(total[0].min()) - float(total[s, k])) / used) - 1


def _check_grid(values: Tensor, name: str) -> None:
    """Refuse a grid that is not 1-D, finite and evenly spaced from 0."""
    if values.dim() != 1 or len(values) == 0 or not bool(torch.isfinite(values).all()):
        raise ValueError(f"{name} must be a non-empty 1-D tensor of finite latencies (µs), got shape "
                         f"{tuple(values.shape)}")
    grid = values.detach().double().cpu()
    step = float(grid[1] - grid[0]) if len(grid) > 1 else 0.0
    expected = torch.arange(len(grid), dtype=torch.float64) * step
    even = torch.allclose(grid, expected, atol=1e-6 * max(step, 1.0))
    if float(grid[0]) != 0 or (len(grid) > 1 and step <= 0) or not even:
        raise ValueError(f"{name} must run from 0 in even, increasing steps")
