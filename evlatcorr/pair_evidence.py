"""Two consecutive frames' agreement as evidence of a recording's latency, with each event the end of a ramp.

Each blurry frame and the events give the latent image at any time (EDI); between two exposures both frames give
it, and at the right latency they agree (:mod:`evlatcorr.consistency`). With step EDI the latency at which they agree
best lies a millisecond or so after the true one: a step holds a pixel's level until its event, while the scene
crossed the threshold gradually, so both frames' latents lag the scene and reading the events later makes up for it.
Here each event is the end of a ramp from the pixel's previous event, at most ``max_spread_us`` long and at most
twice the interval to the pixel's next event (:func:`evlatcorr.integral.cumulative_event_grid`'s ``"linear"``
integral; an event after a long quiet is an edge's first crossing, and the edge's own pace says how long the change
before it took), and the lag goes (``docs/estimator.md``, "two frames' agreement with each event a ramp").

:func:`pair_log_odds` turns a pair's disagreement over the candidate latencies into log-odds that are added to the
first frame's reader evidence: by :func:`evlatcorr.temporal.fuse_latencies` (``pair_log_odds=``, as ``evlatcorr
correct`` fuses a recording), and by the constant corrector itself where it is given pairs (``pair_weight``, as
interpolation and REFID read them; in a :class:`~evlatcorr.temporal.StreamingLatencyCorrector` with the earlier
frames' evidence too). Two cues that share nothing but EDI.
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import torch
from torch import Tensor

from evlatcorr.blank_frames import blank_pairs
from evlatcorr.checks import check_threshold, resolve_memory_budget
from evlatcorr.config import DEFAULT_PAIR_WEIGHT
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.integral import cumulative_event_grid, grid_bytes_per_point

__all__ = ["DEFAULT_RAMP_US", "DEFAULT_RAMP_NEXT_FACTOR", "DEFAULT_PAIR_WEIGHT", "pair_disagreement_curve",
           "pair_disagreement_maps", "pair_log_odds"]

#: the ramps' longest, µs, and their longest as a multiple of the interval to the pixel's next event: on the accuracy
#: suite's tuning pairs (``docs/estimator.md``) these took the lag off on slow and fast scenes alike (median signed
#: error +6 / +24 µs on dev / dev_wide, ideal events' median estimate 0 µs); a cap alone had to trade them (3 ms still
#: late where pixels fire slowly, 5 ms early where they fire fast)
DEFAULT_RAMP_US = 10000.0
DEFAULT_RAMP_NEXT_FACTOR = 2.0
_FLOOR = 0.02  # log(I + c), as evlatcorr.consistency: the dark pixels' noise does not dominate
_GRID_US = 125.0  # the integral's finest grid spacing, µs


def pair_disagreement_curve(pair: EventFrames, threshold: float, candidates: Tensor,
                            max_spread_us: float = DEFAULT_RAMP_US, grid_us: float = _GRID_US,
                            next_spread_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> Tensor:
    """For each candidate latency, the mean over pixels of ``|log(I_1(t) + c) − log(I_2(t) + c)|`` (c = 0.02):
    the two frames' EDI latents at ``t``, the middle of the gap between their exposures, from the events read that
    late, each event a ramp of at most ``max_spread_us`` (0: a step) and ``next_spread_factor`` times the interval to
    its pixel's next event.

    Only the pixels with events are integrated (elsewhere each latent is its blurry frame at every candidate, one
    constant disagreement), in runs of pixels whose grid fits a quarter of the memory budget
    (:data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`): a DAVIS346 pair 40 ms apart spans about 600 grid points. Where
    not even a row's worth of pixels would fit (exposures of seconds), the grid is coarser.

    Args:
        pair: one pair (``B = 1``): ``blurry``, ``blurry_next``, both exposures and the events over both.
        threshold: contrast threshold θ.
        candidates: :math:`(K,)` latencies, µs, increasing.
        max_spread_us: the ramps' longest, µs; 0 for step EDI.
        grid_us: the integral's finest grid spacing, µs (times are read at the nearest grid point).
        next_spread_factor: each ramp also no longer than this many times the interval to the pixel's next event
            (:func:`~evlatcorr.integral.cumulative_event_grid`'s; None: the cap alone).

    Returns:
        :math:`(K,)` float64.

    Raises:
        ValueError: for a batch that is not one pair, a bad threshold, ramp, grid or candidates.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pair = simulate("camera", num_frames=2, height=24, width=32, latency_us=3000.0, seed=0).pairs()
        >>> curve = pair_disagreement_curve(pair, 0.2, torch.tensor([0.0, 3000.0]), 3000.0)
        >>> bool(curve[1] < curve[0])
        True
    """
    bands = _band_disagreements(pair, threshold, candidates, max_spread_us, grid_us, next_spread_factor,
                                "pair_disagreement_curve")
    total = torch.zeros(len(candidates), dtype=torch.float64)
    for _, band in bands:
        total += band.double().sum(1).cpu()
    h, w = pair.sensor_size
    return total / (h * w)


def pair_disagreement_maps(pair: EventFrames, threshold: float, candidates: Tensor,
                           max_spread_us: float = DEFAULT_RAMP_US, grid_us: float = _GRID_US,
                           next_spread_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> Tensor:
    """:func:`pair_disagreement_curve` pixel by pixel: ``|log(I_1(t) + c) − log(I_2(t) + c)|`` for each candidate
    :math:`(K, H, W)` float32, on the pair's device (its mean over the pixels is the curve, to float32 rounding).

    For a latency per region or per brightness (``benchmarks/pair_bands.py``: one per brightness band of the
    first frame); the arguments are :func:`pair_disagreement_curve`'s.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pair = simulate("camera", num_frames=2, height=24, width=32, latency_us=3000.0, seed=0).pairs()
        >>> pair_disagreement_maps(pair, 0.2, torch.tensor([0.0, 3000.0])).shape
        torch.Size([2, 24, 32])
    """
    bands = _band_disagreements(pair, threshold, candidates, max_spread_us, grid_us, next_spread_factor,
                                "pair_disagreement_maps")
    h, w = pair.sensor_size
    out = torch.empty((len(candidates), h * w), dtype=torch.float32, device=pair.device)
    for pixels, band in bands:
        out[:, pixels] = band
    return out.view(len(candidates), h, w)


def _band_disagreements(pair: EventFrames, threshold: float, candidates: Tensor, max_spread_us: float,
                        grid_us: float, next_spread_factor: float | None, name: str) -> Iterator[tuple[Tensor, Tensor]]:
    """The arguments' disagreement, a run of pixels at a time: ``(flat pixel indices (n,), (K, n) float32)``, first
    the pixels without events (their latents are their blurry frames at every candidate), then the others in runs
    whose grid fits a quarter of the memory budget; checked here, before the first run is asked for."""
    _check_pair_arguments(pair, threshold, candidates, max_spread_us, grid_us, next_spread_factor, name)
    return _bands(pair, threshold, candidates, max_spread_us, grid_us, next_spread_factor)


def _check_pair_arguments(pair: EventFrames, threshold: float, candidates: Tensor, max_spread_us: float,
                          grid_us: float, next_spread_factor: float | None, name: str) -> None:
    """Refuse what :func:`pair_disagreement_curve` cannot read (``name`` is the caller's, for the message)."""
    if pair.batch_size != 1 or pair.blurry_next is None:
        raise ValueError(f"{name} reads one pair of frames (B = 1, with blurry_next)")
    if not (isinstance(threshold, (int, float)) and math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number, got {threshold}")
    if not (math.isfinite(max_spread_us) and max_spread_us >= 0):
        raise ValueError(f"max_spread_us must be 0 or more, got {max_spread_us}")
    if next_spread_factor is not None and not (math.isfinite(next_spread_factor) and next_spread_factor > 0):
        raise ValueError(f"next_spread_factor must be positive or None, got {next_spread_factor}")
    if not (math.isfinite(grid_us) and grid_us > 0):
        raise ValueError(f"grid_us must be positive, got {grid_us}")
    check_candidates(candidates)


def _bands(pair: EventFrames, threshold: float, candidates: Tensor, max_spread_us: float, grid_us: float,
           next_spread_factor: float | None) -> Iterator[tuple[Tensor, Tensor]]:
    """:func:`_band_disagreements` after its checks."""
    s1, e1 = float(pair.exposure_start[0]), float(pair.exposure_end[0])
    s2, e2 = float(pair.exposure_start_next[0]), float(pair.exposure_end_next[0])
    integral = "linear" if max_spread_us > 0 else "step"
    # events read l late: their integral at t is the stamped events' at t + l, so one grid serves every candidate;
    # each exposure's mean of exp(θ C) is a difference of prefix sums (trapezoids between grid points), and times are
    # taken at the nearest grid point
    h, w = pair.sensor_size
    per_point = w * (grid_bytes_per_point(integral, torch.float64) + 16)  # a row's grid, its exp and sums
    span = e2 + max(float(candidates.max()), 0.0) - s1
    grid_us = max(grid_us, span / max(resolve_memory_budget() // 4 // per_point - 4, 1))  # a row fits, at least
    start = s1 - grid_us
    bins = int(math.ceil((span + grid_us) / grid_us)) + 2
    latency = candidates.detach().to("cpu", torch.float64)

    def index(t: float) -> Tensor:  # (K,) grid points of t + each candidate
        return ((t + latency - start) / grid_us).round().long().clamp(0, bins)

    middle, windows = index((e1 + s2) / 2), ((index(s1), index(e1)), (index(s2), index(e2)))
    zero = round(((e1 + s2) / 2 - start) / grid_us)
    spread = {"max_spread_us": max_spread_us, "next_spread_factor": next_spread_factor} if max_spread_us > 0 else {}
    events = pair.events
    first, second = pair.blurry[0].float().mean(0).flatten(), pair.blurry_next[0].float().mean(0).flatten()
    # a pixel without events has its blurry frame as latent at every candidate: its disagreement is one constant
    pixel = events.y * w + events.x
    active = torch.unique(pixel)
    still = torch.ones(h * w, dtype=torch.bool, device=first.device)
    still[active.to(first.device)] = False
    still = still.nonzero().flatten()
    yield still, (torch.log(first[still].clamp_min(0) + _FLOOR) - torch.log(second[still].clamp_min(0) + _FLOOR)
                  ).abs()[None].expand(len(latency), -1)
    # the pixels with events, in runs that fit a quarter of the memory budget (a few rows' worth at least)
    column = torch.searchsorted(active, pixel)  # each event's pixel among the active ones
    band = w * max(1, min(h, resolve_memory_budget() // 4 // ((bins + 1) * per_point)))
    for lo in range(0, len(active), band):
        count = min(band, len(active) - lo)
        inside = (column >= lo) & (column < lo + count)
        part = Events.from_canonical(column[inside] - lo, torch.zeros_like(column[inside]), events.t[inside],
                                     events.p[inside], events.batch[inside], (1, count), 1)
        grid = cumulative_event_grid(part, start, grid_us, bins, integral, torch.float64, **spread)[0, :, 0]
        weights = grid.sub_(grid[zero].clone()).mul_(threshold).exp_()  # levels about the gap's middle: no overflow
        # trapezoids from grid point a to b: T[b] - T[a] with T = cumsum(w) - w / 2, summed in float64; read as
        # float32 (a window's sum keeps 7 digits: the levels are taken about the gap's middle), half the traffic of
        # the K reads per frame
        at_middle = weights[middle.to(weights.device)].float()
        trapezoids = weights.cumsum(0).sub_(weights, alpha=0.5).float()
        del weights, grid
        which = active[lo:lo + count].to(first.device)
        logs = []
        for blurry, (a, b) in ((first, windows[0]), (second, windows[1])):
            a, b = a.to(trapezoids.device), b.to(trapezoids.device)
            mean = (trapezoids[b] - trapezoids[a]) / (b - a).clamp_min(1).float()[:, None]
            latent = blurry[which].to(trapezoids.device) * at_middle / mean
            logs.append(torch.log(latent.clamp_min(0) + _FLOOR))
        yield which, (logs[0] - logs[1]).abs()


def check_candidates(candidates: Tensor) -> None:
    """Refuse candidates that are not a non-empty, increasing 1-D tensor of finite latencies."""
    if candidates.dim() != 1 or len(candidates) == 0 or not bool(torch.isfinite(candidates).all()):
        raise ValueError(f"candidates must be a non-empty 1-D tensor of finite latencies (us), got shape "
                         f"{tuple(candidates.shape)}")
    if len(candidates) > 1 and not bool((candidates.diff() > 0).all()):
        raise ValueError("candidates must be increasing")


def pair_log_odds(pair: EventFrames, threshold: float, candidates: Tensor, max_spread_us: float = DEFAULT_RAMP_US,
                  weight: float = DEFAULT_PAIR_WEIGHT,
                  next_spread_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> Tensor | None:
    """A pair's evidence of its latency over the first frame's candidates: ``−weight · log(d(l) / min d)``, where
    ``d`` is :func:`pair_disagreement_curve`.

    A pixel's disagreement taken as Laplace noise of one scale, the pair's log-likelihood at ``l`` is ``−P log d(l)``
    for ``P`` independent pixels; neighbouring pixels are not independent, and ``weight`` stands for how many count
    (:data:`DEFAULT_PAIR_WEIGHT`). Only candidates whose windows end before the pair's last event are read; the others
    get the median of the read ones (no evidence either way, as :func:`~evlatcorr.temporal.fuse_latencies` fills a
    frame's unscored candidates).

    Args:
        pair: one pair (``B = 1``, with ``blurry_next``) whose events reach past the second exposure.
        threshold: contrast threshold θ.
        candidates: :math:`(K,)` the first frame's candidate latencies, µs, increasing.
        max_spread_us: the ramps' longest, µs.
        weight: log-odds per unit of log disagreement, positive.
        next_spread_factor: the ramps' longest as a multiple of the interval to the pixel's next event (None: none).

    Returns:
        :math:`(K,)` float64 log-odds (their maximum 0), or None where the pair tells nothing: either frame is black,
        saturated or flat (:func:`evlatcorr.blank_frames.blank_pairs`: it agrees with its neighbour at no latency; a
        black next frame agreed best wherever the first frame's latent was darkest), fewer than three candidates can
        be read, or the disagreement is lowest at the last two of them (no minimum before the events run out: latency
        does not change the frames' latents, or the events stop too early).

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pair = simulate("camera", num_frames=2, height=24, width=32, latency_us=3000.0, seed=0).pairs()
        >>> log_odds = pair_log_odds(pair, 0.2, torch.arange(0.0, 6001.0, 500.0))
        >>> int(log_odds.argmax()) * 500
        3000
    """
    if not (isinstance(weight, (int, float)) and math.isfinite(weight) and weight > 0):
        raise ValueError(f"weight must be a positive number, got {weight!r}")
    if pair.batch_size != 1 or pair.blurry_next is None:
        raise ValueError("pair_log_odds reads one pair of frames (B = 1, with blurry_next)")
    threshold = float(check_threshold(threshold, 1)[0])
    check_candidates(candidates)
    candidates = candidates.detach().to("cpu", torch.float64)
    if len(pair.events) == 0 or bool(blank_pairs(pair.blurry, pair.blurry_next)[0]):
        return None
    reach = float(pair.events.t.max() - pair.exposure_end_next[0])  # a window never runs past the last event
    readable = candidates <= reach
    if int(readable.sum()) < 3:
        return None
    curve = pair_disagreement_curve(pair, threshold, candidates[readable], max_spread_us,
                                    next_spread_factor=next_spread_factor)
    if int(curve.argmin()) >= len(curve) - 2 or not bool(torch.isfinite(curve).all()):
        return None
    read = -weight * torch.log(curve / curve.min())
    out = torch.full_like(candidates, float(read.median()))
    out[readable] = read
    return out
