"""Frames with nothing for EDI to sharpen, which the latency search does not read.

EDI sharpens a blurry frame with the events: ``latent = blurry / mean(exp(θ C))``. Where the frame tells nothing of
the scene, every candidate latency's latent is as made up from the events as any other, and the reader used to
answer anything, often the top of the range. Two kinds are recognised:

- ``"clipped"``: black or saturated in nearly every pixel (a lens cap, a flash; :func:`unclipped_share`);
- ``"flat"``: no structure above the frame's own pixel noise (:func:`structure_ratio`): a grey frame, a blank wall
  under a flickering lamp, a frame paired with the wrong events.

Such frames keep the fallback latency (the previous frame's, or the low end of the range) with a warning, and the
two-frame threshold estimate leaves their pairs out (:func:`blank_pairs`).
"""

from __future__ import annotations

import kornia
import torch
from torch import Tensor

__all__ = ["MIN_UNCLIPPED_SHARE", "MIN_STRUCTURE_RATIO", "BLANK_KINDS", "unclipped_share", "structure_ratio",
           "blank_codes", "blank_kinds", "blank_pairs"]

#: a frame with fewer of its pixels inside the sensor's range (not black, not saturated) is not searched: its
#: latency is the fallback (the suite's darkest frames keep 12 % or more of theirs; a lens cap or a flash none)
MIN_UNCLIPPED_SHARE = 0.005
#: a frame whose smoothed contrast is under this many times what its pixel noise alone leaves is "flat". Measured
#: (`structure_ratio`): the accuracy suite's 160 tuning cases' frames 7.8 or more, the shared DAVIS346 recordings'
#: 31-37, a grey frame with white noise about 1
MIN_STRUCTURE_RATIO = 3.0
#: the kinds of blank frames, as :func:`blank_codes` numbers them from 1 (``meta["latency_source"]`` names them)
BLANK_KINDS = ("clipped", "flat")

# the frame is smoothed by averaging blocks of this many pixels a side (fewer on frames under twice as wide): a
# block's mean keeps 1 / side of white noise's standard deviation
_BLOCK = 4
# the median absolute difference of two neighbours is 0.6745 sqrt(2) σ for white noise of σ
_MAD_TO_SIGMA = 1.4826 / 2**0.5
# the noise's median is read from about this many of the neighbours' steps (a DAVIS346 frame has 180 000: their
# median alone took 1.6 ms of a 3.3 ms check on a CPU)
_NOISE_SAMPLES = 20_000
_UNIFORM = 1e-3 / 255


def _grey(images: Tensor) -> Tensor:
    if not isinstance(images, Tensor) or images.ndim != 4:
        raise ValueError(f"images must be a (B, C, H, W) tensor, got {getattr(images, 'shape', type(images))}")
    return kornia.color.rgb_to_grayscale(images) if images.shape[1] == 3 else images


def unclipped_share(images: Tensor) -> Tensor:
    """The share of each image's pixels inside the sensor's range :math:`(B,)`, of images :math:`(B, C, H, W)` in
    [0, 1] (grey when they have three channels): a pixel black or saturated (within half an 8-bit grey level of 0 or
    1) tells EDI nothing of the scene's mean over the exposure. Below :data:`MIN_UNCLIPPED_SHARE` a frame is not
    searched.

    Example:
        >>> frame = torch.zeros(1, 1, 10, 10)
        >>> frame[..., 0, :5] = 0.5
        >>> unclipped_share(frame).tolist()
        [0.05000000074505806]
    """
    grey = _grey(images)
    margin = 1 / 512
    return ((grey > margin) & (grey < 1 - margin)).flatten(1).float().mean(1)


