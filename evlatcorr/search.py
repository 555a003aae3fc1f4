"""Constant-latency search in one pass over the events (paper Sec. 3.3, ``l_const``).

Every candidate latency ``l`` needs the EDI ratio ``R`` of the window ``[τ + l, t + l]`` of stamped
events (Eq. 7). Two ways to read all candidates at once:

- ``"continuous"`` (default): :class:`~evlatcorr.continuous.ContinuousIntegral` evaluates each pixel's
  exact integral of ``exp(θC)`` at every window end from one scatter of the events. No temporal bins, so
  the candidates may lie anywhere; they are spaced so that windows share their ends (about two time
  points per candidate).
- ``"binned"``: for a latency ``l = dΔ`` that is a whole number ``d`` of sub-intervals ``Δ = T / n``
  the EDI reads the cumulative sum ``C`` at grid points ``d .. d + n``, so

      R_d = mean_j exp(θ (C[d + j] − C[d + n/2]))  =  (P[d + n + 1] − P[d] − ½(Y_d + Y_{d+n})) / n / Y_{d+n/2}

  with ``Y = exp(θC − max θC)`` and ``P`` its prefix sum (trapezoidal rule, log domain): one table of
  ``(n + span) × H × W`` serves every candidate. Needed for the ``"linear"`` integral.

The scores of all candidates are batched calls. With a sharpness score the best candidate is refined at every
``T / n`` around it (40 µs at the defaults, far below what any score can tell apart), and the latent image at the
latency chosen is the one its candidate was scored on (no further read of the events). With the learned reader
(the default) the estimate is the centre of the reader's probability around its pick, between candidates; the
latent image there takes one more read of the events' window.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

import kornia
import torch
from torch import Tensor

from evlatcorr import continuous
from evlatcorr.checks import (
    check_batch_vector,
    check_exposure,
    check_image,
    check_memory,
    check_threshold,
    resolve_memory_budget,
)
from evlatcorr.config import DEFAULT_SCORE, SCORES, SPARSITY_SCORES, SearchConfig
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
from evlatcorr.events import Events
from evlatcorr.ghost import ghost_root, inverse_ratio_moment
from evlatcorr.integral import _row_strips, cumsum_, cumulative_event_grid
from evlatcorr.overshoot import overshoot, overshoot_stride
from evlatcorr.sharpness import _scores_of, sharpness_score, sharpness_scores
from evlatcorr.temporal import LatencyHistory

__all__ = ["ConstantSearchResult", "search_constant_latency", "default_search_range", "sharpness_score",
           "sharpness_scores", "candidate_curves", "SCORES", "DEFAULT_SCORE", "SearchConfig"]

_SPARSITY = SPARSITY_SCORES
# Memory bound of one strip of the prefix-sum table (float64), in elements.
_STRIP_ELEMENTS = 4_000_000
# Bytes per grid point and pixel that the search table keeps: the cumulative event sum (float32) and the
# prefix sum of exp(θC − peak) (float64).
_TABLE_BYTES = 4 + 8
# The largest search table kept between reads (larger ones are rebuilt per read, in strips).
_KEEP_TABLE_BYTES = 512 * 2**20
# The most one read of the continuous integral may take (events kept and the candidates read at once): at
# DAVIS346 size with 2 M events, about 170 candidates per read, so the default 101 are read in one pass.
_CONTINUOUS_READ_BYTES = 256 * 2**20
# A pixel whose events span more log intensity than this over the stream (e^15, 130 dB: more than a DAVIS
# sensor's ~120 dB can see) is a hot pixel firing one polarity: the continuous search reads it as having no
# events. One such pixel of 300 events moved a dev estimate by 11 ms; the suite's and the real recordings'
# pixels span at most 5.3 and 5.7.
HOT_PIXEL_LOG_RANGE = 15.0
# Candidates scored at once on a CPU (their latent images and score work arrays stay in cache).
_SCORE_CHUNK = 16
# Elsewhere (a GPU), as many as fit in this many bytes of score work arrays (about 8 float32 images each): there
# each kernel launch costs more than the memory, and 101 candidates at DAVIS346 size take about 290 MB
_DEVICE_SCORE_BYTES = 2**30
# Peak bytes per grid point and pixel while one strip of the table is built (the integral's work
# arrays, θC in float64, its exponential and prefix sum).
_BUILD_BYTES = 64


@dataclass
class ConstantSearchResult:
    """Result of :func:`search_constant_latency`.

    Attributes:
        latency: best constant latency per sample :math:`(B,)`, µs.
        candidates: coarse candidate latencies :math:`(B, K)`, µs.
        etf: ETF of the coarse candidates :math:`(B, K)` (the paper's Fig. 2b curve).
        fine_candidates: list per sample of the refined candidates, µs.
        fine_etf: list per sample of their ETF values.
        confidence: :math:`(B,)` in [0, 1]: how clearly the score curve has an interior minimum
            (its relative depth below the curve's median, 0 when the minimum lies on the upper edge
            of the range searched).
        fallback: :math:`(B,)` bool: the curve had no clear minimum and ``latency`` is the fallback
            (``previous_latency`` when given, else the lower end of the range); with ``score="learned"`` only
            where fewer than three candidates could be scored.
        source: per sample, what set ``latency``: ``"sharpness"`` (the score's minimum), ``"ghost"`` (the
            score curve was nearly flat and :mod:`evlatcorr.ghost`'s moment crossed zero once), ``"reader"``
            (``score="learned"``: the scores had no minimum and the curve reader's estimate stands) or
            ``"fallback"``.
        ignored_pixels: per sample, the hot pixels the search read as having no events (their events span more
            than :data:`HOT_PIXEL_LOG_RANGE` of log intensity; continuous method only).
        latency_spread: :math:`(B,)` µs, ``score="learned"``: the standard deviation of the curve reader's
            probability over the candidates, how unsure it is (NaN for the other scores, or where nothing could be
            scored). On the suite's tuning cases the estimate's error grows with it (see the README).
        log_probability: :math:`(B, K)` float64, ``score="learned"``: the curve reader's log-probability of each
            coarse candidate (``candidates``) from the frame alone (no temporal prior), normalised over the candidates
            that could be scored (−inf elsewhere); NaN rows for samples where the reader did not run, None when no
            sample has one. :func:`evlatcorr.temporal.fuse_latencies` combines consecutive frames' rows.
        own_latency: :math:`(B,)` µs, where a :class:`~evlatcorr.temporal.LatencyHistory` fused ``latency`` with
            earlier frames': each frame's own estimate (None otherwise).
        log_ratio: :math:`(B, 1, H, W)` float64 EDI ``log R`` at ``latency`` (latent image at mid-exposure
            ``blurry · exp(−log R)``), exact in continuous time (to float32 rounding when ``latency`` is a scored
            candidate: the ratio its score saw); None with ``method="binned"`` or when a sample had no window to
            score.
    """

    latency: Tensor
    candidates: Tensor
    etf: Tensor
    fine_candidates: list[Tensor]
    fine_etf: list[Tensor]
    confidence: Tensor | None = None
    fallback: Tensor | None = None
    log_ratio: Tensor | None = None
    source: list[str] | None = None
    ignored_pixels: list[int] | None = None
    latency_spread: Tensor | None = None
    log_probability: Tensor | None = None
    own_latency: Tensor | None = None


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
    score: str = DEFAULT_SCORE,
    memory_budget: int | None = None,
    method: str | None = None,
    config: SearchConfig | None = None,
) -> ConstantSearchResult:
    """Find the constant latency per sample that minimises the ETF of the EDI latent image.

    Args:
        blurry: :math:`(B, C, H, W)` in [0, 1].
        events: events of each sample; they must reach ``exposure_end + search_range[1]``.
        exposure_start: :math:`(B,)` µs.
        exposure_end: :math:`(B,)` µs.
        threshold: contrast threshold θ, float or :math:`(B,)`.
        num_bins: sub-intervals of the exposure ``n`` (paper: 500); candidates are whole sub-intervals.
        search_range: ``(low, high)`` µs, finite, ``high > low``; default ``(0, exposure time)`` per sample.
        num_candidates: number of coarse candidates over the range (default 100).
        refine: search every sub-interval around the best candidate (``score="learned"``: take the centre of the
            reader's probability around its pick instead of the pick itself).
        previous_latency: ``l'`` :math:`(B,)` µs for the temporal term ``g``; None drops it.
        epsilon: ETF edge amplifier.
        window: ETF contrast window.
        sigma_us: σ of the temporal prior, µs.
        integral: ``"step"`` (impulse events) or ``"linear"`` (each event spread since the previous one
            at its pixel, Eq. 16-18; see :mod:`evlatcorr.integral`).
        score: ``"learned"`` (default: :mod:`evlatcorr.curve_reader` reads the three sparsity curves and the
            ghost moment; the estimate is the centre of its probability around its likeliest candidate),
            ``"consensus"`` (the median of the estimates of the three sparsity scores), ``"sparsity"``,
            ``"sparsity_bright"``, ``"sparsity_multiscale"`` or ``"etf"`` (paper Eq. 14; see
            :func:`sharpness_score`).
        memory_budget: bytes the search table may take; default
            :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`. A larger table is built strip by strip for
            each batch of candidates (the same values, more time).
        method: ``"continuous"`` (default for the step integral): each candidate window's EDI is exact in
            continuous time (:mod:`evlatcorr.continuous`), candidates are evenly spaced over the range and
            the refinement steps by ``exposure time / num_bins``; ``"binned"`` (default for ``"linear"``, the
            only one for it): candidates are whole sub-intervals of a ``num_bins`` grid read from one
            prefix-sum table (trapezoidal rule), as before the continuous integral; kept for comparison.
        config: the search settings as one :class:`~evlatcorr.config.SearchConfig` (already validated); when
            given it replaces ``num_bins``, ``search_range``, ``num_candidates``, ``refine``, ``epsilon``,
            ``window``, ``sigma_us`` and ``score``, and sets ``ghost_confidence``.

    Candidates whose window ``[exposure_start + l, exposure_end + l]`` runs past a sample's last
    event are never scored. When the curve has no interior minimum (see ``confidence``), the
    latency falls back to ``previous_latency`` or, without it, to the zero of the ghost-moment cue
    (:mod:`evlatcorr.ghost`, ``config.ghost_confidence``) where it has a clear one, else to the lower end
    of the range; ``source`` says which.

    Candidates are whole sub-intervals ``exposure time / num_bins``, so the first one may lie up to
    a sub-interval below ``low`` and the last above ``high`` (a range narrower than a sub-interval
    still gets two); the returned ``latency`` is clamped into ``[low, high]``.

    Returns:
        a :class:`ConstantSearchResult`.

    Raises:
        ValueError: for a bad argument (e.g. a non-finite ``search_range``), or when even one row of
            the search table would exceed the memory budget: the message says what to narrow.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> frames = simulate("camera", num_frames=1, latency="constant", latency_us=2000.0, seed=0,
        ...                   height=24, width=32, exposure_us=10_000.0).frames("delayed")
        >>> res = search_constant_latency(frames.blurry, frames.events, frames.exposure_start,
        ...                               frames.exposure_end, num_bins=50, search_range=(1000.0, 1100.0))
        >>> 1000.0 <= res.latency.item() <= 1100.0  # clamped: the candidates are 200 us apart
        True
    """
    if config is None:
        config = SearchConfig(num_bins=num_bins, search_range=search_range, num_candidates=num_candidates,
                              refine=refine, score=score, epsilon=epsilon, window=window, sigma_us=sigma_us)
    check_image(blurry, "blurry")
    b = blurry.shape[0]
    if events.batch_size != b:
        raise ValueError(f"events have batch_size {events.batch_size} but blurry has {b} frames")
    if events.sensor_size != tuple(blurry.shape[-2:]):
        raise ValueError(f"events sensor_size {events.sensor_size} does not match blurry {tuple(blurry.shape[-2:])}")
    start = check_batch_vector(exposure_start, b, "exposure_start").to(events.device, torch.float64)
    end = check_batch_vector(exposure_end, b, "exposure_end").to(events.device, torch.float64)
    check_exposure(start, end)
    if integral not in ("step", "linear"):
        raise ValueError(f"integral must be 'step' or 'linear', got {integral!r}")
    method = method or ("continuous" if integral == "step" else "binned")
    if method not in ("continuous", "binned"):
        raise ValueError(f"method must be 'continuous' or 'binned', got {method!r}")
    if method == "continuous" and integral != "step":
        raise ValueError("method='continuous' computes the step integral; use method='binned' for integral='linear'")
    theta = check_threshold(threshold, b)
    budget = resolve_memory_budget(memory_budget)
    prev = None if previous_latency is None else check_batch_vector(previous_latency, b, "previous_latency")
    return _search_constant_latency(blurry, events, start, end, theta, config, prev, integral, method, budget)


def _search_constant_latency(blurry: Tensor, events: Events, exposure_start: Tensor, exposure_end: Tensor,
                             threshold: Tensor, config: SearchConfig, previous_latency: Tensor | None = None,
                             integral: str = "step", method: str = "continuous",
                             memory_budget: int | None = None,
                             history: LatencyHistory | None = None) -> ConstantSearchResult:
    """:func:`search_constant_latency` of checked inputs: an image batch, its events, exposures (float64
    :math:`(B,)`, end after start), a positive threshold :math:`(B,)` and a finite ``previous_latency`` :math:`(B,)`.

    ``history``: the frames are the next of a stream, in order: each frame's latency is fused with the earlier
    frames' as it is decided (:class:`~evlatcorr.temporal.LatencyHistory`), and its latent read there."""
    b = blurry.shape[0]
    start = exposure_start.to(events.device, torch.float64)
    end = exposure_end.to(events.device, torch.float64)
    theta = threshold.to(torch.float64)
    prev, budget = previous_latency, memory_budget
    rng = config.search_range
    if rng is None:
        lows, highs = default_search_range(end - start)
    else:
        lows, highs = torch.full_like(start, rng[0]), torch.full_like(start, rng[1])

    grey = kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry
    # a candidate's window [start + l, end + l] must not run past the sample's last event: past it
    # the EDI sees "no change" where the events were merely cut off, which looks sharp to any score
    reach = events.last_times() - end
    # every sample's bounds in one copy to the host (one wait for a GPU, not five per sample)
    spans = torch.stack([start, end, lows.to(start), highs.to(start), reach]).T.cpu().tolist()
    thetas = theta.cpu().tolist()
    windows = [_Window(*span) for span in spans]
    from evlatcorr import search_batched  # it builds on this module

    if search_batched.frames_can_share_a_pass(grey, windows, thetas, config, method):
        # on a GPU each frame's search is bound by launches and waits: frames alike share one pass
        results = search_batched.search_frames_together(grey, events, windows, thetas[0], config, prev, budget,
                                                        history)
    else:
        results = []
        for i in range(b):
            res = _search_one(grey[i:i + 1], events.sample(i), windows[i], thetas[i], config,
                              None if prev is None else prev[i:i + 1], integral, budget, method,
                              defer_latent=history is not None)
            if history is not None:
                _fuse_with_history(res, history)
                if res.read_latent is not None:
                    res.log_ratio = res.read_latent(res.latency)
            results.append(res)
    return ConstantSearchResult(
        latency=torch.tensor([r.latency for r in results], dtype=torch.float64, device=blurry.device),
        candidates=torch.stack([r.candidates for r in results]).to(blurry.device),
        etf=torch.stack([r.scores for r in results]).to(blurry.device),
        fine_candidates=[r.fine_candidates for r in results],
        fine_etf=[r.fine_scores for r in results],
        confidence=torch.tensor([r.confidence for r in results], dtype=torch.float64, device=blurry.device),
        fallback=torch.tensor([r.fallback for r in results], dtype=torch.bool, device=blurry.device),
        log_ratio=(torch.cat([r.log_ratio for r in results]).to(blurry.device)
                   if all(r.log_ratio is not None for r in results) else None),
        source=[r.source for r in results],
        ignored_pixels=[r.ignored_pixels for r in results],
        latency_spread=torch.tensor([r.spread_us for r in results], dtype=torch.float64, device=blurry.device),
        log_probability=_stack_log_probability([r.log_probability for r in results], blurry.device),
        own_latency=(None if history is None else
                     torch.tensor([r.own_latency for r in results], dtype=torch.float64, device=blurry.device)),
    )


def _stack_log_probability(rows: list[Tensor | None], device: torch.device) -> Tensor | None:
    """The samples' reader log-probabilities as :math:`(B, K)`, NaN rows where a sample has none; None if none has."""
    if all(r is None for r in rows):
        return None
    missing = torch.full((next(len(r) for r in rows if r is not None),), math.nan, dtype=torch.float64)
    return torch.stack([missing if r is None else r for r in rows]).to(device)


@dataclass
class _OneResult:
    latency: float
    candidates: Tensor
    scores: Tensor
    fine_candidates: Tensor
    fine_scores: Tensor
    confidence: float
    fallback: bool
    log_ratio: Tensor | None = None  # (1, 1, H, W) at ``latency``, from the continuous integral
    source: str = "sharpness"
    ignored_pixels: int = 0
    spread_us: float = math.nan  # the learned reader's standard deviation, µs
    log_probability: Tensor | None = None  # (K,) the learned reader's, without the prior (−inf: not scored)
    own_latency: float | None = None  # the frame's own estimate, where a history fused ``latency`` with others'
    # the latent's read at a latency, where it was left until the latency is final (a history to fuse with)
    read_latent: Callable[[float], Tensor | None] | None = None


def _fuse_with_history(result: _OneResult, history: LatencyHistory) -> None:
    """The frame's latency fused with the earlier frames' of ``history`` (its own estimate kept in ``own_latency``)."""
    result.own_latency = result.latency
    result.latency = history.fuse(result.latency, result.candidates, result.log_probability)


@dataclass
class _Evidence:
    """What :func:`_search_one` reads of one frame with ``score="learned"``, when made with other frames': its
    reader (``final_ratio`` may give None: the latent at the estimate is read afterwards), coarse scores
    :math:`(3, K)` (inf: not scored), the curve reader's log-odds :math:`(K,)` on the host and the ghost moments
    :math:`(K,)`."""

    reader: _CandidateReader
    scores: Tensor
    log_p: Tensor
    moment: Tensor


@dataclass(frozen=True)
class _Window:
    """One sample's exposure ``[start, end]``, latency range ``[low, high]`` and ``reach`` = last event − end, µs."""

    start: float
    end: float
    low: float
    high: float
    reach: float


@dataclass
class _CandidateReader:
    """How one sample's candidates are laid out and read (``"continuous"`` or ``"binned"``).

    ``coarse`` are the candidates in the reader's own units (µs, or sub-intervals for ``"binned"``),
    ``step`` their spacing, ``top`` the last one whose window stays inside the events (below ``floor``: none
    does), ``to_us`` converts to µs, ``inverse_ratio`` reads 1 / R :math:`(K, 1, H, W)` float32 of candidates
    (the latent at mid-exposure is ``grey`` times it),
    ``fine_of`` gives the refinement's candidates around a best one, ``final_ratio`` the log R of the
    chosen latency in µs (None where the reader cannot give it) and ``log_change`` the windows' event
    change θN :math:`(K, 1, H, W)` (None: the reader has no ghost cue).
    """

    coarse: Tensor
    top: float
    floor: float
    to_us: Callable[[Tensor], Tensor]
    inverse_ratio: Callable[[Tensor], Tensor]
    fine_of: Callable[[float], Tensor]
    final_ratio: Callable[[float], Tensor | None]
    log_change: Callable[[Tensor], Tensor] | None = None
    ignored_pixels: int = 0  # hot pixels read as having no events
    # θ (max C − C(reference)) over each window at the overshoot's pixels (every s-th row and column,
    # :func:`~evlatcorr.overshoot.overshoot_stride`) :math:`(K, 1, ⌈H/s⌉, ⌈W/s⌉)` float32 (None: none)
    log_peak: Callable[[Tensor], Tensor] | None = None


def _continuous_reader(grey: Tensor, events: Events, span: _Window, theta: float, config: SearchConfig,
                       budget: int | None) -> _CandidateReader:
    """Candidates evenly spaced over ``[low, high]``, each window's EDI exact in continuous time; the refinement
    spaces them by ``exposure / n``."""
    start, end, low, high = span.start, span.end, span.low, span.high
    coarse, step = _aligned_candidates(low, high, config.num_candidates, end - start)
    top = span.reach if math.isfinite(span.reach) else -math.inf
    fine_step = min((end - start) / config.num_bins, step)
    limit = resolve_memory_budget(budget)
    # the learned score also keeps each candidate's event change and peak log rise (float32)
    with_change = config.score == "learned"
    candidate_bytes = grey.numel() * (continuous.BYTES_PER_CANDIDATE + 8 * with_change)
    check_memory(len(events) * continuous.BYTES_PER_EVENT + candidate_bytes, f"the continuous integral of "
                 f"{len(events)} events", "pass only the events of the exposure and the latencies searched, or a "
                 "smaller sensor crop", limit)
    # candidates read at once: a few reads of the events for 100 candidates, a few hundred MB at DAVIS346 size
    chunk = max(1, (min(limit, _CONTINUOUS_READ_BYTES) - len(events) * continuous.BYTES_PER_EVENT_KEPT)
                // candidate_bytes)
    integral = ContinuousIntegral(events, theta, HOT_PIXEL_LOG_RANGE) if top >= low else None

    # the last read's latencies, ratios and (learned score) the windows' event change and peak rise, from the same
    # tables
    last_read: dict[str, Tensor] = {}
    # the overshoot's pixels: every stride-th row and column
    stride = overshoot_stride(*grey.shape[-2:])

    def empty_peak(num: int) -> Tensor:
        sampled = (-(-grey.shape[-2] // stride), -(-grey.shape[-1] // stride))
        return torch.empty((num, 1, *sampled), dtype=torch.float32, device=events.device)

    def inverse_ratio(lat: Tensor) -> Tensor:
        if last_read and torch.equal(last_read["latencies"], lat.cpu()):  # e.g. the learned score's ghost moment
            return last_read["inverse"]
        out = torch.empty((len(lat), 1, *grey.shape[-2:]), dtype=torch.float32, device=events.device)
        change = torch.empty_like(out) if with_change else None
        peak = empty_peak(len(lat)) if with_change else None
        for k in range(0, len(lat), chunk):  # each read writes its slice: no concatenated copy
            integral.inverse_ratio(start, end, lat[k:k + chunk], out=out[k:k + chunk],
                                   change_out=None if change is None else change[k:k + chunk],
                                   peak_out=None if peak is None else peak[k:k + chunk], peak_stride=stride)
        last_read.clear()
        last_read.update(latencies=lat.cpu(), inverse=out)
        if change is not None:
            last_read.update(change=change, peak=peak)
        return out

    def fine_of(best: float) -> Tensor:
        k = torch.arange(-math.floor(step / fine_step), math.floor(step / fine_step) + 1, dtype=torch.float64)
        return torch.unique((best + k * fine_step).clamp(low, min(high, top)))

    def final_ratio(latency: float) -> Tensor:
        # the chosen latency is usually a candidate of the last read: its latent is the one the score saw
        if last_read:
            hit = torch.nonzero(last_read["latencies"] == latency).flatten()
            if len(hit):
                k = int(hit[0])
                return torch.log(last_read["inverse"][k:k + 1].double()).neg_()
        return integral.log_ratio(start, end, torch.tensor([latency], dtype=torch.float64))

    def log_change(lat: Tensor) -> Tensor:
        if "change" in last_read and torch.equal(last_read["latencies"], lat.cpu()):
            return last_read["change"]
        return integral.log_change(start, end, lat)

    def log_peak(lat: Tensor) -> Tensor:
        if not ("peak" in last_read and torch.equal(last_read["latencies"], lat.cpu())):
            peak = empty_peak(len(lat))
            for k in range(0, len(lat), chunk):
                integral.inverse_ratio(start, end, lat[k:k + chunk], peak_out=peak[k:k + chunk], peak_stride=stride)
            return peak
        return last_read["peak"]

    ignored = 0 if integral is None else int(integral.ignored.sum())
    return _CandidateReader(coarse, top, low, lambda v: v, inverse_ratio, fine_of, final_ratio, log_change, ignored,
                            log_peak)


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


def _score_candidates(reader: _CandidateReader, grey: Tensor, members: tuple[str, ...], config: SearchConfig,
                      prev: Tensor | None, requests: list[Tensor]) -> list[Tensor]:
    """Each member score's values on its own candidates (inf past the last event), from one read of their
    union."""
    union = torch.unique(torch.cat(requests))  # sorted
    valid = union <= reader.top
    out = torch.full((len(members), len(union)), math.inf, dtype=torch.float64)
    if bool(valid.any()):
        kept = union[valid]
        kept_cols = torch.nonzero(valid.cpu()).flatten()
        wanted = torch.zeros((len(members), len(kept)), dtype=torch.bool)
        for m, cand in enumerate(requests):
            wanted[m, torch.searchsorted(kept.cpu(), cand.cpu()[cand.cpu() <= reader.top])] = True
        lat = reader.to_us(kept).to(torch.float64)
        inverse = reader.inverse_ratio(kept)  # (K, 1, H, W): the latents at mid-exposure are grey times it
        previous = None if prev is None else prev.expand(len(kept)).float()
        # on a CPU a few candidates' latent images at a time: scoring all at once held ~7 (K, H, W) arrays
        chunk = _score_chunk(grey)
        for k0 in range(0, len(kept), chunk):
            k1 = min(k0 + chunk, len(kept))
            needed = [m for m in range(len(members)) if bool(wanted[m, k0:k1].any())]
            if not needed:
                continue
            values = _latent_scores(grey, inverse[k0:k1], lat[k0:k1].float().to(grey.device),
                                    None if previous is None else previous[k0:k1], tuple(members[m] for m in needed),
                                    config).double().cpu()
            for value, m in zip(values, needed):
                out[m, kept_cols[k0:k1]] = torch.where(wanted[m, k0:k1], value, math.inf)
    return [out[m, torch.searchsorted(union.cpu(), cand.cpu())] for m, cand in enumerate(requests)]


def _score_chunk(image: Tensor) -> int:
    """Candidates of the image ``image`` :math:`(1, 1, H, W)` to score at once on its device."""
    if image.device.type == "cpu":
        return _SCORE_CHUNK
    return max(1, _DEVICE_SCORE_BYTES // (8 * 4 * image.numel()))


def _latent_scores(grey: Tensor, inverse: Tensor, latency: Tensor, previous: Tensor | None, scores: tuple[str, ...],
                   config: SearchConfig) -> Tensor:
    """:func:`sharpness_scores` of the latent images ``grey · inverse`` :math:`(K, 1, H, W)` without making them:
    each image's mean is one product with ``grey``, and ``log(grey · inverse + c · mean)`` one fused pass."""
    mean = (inverse.flatten(1) @ grey.flatten().to(inverse)).div_(grey.numel()).clamp_min_(1e-12)[:, None, None, None]
    return _scores_of(lambda floor: torch.addcmul(floor * mean, inverse, grey).log_(), lambda: grey * inverse, latency,
                      previous, scores, config.epsilon, config.window, config.sigma_us)


def _search_one(grey: Tensor, events: Events | None, span: _Window, theta: float, config: SearchConfig,
                prev: Tensor | None, integral: str, budget: int | None = None,
                method: str = "continuous", evidence: _Evidence | None = None,
                defer_latent: bool = False) -> _OneResult:
    """Search for one sample; ``grey`` is :math:`(1, 1, H, W)`. See :func:`_continuous_reader` and
    :func:`_binned_reader` for how each ``method`` lays out its candidates.

    ``evidence``: the sample's reader, coarse scores and curve reader output, already made with other frames'
    (``score="learned"``, :mod:`evlatcorr.search_batched`); ``events`` is then not read. ``defer_latent``: the
    latent image at the estimate is not read; the result's ``read_latent`` reads it at a latency given later."""
    low, high = span.low, span.high
    width_us = (span.end - span.start) / config.num_bins
    if max(abs(low), abs(high)) / width_us >= 2**53:  # beyond float64's whole numbers of sub-intervals
        raise ValueError(f"search_range [{low:.4g}, {high:.4g}] us reaches {max(abs(low), abs(high)) / width_us:.3g} "
                         f"sub-intervals of {width_us:.4g} us (exposure time / num_bins), more than the search "
                         "can count (2**53): narrow search_range")
    members = tuple(_SPARSITY) if config.score in ("consensus", "learned") else (config.score,)
    if evidence is not None:
        reader = evidence.reader
    else:
        reader = (_continuous_reader(grey, events, span, theta, config, budget) if method == "continuous"
                  else _binned_reader(events, span, theta, config, integral, budget))
    read_latent = None
    if defer_latent and evidence is None:
        read_latent, reader = reader.final_ratio, dataclasses.replace(reader, final_ratio=_read_later)
    coarse, to_us = reader.coarse, reader.to_us

    spread, log_probability = math.nan, None

    def result(*args, **kwargs) -> _OneResult:
        return _OneResult(*args, **kwargs, ignored_pixels=reader.ignored_pixels, spread_us=spread,
                          log_probability=log_probability, read_latent=read_latent)

    fallback = low if prev is None else min(max(float(prev), low), high)
    if reader.top < reader.floor:  # no candidate window holds events: nothing to score
        read_latent = None  # and no latent image to read
        nan = torch.full((len(coarse),), math.nan, dtype=torch.float64)
        return result(fallback, to_us(coarse).cpu(), nan, to_us(coarse).cpu(), nan, 0.0, True, source="fallback")

    # the learned reader reads the curves as it was trained (no temporal prior) and takes the prior afterwards
    coarse_prev = None if config.score == "learned" else prev
    moment = None
    if evidence is not None:
        coarse_scores = evidence.scores
    else:
        coarse_scores = torch.stack(_score_candidates(reader, grey, members, config, coarse_prev,
                                                      [coarse] * len(members)))
    if config.score == "learned":  # the reader refines its own pick: no fine candidates to score
        if evidence is not None:
            log_p, moment = evidence.log_p, evidence.moment
        else:
            log_p, moment = _learned_log_p(reader, grey, coarse, coarse_scores)
        prior = None if prev is None else (to_us(coarse).cpu().double(), float(prev), config.sigma_us)
        pick, centre, spread, log_probability = _learned_pick(reader, coarse, log_p,
                                                              torch.isfinite(coarse_scores[0]), prior)
        estimates = [_refine(coarse, coarse_scores[m], coarse, None, False) for m in range(len(members))]
    else:
        fines = [reader.fine_of(float(coarse[int(torch.argmin(coarse_scores[m]))])) for m in range(len(members))]
        fine_scores = (_score_candidates(reader, grey, members, config, prev, fines) if config.refine
                       else [None] * len(members))
        estimates = [_refine(coarse, coarse_scores[m], fines[m], fine_scores[m], config.refine)
                     for m in range(len(members))]
    confidence = sorted(e[1] for e in estimates)[len(estimates) // 2]
    ghost_wanted = config.ghost_confidence is not None and confidence <= config.ghost_confidence
    if ghost_wanted and (confidence > 0 or prev is None) and reader.log_change is not None:
        # a flat sharpness curve: the ghost moment's zero where it crosses once (a frame with no minimum at all
        # keeps the previous frame's latency when there is one)
        ghost = _ghost_latency(reader, grey, coarse, moment)
        if ghost is not None:
            latency = min(max(ghost, low), high)
            return result(latency, to_us(coarse).cpu(), coarse_scores[0], to_us(coarse).cpu(),
                          coarse_scores[0], confidence, False, reader.final_ratio(latency), "ghost")
    # the learned reader was trained on such frames too: it picks the latency where three candidates could be
    # scored (a fallback gains nothing); the other scores fall back
    reader_only = config.score == "learned" and int(torch.isfinite(coarse_scores[0]).sum()) >= 3
    if confidence == 0.0 and not reader_only:  # most scores have no interior minimum
        return result(fallback, to_us(coarse).cpu(), coarse_scores[0], to_us(coarse).cpu(), coarse_scores[0],
                      0.0, True, reader.final_ratio(fallback), "fallback")
    if config.score == "learned":
        best, fine, fine_score = (centre if config.refine else pick), coarse, coarse_scores[0]
    else:
        chosen = sorted(range(len(members)), key=lambda m: estimates[m][0])[len(members) // 2]  # the median
        best, _, fine, fine_score = estimates[chosen]
    latency = min(max(float(to_us(torch.tensor(best, dtype=torch.float64))), low), high)
    return result(latency, to_us(coarse).cpu(), coarse_scores[0], to_us(fine).cpu(), fine_score, confidence, False,
                  reader.final_ratio(latency), "reader" if confidence == 0.0 else "sharpness")


def _read_later(latency: float) -> None:
    """The latent at the estimate is read once the latency is final (fused with a history's frames)."""
    return None


def _curve_inputs(reader: _CandidateReader, grey: Tensor, coarse: Tensor, coarse_scores: Tensor
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~evlatcorr.curve_reader.curve_features` of one frame's coarse candidates on the frame's device, which
    are valid (on the scores' device, the host), and their ghost moments :math:`(K,)` (0 past the last event)."""
    from evlatcorr.curve_reader import curve_features

    valid = torch.isfinite(coarse_scores[0])
    kept = coarse[coarse <= reader.top]  # the valid candidates: a prefix of the sorted coarse ones
    moment = torch.zeros(len(coarse), dtype=torch.float64, device=grey.device)
    moment[:len(kept)] = _candidate_moments(reader, grey, kept)
    over = torch.zeros(len(coarse), dtype=torch.float64, device=grey.device)
    if len(kept):
        over[:len(kept)] = overshoot(grey, reader.inverse_ratio(kept), reader.log_peak(kept))
    # the features are made where the moments are: on a GPU the moments are not waited for, and the reader runs
    # there too (on a many-core host its few tiny convolutions cost milliseconds of thread wake-ups)
    return curve_features(coarse_scores.to(grey.device), moment, valid.to(grey.device), over), valid, moment


def _learned_log_p(reader: _CandidateReader, grey: Tensor, coarse: Tensor, coarse_scores: Tensor
                   ) -> tuple[Tensor, Tensor]:
    """The shipped curve reader's log-odds of one frame's coarse candidates :math:`(K,)` float64 on the host, and
    their ghost moments :math:`(K,)` on the frame's device (0 past the last event)."""
    curves, valid, moment = _curve_inputs(reader, grey, coarse, coarse_scores)
    return _read_curves(curves[None], valid[None])[0], moment


def _read_curves(curves: Tensor, valid: Tensor) -> Tensor:
    """The shipped curve reader's log-odds :math:`(N, K)` float64 on the host of :math:`(N, F, K)` curves (on the
    device they were made on) and their valid candidates :math:`(N, K)`: the one wait for the device."""
    ensemble = _curve_reader_on(curves.device)
    with torch.no_grad():
        log_p = ensemble(curves.to(next(ensemble.parameters()).dtype), valid.to(curves.device))
    return log_p.double().cpu()


def _candidate_moments(reader: _CandidateReader, grey: Tensor, kept: Tensor) -> Tensor:
    """:func:`~evlatcorr.ghost.ghost_moment` of candidates whose windows hold events, float64 :math:`(K,)` on the
    frame's device: in float32, a few candidates at a time on a CPU (their images stay in cache)."""
    moment = torch.zeros(len(kept), dtype=torch.float64, device=grey.device)
    if len(kept):
        inverse, change = reader.inverse_ratio(kept), reader.log_change(kept)
        chunk = _score_chunk(grey)
        for k0 in range(0, len(kept), chunk):
            k1 = min(k0 + chunk, len(kept))
            moment[k0:k1] = inverse_ratio_moment(grey, inverse[k0:k1], change[k0:k1])
    return moment


@functools.lru_cache(maxsize=4)
def _curve_reader_on(device: torch.device) -> torch.nn.Module:
    """The shipped curve reader on ``device``, its members fused into grouped convolutions (a fifth of the calls,
    each a fixed cost far above the arithmetic of one frame's curves): float32 on a CPU, as trained; float64
    elsewhere, where a GPU's convolutions may otherwise round through TF32 and pick another candidate than a CPU on
    near ties. The search reads its curves on the frame's device."""
    from evlatcorr.curve_reader import FusedCurveReaderEnsemble, load_curve_reader

    fused = FusedCurveReaderEnsemble(load_curve_reader()).eval()
    return fused if device.type == "cpu" else fused.to(device, torch.float64)


def _learned_pick(reader: _CandidateReader, coarse: Tensor, log_p: Tensor, valid: Tensor,
                  prior: tuple[Tensor, float, float] | None = None) -> tuple[float, float, float, Tensor]:
    """The coarse candidate :mod:`evlatcorr.curve_reader`'s shipped ensemble finds likeliest (its log-odds
    ``log_p`` :math:`(K,)` on the host, :func:`_learned_log_p`; ``valid``: the scored candidates) and the centre of
    its probability over that candidate's neighbours (both in reader units), the standard deviation of its
    probability over all candidates (µs), and the reader's log-probability of each candidate without the prior
    :math:`(K,)` (normalised over the scored candidates, −inf elsewhere).

    The centre is the probability-weighted mean of the likeliest candidate and
    :data:`~evlatcorr.curve_reader.CENTRE_HALF_WIDTH` valid
    candidates either side (fewer at the edges, as many on both sides): a latency between candidates, the
    sub-candidate estimate of ``refine=True``.

    ``prior``: ``(candidates in µs, previous latency, σ)``: the temporal prior of the sparsity scores,
    ``exp((l − l')² / 4σ²)`` on a score, enters as ``−(l − l')² / 4σ²`` on the reader's log-probability.
    """
    from evlatcorr.curve_reader import probability_centre

    valid = valid.cpu()
    # what the frame alone says, for fusing frames (evlatcorr.temporal): normalised over the scored candidates
    own = torch.full_like(log_p, -math.inf)
    own[valid] = torch.log_softmax(log_p[valid], 0)
    if prior is not None:
        latencies, previous, sigma = prior
        log_p = log_p - (latencies.double() - previous) ** 2 / (4 * sigma**2)
    candidates = coarse.cpu().double()
    pick, centre = probability_centre(log_p, candidates, int(valid.sum()))
    probability, latencies = torch.softmax(log_p, 0), reader.to_us(candidates).double()
    mean = (probability * latencies).sum()
    spread = float((probability * (latencies - mean) ** 2).sum().sqrt())
    return pick, centre, spread, own


def candidate_curves(blurry: Tensor, events: Events, exposure_start: float, exposure_end: float,
                     threshold: float) -> tuple[Tensor, Tensor, Tensor]:
    """What ``score="learned"`` reads for one frame at the default settings: the coarse candidates
    :math:`(K,)` µs, their :func:`~evlatcorr.curve_reader.curve_features` :math:`(F, K)` and which are valid
    :math:`(K,)` (what :func:`evlatcorr.curve_reader.train_curve_reader` is trained on).

    Args:
        blurry: :math:`(1, C, H, W)` in [0, 1].
        events: the frame's events (``batch_size == 1``), reaching past ``exposure_end``.
        exposure_start, exposure_end: µs.
        threshold: contrast threshold θ.
    """
    check_image(blurry, "blurry")
    if blurry.shape[0] != 1 or events.batch_size != 1:
        raise ValueError(f"candidate_curves takes one frame, got {blurry.shape[0]} images and {events.batch_size} "
                         "event samples")
    config = SearchConfig(score="learned")
    grey = kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry
    last = float(events.t.max()) if len(events) else -math.inf
    span = _Window(exposure_start, exposure_end, 0.0, exposure_end - exposure_start, last - exposure_end)
    reader = _continuous_reader(grey, events, span, float(threshold), config, None)
    coarse_scores = torch.stack(_score_candidates(reader, grey, tuple(_SPARSITY), config, None,
                                                  [reader.coarse] * len(_SPARSITY)))
    curves, valid, _ = _curve_inputs(reader, grey, reader.coarse, coarse_scores)
    return reader.coarse.cpu(), curves.cpu(), valid.cpu()


def _ghost_latency(reader: _CandidateReader, grey: Tensor, coarse: Tensor, moment: Tensor | None = None
                   ) -> float | None:
    """:func:`~evlatcorr.ghost.ghost_root` over the coarse candidates whose windows hold events, µs (``moment``:
    the coarse candidates' moments when already made, :func:`_learned_log_p`)."""
    kept = coarse[coarse <= reader.top]
    if len(kept) < 3:
        return None
    moment = _candidate_moments(reader, grey, kept) if moment is None else moment[:len(kept)]
    return ghost_root(reader.to_us(kept).cpu(), moment.cpu())


def _aligned_candidates(low: float, high: float, num: int, exposure: float) -> tuple[Tensor, float]:
    """About ``num`` candidates from ``low`` to ``high`` (both included), spaced by ``exposure / (2q)``.

    With that spacing one candidate's window end and mid-exposure reference fall on other candidates' window
    starts, so all windows read about ``2 num`` distinct times instead of ``3 num``.
    """
    if high <= low:
        return torch.tensor([low, high], dtype=torch.float64), 0.0
    half_steps = math.ceil(exposure / 2 / ((high - low) / (max(2, num) - 1)) - 1e-9)
    step = exposure / 2 / half_steps
    count = math.floor((high - low) / step + 1e-9)
    coarse = low + torch.arange(count + 1, dtype=torch.float64) * step
    if high - float(coarse[-1]) > 1e-6 * step:
        coarse = torch.cat([coarse, torch.tensor([high], dtype=torch.float64)])
    return coarse, step


def _refine(coarse: Tensor, coarse_scores: Tensor, fine: Tensor, fine_scores: Tensor | None,
            refine: bool) -> tuple[float, float, Tensor, Tensor]:
    """One score's best candidate (a fine one when refined), its confidence, and the candidates it refined."""
    finite = torch.isfinite(coarse_scores)
    k_best = int(torch.argmin(coarse_scores))
    confidence = _confidence(coarse_scores[finite], k_best)
    best = coarse[k_best].item()
    if not refine or fine_scores is None:
        return float(best), confidence, coarse, coarse_scores
    return fine[int(torch.argmin(fine_scores))].item(), confidence, fine, fine_scores


def _confidence(scores: Tensor, k_best: int) -> float:
    """How clearly a score curve (lower is better) has an interior minimum, in [0, 1].

    0 when fewer than three candidates could be scored or the minimum is the last one (the curve
    still falls at the top of the range: the minimum, if any, lies beyond what the events show);
    otherwise the minimum's depth below the curve's median, relative to the median.
    """
    if scores.numel() < 3 or k_best == scores.numel() - 1:
        return 0.0
    median = float(scores.median())
    depth = (median - float(scores.min())) / max(abs(median), 1e-12)
    return max(0.0, min(1.0, depth))


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
