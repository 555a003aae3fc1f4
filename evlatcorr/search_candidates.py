"""The constant-latency search's candidates: how they are laid out, read and scored (:mod:`evlatcorr.search`).

Every candidate latency ``l`` needs the EDI ratio ``R`` of the window ``[τ + l, t + l]`` of stamped events (Eq. 7).
A :class:`_CandidateReader` says how one frame's candidates lie and reads their ratios. The default,
:func:`_continuous_reader`, reads them from :class:`~evlatcorr.continuous.ContinuousIntegral`: each pixel's exact
integral of ``exp(θC)`` at every window end from one scatter of the events, no temporal bins, so the candidates may
lie anywhere; they are spaced so that windows share their ends (about two time points per candidate,
:func:`_aligned_candidates`). The binned table (``method="binned"``) is :mod:`evlatcorr.search_binned`.
:func:`_score_candidates` scores the latents ``grey / R`` of any candidates in batched calls, without making them.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from evlatcorr import compiled, continuous
from evlatcorr.checks import check_memory, resolve_memory_budget
from evlatcorr.config import SearchConfig
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.events import Events
from evlatcorr.overshoot import overshoot_stride
from evlatcorr.sharpness import _scores_of

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
# With the compiled passes (evlatcorr.compiled), as many as take this many bytes of one float32 image each (all 101
# at DAVIS346 size): each pass starts threads that share the cores with PyTorch's still spinning ones, so the fewer
# passes the better, and a log image of all of them is what the compiled scores and moments read
_COMPILED_SCORE_BYTES = 64 * 2**20
# Elsewhere (a GPU), as many as fit in this many bytes of score work arrays (about 8 float32 images each): there
# each kernel launch costs more than the memory, and 101 candidates at DAVIS346 size take about 290 MB
_DEVICE_SCORE_BYTES = 2**30


@dataclass(frozen=True)
class _Window:
    """One sample's exposure ``[start, end]``, the latency range ``[low, high]`` its candidates span and ``reach``
    = last event − end, µs; ``answer``: the range the estimate must lie in where it is narrower than the
    candidates' (the learned reader reads the range it was trained on,
    :func:`evlatcorr.search_learned._reader_windows`), else None; ``blank``: the frame's kind of blank, which is
    not searched (:mod:`evlatcorr.blank_frames`: ``"clipped"``, ``"flat"``), else None."""

    start: float
    end: float
    low: float
    high: float
    reach: float
    answer: tuple[float, float] | None = None
    blank: str | None = None  # nothing for EDI to sharpen: black or saturated nearly everywhere, or flat

    @property
    def answer_range(self) -> tuple[float, float]:
        return (self.low, self.high) if self.answer is None else self.answer


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
        return max(_SCORE_CHUNK, _COMPILED_SCORE_BYTES // (4 * image.numel())) if compiled.ENABLED else _SCORE_CHUNK
    return max(1, _DEVICE_SCORE_BYTES // (8 * 4 * image.numel()))


def _latent_scores(grey: Tensor, inverse: Tensor, latency: Tensor, previous: Tensor | None, scores: tuple[str, ...],
                   config: SearchConfig) -> Tensor:
    """:func:`sharpness_scores` of the latent images ``grey · inverse`` :math:`(K, 1, H, W)` without making them:
    each image's mean is one product with ``grey``, and ``log(grey · inverse + c · mean)`` one fused pass."""
    mean = (inverse.flatten(1) @ grey.flatten().to(inverse)).div_(grey.numel()).clamp_min_(1e-12)[:, None, None, None]
    return _scores_of(lambda floor: torch.addcmul(floor * mean, inverse, grey).log_(), lambda: grey * inverse, latency,
                      previous, scores, config.epsilon, config.window, config.sigma_us)
