"""The default constant-latency search of several frames in one pass, for a GPU.

On a GPU the search of one frame is bound by kernel launches, Python and its waits for the device, not by
arithmetic: a frame a hundredth of DAVIS346's size took nearly as long on an H100. Frames with the same
exposure time, search range and contrast threshold can share every launch. Their events, each frame's times taken
from its own exposure start, are laid out as one tall image (frame ``j``'s rows ``j·H .. (j + 1)·H``), so one
:class:`~evlatcorr.continuous.ContinuousIntegral` reads every frame's candidate windows at once. The scores, ghost
moments and curve-reader inputs of all frames are then batched calls, and one read of every frame's window at
its estimate gives the latents. Each frame's decision is still its own
(:func:`evlatcorr.search._search_one`), so the results are those of the frame-by-frame search (to float32
rounding).

On a CPU the frame-by-frame search is bound by memory traffic instead: one pass for many frames saves nothing
there and gives up its cache-sized strips, so :func:`search_frames_together` is used on other devices only.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from evlatcorr import continuous
from evlatcorr.checks import resolve_memory_budget
from evlatcorr.config import SearchConfig
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.curve_reader import curve_features
from evlatcorr.events import Events
from evlatcorr.ghost import stacked_inverse_ratio_moment
from evlatcorr.image_tiles import TILE_GRID, tile_sums, tiles_fit
from evlatcorr.overshoot import overshoot, overshoot_stride
from evlatcorr.search import _SPARSITY, _Evidence, _fuse_with_history, _OneResult, _read_later, _search_one
from evlatcorr.search_candidates import (
    HOT_PIXEL_LOG_RANGE,
    _aligned_candidates,
    _CandidateReader,
    _score_chunk,
    _Window,
)
from evlatcorr.search_learned import _read_curves, _tile_reader
from evlatcorr.sharpness import _scores_of
from evlatcorr.temporal import LatencyHistory
from evlatcorr.tile_curves import tile_moments, tile_overshoots, tile_sparsity_scores
from evlatcorr.tile_reader import tile_inputs, tile_log_probability

__all__ = ["frames_can_share_a_pass", "search_frames_together"]

# Frames searched in one pass at most: the read of the latents at the estimates takes every frame's window over
# every frame's pixels (a square in the number of frames)
MAX_FRAMES = 16
# Whether a CPU batches frames too (tests compare the two searches there)
ON_CPU = False


def frames_can_share_a_pass(grey: Tensor, spans: list[_Window], thetas: list[float], config: SearchConfig,
                            method: str) -> bool:
    """Whether :func:`search_frames_together` serves the frames ``grey`` :math:`(B, 1, H, W)`: the learned score
    (the default) with the continuous integral, on a GPU, more than one frame, one threshold, and one exposure time
    and search range for all."""
    if len(spans) < 2 or method != "continuous" or config.score != "learned":
        return False
    if grey.device.type == "cpu" and not ON_CPU:
        return False
    shapes = {(s.end - s.start, s.low, s.high) for s in spans}
    return len(shapes) == 1 and len(set(thetas)) == 1


def search_frames_together(grey: Tensor, events: Events, spans: list[_Window], theta: float, config: SearchConfig,
                           previous: Tensor | None, budget: int | None,
                           history: LatencyHistory | None = None) -> list[_OneResult]:
    """:func:`evlatcorr.search._search_one` of every frame, the events read in passes of several frames.

    Args:
        grey: the frames :math:`(B, 1, H, W)`.
        events: their events (``batch_size == B``).
        spans: each frame's exposure, range and reach (:func:`frames_can_share_a_pass` holds).
        theta: the contrast threshold of all.
        config: the search settings (``score="learned"``).
        previous: the previous latencies :math:`(B,)` µs, or None.
        budget: the memory budget in bytes (None: the default); each pass takes as many frames as fit in it (at
            most :data:`MAX_FRAMES`).
        history: the frames are the next of a stream: each one's latency is fused with the earlier frames' in
            order, before the latents are read.

    Returns:
        one result per frame, as the frame-by-frame search gives it.
    """
    limit = resolve_memory_budget(budget)
    num_candidates = len(_aligned_candidates(spans[0].low, spans[0].high, config.num_candidates,
                                             spans[0].end - spans[0].start)[0])
    bounds = events.sample_bounds().tolist()  # one wait for the device, for every pass's plan
    # each frame's events and its candidates' reads (1 / R, the event change and the peak rise) with their scores'
    # work arrays
    frame_bytes = [(hi - lo) * continuous.BYTES_PER_EVENT + grey[0].numel() * num_candidates * 28
                   for lo, hi in zip(bounds[:-1], bounds[1:])]
    results: list[_OneResult] = []
    first = 0
    while first < len(spans):
        last, used = first + 1, frame_bytes[first]
        while last < len(spans) and last - first < MAX_FRAMES and used + frame_bytes[last] <= limit:
            used += frame_bytes[last]
            last += 1
        results += _search_pass(grey, events, bounds, spans, theta, config, previous, first, last, limit, history)
        first = last
    return results


def _search_pass(grey: Tensor, events: Events, bounds: list[int], spans: list[_Window], theta: float,
                 config: SearchConfig, previous: Tensor | None, first: int, last: int, limit: int,
                 history: LatencyHistory | None) -> list[_OneResult]:
    """The frames ``first .. last − 1`` in one pass (``bounds``: where each frame's events start, and the end)."""
    frames, (height, width) = last - first, grey.shape[-2:]
    span = spans[first]
    exposure = span.end - span.start
    coarse, _ = _aligned_candidates(span.low, span.high, config.num_candidates, exposure)
    tops = [s.reach if math.isfinite(s.reach) else -math.inf for s in spans[first:last]]
    integral = ContinuousIntegral(_tall_events(events, bounds, spans, first, last), theta, HOT_PIXEL_LOG_RANGE,
                                  time_sorted=False)
    ignored = integral.ignored.view(frames, -1).sum(1).tolist()
    kept = coarse[coarse <= max(tops)]  # sorted: each frame's own candidates are a prefix of them
    own = [int((kept <= top).sum()) for top in tops]
    tiles = config.tiles and tiles_fit(height, width)
    regions = 1 + TILE_GRID[0] * TILE_GRID[1] if tiles else 1  # the whole frame, then its tiles
    scores = torch.full((frames, regions, len(_SPARSITY), len(coarse)), math.inf, dtype=torch.float64)
    moments = torch.zeros((frames, regions, len(coarse)), dtype=torch.float64, device=grey.device)
    overshoots = torch.zeros_like(moments)
    activity = torch.zeros((frames, regions - 1), dtype=torch.float64, device=grey.device)
    inverse = None
    if len(kept):
        inverse, change, peak = _read(integral, exposure, kept, (frames, height, width), limit)
        block = grey[first:last, 0][None]  # (1, F, H, W): frame j's pixels are block j of the tall image
        tall = (len(kept), frames, height, width)
        if tiles:
            values, moment, over = _tile_reductions(block, inverse.view(tall), change.view(tall), peak)
            # each frame's share of its events' change over its own candidates, as the frame alone takes it
            activity = torch.stack([tile_sums(change.view(tall)[:n, j].abs().sum(0).double(), TILE_GRID)
                                    for j, n in enumerate(own)])
        else:
            values, moment = _scores_and_moments(block, inverse.view(tall), change.view(tall), config)
            over = overshoot(block.to(inverse), inverse.view(tall), peak).view(len(kept), frames)
            values, moment, over = values[..., None], moment[..., None], over[..., None]
        for j, n in enumerate(own):
            scores[j, :, :, :n] = values[:, :n, j].permute(2, 0, 1)
            moments[j, :, :n] = moment[:n, j].T
            overshoots[j, :, :n] = over[:n, j].T
        del change, peak
    valid = torch.isfinite(scores[:, 0, 0])  # (F, K)
    every = valid[:, None].expand(-1, regions, -1)
    curves = curve_features(scores.flatten(0, 1).to(grey.device), moments.flatten(0, 1),
                            every.flatten(0, 1).to(grey.device), overshoots.flatten(0, 1))
    log_p = _read_curves(curves, every.flatten(0, 1)).view(frames, regions, -1)
    curves = curves.view(frames, regions, *curves.shape[1:])
    if tiles:
        share = (activity / activity.sum(1, keepdim=True).clamp_min(1e-12)).cpu()
        inputs = tile_inputs(curves[:, 0].cpu(), log_p[:, 1:], share, valid)
        log_p = tile_log_probability(inputs, log_p[:, 0], valid, _tile_reader())
    else:
        log_p = log_p[:, 0]
    scores, moments = scores[:, 0], moments[:, 0]

    results = []
    for j in range(frames):
        reader = _CandidateReader(coarse, tops[j], span.low, _same, _read_with_the_pass, _read_with_the_pass,
                                  _read_later, _read_with_the_pass, ignored[j])
        evidence = _Evidence(reader, scores[j], log_p[j], moments[j])
        prev = None if previous is None else previous[first + j:first + j + 1]
        results.append(_search_one(grey[first + j:first + j + 1], None, spans[first + j], theta, config, prev,
                                   "step", evidence=evidence))
        if history is not None:
            _fuse_with_history(results[-1], history, spans[first + j])
    _read_latents(integral, exposure, results, tops, span.low, kept, own, inverse, (frames, height, width))
    return results


def _tall_events(events: Events, bounds: list[int], spans: list[_Window], first: int, last: int) -> Events:
    """The events of frames ``first .. last − 1`` as one sample of a tall sensor: frame ``j``'s rows moved down by
    ``j·H`` and its times counted from its exposure start (sorted within each pixel, not overall)."""
    height, width = events.sensor_size
    lo, hi = bounds[first], bounds[last]
    batch = events.batch[lo:hi] - first
    starts = torch.tensor([s.start for s in spans[first:last]], dtype=torch.float64, device=events.device)
    t = events.t[lo:hi] - starts.index_select(0, batch)
    y = torch.addcmul(events.y[lo:hi], batch, torch.full_like(batch, height))
    return Events.from_canonical(events.x[lo:hi], y, t, events.p[lo:hi], torch.zeros_like(batch),
                                 ((last - first) * height, width), 1)


def _read(integral: ContinuousIntegral, exposure: float, kept: Tensor, shape: tuple[int, int, int], limit: int
          ) -> tuple[Tensor, Tensor, Tensor]:
    """``1 / R`` and the event change of the candidates ``kept`` over every frame's windows, :math:`(K, 1, F·H, W)`
    float32 each, and the peak log rise at each frame's own every s-th row and column (the overshoot's pixels,
    :func:`~evlatcorr.overshoot.overshoot_stride`) :math:`(K, F, ⌈H/s⌉, ⌈W/s⌉)`, as many candidates per read as the
    budget allows (``shape``: the frames' ``(F, H, W)``)."""
    frames, height, width = shape
    stride = overshoot_stride(height, width)
    inverse = torch.empty((len(kept), 1, frames * height, width), dtype=torch.float32, device=integral.device)
    change = torch.empty_like(inverse)
    peak = torch.empty((len(kept), 1, frames * -(-height // stride), -(-width // stride)), dtype=torch.float32,
                       device=integral.device)
    # the pass was sized to hold every candidate's read (search_frames_together): one read unless over the budget
    chunk = max(1, limit // (inverse[0].numel() * (continuous.BYTES_PER_CANDIDATE + 8)))
    for k in range(0, len(kept), chunk):
        integral.inverse_ratio(0.0, exposure, kept[k:k + chunk], out=inverse[k:k + chunk],
                               change_out=change[k:k + chunk], peak_out=peak[k:k + chunk], peak_stride=stride,
                               peak_frame_height=height)
    return inverse, change, peak.view(len(kept), frames, -(-height // stride), peak.shape[-1])


def _scores_and_moments(grey: Tensor, inverse: Tensor, change: Tensor, config: SearchConfig
                        ) -> tuple[Tensor, Tensor]:
    """The sparsity scores :math:`(3, K, F)` (float64, host) and ghost moments :math:`(K, F)` (float64, device) of
    the latents ``grey · inverse`` :math:`(K, F, H, W)` (``grey`` :math:`(1, F, H, W)`), as
    :func:`evlatcorr.search_candidates._latent_scores` and :func:`evlatcorr.ghost.inverse_ratio_moment` give them
    frame by frame."""
    k, frames, height, width = inverse.shape
    grey = grey.to(inverse)
    # a few candidates of every frame at a time, as the frame-by-frame search takes a few of one frame's
    chunk = max(1, _score_chunk(grey[:, :1]) // frames)
    values = [_chunk_scores(grey, inverse[k0:k0 + chunk], config) for k0 in range(0, k, chunk)]
    moments = [stacked_inverse_ratio_moment(grey, inverse[k0:k0 + chunk], change[k0:k0 + chunk])
               for k0 in range(0, k, chunk)]
    return torch.cat(values, 1).double().cpu(), torch.cat(moments).double()


def _tile_reductions(grey: Tensor, inverse: Tensor, change: Tensor, peak: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The sparsity scores :math:`(3, K, F, 1 + T)` (float64, host), ghost moments and overshoots
    :math:`(K, F, 1 + T)` (float64, device) of the latents ``grey · inverse`` :math:`(K, F, H, W)` over each whole
    frame and its tiles, as :func:`evlatcorr.tile_curves.tile_reductions` gives them frame by frame."""
    k, frames = inverse.shape[:2]
    grey = grey.to(inverse)
    chunk = max(1, _score_chunk(grey[:, :1]) // frames)
    values = [tile_sparsity_scores(grey, inverse[k0:k0 + chunk]) for k0 in range(0, k, chunk)]
    moments = [tile_moments(grey, inverse[k0:k0 + chunk], change[k0:k0 + chunk]) for k0 in range(0, k, chunk)]
    over = tile_overshoots(grey, inverse, peak)
    return torch.cat(values, 1).cpu(), torch.cat(moments).to(grey.device), over.to(grey.device)


def _chunk_scores(grey: Tensor, inverse: Tensor, config: SearchConfig) -> Tensor:
    """The sparsity scores :math:`(3, K, F)` of the latents ``grey · inverse`` :math:`(K, F, H, W)`: each latent's
    mean and ``log(latent + c · mean)`` as :func:`evlatcorr.search_candidates._latent_scores` makes them."""
    k, frames, height, width = inverse.shape
    mean = torch.einsum("kfhw,fhw->kf", inverse, grey[0]).div_(height * width).clamp_min_(1e-12)[..., None, None]
    flat = (k * frames, 1, height, width)
    values = _scores_of(lambda floor: torch.mul(inverse, grey).add_(floor * mean).log_().view(flat), None,
                        torch.zeros(k * frames, device=inverse.device), None, tuple(_SPARSITY), config.epsilon,
                        config.window, config.sigma_us)
    return values.view(len(_SPARSITY), k, frames)


def _read_latents(integral: ContinuousIntegral, exposure: float, results: list[_OneResult], tops: list[float],
                  floor: float, kept: Tensor, own: list[int], inverse: Tensor | None,
                  shape: tuple[int, int, int]) -> None:
    """Give every result whose frame had a window to score its ``log_ratio`` at its latency :math:`(1, 1, H, W)`
    float64: a scored candidate's from its read (as the frame-by-frame search does), the others' from one more
    read of every such window."""
    frames, height, width = shape
    fresh = []
    for j, result in enumerate(results):
        if tops[j] < floor:  # nothing to score: no latent, as frame by frame
            continue
        hit = torch.nonzero(kept[:own[j]] == result.latency).flatten()
        if len(hit) and inverse is not None:
            k = int(hit[0])
            result.log_ratio = torch.log(inverse[k:k + 1, :, j * height:(j + 1) * height].double()).neg_()
        else:
            fresh.append(j)
    if not fresh:
        return
    latencies = torch.tensor([results[j].latency for j in fresh], dtype=torch.float64)
    ratio = integral.log_ratio(0.0, exposure, latencies).view(len(fresh), frames, height, width)
    for row, j in enumerate(fresh):
        results[j].log_ratio = ratio[row, j][None, None]


def _same(value: Tensor) -> Tensor:
    """Candidates are in µs already."""
    return value


def _read_with_the_pass(*args: object) -> Tensor:
    raise RuntimeError("a frame searched with others reads its candidates with them (search_frames_together)")
