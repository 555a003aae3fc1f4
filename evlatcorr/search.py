"""Constant-latency search in one pass over the events (paper Sec. 3.3, ``l_const``).

Every candidate latency ``l`` needs the EDI ratio ``R`` of the window ``[τ + l, t + l]`` of stamped
events (Eq. 7). Two ways to read all candidates at once:

- ``"continuous"`` (default, :mod:`evlatcorr.search_candidates`): :class:`~evlatcorr.continuous.ContinuousIntegral`
  evaluates each pixel's exact integral of ``exp(θC)`` at every window end from one scatter of the events. No
  temporal bins, so the candidates may lie anywhere; they are spaced so that windows share their ends (about two
  time points per candidate).
- ``"binned"`` (:mod:`evlatcorr.search_binned`): candidates that are whole sub-intervals of the exposure, all read
  from one prefix-sum table. Needed for the ``"linear"`` integral.

The scores of all candidates are batched calls. With a sharpness score the best candidate is refined at every
``T / n`` around it (40 µs at the defaults, far below what any score can tell apart), and the latent image at the
latency chosen is the one its candidate was scored on (no further read of the events). With the learned reader
(the default, :mod:`evlatcorr.search_learned`) the estimate is the centre of the reader's probability around its
pick, between candidates; the latent image there takes one more read of the events' window. Frames alike share one
pass on a GPU (:mod:`evlatcorr.search_batched`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass

import kornia
import torch
from torch import Tensor

from evlatcorr.blank_frames import BLANK_KINDS, MIN_STRUCTURE_RATIO, MIN_UNCLIPPED_SHARE, blank_codes
from evlatcorr.checks import (
    FEW_EVENTS,
    check_batch_vector,
    check_exposure,
    check_image,
    check_search_size,
    check_threshold,
    resolve_memory_budget,
)
from evlatcorr.config import DEFAULT_SCORE, SCORES, SPARSITY_SCORES, SearchConfig
from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
from evlatcorr.events import Events
from evlatcorr.image_tiles import tiles_fit
from evlatcorr.sample_warnings import SampleWarning
from evlatcorr.search_binned import _binned_reader
from evlatcorr.search_candidates import (
    _CandidateReader,
    _continuous_reader,
    _score_candidates,
    _Window,
)
from evlatcorr.search_learned import (
    _answer_block,
    _ghost_latency,
    _learned_log_p,
    _learned_pick,
    _reader_windows,
    _tiled_log_p,
    candidate_curves,
)
from evlatcorr.sharpness import sharpness_score, sharpness_scores
from evlatcorr.temporal import LatencyHistory

__all__ = ["ConstantSearchResult", "search_constant_latency", "default_search_range", "sharpness_score",
           "sharpness_scores", "candidate_curves", "SCORES", "DEFAULT_SCORE", "SearchConfig", "fallback_warning",
           "few_events_warning"]

_SPARSITY = SPARSITY_SCORES


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
        source: per sample, what set ``latency``: ``"reader"`` (``score="learned"``, the default: the curve
            reader's estimate), ``"sharpness"`` (the other scores: their minimum), ``"ghost"`` (the score curve
            was nearly flat and :mod:`evlatcorr.ghost`'s moment crossed zero once), ``"fallback"``, or, with the
            fallback latency, ``"clipped"`` (black or saturated nearly everywhere) or ``"flat"`` (no structure
            above the frame's noise; :mod:`evlatcorr.blank_frames`).
        ignored_pixels: per sample, the hot pixels the search read as having no events (their events span more
            than :data:`~evlatcorr.search_candidates.HOT_PIXEL_LOG_RANGE` of log intensity; continuous method only).
        latency_spread: :math:`(B,)` µs, ``score="learned"``: the standard deviation of the curve reader's
            probability over the candidates, how unsure it is (NaN for the other scores, or where nothing could be
            scored). On the suite's tuning cases the estimate's error grows with it (``docs/accuracy.md``).
        log_probability: :math:`(B, K)` float64, ``score="learned"``: the curve reader's log-probability of each
            coarse candidate (``candidates``) from the frame alone (no temporal prior), normalised over the candidates
            that could be scored (−inf elsewhere); NaN rows for samples where the reader did not run, None when no
            sample has one. :func:`evlatcorr.temporal.fuse_latencies` combines consecutive frames' rows.
        own_latency: :math:`(B,)` µs, where a :class:`~evlatcorr.temporal.LatencyHistory` fused ``latency`` with
            earlier frames': each frame's own estimate (None otherwise).
        pair_latency: :math:`(B,)` µs, with ``own_latency``: where each frame's pair with the next frame agreed best
            (NaN where it came without one, or the pair told nothing).
        outside_range: :math:`(B,)` µs, ``score="learned"`` with a ``search_range`` narrower than the candidates it
            reads: where the reader puts more than half its probability outside that range, its likeliest latency
            there (the estimate is held at the range's edge); NaN elsewhere.
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
    outside_range: Tensor | None = None
    pair_latency: Tensor | None = None


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
    tiles: bool = True,
) -> ConstantSearchResult:
    """Find the constant latency per sample that minimises the ETF of the EDI latent image.

    Args:
        blurry: :math:`(B, C, H, W)` in [0, 1].
        events: events of each sample; they must reach ``exposure_end + search_range[1]`` (``score="learned"``:
            at least one exposure time past ``exposure_end``, the range its reader reads).
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
        score: ``"learned"`` (default: :mod:`evlatcorr.curve_reader` reads the three sparsity curves, the ghost
            moment and the overshoot, of the whole frame and, with ``tiles``, of each of its tiles; the estimate is
            the centre of the probability around its likeliest candidate),
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
            ``window``, ``sigma_us``, ``score`` and ``tiles``, and sets ``ghost_confidence``.
        tiles: ``score="learned"`` (continuous method): also read the curves of the frame's 3x3 tiles and weigh
            them against the whole frame's with the tile reader (:mod:`evlatcorr.tile_reader`); False: the whole
            frame's alone.

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
                              refine=refine, score=score, epsilon=epsilon, window=window, sigma_us=sigma_us,
                              tiles=tiles)
    check_image(blurry, "blurry")
    check_search_size(blurry.shape, "blurry frames")
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


