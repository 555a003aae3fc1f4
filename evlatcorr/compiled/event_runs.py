"""One sample's events sorted into per-pixel runs, with each event's count and each pixel's peak: compiled passes.

What :class:`evlatcorr.continuous.ContinuousIntegral` prepares before it reads any window: the events in pixel order
(each pixel's in the order given: a stable sort), where each pixel's run starts, each event's count after it at its
pixel, each pixel's highest count, and the hot pixels (one polarity spanning more log intensity than any scene can)
read as having no events. In eager PyTorch that is a sort, gathers, running sums and scatter-reductions over the
events (about 30 ms for 2 M events on 2 cores); here a counting sort (each thread counts and then places its own
share of the events, so the order within a pixel is kept) and one pass over each pixel's run, the same integers
(tested).
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from evlatcorr.compiled import check_arrays, in_threads, jit, workers_for

__all__ = ["PixelRuns", "sort_into_runs"]

# events per thread at least: fewer are not worth a thread
_EVENTS_PER_WORKER = 65536
# pixels per block of the per-pixel pass, dealt to the threads in turn
_BLOCK = 256


@dataclass
class PixelRuns:
    """Events in pixel order and their levels (see :func:`sort_into_runs`)."""

    pixel: Tensor  # (N,) int64: each event's pixel y·W + x, non-decreasing
    t: Tensor  # (N,) float64 µs
    step: Tensor  # (N,) int8: ±1, 0 at an ignored pixel
    order: Tensor  # (N,) int32 (int64 from 2^31 events): where each came from in the input
    run_start: Tensor  # (P,) int64: each pixel's first event
    bounds: Tensor  # (P + 1,) int64: run_start and the number of events
    after: Tensor  # (N,) int32: each event's count after it at its pixel (0 at an ignored pixel)
    peak_count: Tensor  # (P,) int32: each pixel's highest count, 0 before its first event included
    ignored: Tensor  # (P,) bool: the hot pixels


def sort_into_runs(x: Tensor, y: Tensor, t: Tensor, p: Tensor, sensor_size: tuple[int, int], theta: float,
                   max_log_range: float | None) -> PixelRuns:
    """Sort one sample's events into per-pixel runs (stable) and count their levels.

    Args:
        x, y: event coordinates :math:`(N,)` int64, inside ``sensor_size`` :math:`(H, W)`.
        t: event times :math:`(N,)` float64 µs.
        p: polarities :math:`(N,)` int8, ±1.
        theta: contrast threshold θ.
        max_log_range: a pixel whose θ·count spans more than this (its events' lowest to highest level, 0 before
            the first included) is ignored: its steps and counts are 0; None ignores none.

    Every tensor is on the CPU and contiguous, the coordinates inside the sensor (as :class:`~evlatcorr.events.Events`
    ensures; they are not scanned here). Equals ``ContinuousIntegral``'s eager preparation exactly.

    Raises:
        ValueError: when the events are not four 1-D CPU tensors of one length, or ``theta`` is not positive.
    """
    check_arrays({"x": x, "y": y, "t": t, "p": p}, 1)
    if not len(x) == len(y) == len(t) == len(p):
        raise ValueError(f"x, y, t and p must have one length, got {len(x)}, {len(y)}, {len(t)} and {len(p)}")
    if t.dtype != torch.float64 or p.dtype != torch.int8:
        raise ValueError(f"t must be float64 and p int8 (±1), got {t.dtype} and {p.dtype}")
    if not theta > 0:
        raise ValueError(f"theta must be positive, got {theta}")
    height, width = sensor_size
    num, num_pixels = len(t), height * width
    index_type = np.int32 if num < 2**31 else np.int64
    x_np, y_np, p_np = x.numpy(), y.numpy(), p.numpy()
    workers = workers_for(num, _EVENTS_PER_WORKER)
    chunks = np.linspace(0, num, workers + 1).astype(np.int64)
    # each thread counts its share of the events per pixel, then places them after the shares before its own
    counts = np.zeros((workers, num_pixels), dtype=np.int64)
    in_threads(_counting()[0], workers, x_np, y_np, width, chunks, counts)
    total = counts.sum(0)
    bounds = np.zeros(num_pixels + 1, dtype=np.int64)
    np.cumsum(total, out=bounds[1:])
    cursors = bounds[:-1] + np.cumsum(counts, 0) - counts  # (workers, P): where each thread's share of a pixel goes
    sorted_t, step = np.empty(num, dtype=np.float64), np.empty(num, dtype=np.int8)
    order = np.empty(num, dtype=index_type)
    in_threads(_counting()[1], workers, x_np, y_np, t.numpy(), p_np, width, chunks, cursors, sorted_t, step, order)
    # each pixel's run: its events' counts, its peak, whether it is hot (then its steps are 0)
    pixel, after = np.empty(num, dtype=np.int64), np.empty(num, dtype=np.int32)
    peak_count, ignored = np.empty(num_pixels, dtype=np.int32), np.zeros(num_pixels, dtype=np.bool_)
    limit = -1.0 if max_log_range is None else float(max_log_range)
    in_threads(_levels(), workers_for(num_pixels, _BLOCK), _BLOCK, bounds, step, np.float32(theta), np.float32(limit),
               pixel, after, peak_count, ignored)
    as_tensor = torch.from_numpy
    return PixelRuns(as_tensor(pixel), as_tensor(sorted_t), as_tensor(step), as_tensor(order),
                     as_tensor(bounds[:-1]), as_tensor(bounds), as_tensor(after), as_tensor(peak_count),
                     as_tensor(ignored))


@functools.cache
def _counting():
    """The counting sort's two compiled passes: count each share's events per pixel, then place them (each event's
    time, step and origin where it goes: faster here than placing the origins alone and gathering the rest)."""

    def count(worker, workers, x, y, width, chunks, counts):  # pragma: no cover (compiled)
        own = counts[worker]
        for i in range(chunks[worker], chunks[worker + 1]):
            own[y[i] * width + x[i]] += 1

    def place(worker, workers, x, y, t, p, width, chunks, cursors, sorted_t, step, order):  # pragma: no cover
        cursor = cursors[worker]
        for i in range(chunks[worker], chunks[worker + 1]):
            pixel = y[i] * width + x[i]
            place = cursor[pixel]
            cursor[pixel] = place + 1
            sorted_t[place] = t[i]
            step[place] = p[i]
            order[place] = i

    return jit(count), jit(place)


@functools.cache
def _levels():
    """The compiled pass over each pixel's run."""

    def levels(first_block, block_step, block, bounds, step, theta, limit, pixel, after, peak_count,
               ignored):  # pragma: no cover (compiled)
        num_pixels = bounds.shape[0] - 1
        for p0 in range(first_block * block, num_pixels, block_step * block):
            for pix in range(p0, min(num_pixels, p0 + block)):
                lo, hi = bounds[pix], bounds[pix + 1]
                count, top, low = 0, 0, 0
                for e in range(lo, hi):
                    count += step[e]
                    after[e] = count
                    pixel[e] = pix
                    top = max(top, count)
                    low = min(low, count)
                # a hot pixel, read as having no events (θ·span in float32, as the eager preparation reckons it)
                if limit >= 0 and theta * np.float32(top - low) > limit:
                    ignored[pix] = True
                    top = 0
                    for e in range(lo, hi):
                        step[e] = 0
                        after[e] = 0
                peak_count[pix] = top

    return jit(levels)
