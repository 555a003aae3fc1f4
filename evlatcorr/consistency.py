"""Two-frame consistency: do two consecutive frames' EDI reconstructions agree between them?

Each blurry frame, with the events, gives the latent image at any time (EDI with that time as its
reference). Between two exposures both frames give it: frame ``i`` from its exposure forwards,
frame ``i + 1`` from its exposure backwards. With the right contrast threshold θ and latency the
two agree up to noise; a wrong θ scales every event's step and a wrong latency reads the wrong
events, and both make them disagree. No ground truth is needed, and the sharpness score the
latency search minimises plays no part, so it is a fair check of a correction on real recordings
and a way to estimate a recording's θ (:func:`estimate_recording_threshold`).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from torch import Tensor

from evlatcorr.checks import check_threshold, resolve_memory_budget
from evlatcorr.edi import _log_ratio_of_differences, event_grid, grid_reads
from evlatcorr.frames import EventFrames
from evlatcorr.integral import grid_bytes_per_point

__all__ = ["THRESHOLD_BOUNDS", "pair_disagreement", "estimate_recording_threshold"]

# log(I + c): c keeps the dark pixels' noise from dominating (images in [0, 1])
_FLOOR = 0.02
# Most grid points an EDI grid may span: it reaches from an exposure to the gap's middle in steps of
# exposure / num_bins, so short exposures far apart get fewer sub-intervals (not gigabytes of grid). The two
# frames' grids are held at once, so each also fits in half the memory budget: at DAVIS346 size about 1000
# points (a 5 ms exposure read 20 ms away asked for 1990, 2 GB each, and the command line stopped).
_MAX_GRID_POINTS = 4000


def _num_bins(pairs: EventFrames, latency: Tensor, num_bins: int) -> int:
    exposure = float(torch.minimum(pairs.exposure_time, pairs.exposure_end_next - pairs.exposure_start_next).min())
    span = float((pairs.exposure_end_next - pairs.exposure_start + latency.abs()).max())
    per_point = pairs.batch_size * pairs.sensor_size[0] * pairs.sensor_size[1] * grid_bytes_per_point()
    points = min(_MAX_GRID_POINTS, resolve_memory_budget() // 2 // per_point - 4)  # a point either side, rounding
    return max(8, min(num_bins, int(points * exposure / max(span, exposure))))


def _check_pairs(pairs: EventFrames) -> None:
    if not isinstance(pairs, EventFrames):
        raise ValueError(f"pairs must be an EventFrames batch, got {type(pairs).__name__}")
    if pairs.blurry_next is None or pairs.exposure_start_next is None or pairs.exposure_end_next is None:
        raise ValueError("pairs need blurry_next, exposure_start_next and exposure_end_next (two consecutive frames)")
    if bool((pairs.exposure_start_next < pairs.exposure_end).any()):
        raise ValueError("the next exposure must start after the first one ends")


def _gap_middle(pairs: EventFrames) -> Tensor:
    return (pairs.exposure_end + pairs.exposure_start_next) / 2


class _GapReads(NamedTuple):
    """What the two frames' EDI at the middle of the gap reads of the events, whatever θ, kept only at the pixels
    where either frame's events change it: elsewhere each latent is its blurry frame at every θ, so their part of
    the disagreement is summed once. A low-light recording has events at a few tenths of its pixels, and a search
    over θ then costs that share of the whole image's."""

    batch: Tensor  # (P,) the sample of each pixel kept
    frames: list[tuple[Tensor, list[Tensor]]]  # each frame's blurry values (C, P) and reads (n, P), chunk by chunk
    still: Tensor  # (B,) the other pixels' sum of |log(B_i + c) − log(B_{i+1} + c)| over pixels and channels
    size: int  # C·H·W: what the sums are divided by


def _gap_reads(pairs: EventFrames, latency: Tensor, num_bins: int) -> _GapReads:
    """What each frame's EDI at the middle of the gap reads of its events, whatever θ
    (:func:`~evlatcorr.edi.grid_reads`), at the pixels it changes: a search over θ reads the events once."""
    t = _gap_middle(pairs)
    frames = ((pairs.blurry, pairs.exposure_start, pairs.exposure_end),
              (pairs.blurry_next, pairs.exposure_start_next, pairs.exposure_end_next))
    full = []
    for blurry, start, end in frames:
        grid = event_grid(pairs.events, start, end, num_bins, (latency, latency), time=t)
        full.append((blurry, grid_reads(blurry, pairs.events, start, end, grid, latency, num_bins, t)))
    b, _, h, w = pairs.blurry.shape
    moving = torch.zeros(b, h, w, dtype=torch.bool, device=pairs.blurry.device)
    for _, reads in full:
        for chunk in reads:
            moving |= (chunk != 0).any(1)
    index = moving.flatten().nonzero().squeeze(1)

    def kept(x: Tensor) -> Tensor:  # (B, K, H, W) -> (K, P): the kept pixels of each of the K planes
        return x.transpose(0, 1).reshape(x.shape[1], -1)[:, index]

    (first, _), (second, _) = full
    still = (torch.log(first.clamp_min(0) + _FLOOR) - torch.log(second.clamp_min(0) + _FLOOR)).abs()
    still = still.masked_fill(moving[:, None], 0.0).sum(dim=(1, 2, 3))
    return _GapReads(index // (h * w), [(kept(blurry), [kept(chunk) for chunk in reads]) for blurry, reads in full],
                     still, first[0].numel())


