"""Sharpness scores of candidate latent images, lower is sharper: the curves the constant-latency search reads.

``"sparsity"`` and its variants score the normalised sparsity of the log image's gradient, ``"etf"`` is the paper's
ETF (Eq. 14). :func:`sharpness_scores` shares the work several scores have in common; the search
(:mod:`evlatcorr.search`) scores latents it never makes (``grey · 1 / R``) through :func:`_scores_of`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator

import torch
from torch import Tensor

from evlatcorr import compiled
from evlatcorr.compiled.gradients import gradient_sparsity
from evlatcorr.config import SCORES, SPARSITY_SCORES
from evlatcorr.etf import etf_loss

__all__ = ["sharpness_score", "sharpness_scores"]

_SPARSITY = SPARSITY_SCORES
# On a GPU, images up to this many pixels in all take their gradients padded (fewer launches), more take them in
# pieces (less memory traffic): on an H100, padding was the faster for 101 DAVIS346 images (one frame's candidates)
# and the slower for 368 (several frames' candidates at once)
_PADDED_GRADIENT_ELEMENTS = 2**24


def sharpness_score(latent: Tensor, latency: Tensor, previous: Tensor | None, score: str, epsilon: float,
                    window: int, sigma_us: float) -> Tensor:
    """Score of candidate latent images :math:`(K, 1, H, W)`, lower is sharper.

    ``"etf"`` is the paper's ETF (Eq. 14). ``"sparsity"`` is the normalised sparsity of the
    log-image gradient, ``‖∇ log(I/Ī + c)‖₁ / ‖∇ log(I/Ī + c)‖₂`` (c = 0.25): blur and ghost edges
    spread the gradient over more pixels and raise it, and it does not change when the whole image is
    brighter or darker (the ETF drifts with the latent's overall brightness, which a late window
    changes). The temporal prior multiplies it by ``1 / sqrt(2π g)`` as in the ETF.

    Args:
        latent: candidate latent images :math:`(K, C, H, W)`.
        latency: their latencies :math:`(K,)` µs (for the temporal prior).
        previous: ``l'`` µs, broadcastable to ``latency``, or None for no prior.
        score: ``"sparsity"``, ``"sparsity_bright"``, ``"sparsity_multiscale"`` or ``"etf"``.
        epsilon, window, sigma_us: the ETF's settings (:func:`~evlatcorr.etf.etf_loss`); ``sigma_us`` is the
            temporal prior's σ for every score.

    Returns:
        :math:`(K,)`.

    Example:
        >>> edge = torch.zeros(1, 1, 16, 16); edge[..., 8:] = 1.0
        >>> ghosted = 0.5 * (edge + edge.roll(3, dims=-1))  # the same edge a few pixels away, at half contrast
        >>> scores = sharpness_score(torch.cat([edge, ghosted]), torch.zeros(2), None, "sparsity", 20.0, 7, 1000.0)
        >>> bool(scores[0] < scores[1])
        True
    """
    return sharpness_scores(latent, latency, previous, (score,), epsilon, window, sigma_us)[0]


def sharpness_scores(latent: Tensor, latency: Tensor, previous: Tensor | None, scores: tuple[str, ...],
                     epsilon: float, window: int, sigma_us: float) -> Tensor:
    """Several :func:`sharpness_score` of the same images :math:`(M, K)`, sharing the work they have in common
    (the log image of each floor ``c``, the gradient term of each floor and scale)."""
    _check_scores(scores)
    relative = latent.clamp_min(0)
    mean = relative.mean(dim=(1, 2, 3), keepdim=True).clamp_min_(1e-12)
    # log(I + c·Ī) is log(I / Ī + c) plus the constant log Ī, which no gradient sees: exactly invariant to the
    # brightness scale
    return _scores_of(lambda floor: torch.add(relative, mean, alpha=floor).log_(), lambda: latent, latency, previous,
                      scores, epsilon, window, sigma_us)


def _check_scores(scores: tuple[str, ...]) -> None:
    for score in scores:
        if score != "etf" and score not in _SPARSITY:
            raise ValueError(f"score must be one of {SCORES[:-2]} here ('consensus' and 'learned' search over "
                             f"several), got {score!r}")


def _scores_of(log_image: Callable[[float], Tensor], latent: Callable[[], Tensor], latency: Tensor,
               previous: Tensor | None, scores: tuple[str, ...], epsilon: float, window: int,
               sigma_us: float) -> Tensor:
    """:func:`sharpness_scores` from ``log_image(c)`` (the log of the latent plus ``c`` times its mean, up to a
    constant per image) and ``latent()`` (for the ETF only): each log image and gradient term made once."""
    terms: dict[tuple[float, int], Tensor] = {}
    # each floor's log image, made once, and the scales it is scored at
    scales: dict[float, set[int]] = {}
    for score in scores:
        if score != "etf":
            floor, factors = _SPARSITY[score]
            scales.setdefault(floor, set()).update(factors)
    for floor, factors in scales.items():
        log = log_image(floor)
        if _compiled_scales(log, factors):  # a CPU: both scales' gradient norms in one compiled pass
            both = torch.from_numpy(gradient_sparsity(log.flatten(0, 1).contiguous(), 2 in factors)).to(log.dtype)
            terms.update({(floor, factor): both[factor - 1] for factor in factors})
        else:
            for factor in factors:
                terms[floor, factor] = _gradient_sparsity(log if factor == 1 else _mean_pool(log, factor))
        del log  # before the next floor's is made
    out = []
    for score in scores:
        if score == "etf":
            out.append(etf_loss(latent(), latency, previous, epsilon, window, sigma_us))
            continue
        floor, factors = _SPARSITY[score]
        value = sum(terms[floor, factor] for factor in factors)
        if previous is not None:
            value = value * torch.exp((latency - previous.to(latency)) ** 2 / (4 * sigma_us**2))
        out.append(value)
    return torch.stack(out)


def _compiled_scales(log: Tensor, factors: set[int]) -> bool:
    """Whether :mod:`evlatcorr.compiled.gradients` scores ``log`` :math:`(K, 1, H, W)` at ``factors``: on a CPU, at full
    and half resolution, images of one channel at least 4 pixels each way, with no gradient to keep (the compiled
    pass is not differentiable; the scores are, through eager PyTorch)."""
    return (log.device.type == "cpu" and compiled.ENABLED and factors <= {1, 2} and log.dim() == 4
            and log.shape[1] == 1 and min(log.shape[-2:]) >= 4 and not log.requires_grad)


def _mean_pool(image: Tensor, factor: int) -> Tensor:
    """``avg_pool2d(image, factor)`` (the last rows and columns that fill no whole block dropped); for 2x2 on a
    CPU, four strided adds, faster there than ``avg_pool2d`` (the same values to float32 rounding)."""
    if factor != 2 or image.device.type != "cpu" or min(image.shape[-2:]) < 2:
        return torch.nn.functional.avg_pool2d(image, factor)
    rows, cols = 2 * (image.shape[-2] // 2), 2 * (image.shape[-1] // 2)
    pairs = image[..., 0:rows:2, :] + image[..., 1:rows:2, :]
    return (pairs[..., 0:cols:2] + pairs[..., 1:cols:2]).mul_(0.25)


def _gradient_sparsity(image: Tensor) -> Tensor:
    """``‖∇I‖₁ / (‖∇I‖₂ · sqrt(n))`` per image :math:`(K, 1, H, W)` → :math:`(K,)`, in (0, 1] whatever the size.

    Central differences with replicated borders (kornia's normalised ``"diff"`` gradient): one-sided at the
    border rows and columns. The ratio does not depend on the gradient's scale, so the differences are not
    halved; on a CPU, and for many images on a GPU, the norms are taken without padding the image or keeping
    absolute values and squares.
    """
    if image.device.type != "cpu" and image.numel() <= _PADDED_GRADIENT_ELEMENTS:
        return _padded_gradient_sparsity(image)
    norms = [torch.linalg.vector_norm(d.flatten(1), order, dim=1) for d in _central_differences(image)
             for order in (1, 2)]
    if not norms:  # a single pixel has no gradient
        return torch.zeros(image.shape[0], dtype=image.dtype, device=image.device)
    l1 = sum(norms[0::2])
    l2 = torch.stack(norms[1::2]).square_().sum(0).sqrt_()
    n = 2 * image.shape[-2] * image.shape[-1]
    return l1 / (l2 * math.sqrt(n) + 1e-12)


def _padded_gradient_sparsity(image: Tensor) -> Tensor:
    """:func:`_gradient_sparsity` from whole gradient images, their borders replicated by padding: a dozen kernel
    launches instead of thirty (what a GPU is bound by), for two image-sized copies (what a CPU is bound by)."""
    height, width = image.shape[-2:]
    l1 = l2_squared = torch.zeros(image.shape[0], dtype=image.dtype, device=image.device)
    for gradient in _padded_gradients(image):
        gradient = gradient.flatten(1)
        l1 = l1 + torch.linalg.vector_norm(gradient, 1, dim=1)
        l2_squared = l2_squared + torch.linalg.vector_norm(gradient, 2, dim=1).square()
    n = 2 * height * width
    return l1 / (l2_squared.sqrt() * math.sqrt(n) + 1e-12)


def _padded_gradients(image: Tensor) -> Iterator[Tensor]:
    """The x and then y central differences of :math:`(K, 1, H, W)` as whole images, not halved, their borders
    one-sided (replicated padding); none along a side of one pixel."""
    height, width = image.shape[-2:]
    for size, pad, axis in ((width, (1, 1, 0, 0), -1), (height, (0, 0, 1, 1), -2)):
        if size > 1:
            padded = torch.nn.functional.pad(image, pad, mode="replicate")
            yield padded.narrow(axis, 2, size) - padded.narrow(axis, 0, size)


def _central_differences(image: Tensor) -> list[Tensor]:
    """Twice kornia's normalised central differences of :math:`(K, 1, H, W)` with replicated borders, as the
    interior and border pieces of the x and y gradients (empty pieces left out)."""
    height, width = image.shape[-2:]
    pieces = []
    if width > 1:
        pieces += [image[..., 2:] - image[..., :-2], image[..., 1:2] - image[..., :1],
                   image[..., -1:] - image[..., -2:-1]]
    if height > 1:
        pieces += [image[..., 2:, :] - image[..., :-2, :], image[..., 1:2, :] - image[..., :1, :],
                   image[..., -1:, :] - image[..., -2:-1, :]]
    return [piece for piece in pieces if piece.numel()]