def fallback_warning(kind: str, samples: list[int], outcome: str) -> SampleWarning:
    """The warning of samples given a fallback latency, in the constant and the spatial mode alike: ``kind``
    ``"clipped"`` (black or saturated nearly everywhere), ``"flat"`` (no structure above the frame's noise; both
    :mod:`evlatcorr.blank_frames`) or ``"fallback"`` (no clear sharpness minimum); ``outcome`` says what their
    latency is, with ``{its}`` for "its" / "their".

    Raises:
        ValueError: for another ``kind``.

    Example:
        >>> str(fallback_warning("fallback", [2], "{its} latency is the fallback 0 us"))[:58]
        'sample 2: the sharpness score has no clear minimum inside '
        >>> str(fallback_warning("clipped", [0, 1], "{its} latency is 0 us")).endswith("; their latency is 0 us")
        True
    """
    if kind == "clipped":
        why = (f"black or saturated in nearly every pixel (fewer than {MIN_UNCLIPPED_SHARE:.1%} inside the sensor's "
               "range): nothing for EDI to sharpen")
        summary = "black or saturated in nearly every pixel: the fallback latency"
    elif kind == "flat":
        why = (f"flat: no structure above its pixel noise (its smoothed contrast under {MIN_STRUCTURE_RATIO:g} times "
               "what the noise alone leaves; a blank or grey frame, or one paired with the wrong events): nothing "
               "for EDI to sharpen")
        summary = "flat, no structure above its noise: the fallback latency"
    elif kind == "fallback":
        why = ("the sharpness score has no clear minimum inside the latency range the events cover (too few events "
               "or no texture)")
        summary = "no clear sharpness minimum inside the latency range the events cover: the fallback latency"
    else:
        raise ValueError(f"kind must be 'clipped', 'flat' or 'fallback', got {kind!r}")
    return SampleWarning(kind, samples, f"{{which}}: {why}; {outcome}", summary)


