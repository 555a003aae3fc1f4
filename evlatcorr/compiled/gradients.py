"""The sharpness scores' gradient norms of many images, at full and half resolution, in one compiled pass each.

:func:`evlatcorr.sharpness._gradient_sparsity` scores an image by ``‖∇I‖₁ / (‖∇I‖₂ · sqrt(n))`` over kornia's central
differences with replicated borders (one-sided at the border rows and columns, not halved: the ratio does not see
the scale). In eager PyTorch that is six difference tensors and twelve norms an image, and a mean-pooled copy for the
half-resolution term. Here each image's differences are made and summed where they are read (per column in float64,
so the loops vectorise without reordering a sum), and the 2x2 means of its half-resolution copy go to a small
scratch image: one pass over the input per resolution.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from evlatcorr.compiled import check_arrays, in_threads, jit, workers_for

__all__ = ["gradient_sparsity"]


def gradient_sparsity(image: Tensor, half: bool) -> np.ndarray:
    """The gradient sparsity of each image at full resolution and, with ``half``, of its 2x2 means.

    Args:
        image: :math:`(K, H, W)` float32 or float64 on the CPU, contiguous.
        half: also score each image's 2x2 block means (the last row and column dropped where odd).

    Returns:
        :math:`(2, K)` float64: row 0 full resolution, row 1 half (0 without ``half``); 0 for a single pixel.

    Raises:
        ValueError: when ``image`` is not a contiguous 3-D float CPU tensor.
    """
    check_arrays({"image": image}, 3, (torch.float32, torch.float64))
    out = np.zeros((2, image.shape[0]), dtype=np.float64)
    in_threads(_kernel(), workers_for(image.shape[0]), image.numpy(), half, out)
    return out


@functools.cache
def _kernel():
    """The compiled pass, images dealt to the threads in turn."""

    def sparsity(first, step, images, half, out):  # pragma: no cover (compiled)
        count, height, width = images.shape
        sums = np.empty((2, width), np.float64)
        small = np.empty((max(height // 2, 1), max(width // 2, 1)), images.dtype)
        for k in range(first, count, step):
            for level in range(2 if half else 1):
                if level == 0:
                    source = images[k]
                else:  # the 2x2 means, as sharpness._mean_pool makes them
                    source = small[:height // 2, :width // 2]
                    image = images[k]
                    for y in range(height // 2):
                        top, bottom, row = image[2 * y], image[2 * y + 1], source[y]
                        for x in range(width // 2):
                            row[x] = ((top[2 * x] + bottom[2 * x]) + (top[2 * x + 1] + bottom[2 * x + 1])) * 0.25
                h, w = source.shape
                if h * w < 2:
                    out[level, k] = 0.0
                    continue
                sums[:] = 0.0
                for y in range(h):
                    row = source[y]
                    if h > 1:  # down the column: central inside, one-sided at the first and last rows
                        above = source[max(y - 1, 0)] if y < h - 1 else source[h - 2]
                        below = source[min(y + 1, h - 1)] if y > 0 else source[1]
                        for x in range(w):
                            d = below[x] - above[x]
                            sums[0, x] += abs(d)
                            sums[1, x] += d * d
                    if w > 1:  # along the row, likewise
                        for x in range(1, w - 1):
                            d = row[x + 1] - row[x - 1]
                            sums[0, x] += abs(d)
                            sums[1, x] += d * d
                        for x, d in ((0, row[1] - row[0]), (w - 1, row[w - 1] - row[w - 2])):
                            sums[0, x] += abs(d)
                            sums[1, x] += d * d
                out[level, k] = sums[0].sum() / (np.sqrt(sums[1].sum()) * np.sqrt(2.0 * h * w) + 1e-12)

    return jit(sparsity)
