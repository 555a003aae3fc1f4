"""The ghost-moment cue: a second opinion on the constant latency where the sharpness curve has no clear minimum.

Read ``l`` late, a window that starts ``δ = l − l*`` after the true one leaves out the events of ``δ`` at its
start and takes in those of ``δ`` past its end. To first order that adds ``(δ / T)`` times the window's own
event change ``θ N`` (``N``: the pixel's net signed events in the window) to the latent image's log: the
latent carries a ghost of the event image, with a sign that follows ``δ``. The cue is the correlation of
the two, after a high-pass (a Gaussian of σ = 1 px removed) that leaves out the smooth shading both share
whatever the latency:

    m(l) = corr(hp(log L_l), hp(θ N_l))

which falls through zero at the latency where the ghost vanishes. The sharpness scores lose their minimum
on small objects over a static background and on dark, low-texture scenes; this curve is smooth there, but
it carries a scene-dependent offset of its own (the sharp image itself correlates with ``N`` on text and
rotating scenes), and under a latency that varies with intensity it follows the late pixels. The search
therefore asks it only where the sharpness curve has no minimum (or, with ``SearchConfig.ghost_confidence``
above 0, a shallow one), and takes its answer only when the curve crosses zero once, from above. Below a
confidence of 0.01 it fixed the dev split's three constant-latency misses of 2-5 ms, but in a larger draw of
the dev distribution it made 5 of 8 photoreceptor-lag frames worse, so by default it only replaces the
fallback of a frame with no minimum and no previous latency (no shift, which gains nothing).
"""

from __future__ import annotations

import functools

import kornia
import torch
from torch import Tensor

from evlatcorr import compiled
from evlatcorr.compiled.high_pass import TAPS, high_pass_correlation

__all__ = ["ghost_moment", "ghost_root", "inverse_ratio_moment", "log_grey", "stacked_inverse_ratio_moment"]

# σ of the high-pass, px: 1 removed the shading offset on most dev scenes; 0 (none) and 2 were worse
HIGH_PASS_SIGMA = 1.0
# darkest grey level taken into the log latent (a black pixel has no log)
_FLOOR = 1e-4


def log_grey(grey: Tensor, dtype: torch.dtype) -> Tensor:
    """``log`` of the blurry frame in ``dtype``, its black pixels read as the darkest level the cues take (1e-4).

    Raises:
        ValueError: when ``grey`` is not a tensor or ``dtype`` not a floating type.

    Example:
        >>> log_grey(torch.tensor([0.0, 1.0]), torch.float64)
        tensor([-9.2103,  0.0000], dtype=torch.float64)
    """
    if not isinstance(grey, Tensor) or not dtype.is_floating_point:
        raise ValueError(f"log_grey takes a tensor and a floating dtype, got {type(grey).__name__} and {dtype}")
    return torch.log(grey.to(dtype).clamp_min(_FLOOR))


def ghost_moment(grey: Tensor, log_ratio: Tensor, log_change: Tensor, sigma: float = HIGH_PASS_SIGMA) -> Tensor:
    """Correlation of each candidate's high-passed log latent with its window's high-passed event change.

    Args:
        grey: the blurry frame :math:`(1, 1, H, W)` in [0, 1].
        log_ratio: EDI ``log R`` of the candidates :math:`(K, 1, H, W)` (latent ``grey · exp(−log R)``).
        log_change: ``θ N`` of each candidate's window :math:`(K, 1, H, W)`
            (:meth:`~evlatcorr.continuous.ContinuousIntegral.log_change`).
        sigma: σ of the Gaussian the high-pass removes, px.

    Returns:
        :math:`(K,)` in [-1, 1]; 0 where either image is flat.

    Raises:
        ValueError: when the shapes do not match or ``sigma`` is not positive.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> grey = 0.4 + 0.2 * torch.rand(1, 1, 16, 16, generator=g)
        >>> change = torch.randn(3, 1, 16, 16, generator=g)
        >>> log_ratio = torch.stack([-0.5 * change[0], 0 * change[1], 0.5 * change[2]])  # ghost of +, 0, − sign
        >>> m = ghost_moment(grey, log_ratio, change)
        >>> bool(m[0] > 0 > m[2])
        True
    """
    _check_moment_inputs(grey, log_ratio, log_change, "log_ratio")
    if not sigma > 0:
        raise ValueError(f"sigma must be positive, got {sigma}")
    # float64 unless both curves come in float32 (a correlation over the image needs no more)
    dtype = torch.float32 if log_ratio.dtype == log_change.dtype == torch.float32 else torch.float64
    log_latent = log_grey(grey, dtype) - log_ratio.to(dtype)
    return _high_pass_correlation(log_latent, log_change.to(dtype), sigma)


