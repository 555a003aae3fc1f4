"""Every window's step-EDI ratio, event change and peak rise in one compiled pass per pixel (a CPU's reads).

:meth:`evlatcorr.continuous.ContinuousIntegral.inverse_ratio` and ``log_ratio`` read many windows ``[a_k, b_k]`` of
one sample's events at a few hundred sorted times. In eager PyTorch that builds tables of every pixel's count, level
and interval integral at every time and sums the windows from them: a dozen passes over tables of tens of MB, bound
by memory traffic on a CPU (a DAVIS346 frame's 101 candidates: about 55 ms on 2 cores). Here each pixel walks its own
events once, in time order, keeping its count and running integral at each time in a few KB of scratch, and writes
only the results: no tables. The sums are float64 throughout, and a window whose running sums would cancel (a pixel
much brighter before the window than inside it) is summed again from its own events, so the results equal the
tables' to float32 rounding (tested).

Compiled on first use and run in threads over interleaved blocks of pixels (:mod:`evlatcorr.compiled`).
"""

from __future__ import annotations

import functools

import numpy as np
import torch
from torch import Tensor

from evlatcorr.compiled import check_arrays, in_threads, jit, workers_for

__all__ = ["read_windows"]

# pixels per block of work: the scratch of one block's results stays in a core's cache, and blocks are dealt to the
# threads in turn so that their writes to each output row interleave
_BLOCK = 32
# a window whose sum is below this share of the running integral at its end is summed again from its events: the
# difference of two running sums keeps float64's 16 digits less the decades between them
_CANCELLATION = 1e-6
# the least a window's sum is taken to be (float64's least normal number): never a division by 0
_TINY = 2.2250738585072014e-308