def structure_ratio(images: Tensor) -> Tensor:
    """How far each image's structure stands above its pixel noise :math:`(B,)`, of images :math:`(B, C, H, W)`.

    The standard deviation of the means of the image's 4x4 blocks, over what white noise of the image's own level
    would leave of it. The noise is read robustly from the median absolute difference of neighbouring
    pixels (edges and texture raise it, so a fine texture counts partly as noise: the ratio errs towards "flat" only
    where the smoothed image barely varies). About 1 for a uniform frame with noise, 0 for an exactly uniform one,
    tens for a real scene. Below :data:`MIN_STRUCTURE_RATIO` a frame is not searched.

    Example:
        >>> g = torch.Generator().manual_seed(0)
        >>> noise = 0.5 + 0.01 * torch.randn(1, 1, 64, 64, generator=g)
        >>> ramp = noise + torch.linspace(-0.1, 0.1, 64)
        >>> [round(v) for v in structure_ratio(torch.cat([noise, ramp])).tolist()]
        [1, 23]
    """
    grey = _grey(images).float()
    block = max(1, min(_BLOCK, grey.shape[-2] // 2, grey.shape[-1] // 2))
    smooth = torch.nn.functional.avg_pool2d(grey, block).flatten(1)
    structure = smooth.std(1) if smooth.shape[1] > 1 else torch.zeros_like(smooth[:, 0])
    steps = torch.cat([(grey[..., 1:, :] - grey[..., :-1, :]).flatten(1),
                       (grey[..., :, 1:] - grey[..., :, :-1]).flatten(1)], 1)
    steps = steps[:, ::max(1, steps.shape[1] // _NOISE_SAMPLES)]  # an even sample of them
    noise = _MAD_TO_SIGMA * steps.abs().median(1).values if steps.shape[1] else torch.zeros_like(structure)
    kept = noise / block  # what the blocks' means keep of white noise's deviation
    # uniform to a thousandth of an 8-bit grey level (float rounding): 0; noiseless with structure: far above 3
    return torch.where(structure > _UNIFORM, structure / kept.clamp_min(structure * 1e-6), torch.zeros_like(structure))


def blank_codes(images: Tensor) -> Tensor:
    """Each image's kind of blank :math:`(B,)` int64, on its device and without a host read: 0 for a frame to search,
    else 1 + its index in :data:`BLANK_KINDS` (clipped first: a black frame is also flat).

    Example:
        >>> ramp = torch.linspace(0.1, 0.9, 8).expand(1, 8, 8)
        >>> blank_codes(torch.stack([torch.zeros(1, 8, 8), torch.full((1, 8, 8), 0.5), ramp])).tolist()
        [1, 2, 0]
    """
    clipped = unclipped_share(images) < MIN_UNCLIPPED_SHARE
    flat = structure_ratio(images) < MIN_STRUCTURE_RATIO
    return torch.where(clipped, 1, torch.where(flat, 2, 0))


def blank_kinds(images: Tensor) -> list[str | None]:
    """Each image's kind of blank (``"clipped"``, ``"flat"``), or None for a frame to search (one host read).

    Example:
        >>> ramp = torch.linspace(0.1, 0.9, 8).expand(1, 8, 8)
        >>> blank_kinds(torch.stack([torch.ones(1, 8, 8), torch.rand(1, 8, 8), ramp]))  # white noise is flat
        ['clipped', 'flat', None]
    """
    return [BLANK_KINDS[code - 1] if code else None for code in blank_codes(images).tolist()]


def blank_pairs(blurry: Tensor, blurry_next: Tensor) -> Tensor:
    """Which frame pairs :math:`(B,)` hold a blank frame (:func:`blank_codes`): such a frame agrees with its
    neighbour at no contrast threshold, so the two-frame estimates of θ leave its pair out.

    Example:
        >>> ramp = torch.linspace(0.1, 0.9, 4).expand(1, 4, 4)
        >>> blank_pairs(torch.stack([ramp, ramp]), torch.stack([torch.zeros(1, 4, 4), ramp]))
        tensor([ True, False])
    """
    return (blank_codes(torch.cat([blurry, blurry_next])) > 0).view(2, -1).any(0)