def inverse_ratio_moment(grey: Tensor, inverse: Tensor, log_change: Tensor) -> Tensor:
    """:func:`ghost_moment` of the latents ``grey · inverse`` :math:`(K, 1, H, W)` float32 (``inverse = 1 / R``, what
    the search reads), without a logarithm and a negation of ``R`` first; ``grey`` :math:`(1, 1, H, W)`.

    Raises:
        ValueError: when the shapes do not match.
    """
    _check_moment_inputs(grey, inverse, log_change, "inverse")
    log_latent = torch.log(inverse).add_(log_grey(grey, inverse.dtype))
    return _high_pass_correlation(log_latent, log_change, HIGH_PASS_SIGMA)


def stacked_inverse_ratio_moment(grey: Tensor, inverse: Tensor, log_change: Tensor) -> Tensor:
    """:func:`inverse_ratio_moment` of several frames' candidates at once: ``grey`` :math:`(1, F, H, W)`, ``inverse``
    and ``log_change`` :math:`(K, F, H, W)` float32 (frame ``f``'s candidates in channel ``f``) → :math:`(K, F)`.

    Raises:
        ValueError: when the shapes do not match.
    """
    if (grey.dim() != 4 or grey.shape[0] != 1 or inverse.shape[1:] != grey.shape[1:]
            or log_change.shape != inverse.shape):
        raise ValueError(f"grey must be (1, F, H, W) and inverse and log_change both (K, F, H, W), got "
                         f"{tuple(grey.shape)}, {tuple(inverse.shape)} and {tuple(log_change.shape)}")
    k, frames, height, width = inverse.shape
    log_latent = torch.log(inverse).add_(log_grey(grey, inverse.dtype))
    flat = (k * frames, 1, height, width)
    return _high_pass_correlation(log_latent.view(flat), log_change.reshape(flat), HIGH_PASS_SIGMA).view(k, frames)


def _check_moment_inputs(grey: Tensor, ratio: Tensor, log_change: Tensor, name: str) -> None:
    if grey.dim() != 4 or grey.shape[:2] != (1, 1):
        raise ValueError(f"grey must be (1, 1, H, W), got {tuple(grey.shape)}")
    if ratio.dim() != 4 or ratio.shape[1:] != grey.shape[1:] or log_change.shape != ratio.shape:
        raise ValueError(f"{name} and log_change must both be (K, 1, H, W) with (H, W) = {tuple(grey.shape[-2:])}, "
                         f"got {tuple(ratio.shape)} and {tuple(log_change.shape)}")


def _high_pass_correlation(a: Tensor, b: Tensor, sigma: float) -> Tensor:
    """Correlation of each image of ``a`` with its image of ``b`` :math:`(K, 1, H, W)` after a Gaussian of ``sigma``
    is removed from both (``a`` may be overwritten), from sums: no centred copies. On a CPU, for the cue's σ, one
    compiled pass (:mod:`evlatcorr.compiled.high_pass`); tensors that ask for a gradient take the eager way."""
    size = 2 * int(3 * sigma + 0.5) + 1
    if (a.device.type == "cpu" and compiled.ENABLED and size == TAPS and min(a.shape[-2:]) > TAPS // 2
            and a.dtype == b.dtype and a.shape[1] == 1 and not (a.requires_grad or b.requires_grad)):
        taps = kornia.filters.get_gaussian_kernel1d(size, sigma, dtype=torch.float64)[0].numpy()
        out = high_pass_correlation(a.flatten(0, 1).contiguous(), b.flatten(0, 1).contiguous(), taps)
        return torch.from_numpy(out).to(a.dtype)
    a = a.sub_(_gaussian_blur(a, sigma)).flatten(1)
    b = (b - _gaussian_blur(b, sigma)).flatten(1)
    return _correlation_of_sums(a.sum(1), b.sum(1), torch.linalg.vecdot(a, b), torch.linalg.vecdot(a, a),
                                torch.linalg.vecdot(b, b), a.shape[1])


