"""The ghost cue's correlation of many image pairs after a Gaussian high-pass, in one compiled pass (a CPU's way).

:func:`evlatcorr.ghost.ghost_moment` correlates each candidate's high-passed log latent with its high-passed event
change. In eager PyTorch that is two Gaussian blurs per pair (kornia's, seven taps a direction), two subtractions and
five reductions: a dozen passes over the candidates' images. Here each pair is blurred along its rows into a scratch
image, then down its columns, the high-passed values made and summed on the fly (per column in float64, so the loops
vectorise without reordering a sum): two passes over the inputs and none over a result. Borders are reflected as
kornia's ``"reflect"`` does (``x[-1] = x[1]``).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from evlatcorr.compiled import check_arrays, in_threads, jit, workers_for
from evlatcorr.image_tiles import check_grid, row_bands, tile_edges

__all__ = ["TAPS", "high_pass_correlation", "high_pass_tile_correlation"]

# the blur's taps: 6σ + 1 at σ = 1 px (the ghost cue's), the only size compiled
TAPS = 7


def high_pass_correlation(a: Tensor, b: Tensor, kernel: np.ndarray) -> np.ndarray:
    """Correlation of each image of ``a`` with its image of ``b`` after the Gaussian ``kernel`` is removed from both.

    Args:
        a, b: :math:`(K, H, W)` float32 or float64 on the CPU, contiguous, at least 4 pixels each way.
        kernel: the blur's :data:`TAPS` normalised taps (float64), symmetric.

    Returns:
        :math:`(K,)` float64 in [-1, 1]; 0 where either high-passed image is flat.

    Raises:
        ValueError: when ``a`` and ``b`` are not alike as above, or ``kernel`` has not :data:`TAPS` taps.
    """
    return high_pass_tile_correlation(a, b, kernel, (1, 1))[:, 0]


def high_pass_tile_correlation(a: Tensor, b: Tensor, kernel: np.ndarray, grid: tuple[int, int]) -> np.ndarray:
    """:func:`high_pass_correlation` over each whole image and over each tile of it
    (:mod:`evlatcorr.image_tiles`) from the same pass: each tile's correlation of the high-passed values in it.

    Args:
        a, b, kernel: as :func:`high_pass_correlation`.
        grid: ``(rows, columns)`` of tiles; ``(1, 1)`` for the whole images alone.

    Returns:
        :math:`(K, 1 + R C)` float64: the whole image, then the tiles row by row (none for a ``(1, 1)`` grid).

    Raises:
        ValueError: as :func:`high_pass_correlation`, or for a grid that does not fit the images.
    """
    check_arrays({"a": a, "b": b}, 3, (torch.float32, torch.float64))
    if a.shape != b.shape or a.dtype != b.dtype or min(a.shape[1:]) <= TAPS // 2:
        raise ValueError(f"a and b must be alike, at least {TAPS // 2 + 1} pixels each way, got {tuple(a.shape)} "
                         f"{a.dtype} and {tuple(b.shape)} {b.dtype}")
    if np.shape(kernel) != (TAPS,):
        raise ValueError(f"kernel must have {TAPS} taps, got shape {np.shape(kernel)}")
    height, width = a.shape[1:]
    check_grid(grid, height, width)
    tiles = 0 if grid == (1, 1) else grid[0] * grid[1]
    out = np.empty((a.shape[0], 1 + tiles), dtype=np.float64)
    columns = np.asarray(tile_edges(width, grid[1]), dtype=np.int64)
    in_threads(_kernel(), workers_for(a.shape[0]), a.numpy(), b.numpy(), kernel.astype(a.numpy().dtype),
               row_bands(height, grid[0]), columns, tiles, out)
    return out


@functools.cache
def _kernel():
    """The compiled pass, candidates dealt to the threads in turn."""

    def correlate(first, step, a, b, w, bands, columns, tiles, out):  # pragma: no cover (compiled)
        count, height, width = a.shape
        rows_of = np.zeros(bands[-1] + 1, np.int64)
        for y in range(height):
            rows_of[bands[y]] += 1
        totals = np.empty((1 + tiles, 5), np.float64)
        counts = np.empty(1 + tiles, np.float64)
        row_a = np.empty((height, width), a.dtype)
        row_b = np.empty((height, width), a.dtype)
        sums = np.empty((bands[-1] + 1, 5, width), np.float64)  # per tile row: its tiles' sums are column runs
        w0, w1, w2, w3 = w[0], w[1], w[2], w[3]
        rows = np.empty(TAPS, np.int64)
        for k in range(first, count, step):
            ak, bk = a[k], b[k]
            for y in range(height):  # along the rows
                ar, br, oa, ob = ak[y], bk[y], row_a[y], row_b[y]
                for x in range(3, width - 3):
                    oa[x] = w0 * (ar[x - 3] + ar[x + 3]) + w1 * (ar[x - 2] + ar[x + 2]) + w2 * (ar[x - 1] + ar[x + 1]) \
                        + w3 * ar[x]
                    ob[x] = w0 * (br[x - 3] + br[x + 3]) + w1 * (br[x - 2] + br[x + 2]) + w2 * (br[x - 1] + br[x + 1]) \
                        + w3 * br[x]
                for x in (0, 1, 2, width - 3, width - 2, width - 1):
                    va, vb = 0.0, 0.0
                    for t in range(TAPS):
                        i = abs(x + t - 3)
                        if i > width - 1:
                            i = 2 * (width - 1) - i
                        va += w[t] * ar[i]
                        vb += w[t] * br[i]
                    oa[x], ob[x] = va, vb
            sums[:] = 0.0
            for y in range(height):  # down the columns, each high-passed value summed where it is made
                for t in range(TAPS):
                    i = abs(y + t - 3)
                    rows[t] = 2 * (height - 1) - i if i > height - 1 else i
                p0, p1, p2, p3, p4, p5, p6 = (row_a[rows[0]], row_a[rows[1]], row_a[rows[2]], row_a[rows[3]],
                                              row_a[rows[4]], row_a[rows[5]], row_a[rows[6]])
                q0, q1, q2, q3, q4, q5, q6 = (row_b[rows[0]], row_b[rows[1]], row_b[rows[2]], row_b[rows[3]],
                                              row_b[rows[4]], row_b[rows[5]], row_b[rows[6]])
                ar, br, band = ak[y], bk[y], sums[bands[y]]
                for x in range(width):
                    ha = ar[x] - (w0 * (p0[x] + p6[x]) + w1 * (p1[x] + p5[x]) + w2 * (p2[x] + p4[x]) + w3 * p3[x])
                    hb = br[x] - (w0 * (q0[x] + q6[x]) + w1 * (q1[x] + q5[x]) + w2 * (q2[x] + q4[x]) + w3 * q3[x])
                    band[0, x] += ha
                    band[1, x] += hb
                    band[2, x] += ha * hb
                    band[3, x] += ha * ha
                    band[4, x] += hb * hb
            totals[:] = 0.0
            counts[0] = height * width
            for r in range(sums.shape[0]):
                for j in range(5):
                    totals[0, j] += sums[r, j].sum()
                if tiles:
                    for c in range(len(columns) - 1):
                        t = 1 + r * (len(columns) - 1) + c
                        counts[t] = rows_of[r] * (columns[c + 1] - columns[c])
                        for j in range(5):
                            totals[t, j] = sums[r, j, columns[c]:columns[c + 1]].sum()
            for t in range(1 + tiles):
                n = counts[t]
                sum_a, sum_b = totals[t, 0], totals[t, 1]
                covariance = totals[t, 2] - sum_a * sum_b / n
                spread = (totals[t, 3] - sum_a * sum_a / n) * (totals[t, 4] - sum_b * sum_b / n)
                out[k, t] = min(1.0, max(-1.0, covariance / max(np.sqrt(max(spread, 0.0)), 1e-12)))

    return jit(correlate)
