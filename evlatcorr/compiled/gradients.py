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
from evlatcorr.image_tiles import check_grid, row_bands, tile_edges

__all__ = ["gradient_sparsity", "gradient_tile_sparsity"]


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
    return gradient_tile_sparsity(image, half, (1, 1))[..., 0]


def gradient_tile_sparsity(image: Tensor, half: bool, grid: tuple[int, int]) -> np.ndarray:
    """:func:`gradient_sparsity` of each whole image and of each tile of it (:mod:`evlatcorr.image_tiles`) from the
    same pass: a tile's ratio is over the differences at its pixels (the same differences as the whole image's,
    made with the pixels beyond the tile where there are). At half resolution the tiles are those of the 2x2 means'
    own size.

    Args:
        image, half: as :func:`gradient_sparsity`.
        grid: ``(rows, columns)`` of tiles; ``(1, 1)`` for the whole images alone.

    Returns:
        :math:`(2, K, 1 + R C)` float64: the whole image, then the tiles row by row (none for a ``(1, 1)`` grid);
        0 for a tile, or an image, of a single pixel.

    Raises:
        ValueError: as :func:`gradient_sparsity`, or for a grid that does not fit the images (or their 2x2 means).
    """
    check_arrays({"image": image}, 3, (torch.float32, torch.float64))
    height, width = image.shape[1:]
    small = (max(height // 2, 1), max(width // 2, 1))
    check_grid(grid, height, width)
    if half:
        check_grid(grid, *small)
    tiles = 0 if grid == (1, 1) else grid[0] * grid[1]
    out = np.zeros((2, image.shape[0], 1 + tiles), dtype=np.float64)
    layout = [(row_bands(h, grid[0]), np.asarray(tile_edges(w, grid[1]), dtype=np.int64))
              for h, w in ((height, width), small)]
    in_threads(_kernel(), workers_for(image.shape[0]), image.numpy(), half, *layout[0], *layout[1], tiles, out)
    return out


@functools.cache
def _kernel():
    """The compiled pass, images dealt to the threads in turn."""

    def sparsity(first, step, images, half, bands, columns, half_bands, half_columns, tiles,
                 out):  # pragma: no cover (compiled)
        count, height, width = images.shape
        sums = np.empty((max(bands[-1], half_bands[-1]) + 1, 2, width), np.float64)  # per tile row
        rows_of = np.zeros((2, sums.shape[0]), np.int64)
        for y in range(len(bands)):
            rows_of[0, bands[y]] += 1
        for y in range(len(half_bands)):
            rows_of[1, half_bands[y]] += 1
        small = np.empty((max(height // 2, 1), max(width // 2, 1)), images.dtype)
        for k in range(first, count, step):
            for level in range(2 if half else 1):
                if level == 0:
                    source, band_of, edges = images[k], bands, columns
                else:  # the 2x2 means, as sharpness._mean_pool makes them
                    source, band_of, edges = small[:height // 2, :width // 2], half_bands, half_columns
                    image = images[k]
                    for y in range(height // 2):
                        top, bottom, row = image[2 * y], image[2 * y + 1], source[y]
                        for x in range(width // 2):
                            row[x] = ((top[2 * x] + bottom[2 * x]) + (top[2 * x + 1] + bottom[2 * x + 1])) * 0.25
                h, w = source.shape
                if h * w < 2:
                    out[level, k, :] = 0.0
                    continue
                sums[:] = 0.0
                for y in range(h):
                    row, band = source[y], sums[band_of[y]]
                    if h > 1:  # down the column: central inside, one-sided at the first and last rows
                        above = source[max(y - 1, 0)] if y < h - 1 else source[h - 2]
                        below = source[min(y + 1, h - 1)] if y > 0 else source[1]
                        for x in range(w):
                            d = below[x] - above[x]
                            band[0, x] += abs(d)
                            band[1, x] += d * d
                    if w > 1:  # along the row, likewise
                        for x in range(1, w - 1):
                            d = row[x + 1] - row[x - 1]
                            band[0, x] += abs(d)
                            band[1, x] += d * d
                        for x, d in ((0, row[1] - row[0]), (w - 1, row[w - 1] - row[w - 2])):
                            band[0, x] += abs(d)
                            band[1, x] += d * d
                l1, l2 = 0.0, 0.0
                for r in range(band_of[-1] + 1):
                    l1 += sums[r, 0].sum()
                    l2 += sums[r, 1].sum()
                    if tiles:
                        for c in range(len(edges) - 1):
                            n = rows_of[level, r] * (edges[c + 1] - edges[c])
                            t1 = sums[r, 0, edges[c]:edges[c + 1]].sum()
                            t2 = sums[r, 1, edges[c]:edges[c + 1]].sum()
                            out[level, k, 1 + r * (len(edges) - 1) + c] = (
                                t1 / (np.sqrt(t2) * np.sqrt(2.0 * n) + 1e-12) if n >= 1 else 0.0)
                out[level, k, 0] = l1 / (np.sqrt(l2) * np.sqrt(2.0 * h * w) + 1e-12)

    return jit(sparsity)
