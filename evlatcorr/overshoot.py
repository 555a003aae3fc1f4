"""The overshoot cue: how far a candidate's latent image rises above anything the blurry frame allows.

EDI's latent at any time of the exposure is the latent at the reference times ``exp(θ (C(t) − C(reference)))``.
Read at the true latency, every pixel's trajectory over the exposure is the scene's own, and its brightest values
stay near the frame's brightest (a sharp image is brighter than its blur only where an edge was averaged away).
Read at a wrong latency, the window holds events of other times: the ghosts they leave push some pixels' trajectory
far above that, most where the scene is bright and moves fast. The cue is the 99th percentile over the pixels of
each pixel's highest log latent over the window (its start, quarters, reference and end), relative to the log of the
blurry frame's brightest pixel:

    o(l) = q99_x [ log L_l(x) + θ (max_t C_l(x, t) − C_l(x, reference)) ] − log max_x B(x)

It is low near the true latency on many scenes where the sharpness scores mislead (dark or low-texture scenes,
noise textures, fast rotation; ``docs/estimator.md``), and the learned curve reader reads it beside them.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from evlatcorr.ghost import log_grey

__all__ = ["OVERSHOOT_RANGE", "overshoot", "overshoot_stride"]

# the percentile over the pixels: the brightest 1 %, not the single brightest pixel (noise, a hot pixel)
QUANTILE = 0.99
# the reader reads the cue clamped to this range of log intensity (e^3: a latent 20x brighter than the frame allows)
OVERSHOOT_RANGE = (-1.0, 3.0)
# pixels the percentile is taken over at most: larger images are read every s-th row and column (a DAVIS346 frame
# every 3rd), a regular sample of the same distribution; the reader was trained on 96x128 frames, read whole
MAX_PIXELS = 96 * 128


def overshoot_stride(height: int, width: int) -> int:
    """The s such that every s-th row and column of an image, at most :data:`MAX_PIXELS` pixels, are read.

    Raises:
        ValueError: when the size is not positive.
    """
    if min(height, width) < 1:
        raise ValueError(f"an image must have at least one pixel, got {height}x{width}")
    return max(1, math.ceil(math.sqrt(height * width / MAX_PIXELS) - 1e-9))


def overshoot(grey: Tensor, inverse: Tensor, log_peak: Tensor) -> Tensor:
    """The overshoot of each candidate's latent :math:`(K,)` float64, clamped to :data:`OVERSHOOT_RANGE`.

    Args:
        grey: the blurry frame :math:`(1, F, H, W)` in [0, 1] (``F`` frames side by side, each its own).
        inverse: ``1 / R`` of each candidate :math:`(K, F, H, W)` (the latent at the reference is ``grey · inverse``).
        log_peak: ``θ (max C − C(reference))`` of each candidate, ≥ 0, at every s-th row and column
            (:func:`overshoot_stride`): :math:`(K, F, ⌈H/s⌉, ⌈W/s⌉)`
            (:meth:`evlatcorr.continuous.ContinuousIntegral.inverse_ratio`'s ``peak_out``).

    Returns:
        :math:`(K,)` for one frame, :math:`(K, F)` for several; log units.

    Raises:
        ValueError: when the shapes do not match.

    Example:
        >>> grey = torch.full((1, 1, 8, 8), 0.5)
        >>> inverse = torch.ones(2, 1, 8, 8)
        >>> log_peak = torch.stack([torch.zeros(1, 8, 8), torch.full((1, 8, 8), math.log(4.0))])
        >>> [round(v, 4) for v in overshoot(grey, inverse, log_peak).tolist()]  # a flat latent, then 4x brighter
        [0.0, 1.3863]
    """
    height, width = grey.shape[-2:]
    stride = overshoot_stride(height, width)
    sampled = (-(-height // stride), -(-width // stride))
    if (grey.dim() != 4 or grey.shape[0] != 1 or inverse.dim() != 4 or inverse.shape[1:] != grey.shape[1:]
            or log_peak.shape != (*inverse.shape[:2], *sampled)):
        raise ValueError(f"grey must be (1, F, H, W), inverse (K, F, H, W) and log_peak (K, F, {sampled[0]}, "
                         f"{sampled[1]}) (every {stride}th row and column), got {tuple(grey.shape)}, "
                         f"{tuple(inverse.shape)} and {tuple(log_peak.shape)}")
    grey, inverse = grey[..., ::stride, ::stride], inverse[..., ::stride, ::stride]
    log_frame = log_grey(grey, inverse.dtype)  # as the ghost cue takes it
    top = torch.log(inverse).add_(log_frame).add_(log_peak).flatten(2)  # (K, F, n)
    brightest = log_frame.flatten(2).amax(2)  # (1, F)
    value = (_upper_quantile(top, QUANTILE) - brightest).double().clamp_(*OVERSHOOT_RANGE)
    return value[:, 0] if grey.shape[1] == 1 else value


def _upper_quantile(values: Tensor, q: float) -> Tensor:
    """``torch.quantile(values, q, dim=-1)`` (linear interpolation) for ``q`` near 1, from the largest values only:
    a partial sort, a third of the full sort's time on a DAVIS346 frame's candidates."""
    n = values.shape[-1]
    position = q * (n - 1)
    low = math.floor(position)
    largest = torch.topk(values, n - low, dim=-1, sorted=True).values  # descending: [..., -1] is the low-th smallest
    if n - low < 2:
        return largest[..., -1]
    return largest[..., -1] + (position - low) * (largest[..., -2] - largest[..., -1])


def _upper_quantiles(values: Tensor, counts: list[int], q: float) -> Tensor:
    """:func:`_upper_quantile` of each row of ``values`` :math:`(..., T, N)` over its first ``counts[t]`` entries,
    the rest padding below every value (``-inf``): one partial sort for all rows, the same values as each row's own."""
    largest_needed, last, before, fraction = _quantile_points(tuple(counts), q, values.dtype, values.device)
    largest = torch.topk(values, largest_needed, dim=-1, sorted=True).values  # descending
    shape = (*largest.shape[:-1], 1)
    at_last = largest.gather(-1, last.expand(shape)).squeeze(-1)
    at_before = largest.gather(-1, before.expand(shape)).squeeze(-1)
    return at_last + fraction * (at_before - at_last)


@functools.lru_cache(maxsize=64)
def _quantile_points(counts: tuple[int, ...], q: float, dtype: torch.dtype, device: torch.device
                     ) -> tuple[int, Tensor, Tensor, Tensor]:
    """For rows of ``counts`` values: how many of the largest to sort, where each row's quantile and the value above it
    lie among them :math:`(T, 1)`, and the fraction between them :math:`(T,)`; made once per shape (no copies to a
    device per call)."""
    positions = [q * (n - 1) for n in counts]
    lows = [math.floor(p) for p in positions]
    last = [n - low - 1 for n, low in zip(counts, lows)]  # the low-th smallest, counted from the largest
    index = torch.tensor(last, dtype=torch.int64, device=device)[:, None]
    fraction = torch.tensor([p - low for p, low in zip(positions, lows)], dtype=dtype, device=device)
    return max(last) + 1, index, index.sub(1).clamp_min(0), fraction