def read_windows(t: Tensor, step: Tensor, run_bounds: Tensor, peak_count: Tensor, theta: float, times: Tensor,
                 a: Tensor, b: Tensor, r: Tensor, quarters: list[Tensor], duration: float, width: int, out: Tensor,
                 change: Tensor | None = None, peak: Tensor | None = None, peak_stride: int = 1,
                 frame_height: int | None = None) -> None:
    """Write every window's ratio (and event change, peak rise) of every pixel.

    Args:
        t: event times :math:`(N,)` float64 µs in pixel order, each pixel's in time order.
        step: their polarity steps :math:`(N,)` int8 (±1; 0 for a pixel read as having none).
        run_bounds: pixel ``i``'s events are ``[run_bounds[i], run_bounds[i + 1])`` :math:`(P + 1,)` int64.
        peak_count: each pixel's highest count over its events :math:`(P,)` int32 (0 before its first); levels are
            read relative to it.
        theta: contrast threshold θ.
        times: sorted distinct times :math:`(G,)` float64 µs.
        a, b, r: each window's start, end and reference as indices into ``times`` :math:`(K,)` int64.
        quarters: more indices :math:`(K,)` each whose counts the peak rise also takes.
        duration: the exposure time the ratio divides by, µs.
        width: the sensor's width (pixel ``i`` is row ``i // width``).
        out: :math:`(K, P)` float32 receives ``1 / R``; float64 receives ``log R``.
        change: optional :math:`(K, P)` float32 that receives ``θ (C(b) − C(a))``.
        peak: optional :math:`(K, F·⌈h/s⌉·⌈W/s⌉)` float32 that receives ``θ (max C − C(r))`` over ``a``, the
            quarters, ``r`` and ``b`` at every ``peak_stride``-th row and column of each frame.
        peak_stride: s.
        frame_height: h, the height of each of the ``F`` frames stacked as the sensor's rows (their sampled rows
            restart at each frame's first); None: one frame, the sensor's height.

    Every tensor is on the CPU and contiguous; ``out``, ``change`` and ``peak`` are written in place.

    Raises:
        ValueError: when the arrays are not on the CPU, contiguous, or of the shapes above (the pass checks no index).
    """
    check_arrays({"t": t, "step": step, "run_bounds": run_bounds, "peak_count": peak_count, "times": times, "a": a,
                  "b": b, "r": r, **{f"quarters[{i}]": q for i, q in enumerate(quarters)}}, 1)
    check_arrays({"out": out}, 2, (torch.float32, torch.float64))
    pixels, k = len(run_bounds) - 1, len(a)
    if len(t) != len(step) or len(peak_count) != pixels or out.shape != (k, pixels):
        raise ValueError(f"t and step must have one length, peak_count {pixels} pixels and out shape {(k, pixels)}, "
                         f"got {len(t)}, {len(step)}, {len(peak_count)} and {tuple(out.shape)}")
    if any(len(index) != k for index in (b, r, *quarters)):
        raise ValueError(f"a, b, r and the quarters must each have one index per window ({k})")
    for name, part, width_of in (("change", change, pixels), ("peak", peak, None)):
        if part is not None:
            check_arrays({name: part}, 2, (torch.float32,))
            if part.shape[0] != k or (width_of is not None and part.shape[1] != width_of):
                raise ValueError(f"{name} must have {k} rows" + (f" of {width_of}" if width_of else "") +
                                 f", got {tuple(part.shape)}")
    kernel = _kernel()
    peak_width = -(-width // peak_stride)
    frame_height = pixels // width if frame_height is None else frame_height
    peak_rows = -(-frame_height // peak_stride)
    lut_size = int((run_bounds[1:] - run_bounds[:-1]).max()) + 1 if len(run_bounds) > 1 else 1
    # exp(θ·c) of every count c relative to the pixel's peak (0 down to minus its events): no exp per event or time
    lut = np.exp(-float(theta) * np.arange(lut_size, dtype=np.float64))
    quarter_rows = (torch.stack(quarters) if quarters else torch.empty((0, len(a)), dtype=torch.int64)).numpy()
    nothing = np.empty((0, 0), dtype=np.float32)
    args = (t.numpy(), step.numpy(), run_bounds.numpy(), peak_count.numpy(), lut, times.numpy(), a.numpy(),
            b.numpy(), r.numpy(), np.ascontiguousarray(quarter_rows), float(duration), int(peak_stride), int(width),
            int(peak_width), int(max(frame_height, 1)), int(peak_rows), float(theta), out.dtype == torch.float64,
            out.numpy(), nothing if change is None else change.numpy(), nothing if peak is None else peak.numpy())
    in_threads(kernel, workers_for(len(run_bounds) - 1, _BLOCK), *args)


@functools.cache
def _kernel():
    """The compiled per-pixel pass."""

    def read_blocks(first_block, block_step, t, step, run_bounds, peak_count, lut, g, ia, ib, ir, iq, duration,
                    stride, width, peak_width, frame_height, peak_rows, theta, log_out, out, change,
                    peak):  # pragma: no cover (compiled)
        num = g.shape[0]
        k_count = ia.shape[0]
        num_pixels = run_bounds.shape[0] - 1
        ratio_free = 0.0 if log_out else 1.0  # a pixel with no events: log R = 0, 1 / R = 1
        count = np.empty(num, np.int32)
        running = np.empty(num, np.float64)
        ratio = np.empty((_BLOCK, k_count), out.dtype)
        events = np.empty((_BLOCK, k_count), np.float32)
        window = np.empty(k_count, np.float64)
        for p0 in range(first_block * _BLOCK, num_pixels, block_step * _BLOCK):
            p1 = min(num_pixels, p0 + _BLOCK)
            for pix in range(p0, p1):
                col = pix - p0
                lo, hi = run_bounds[pix], run_bounds[pix + 1]
                # where the pixel lies among the peak's: every stride-th row and column of each frame, frame after
                # frame (-1: not sampled)
                place = -1
                if peak.shape[0] > 0:
                    y = pix // width
                    x = pix - y * width
                    frame = y // frame_height
                    y -= frame * frame_height
                    if y % stride == 0 and x % stride == 0:
                        place = (frame * peak_rows + y // stride) * peak_width + x // stride
                if lo == hi:
                    for k in range(k_count):
                        ratio[col, k] = ratio_free
                        events[col, k] = 0.0
                    if place >= 0:
                        for k in range(k_count):
                            peak[k, place] = 0.0
                    continue
                # the count (relative to the pixel's peak) and the integral of exp(θ·count) from g[0] at each time;
                # an event counts at the times after it
                c = -np.int32(peak_count[pix])
                e = lo
                while e < hi and t[e] < g[0]:
                    c += step[e]
                    e += 1
                level = lut[-c]
                count[0] = c
                running[0] = 0.0
                total = 0.0
                for j in range(1, num):
                    gj = g[j]
                    part = level * (gj - g[j - 1])
                    if e < hi and t[e] < gj:
                        while e < hi and t[e] < gj:  # each event's new level held from its time on
                            part += (lut[-(c + step[e])] - lut[-c]) * (gj - t[e])
                            c += step[e]
                            e += 1
                        level = lut[-c]
                    count[j] = c
                    total += part
                    running[j] = total
                for k in range(k_count):
                    window[k] = max(running[ib[k]] - running[ia[k]], _TINY)
                    events[col, k] = theta * (count[ib[k]] - count[ia[k]])
                for k in range(k_count):
                    ak, bk = ia[k], ib[k]
                    if window[k] < _CANCELLATION * running[bk]:  # the window again from its own events
                        ck = count[ak]
                        again = lut[-ck] * (g[bk] - g[ak])
                        for f in range(lo, hi):
                            if g[ak] <= t[f] < g[bk]:
                                again += (lut[-(ck + step[f])] - lut[-ck]) * (g[bk] - t[f])
                                ck += step[f]
                        window[k] = max(again, _TINY)
                if log_out:
                    for k in range(k_count):
                        ratio[col, k] = np.log(window[k] / duration) - theta * count[ir[k]]
                else:
                    for k in range(k_count):
                        ratio[col, k] = lut[-count[ir[k]]] * duration / window[k]
                if place >= 0:
                    for k in range(k_count):
                        reference = count[ir[k]]
                        top = max(max(count[ia[k]], count[ib[k]]), reference)
                        for i in range(iq.shape[0]):
                            top = max(top, count[iq[i, k]])
                        peak[k, place] = theta * (top - reference)
            for k in range(k_count):
                for col in range(p1 - p0):
                    out[k, p0 + col] = ratio[col, k]
            if change.shape[0] > 0:
                for k in range(k_count):
                    for col in range(p1 - p0):
                        change[k, p0 + col] = events[col, k]

    return jit(read_blocks)
