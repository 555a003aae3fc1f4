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

__all__ = ["high_pass_correlation", "TAPS"]

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
    check_arrays({"a": a, "b": b}, 3, (torch.float32, torch.float64))
    if a.shape != b.shape or a.dtype != b.dtype or min(a.shape[1:]) <= TAPS // 2:
        raise ValueError(f"a and b must be alike, at least {TAPS // 2 + 1} pixels each way, got {tuple(a.shape)} "
                         f"{a.dtype} and {tuple(b.shape)} {b.dtype}")
    if np.shape(kernel) != (TAPS,):
        raise ValueError(f"kernel must have {TAPS} taps, got shape {np.shape(kernel)}")
    out = np.empty(a.shape[0], dtype=np.float64)
    in_threads(_kernel(), workers_for(a.shape[0]), a.numpy(), b.numpy(), kernel.astype(a.numpy().dtype), out)
    return out


@functools.cache
def _kernel():
    """The compiled pass, candidates dealt to the threads in turn."""

    def correlate(first, step, a, b, w, out):  # pragma: no cover (compiled)
        count, height, width = a.shape
        row_a = np.empty((height, width), a.dtype)
        row_b = np.empty((height, width), a.dtype)
        sums = np.empty((5, width), np.float64)
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
                ar, br = ak[y], bk[y]
                for x in range(width):
                    ha = ar[x] - (w0 * (p0[x] + p6[x]) + w1 * (p1[x] + p5[x]) + w2 * (p2[x] + p4[x]) + w3 * p3[x])
                    hb = br[x] - (w0 * (q0[x] + q6[x]) + w1 * (q1[x] + q5[x]) + w2 * (q2[x] + q4[x]) + w3 * q3[x])
                    sums[0, x] += ha
                    sums[1, x] += hb
                    sums[2, x] += ha * hb
                    sums[3, x] += ha * ha
                    sums[4, x] += hb * hb
            n = height * width
            sum_a, sum_b = sums[0].sum(), sums[1].sum()
            covariance = sums[2].sum() - sum_a * sum_b / n
            spread = (sums[3].sum() - sum_a * sum_a / n) * (sums[4].sum() - sum_b * sum_b / n)
            out[k] = min(1.0, max(-1.0, covariance / max(np.sqrt(max(spread, 0.0)), 1e-12)))

    return jit(correlate)
