"""A frame's tiles: the grid the learned search also reads its curves on, and sums over each tile.

A small object moving over a static background barely moves a whole-frame sharpness score, where the tile holding
it shows the motion clearly (``docs/estimator.md``, "the reader on image tiles too"). The tiles of an ``H x W``
image on an ``R x C`` grid are rows ``round(i H / R)`` to ``round((i + 1) H / R)`` and likewise columns, numbered
row by row; a tile's sums are what the compiled passes (:mod:`evlatcorr.compiled.gradients`,
:mod:`evlatcorr.compiled.high_pass`) accumulate beside the whole image's, and :func:`tile_sums` gives the same from
a per-pixel tensor on any device.
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

__all__ = ["TILE_GRID", "check_grid", "row_bands", "tile_counts", "tile_edges", "tile_pixels", "tile_sums",
           "tiles_fit"]

# the tiles the learned search reads beside the whole frame: 3 rows of 3
TILE_GRID = (3, 3)


def check_grid(grid: tuple[int, int], height: int, width: int) -> None:
    """Refuse a grid that is not whole numbers of tiles, each at least one pixel of an ``height x width`` image.

    Raises:
        ValueError: naming the grid and the image size.
    """
    rows, cols = grid
    if not (isinstance(rows, int) and isinstance(cols, int) and 1 <= rows <= height and 1 <= cols <= width):
        raise ValueError(f"grid must be (rows, columns) of tiles, each at least one pixel of the {height}x{width} "
                         f"image, got {grid}")


def tiles_fit(height: int, width: int, grid: tuple[int, int] = TILE_GRID) -> bool:
    """Whether a frame is read by tiles as well: each tile at least 6x6 pixels (3x3 at half resolution, where the
    sparsity scores also read it). Smaller frames are read whole."""
    return height >= 6 * grid[0] and width >= 6 * grid[1]


def tile_edges(size: int, parts: int) -> list[int]:
    """Where ``parts`` tiles along a side of ``size`` pixels begin, and the side's end (``parts + 1`` values).

    Raises:
        ValueError: when ``size`` or ``parts`` is not a positive whole number.

    Example:
        >>> tile_edges(128, 3)
        [0, 43, 85, 128]
    """
    if not (isinstance(size, int) and isinstance(parts, int) and size >= 1 and parts >= 1):
        raise ValueError(f"size and parts must be positive whole numbers, got {size!r} and {parts!r}")
    return [round(i * size / parts) for i in range(parts + 1)]


def row_bands(height: int, rows: int) -> np.ndarray:
    """The tile row of each image row :math:`(H,)` int64, what the compiled passes read."""
    edges = tile_edges(height, rows)
    return np.repeat(np.arange(rows, dtype=np.int64), np.diff(edges))


def tile_counts(height: int, width: int, grid: tuple[int, int]) -> Tensor:
    """The pixels in each tile :math:`(R C,)` float64.

    Raises:
        ValueError: when the grid does not fit the image (:func:`check_grid`).
    """
    check_grid(grid, height, width)
    rows, cols = (np.diff(tile_edges(size, parts)) for size, parts in zip((height, width), grid))
    return torch.from_numpy(np.outer(rows, cols).reshape(-1).astype(np.float64))


def tile_sums(values: Tensor, grid: tuple[int, int], dtype: torch.dtype | None = None) -> Tensor:
    """The sum over each tile of the last two dimensions: :math:`(..., H, W)` → :math:`(..., R C)`, accumulated in
    ``dtype`` (the values' own by default, float64 for integers).

    A sum over each tile column's pixels, then one matrix product with the tile rows' 0/1 indicator: the values are
    read once, accumulating in ``dtype`` as they are read (a float32 image summed in float64 makes no float64 copy),
    in a handful of kernels on a GPU whatever the image's size.

    Raises:
        ValueError: when the grid does not fit the image (:func:`check_grid`).

    Example:
        >>> tile_sums(torch.ones(2, 4, 6), (2, 3)).tolist()
        [[4.0, 4.0, 4.0, 4.0, 4.0, 4.0], [4.0, 4.0, 4.0, 4.0, 4.0, 4.0]]
    """
    height, width = values.shape[-2:]
    check_grid(grid, height, width)
    if dtype is None:
        dtype = values.dtype if values.is_floating_point() else torch.float64
    cols = tile_edges(width, grid[1])
    across = torch.stack([values[..., c0:c1].sum(-1, dtype=dtype) for c0, c1 in zip(cols, cols[1:])], -1)  # (.., H, C)
    return torch.matmul(_tile_indicator(height, grid[0], dtype, values.device), across).flatten(-2)


@functools.lru_cache(maxsize=64)
def _tile_indicator(size: int, parts: int, dtype: torch.dtype, device: torch.device) -> Tensor:
    """:math:`(parts, size)`: 1 where a pixel along a side of ``size`` lies in that tile, else 0."""
    edges = torch.tensor(tile_edges(size, parts))
    pixel = torch.arange(size)
    return ((pixel >= edges[:-1, None]) & (pixel < edges[1:, None])).to(device=device, dtype=dtype)


def tile_pixels(height: int, width: int, grid: tuple[int, int], device: torch.device | str = "cpu") -> Tensor:
    """Each tile's pixels as indices into the flattened image, row by row: :math:`(R C, N)` int64, ``N`` the largest
    tile's pixels; a smaller tile's row ends with ``height · width``, one past the last pixel (point it at a padding
    value). ``values.flatten(-2)`` padded by one and indexed by it gives every tile's pixels in one gather.

    Raises:
        ValueError: when the grid does not fit the image (:func:`check_grid`).

    Example:
        >>> tile_pixels(2, 3, (1, 2)).tolist()
        [[0, 1, 3, 4], [2, 5, 6, 6]]
    """
    check_grid(grid, height, width)
    return _tile_pixels(height, width, grid, torch.device(device))


@functools.lru_cache(maxsize=64)
def _tile_pixels(height: int, width: int, grid: tuple[int, int], device: torch.device) -> Tensor:
    rows, cols = tile_edges(height, grid[0]), tile_edges(width, grid[1])
    pixels = [torch.arange(r0, r1)[:, None] * width + torch.arange(c0, c1) for r0, r1 in zip(rows, rows[1:])
              for c0, c1 in zip(cols, cols[1:])]
    size = max(p.numel() for p in pixels)
    padded = torch.full((len(pixels), size), height * width, dtype=torch.int64)
    for row, p in zip(padded, pixels):
        row[:p.numel()] = p.flatten()
    return padded.to(device)
