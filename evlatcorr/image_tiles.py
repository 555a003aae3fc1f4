"""A frame's tiles: the grid the learned search also reads its curves on, and sums over each tile.

A small object moving over a static background barely moves a whole-frame sharpness score, where the tile holding
it shows the motion clearly (``docs/estimator.md``, "the reader on image tiles too"). The tiles of an ``H x W``
image on an ``R x C`` grid are rows ``round(i H / R)`` to ``round((i + 1) H / R)`` and likewise columns, numbered
row by row; a tile's sums are what the compiled passes (:mod:`evlatcorr.compiled.gradients`,
:mod:`evlatcorr.compiled.high_pass`) accumulate beside the whole image's, and :func:`tile_sums` gives the same from
a per-pixel tensor on any device.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

__all__ = ["TILE_GRID", "check_grid", "row_bands", "tile_counts", "tile_edges", "tile_sums", "tiles_fit"]

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
    ``dtype`` (the values' own by default).

    Raises:
        ValueError: when the grid does not fit the image (:func:`check_grid`).

    Example:
        >>> tile_sums(torch.ones(2, 4, 6), (2, 3)).tolist()
        [[4.0, 4.0, 4.0, 4.0, 4.0, 4.0], [4.0, 4.0, 4.0, 4.0, 4.0, 4.0]]
    """
    height, width = values.shape[-2:]
    check_grid(grid, height, width)
    rows, cols = tile_edges(height, grid[0]), tile_edges(width, grid[1])
    across = torch.stack([values[..., c0:c1].sum(-1, dtype=dtype) for c0, c1 in zip(cols, cols[1:])], -1)  # (.., H, C)
    return torch.stack([across[..., r0:r1, :].sum(-2) for r0, r1 in zip(rows, rows[1:])], -2).flatten(-2)