def _disagreement(reads: _GapReads, theta: Tensor | float, num_bins: int) -> Tensor:
    """The mean over pixels of ``|log(I_i(t) + c) − log(I_{i+1}(t) + c)|`` at θ, per pair :math:`(B,)`."""
    first = reads.frames[0][1][0]
    theta = check_threshold(theta, len(reads.still)).to(first.device, first.dtype)[reads.batch]
    logs = []
    for blurry, chunks in reads.frames:  # as edi.latent_from_grid_reads, on a (1, n, 1, P) layout
        log_ratio = _log_ratio_of_differences([c[None, :, None] for c in chunks], theta.view(1, 1, 1, -1), num_bins)
        latent = blurry * torch.exp(-log_ratio.view(1, -1)).to(blurry.dtype)
        logs.append(torch.log(latent.clamp_min(0) + _FLOOR))
    moving = (logs[0] - logs[1]).abs().sum(0).to(reads.still.dtype)
    return (reads.still.index_add(0, reads.batch, moving)) / reads.size


def _latency_vector(latency: Tensor | float | None, pairs: EventFrames) -> Tensor:
    value = torch.as_tensor(0.0 if latency is None else latency, dtype=torch.float64, device=pairs.device)
    if value.dim() == 0:
        value = value.expand(pairs.batch_size)
    if tuple(value.shape) != (pairs.batch_size,) or not bool(torch.isfinite(value).all()):
        raise ValueError(f"latency must be a finite scalar or ({pairs.batch_size},) µs, got shape "
                         f"{tuple(value.shape)}")
    return value.contiguous()


def pair_disagreement(pairs: EventFrames, threshold: float | Tensor = 0.2, latency: Tensor | float | None = None,
                      num_bins: int = 200) -> Tensor:
    """How much two consecutive frames' EDI latent images disagree at the middle of the gap between them.

    The mean over pixels of ``|log(I_i(t) + c) − log(I_{i+1}(t) + c)|`` (c = 0.02), where ``I_i(t)`` is
    frame ``i``'s EDI latent image at ``t``, the middle of the gap between the two exposures, from
    the events read ``latency`` late. Lower is more consistent.

    Args:
        pairs: batch of ``B`` pairs: ``blurry`` and ``blurry_next`` :math:`(B, C, H, W)`, both exposures,
            and events covering both exposures plus the latency.
        threshold: contrast threshold θ, float or :math:`(B,)`.
        latency: one latency per pair (scalar or :math:`(B,)`, µs) for both frames' events; None: 0.
        num_bins: EDI sub-intervals per exposure (fewer when the exposures are short and far apart: the
            grid spans at most 4000 of them).

    Returns:
        :math:`(B,)`.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pairs = simulate("camera", num_frames=2, height=32, width=40, latency_us=3000.0,
        ...                  seed=0).pairs("delayed", after_us=5000.0)
        >>> bool(pair_disagreement(pairs, 0.2, 3000.0) < pair_disagreement(pairs, 0.2, 0.0))
        True
    """
    _check_pairs(pairs)
    latency = _latency_vector(latency, pairs)
    num_bins = _num_bins(pairs, latency, num_bins)
    return _disagreement(_gap_reads(pairs, latency, num_bins), threshold, num_bins)


#: the interval :func:`estimate_recording_threshold` searches θ in by default
THRESHOLD_BOUNDS = (0.05, 1.5)


def estimate_recording_threshold(pairs: EventFrames, latency: Tensor | float | None = None,
                                 bounds: tuple[float, float] = THRESHOLD_BOUNDS, iterations: int = 14,
                                 num_bins: int = 200) -> float:
    """The contrast threshold θ that makes consecutive frames most consistent (one θ for all the pairs).

    Golden-section search over ``log θ`` of the mean of :func:`pair_disagreement` over the pairs:
    too small a θ leaves each reconstruction blurred towards its own exposure, too large a θ
    overshoots every change, and either way the two frames disagree between their exposures. A
    camera's θ is a setting of its bias currents, so one value serves a whole recording; a few
    pairs with motion are enough.

    Args:
        pairs: batch of pairs (see :func:`pair_disagreement`), e.g. a few consecutive frame pairs of a
            recording.
        latency: latency per pair (scalar or :math:`(B,)` µs); None: 0.
        bounds: search interval of θ, ``0 < low < high``.
        iterations: golden-section steps (each shrinks the interval by 0.618).
        num_bins: EDI sub-intervals per exposure.

    Returns:
        θ.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pairs = simulate("camera", num_frames=3, height=48, width=64, threshold=0.5,
        ...                  latency_us=2000.0, seed=0).pairs("delayed", after_us=5000.0)
        >>> 0.4 < estimate_recording_threshold(pairs, latency=2000.0) < 0.6
        True
    """
    _check_pairs(pairs)
    if not 0 < bounds[0] < bounds[1] or not math.isfinite(bounds[1]):
        raise ValueError(f"bounds must satisfy 0 < low < high < inf, got {bounds}")
    if iterations < 1:
        raise ValueError(f"iterations must be >= 1, got {iterations}")
    latency = _latency_vector(latency, pairs)
    num_bins = _num_bins(pairs, latency, num_bins)
    reads = _gap_reads(pairs, latency, num_bins)  # the events read once, for every θ tried

    def energy(log_theta: float) -> float:
        return float(_disagreement(reads, math.exp(log_theta), num_bins).mean())

    lo, hi = math.log(bounds[0]), math.log(bounds[1])
    ratio = (math.sqrt(5) - 1) / 2
    x1, x2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    f1, f2 = energy(x1), energy(x2)
    for _ in range(iterations):
        if f1 < f2:  # the minimum lies in [lo, x2]
            hi, x2, f2 = x2, x1, f1
            x1 = hi - ratio * (hi - lo)
            f1 = energy(x1)
        else:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + ratio * (hi - lo)
            f2 = energy(x2)
    return math.exp((lo + hi) / 2)
