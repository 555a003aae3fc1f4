"""Event-based temporal fidelity (ETF, paper Eq. 10-14): a no-reference sharpness score.

``L_ETF(I, l) = s(εI) / sqrt(h(I) · g(l))``, lower is sharper:

- edge thickness ``s(εI)``: with ``ρ(λ) = exp(−λ)`` Eq. (11) integrates in closed form to
  ``Σ_p 1 − exp(−ε‖∇I_p‖)``, a soft count of pixels on edges; ghost edges from late events
  make edges thicker. We average over pixels instead of summing so scores compare across sizes.
- local contrast ``h(I)``: the mean local standard deviation in a ``window × window`` box (the
  paper adopts the local standard deviation ``sqrt`` of Eq. 12 in practice). Sharper is higher.
- temporal consistency ``g(l) = exp(−(l − l')² / (2σ²)) / (2π)``: a Gaussian prior that the
  latency stays close to ``l'`` (previous frame, or the frame's constant latency in training).
  The paper writes σ = 1 in its latency unit; we take ``sigma_us`` (default 1000 µs = 1 ms).

Defaults and why: ``epsilon = 20`` for images in [0, 1] with central-difference gradients
(an edge of contrast 0.1 gives ``1 − e^{−1} ≈ 0.63``, sensor noise of 0.005 only ≈ 0.1), large
enough that ``s`` counts edge pixels and small enough not to count noise; ``window = 7``
pixels, about the width of the blur and ghosting the score has to see (a few pixels at DAVIS
resolution) while staying local, since motion blur is not uniform over the frame.
"""

from __future__ import annotations

import math

import kornia
import torch
from torch import Tensor, nn

from evlatcorr.checks import check_shape
from evlatcorr.config import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW

__all__ = [
    "edge_thickness",
    "local_contrast",
    "temporal_consistency",
    "etf_loss",
    "EdgeThickness",
    "LocalContrast",
    "EventTemporalFidelity",
    "DEFAULT_EPSILON",
    "DEFAULT_WINDOW",
    "DEFAULT_SIGMA_US",
]

_EPS = 1e-8


def _luminance(image: Tensor, name: str = "image") -> Tensor:
    check_shape(image, ["B", "C", "H", "W"], name)
    if image.shape[1] == 3:
        return kornia.color.rgb_to_grayscale(image)
    if image.shape[1] != 1:
        raise ValueError(f"{name} must have 1 or 3 channels, got {image.shape[1]}")
    return image


def edge_thickness(image: Tensor, epsilon: float = DEFAULT_EPSILON) -> Tensor:
    """Soft edge thickness ``mean_p 1 − exp(−ε‖∇I_p‖)`` (Eq. 10-11 with ρ(λ) = e^{−λ}).

    Args:
        image: :math:`(B, C, H, W)`, C = 1 or 3 (RGB is converted to luminance).
        epsilon: gradient amplifier ε.

    Returns:
        :math:`(B,)` in [0, 1).

    Example:
        >>> flat = torch.zeros(1, 1, 8, 8)
        >>> step = torch.zeros(1, 1, 8, 8); step[..., 4:] = 1.0
        >>> [round(s, 4) for s in edge_thickness(torch.cat([flat, step])).tolist()]  # edge: 2 of 8 columns
        [0.0, 0.25]
    """
    if epsilon <= 0:
        raise ValueError(f"epsilon must be positive, got {epsilon}")
    grey = _luminance(image)
    grad = kornia.filters.spatial_gradient(grey, mode="diff", order=1, normalized=True)  # (B, 1, 2, H, W)
    magnitude = torch.sqrt(grad.pow(2).sum(2) + 1e-12)  # smooth at 0, floor far below noise
    return (1 - torch.exp(-epsilon * magnitude)).mean(dim=(1, 2, 3))


def local_contrast(image: Tensor, window: int = DEFAULT_WINDOW) -> Tensor:
    """Mean local standard deviation in ``window × window`` boxes (Eq. 12, as a standard deviation).

    Args:
        image: :math:`(B, C, H, W)`, C = 1 or 3 (RGB is converted to luminance).
        window: odd box size in pixels.

    Returns:
        :math:`(B,)`.

    Raises:
        ValueError: for an even or non-positive ``window``, or an image too small to reflect the box's border
            (fewer than ``window // 2 + 1`` pixels on a side).

    Example:
        >>> img = torch.zeros(1, 1, 9, 9); img[..., ::2] = 1.0
        >>> round(local_contrast(img, window=3).item(), 2)  # stripes: std near 0.47 everywhere
        0.47
    """
    if window < 1 or window % 2 == 0:
        raise ValueError(f"window must be a positive odd number of pixels, got {window}")
    grey = _luminance(image)
    height, width = grey.shape[-2:]
    if min(height, width) <= window // 2:  # the reflected border needs more pixels than it reaches
        raise ValueError(f"local contrast with a {window}x{window} box needs images of at least {window // 2 + 1} "
                         f"pixels on each side, got {height}x{width}: give a smaller window")
    mean = kornia.filters.box_blur(grey, (window, window), border_type="reflect")
    mean_sq = kornia.filters.box_blur(grey * grey, (window, window), border_type="reflect")
    var = (mean_sq - mean * mean).clamp_min(0)
    return torch.sqrt(var + _EPS).mean(dim=(1, 2, 3))