def few_events_warning(samples: list[int], counted: str, guess: str, figures: str = "",
                       together: bool = False) -> SampleWarning:
    """The warning of samples with under :data:`~evlatcorr.checks.FEW_EVENTS` events in their exposure and search
    window, in the constant and the spatial mode alike: ``counted`` says how many (e.g. ``"30, 37"``; ``together``:
    one count of all the samples' windows), ``guess`` what their events cannot tell (``"the estimate"``),
    ``figures`` follows it in the samples' own message.

    Example:
        >>> str(few_events_warning([1], "30", "the estimate", " (16 us)"))[:62]
        'sample 1: only 30 event(s) in its exposure and search window, '
    """
    return SampleWarning(
        "few_events", samples, f"{{which}}: only {counted} event(s) in {{its}} exposure and search window"
        f"{' together' if together else ''}, too few "
        f"(under {FEW_EVENTS}) to tell a latency from: {guess}{figures} is little better than a guess, and moves only "
        "those events",
        f"under {FEW_EVENTS} events in the exposure and search window, too few to tell a latency from: {guess} is "
        "little better than a guess, and moves only those events")


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
    blank = blank_codes(grey).to(start)
    # every sample's bounds in one copy to the host (one wait for a GPU, not six per sample)
    spans = torch.stack([start, end, lows.to(start), highs.to(start), reach, blank]).T.cpu().tolist()
    thetas = theta.cpu().tolist()
    windows = [_Window(*span[:5], blank=BLANK_KINDS[int(span[5]) - 1] if span[5] else None) for span in spans]
    if config.score == "learned" and rng is not None:  # the reader reads the range it was trained on
        windows = _reader_windows(windows)
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
                _fuse_with_history(res, history, windows[i])
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
        outside_range=torch.tensor([r.outside_range_us for r in results], dtype=torch.float64, device=blurry.device),
        pair_latency=(None if history is None else
                      torch.tensor([r.pair_latency_us for r in results], dtype=torch.float64, device=blurry.device)),
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
    pair_latency_us: float = math.nan  # where the frame's pair with the next frame agreed best (a history's)
    outside_range_us: float = math.nan  # the reader's likeliest latency where it lies outside the user's range
    # the latent's read at a latency, where it was left until the latency is final (a history to fuse with)
    read_latent: Callable[[float], Tensor | None] | None = None


def _fuse_with_history(result: _OneResult, history: LatencyHistory, span: _Window) -> None:
    """The frame's latency fused with the earlier frames' of ``history`` (its own estimate kept in ``own_latency``),
    within the frame's answer range."""
    result.own_latency = result.latency
    low, high = span.answer_range
    result.latency = min(max(history.fuse(result.latency, result.candidates, result.log_probability), low), high)
    result.pair_latency_us = history.pair_latency_us


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
    low, high = span.answer_range  # where the estimate must lie (the learned reader's candidates may span more)
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

    spread, log_probability, outside = math.nan, None, None

    def result(*args, **kwargs) -> _OneResult:
        return _OneResult(*args, **kwargs, ignored_pixels=reader.ignored_pixels, spread_us=spread,
                          log_probability=log_probability, read_latent=read_latent,
                          outside_range_us=math.nan if outside is None else outside)

    fallback = low if prev is None else min(max(float(prev), low), high)
    nan = torch.full((len(coarse),), math.nan, dtype=torch.float64)
    if reader.top < reader.floor:  # no candidate window holds events: nothing to score
        read_latent = None  # and no latent image to read
        return result(fallback, to_us(coarse).cpu(), nan, to_us(coarse).cpu(), nan, 0.0, True, source="fallback")
    if span.blank:  # every candidate's latent is as made up from the events as any other
        return result(fallback, to_us(coarse).cpu(), nan, to_us(coarse).cpu(), nan, 0.0, True,
                      reader.final_ratio(fallback), span.blank)

    # the learned reader reads the curves as it was trained (no temporal prior) and takes the prior afterwards
    coarse_prev = None if config.score == "learned" else prev
    moment = None
    if (evidence is None and config.score == "learned" and config.tiles and method == "continuous"
            and tiles_fit(*grey.shape[-2:])):
        # the whole frame's and its tiles' curves from the same passes
        evidence = _Evidence(reader, *_tiled_log_p(reader, grey))
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
        scored = torch.isfinite(coarse_scores[0])
        allowed = None if span.answer is None else _answer_block(to_us(coarse).cpu().double(), *span.answer)
        if allowed is not None and not bool((scored.cpu() & allowed).any()):
            # the events end before any window the user's range allows: nothing in it could be scored
            return result(fallback, to_us(coarse).cpu(), coarse_scores[0], to_us(coarse).cpu(), coarse_scores[0],
                          0.0, True, reader.final_ratio(fallback), "fallback")
        pick, centre, spread, log_probability, outside = _learned_pick(reader, coarse, log_p, scored, prior, allowed)
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
                  reader.final_ratio(latency), "reader" if config.score == "learned" else "sharpness")


def _read_later(latency: float) -> None:
    """The latent at the estimate is read once the latency is final (fused with a history's frames)."""
    return None


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
