"""Input validation at the public boundary (kornia's ``KORNIA_CHECK_*`` in spirit).

Every check raises :class:`ValueError` naming the argument, what was expected and what was
received, so bad input never reaches deep inside torch.

Validate once, at the public boundary: a public function ``foo`` checks its arguments and calls
``_foo``, which does the work on inputs taken as checked; inside the package, a caller whose inputs
are already checked calls ``_foo`` (the value checks read tensor data: on a GPU each is a sync).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch
from torch import Tensor

from evlatcorr.sample_warnings import user_stacklevel

__all__ = [
    "MEMORY_BUDGET_BYTES",
    "check_int",
    "check_image",
    "check_shape",
    "check_batch_vector",
    "check_finite",
    "check_exposure",
    "warn_if_coarse_times",
    "check_search_range",
    "check_memory",
    "check_has_events",
    "FEW_EVENTS",
    "check_search_size",
    "MIN_SEARCH_SIZE",
    "NoEventsError",
    "check_threshold",
    "resolve_memory_budget",
]

#: Most memory (bytes) that one event grid or latency-search table may take (default 2 GiB).
#: Larger ones are computed in strips of rows (the EDI, the latency search) or refused with a
#: :class:`ValueError` that says what to change (a grid asked for whole). Set it (e.g.
#: ``evlatcorr.checks.MEMORY_BUDGET_BYTES = 8 * 2**30``) or pass ``memory_budget=`` where offered.
MEMORY_BUDGET_BYTES = 2 * 1024**3


def check_shape(x: object, shape: Sequence[str | int], name: str) -> None:
    """Check that ``x`` is a tensor of the given symbolic shape, e.g. ``["B", "C", "H", "W"]``.

    Integers in ``shape`` must match exactly; strings match any size but must be consistent
    with each other within the call.
    """
    if not isinstance(x, Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape {tuple(shape)}, got {type(x).__name__}")
    if x.dim() != len(shape):
        raise ValueError(f"{name} must have shape {tuple(shape)} ({len(shape)} dims), got {tuple(x.shape)}")
    seen: dict[str, int] = {}
    for dim, (want, got) in enumerate(zip(shape, x.shape)):
        if isinstance(want, int):
            if want != got:
                raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(x.shape)} (dim {dim})")
        elif want in seen and seen[want] != got:
            raise ValueError(f"{name} must have shape {tuple(shape)}, got {tuple(x.shape)} ({want} differs)")
        else:
            seen[want] = got


def check_int(value: object, name: str, minimum: int = 1) -> int:
    """Refuse anything but a Python integer (not a bool) of at least ``minimum``.

    Example:
        >>> check_int(3, "num_bins")
        3
        >>> check_int(True, "num_bins")
        Traceback (most recent call last):
        ...
        ValueError: num_bins must be a positive integer, got True
    """
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        expected = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return value


def check_finite(x: Tensor, name: str) -> None:
    """Raise when ``x`` has NaN or infinite values."""
    if x.is_floating_point() and not bool(torch.isfinite(x).all()):
        bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name} has {bad} NaN or infinite values")


def check_image(x: object, name: str, channels: Sequence[int] = (1, 3), unit_range: bool = True) -> None:
    """Check a float image batch ``(B, C, H, W)`` with C in ``channels`` and values in [0, 1]."""
    check_shape(x, ["B", "C", "H", "W"], name)
    assert isinstance(x, Tensor)  # for the type checker; check_shape already raised otherwise
    if not x.is_floating_point():
        raise ValueError(f"{name} must be a floating point tensor, got {x.dtype}")
    if x.shape[1] not in channels:
        raise ValueError(f"{name} must have C in {tuple(channels)} channels, got {x.shape[1]}")
    check_finite(x, name)
    if unit_range and x.numel() > 0:
        lo, hi = torch.stack(torch.aminmax(x.detach())).tolist()  # one read; detached: a check, not the graph
        if lo < 0.0 or hi > 1.0:
            raise ValueError(f"{name} must hold linear intensities in [0, 1], got values in [{lo:.4g}, {hi:.4g}]")


def check_batch_vector(x: object, batch_size: int, name: str) -> Tensor:
    """Return ``x`` as a float64 tensor of shape ``(B,)``; scalars are broadcast."""
    if not isinstance(x, Tensor):
        x = torch.as_tensor(x, dtype=torch.float64)
    if x.dim() == 0:
        x = x.expand(batch_size)
    if x.shape != (batch_size,):
        raise ValueError(f"{name} must have shape ({batch_size},) (one value per sample), got {tuple(x.shape)}")
    check_finite(x, name)
    return x


def check_threshold(threshold: object, batch_size: int) -> Tensor:
    """Return the contrast threshold as a tensor :math:`(B,)`, refused unless finite and positive.

    Example:
        >>> check_threshold(0.2, 2).tolist()
        [0.2, 0.2]
        >>> check_threshold(0.0, 1)
        Traceback (most recent call last):
        ...
        ValueError: threshold must be positive, got 0.0
    """
    theta = check_batch_vector(threshold, batch_size, "threshold")
    if bool((theta <= 0).any()):
        raise ValueError(f"threshold must be positive, got {theta.min().item()}")
    return theta


def warn_if_coarse_times(t: Tensor | np.ndarray, name: str) -> None:
    """Warn where times in µs come in a floating type too coarse for them (float32 absolute times, which round a
    camera's timestamps by minutes): the events' order, the exposures and the latency search need µs, and what was
    rounded away cannot be recovered. The warning points at the user's line.

    Example:
        >>> warn_if_coarse_times(torch.tensor([0.0, 20_000.0], dtype=torch.float32), "t")  # 2 ms of resolution: fine
        >>> warn_if_coarse_times(torch.tensor([1.6e15], dtype=torch.float32), "t")  # doctest: +SKIP
        UserWarning: t is float32 with times up to 1.6e+15 us, where it resolves only about 1.91e+08 us: ...
    """
    if isinstance(t, np.ndarray) and t.dtype.kind == "f":  # e.g. times loaded as float32 arrays
        t = torch.from_numpy(t)
    if not isinstance(t, Tensor) or not t.is_floating_point() or t.dtype == torch.float64 or not t.numel():
        return
    largest = float(t.detach().abs().max())
    if not math.isfinite(largest):
        return  # refused next, as NaN or infinite
    resolution = torch.finfo(t.dtype).eps * largest
    if resolution > 1.0:
        warnings.warn(f"{name} is {str(t.dtype).removeprefix('torch.')} with times up to {largest:.6g} us, "
                      f"where it resolves only about {resolution:.3g} us: the times are already rounded; "
                      "pass int64 or float64 microseconds (e.g. times relative to the recording's start)",
                      stacklevel=user_stacklevel())


# No camera exposes a frame for less than a microsecond: every exposure below it means times in other units
SHORTEST_EXPOSURE_US = 1.0


def check_exposure(start: Tensor, end: Tensor) -> None:
    """Exposure windows must have positive length; a warning where every one is shorter than a microsecond (times
    given in seconds, most likely: evlatcorr reads them as µs).

    Example:
        >>> check_exposure(torch.tensor([0.0]), torch.tensor([20000.0]))
        >>> check_exposure(torch.tensor([0.0]), torch.tensor([0.02]))  # doctest: +SKIP
        UserWarning: every exposure is shorter than 1 us (the longest 0.02 us): evlatcorr takes times in ...
    """
    length = end - start
    if not length.numel():
        return
    shortest, longest = torch.stack([length.min(), length.max()]).tolist()  # one read of the device
    if shortest <= 0:
        i = int(torch.nonzero(length <= 0)[0, 0])
        raise ValueError(
            f"exposure_end must be after exposure_start; sample {i} has start {float(start[i]):.1f} us "
            f"and end {float(end[i]):.1f} us"
        )
    if longest < SHORTEST_EXPOSURE_US:
        warnings.warn(f"every exposure is shorter than {SHORTEST_EXPOSURE_US:g} us (the longest {longest:.3g} us): "
                      "evlatcorr takes times in microseconds; times in seconds or milliseconds give latencies in "
                      "the same units and miss its defaults (the search's reach, the reader's training)",
                      stacklevel=user_stacklevel())


def check_search_range(search_range: object, name: str = "search_range") -> tuple[float, float] | None:
    """Validate a latency search range ``(low, high)`` in µs: two finite numbers with ``high > low``.

    Returns:
        ``(low, high)`` as floats, or None for None (the default range).

    Example:
        >>> check_search_range((0, 20000))
        (0.0, 20000.0)
        >>> check_search_range((0, float("inf")))
        Traceback (most recent call last):
        ...
        ValueError: search_range must be two finite numbers (low, high) in us, got (0, inf)
    """
    if search_range is None:
        return None
    try:
        low, high = (float(v) for v in search_range)  # type: ignore[union-attr]
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a pair (low, high) of numbers in us, got {search_range!r}") from None
    if not (math.isfinite(low) and math.isfinite(high)):
        raise ValueError(f"{name} must be two finite numbers (low, high) in us, got {search_range!r}")
    if not high > low:
        raise ValueError(f"{name} must be (low, high) with high > low, got {search_range!r}")
    return low, high


def resolve_memory_budget(budget: int | None = None) -> int:
    """The memory budget in bytes: ``budget`` when given, else :data:`MEMORY_BUDGET_BYTES` (read at call time)."""
    value = MEMORY_BUDGET_BYTES if budget is None else budget
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value) and value > 0):
        raise ValueError(f"memory_budget must be a positive number of bytes, got {value!r}")
    return int(value)


def check_memory(num_bytes: int, what: str, advice: str, budget: int | None = None) -> None:
    """Refuse an allocation of ``num_bytes`` (an estimate, from sizes only) over the memory budget.

    Args:
        num_bytes: estimated bytes.
        what: what would be allocated, e.g. ``"the event grid (1, 25000003, 8, 9)"``.
        advice: what to change, e.g. ``"narrow search_range"``.
        budget: bytes; default :data:`MEMORY_BUDGET_BYTES`.

    Example:
        >>> check_memory(3 * 2**30, "a grid", "use fewer bins", budget=2**30)  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: a grid needs about 3.0 GiB, over the memory budget of 1.0 GiB: use fewer bins (or raise ...)
    """
    limit = resolve_memory_budget(budget)
    if num_bytes > limit:
        raise ValueError(f"{what} needs about {_format_bytes(num_bytes)}, over the memory budget of "
                         f"{_format_bytes(limit)}: {advice} (or raise the budget: memory_budget= or "
                         "evlatcorr.checks.MEMORY_BUDGET_BYTES)")


def _format_bytes(num_bytes: float) -> str:
    """``3.0 GiB``, ``12.5 MiB``, ... (the largest binary unit that keeps the value >= 1)."""
    for unit, size in (("TiB", 2**40), ("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if num_bytes >= size:
            return f"{num_bytes / size:.1f} {unit}"
    return f"{int(num_bytes)} bytes"


#: The smallest frame side (pixels) the latency search takes: its sharpness scores' and ghost cue's filters reach 3
#: pixels from each one.
MIN_SEARCH_SIZE = 4


def check_search_size(size: Sequence[int], name: str = "frames") -> None:
    """Raise when frames of ``size`` ``(H, W)`` are too small for the latency search (:data:`MIN_SEARCH_SIZE`).

    Example:
        >>> check_search_size((4, 346))
        >>> check_search_size((3, 8))  # doctest: +ELLIPSIS
        Traceback (most recent call last):
        ...
        ValueError: frames of 3x8 pixels are too small for the latency search: it needs at least 4x4 ...
    """
    height, width = (int(v) for v in size[-2:])
    if min(height, width) < MIN_SEARCH_SIZE:
        raise ValueError(f"{name} of {height}x{width} pixels are too small for the latency search: it needs at least "
                         f"{MIN_SEARCH_SIZE}x{MIN_SEARCH_SIZE} (its image filters reach 3 pixels); crop less")


#: below this many events in a frame's exposure and search window, its events do not tell its latency: on the
#: accuracy suite's tuning cases with their events thinned at random, such frames' estimates missed by a median 3.0 ms,
#: as much as a guess that knows only the cases' typical latency (``python benchmarks/few_events.py``,
#: docs/accuracy.md); the corrector and ``evlatcorr info`` name them
FEW_EVENTS = 100


def check_has_events(frames: Any) -> Tensor:
    """Every sample of an ``EventFrames`` batch needs events in ``[exposure_start, exposure_end + exposure time)``.

    That is the window the latency is estimated from (exposure plus the default search range);
    without events there is nothing to estimate a latency from, in constant or spatial mode.

    Returns:
        each sample's events in that window :math:`(B,)`, int64 (on the host).
    """
    ev = frames.events
    start = frames.exposure_start.to(ev.device, torch.float64)
    end = (frames.exposure_end + frames.exposure_time).to(ev.device, torch.float64)
    # events are sorted by sample, then time: two binary searches per sample, no pass over the events
    bounds = ev.sample_bounds().tolist()
    counts = torch.stack([torch.searchsorted(ev.t[lo:hi], torch.stack([start[i], end[i]])).diff()[0]
                          for i, (lo, hi) in enumerate(zip(bounds[:-1], bounds[1:]))]).cpu()
    if bool((counts == 0).any()):
        i = int(torch.nonzero(counts == 0)[0, 0])
        exposure = float(frames.exposure_time[i])
        # times given in other units (EventFrames warned when made) are shown, not rounded to 0, and named
        units = ("" if exposure >= SHORTEST_EXPOSURE_US else
                 f" (the exposure is {exposure:.3g} us long: evlatcorr takes times in microseconds)")
        lo, hi = bounds[i], bounds[i + 1]
        # events far from the window are more often a clock or unit mix-up than a still scene: say where they are
        count = f"{hi - lo} events lie" if hi - lo > 1 else "1 event lies"
        elsewhere = ("" if hi == lo else
                     f"; its {count} in [{_time_us(float(ev.t[lo]))}, {_time_us(float(ev.t[hi - 1]))}] us (events "
                     "and frames must share one clock, in microseconds)")
        raise NoEventsError(i, f"sample {i} has no events in its exposure and search window "
                               f"[{_time_us(float(frames.exposure_start[i]))}, "
                               f"{_time_us(float(frames.exposure_end[i] + frames.exposure_time[i]))}) us{units}: "
                               f"latency cannot be estimated without events{elsewhere}")
    return counts


class NoEventsError(ValueError):
    """A sample of the batch has no events in its exposure and search window (:func:`check_has_events`): the first
    such sample's index is ``sample``. A stream (:class:`~evlatcorr.temporal.StreamingLatencyCorrector`) carries the
    previous frame's latency over such a frame; a batch corrector refuses it."""

    def __init__(self, sample: int, message: str) -> None:
        super().__init__(message)
        self.sample = sample


def _time_us(value: float) -> str:
    """A time in µs for a message: whole microseconds, or 6 significant digits below one (times in other units)."""
    return f"{value:.0f}" if abs(value) >= 1 or value == 0 else f"{value:.6g}"