def temporal_consistency(latency: Tensor, previous: Tensor | None, sigma_us: float = DEFAULT_SIGMA_US) -> Tensor:
    """Gaussian temporal prior ``g(l) = exp(−(l − l')² / (2σ²)) / (2π)`` (Eq. 13).

    Args:
        latency: :math:`(B,)` or :math:`(B, K)` µs (K candidates per sample).
        previous: :math:`(B,)` µs, or None for no prior (then ``g = 1/(2π)``).
        sigma_us: standard deviation σ in µs.

    Returns:
        same shape as ``latency``.
    """
    if sigma_us <= 0:
        raise ValueError(f"sigma_us must be positive, got {sigma_us}")
    norm = 1.0 / (2 * math.pi)
    if previous is None:
        return torch.full_like(latency, norm)
    previous = previous.to(latency).view(-1, *([1] * (latency.dim() - 1)))
    return norm * torch.exp(-((latency - previous) ** 2) / (2 * sigma_us**2))


def etf_loss(
    image: Tensor,
    latency: Tensor | None = None,
    previous_latency: Tensor | None = None,
    epsilon: float = DEFAULT_EPSILON,
    window: int = DEFAULT_WINDOW,
    sigma_us: float = DEFAULT_SIGMA_US,
) -> Tensor:
    """Event-based temporal fidelity ``s(εI) / sqrt(h(I) g(l))`` (Eq. 14); lower is sharper.

    Args:
        image: latent images :math:`(B, C, H, W)`.
        latency: the latency :math:`(B,)` µs that produced each image (for ``g``); may be None.
        previous_latency: ``l'`` :math:`(B,)` µs; None drops the temporal term (``g`` constant).
        epsilon: gradient amplifier ε of the edge thickness.
        window: box size of the local contrast.
        sigma_us: σ of the temporal prior, µs.

    Returns:
        :math:`(B,)`.

    Example:
        >>> sharp = torch.zeros(1, 1, 16, 16); sharp[..., 8:] = 1.0
        >>> blurred = kornia.filters.box_blur(sharp, (1, 5))
        >>> bool(etf_loss(sharp) < etf_loss(blurred))
        True
    """
    s = edge_thickness(image, epsilon)
    h = local_contrast(image, window)
    if latency is None or previous_latency is None:
        g = torch.full_like(h, 1.0 / (2 * math.pi))
    else:
        g = temporal_consistency(latency.to(h), previous_latency, sigma_us)
    return s / torch.sqrt(h * g + _EPS)


class EdgeThickness(nn.Module):
    """Module form of :func:`edge_thickness`."""

    def __init__(self, epsilon: float = DEFAULT_EPSILON) -> None:
        super().__init__()
        self.epsilon = epsilon

    def extra_repr(self) -> str:
        return f"epsilon={self.epsilon}"

    def forward(self, image: Tensor) -> Tensor:
        return edge_thickness(image, self.epsilon)


class LocalContrast(nn.Module):
    """Module form of :func:`local_contrast`."""

    def __init__(self, window: int = DEFAULT_WINDOW) -> None:
        super().__init__()
        self.window = window

    def extra_repr(self) -> str:
        return f"window={self.window}"

    def forward(self, image: Tensor) -> Tensor:
        return local_contrast(image, self.window)


class EventTemporalFidelity(nn.Module):
    """Module form of :func:`etf_loss`.

    Example:
        >>> etf = EventTemporalFidelity()
        >>> etf(torch.rand(2, 3, 16, 16)).shape
        torch.Size([2])
    """

    def __init__(self, epsilon: float = DEFAULT_EPSILON, window: int = DEFAULT_WINDOW,
                 sigma_us: float = DEFAULT_SIGMA_US) -> None:
        super().__init__()
        self.epsilon, self.window, self.sigma_us = epsilon, window, sigma_us

    def extra_repr(self) -> str:
        return f"epsilon={self.epsilon}, window={self.window}, sigma_us={self.sigma_us}"

    def forward(self, image: Tensor, latency: Tensor | None = None,
                previous_latency: Tensor | None = None) -> Tensor:
        return etf_loss(image, latency, previous_latency, self.epsilon, self.window, self.sigma_us)
