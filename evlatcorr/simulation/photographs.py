"""Source images of the simulator: the bundled scikit-image photographs, user images, and their luminance."""

from __future__ import annotations

import math
import os

import numpy as np
import torch
from torch import Tensor

__all__ = ["PHOTOGRAPHS_TEST", "PHOTOGRAPHS_TRAIN", "image_tensor", "load_photograph", "luminance", "source_image"]

# scikit-image photographs stored inside the package (no download). Disjoint splits.
_FILES = {
    "astronaut": "astronaut.png", "coffee": "coffee.png", "chelsea": "chelsea.png", "rocket": "rocket.jpg",
    "camera": "camera.png", "motorcycle_right": "motorcycle_right.png", "brick": "brick.png",
    "gravel": "gravel.png", "motorcycle_left": "motorcycle_left.png", "hubble_deep_field": "hubble_deep_field.jpg",
    "retina": "retina.jpg", "immunohistochemistry": "ihc.png", "moon": "moon.png", "coins": "coins.png",
    "page": "page.png", "text": "text.png", "grass": "grass.png", "cell": "cell.png",
}
_ALIASES = {"ihc": "immunohistochemistry"}
PHOTOGRAPHS_TEST = ("astronaut", "coffee", "chelsea", "rocket", "camera", "motorcycle_right", "brick", "gravel")
PHOTOGRAPHS_TRAIN = ("motorcycle_left", "hubble_deep_field", "retina", "immunohistochemistry", "moon", "coins",
                     "page", "text", "grass", "cell")


def luminance(rgb: Tensor) -> Tensor:
    """Luminance ``0.299 R + 0.587 G + 0.114 B`` of images :math:`(..., 3, H, W)` as :math:`(..., 1, H, W)`.

    Example:
        >>> luminance(torch.ones(2, 3, 4, 5)).shape
        torch.Size([2, 1, 4, 5])
    """
    if rgb.dim() < 3 or rgb.shape[-3] != 3:
        raise ValueError(f"rgb must have shape (..., 3, H, W), got {tuple(rgb.shape)}")
    return 0.299 * rgb[..., 0:1, :, :] + 0.587 * rgb[..., 1:2, :, :] + 0.114 * rgb[..., 2:3, :, :]


def load_photograph(name: str, gain: float = 1.0) -> Tensor:
    """A scikit-image photograph as linear RGB :math:`(3, H, W)` in [0, 1] (grey repeated to 3 channels).

    The 8-bit values are taken as linear intensities (no gamma), scaled by ``gain`` and clipped to
    [0, 1], so ``gain < 1`` gives a dim scene.

    Args:
        name: one of :data:`PHOTOGRAPHS_TRAIN` or :data:`PHOTOGRAPHS_TEST` (``"ihc"`` is accepted too).
        gain: intensity scale, > 0.

    Example:
        >>> load_photograph("camera").shape
        torch.Size([3, 512, 512])
    """
    key = _ALIASES.get(name, name) if isinstance(name, str) else name
    if key not in _FILES:
        raise ValueError(f"unknown photograph {name!r}; choose from {sorted(_FILES)}")
    if not gain > 0 or not math.isfinite(gain):
        raise ValueError(f"gain must be a positive number, got {gain}")
    import skimage.data
    import skimage.io

    path = os.path.join(os.path.dirname(skimage.data.__file__), _FILES[key])
    img = np.asarray(skimage.io.imread(path))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3]
    scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
    out = torch.from_numpy(np.ascontiguousarray(img.astype(np.float32) / scale)).permute(2, 0, 1).contiguous()
    return (out * gain).clamp_(0.0, 1.0)


def image_tensor(image: Tensor) -> Tensor:
    """A user image :math:`(3, H, W)`, :math:`(1, H, W)` or :math:`(H, W)` in [0, 1], checked, as RGB :math:`(3, H, W)`.

    Example:
        >>> image_tensor(torch.full((4, 5), 0.5)).shape
        torch.Size([3, 4, 5])
    """
    if not isinstance(image, Tensor):
        raise ValueError(f"image must be a photograph name or a tensor, got {type(image).__name__}")
    if image.dim() == 2:
        image = image[None]
    if image.dim() != 3 or image.shape[0] not in (1, 3) or min(image.shape[-2:]) < 2:
        raise ValueError(f"image must be an RGB (3, H, W) or grey (1, H, W) / (H, W) tensor, got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise ValueError(f"image must be a floating point tensor in [0, 1], got {image.dtype}")
    if not bool(torch.isfinite(image).all()) or float(image.min()) < 0 or float(image.max()) > 1:
        raise ValueError("image must hold finite linear intensities in [0, 1]")
    return image.float().expand(3, -1, -1).contiguous()


def source_image(image: str | Tensor) -> Tensor:
    """The scene to film, RGB :math:`(3, H, W)`: a photograph by name, or a user image (see :func:`image_tensor`)."""
    return load_photograph(image) if isinstance(image, str) else image_tensor(image)