def _correlation_of_sums(sum_a: Tensor, sum_b: Tensor, sum_ab: Tensor, sum_aa: Tensor, sum_bb: Tensor,
                         n: Tensor | int) -> Tensor:
    """The correlation of two images from their sums over ``n`` pixels (of each, of their product, of their squares),
    in [-1, 1]; 0 where either is flat."""
    covariance = sum_ab - sum_a * sum_b / n
    spread = (sum_aa - sum_a**2 / n) * (sum_bb - sum_b**2 / n)
    return (covariance / spread.clamp_min(0).sqrt().clamp_min(1e-12)).clamp_(-1.0, 1.0)


def _gaussian_blur(image: Tensor, sigma: float) -> Tensor:
    """Kornia's Gaussian blur of ``image`` :math:`(K, 1, H, W)` (reflected borders, 6σ + 1 taps).

    On a CPU, kornia's own fast path. Elsewhere (a GPU) the same filter as two matrix products, ``B_H · image ·
    B_Wᵀ``, with the reflected borders folded into banded matrices made once per size: a one-channel 7-tap
    convolution of 100 DAVIS346 images took 0.5 ms per direction there, the products a fraction of it.
    """
    size = 2 * int(3 * sigma + 0.5) + 1
    if image.device.type == "cpu":
        return kornia.filters.gaussian_blur2d(image, (size, size), (sigma, sigma))
    height, width = image.shape[-2:]
    along_w = _reflected_blur_matrix(width, size, sigma, image.device, image.dtype)
    along_h = _reflected_blur_matrix(height, size, sigma, image.device, image.dtype)
    return torch.matmul(along_h, torch.matmul(image, along_w.T))


@functools.lru_cache(maxsize=16)
def _reflected_blur_matrix(n: int, size: int, sigma: float, device: torch.device, dtype: torch.dtype) -> Tensor:
    """:math:`(n, n)` matrix ``B`` with ``B @ x`` = the Gaussian of ``size`` taps over ``x`` :math:`(n,)`, its
    borders reflected as kornia's ``"reflect"`` does (``x[-1] = x[1]``)."""
    radius = size // 2
    if n <= radius:
        raise ValueError(f"a {size}-tap blur with reflected borders needs at least {radius + 1} pixels, got {n}")
    kernel = kornia.filters.get_gaussian_kernel1d(size, sigma, dtype=torch.float64)[0]
    source = torch.arange(n)[:, None] + torch.arange(-radius, radius + 1)[None, :]  # (n, size): x index read
    source = torch.where(source < 0, -source, source)
    source = torch.where(source > n - 1, 2 * (n - 1) - source, source)
    matrix = torch.zeros(n, n, dtype=torch.float64)
    matrix.scatter_add_(1, source, kernel.expand(n, size).contiguous())
    return matrix.to(device, dtype)


def ghost_root(latencies: Tensor, moment: Tensor) -> float | None:
    """The latency where the moment falls through zero, if it does so exactly once, from above.

    Args:
        latencies: increasing candidate latencies :math:`(K,)` µs.
        moment: :func:`ghost_moment` of each :math:`(K,)`.

    Returns:
        the crossing, interpolated linearly between its two candidates, µs; None when the curve never
        changes sign, changes it more than once (noise) or rises through zero (not a ghost that vanishes).

    Raises:
        ValueError: when the two are not 1-D of one length.

    Example:
        >>> ghost_root(torch.tensor([0.0, 100.0, 200.0, 300.0]), torch.tensor([0.3, 0.1, -0.1, -0.3]))
        150.0
        >>> ghost_root(torch.tensor([0.0, 100.0, 200.0]), torch.tensor([0.2, -0.1, 0.1])) is None
        True
    """
    if latencies.dim() != 1 or moment.shape != latencies.shape:
        raise ValueError(f"latencies and moment must be 1-D of one length, got {tuple(latencies.shape)} and "
                         f"{tuple(moment.shape)}")
    if len(moment) < 3:
        return None
    above = (moment > 0).cpu()
    changes = torch.nonzero(above[1:] != above[:-1]).flatten()
    if len(changes) != 1 or not bool(above[changes[0]]):
        return None
    k = int(changes[0])
    m0, m1 = float(moment[k]), float(moment[k + 1])
    l0, l1 = float(latencies[k]), float(latencies[k + 1])
    return l0 + m0 / (m0 - m1) * (l1 - l0)
