"""Converting a file's conventions to ours, once, at the edge: event columns, time units, images.

Ours: timestamps in microseconds (float64), polarity ±1, frames float32 ``(C, H, W)`` in [0, 1].
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from typing import Any

import numpy as np

from evlatcorr.events import Events
from evlatcorr.io.records import EVENT_DTYPE, RecordingError

__all__ = [
    "TIME_UNITS",
    "iter_events_as_chunks",
    "sorted_by_time",
    "structured_events",
    "time_scale",
    "to_microseconds",
    "to_unit_image",
]


def structured_events(x: np.ndarray, y: np.ndarray, t: np.ndarray, p: np.ndarray,
                      where: str | None = None) -> np.ndarray:
    """Pack columns into our structured layout: t as float64 µs, polarity {0,1}, ±1 or bool as ±1.

    Columns may be 1-D or ``(N, 1)`` (some datasets store column vectors). They are validated the way
    :class:`~evlatcorr.Events` validates its input, vectorised over the chunk: one length, integer
    pixel coordinates, and polarities all in {0, 1}, all in {-1, +1}, or bool.

    Args:
        x, y, t, p: the columns (t already in µs).
        where: the file and dataset they come from, to start error messages with; with it the
            error is a :class:`RecordingError`, without a plain :class:`ValueError`.

    Raises:
        RecordingError: (a :class:`ValueError`) for columns of different lengths, non-integer
            coordinates, or a polarity outside {0, 1} / {-1, +1} / bool.

    Example:
        >>> ev = structured_events(np.array([1]), np.array([2]), np.array([3.0]), np.array([0]))
        >>> int(ev["p"][0]), float(ev["t"][0])
        (-1, 3.0)
        >>> try:
        ...     structured_events(np.array([1]), np.array([2]), np.array([3.0]), np.array([5]), where="a.h5: /events")
        ... except RecordingError as exc:
        ...     print(exc)
        a.h5: /events: polarity must be 0/1, -1/+1 or bool, got values [5]
    """
    error = RecordingError if where else ValueError
    prefix = f"{where}: " if where else ""
    x, y, t, p = (np.asarray(v).reshape(-1) for v in (x, y, t, p))
    n = len(t)
    if not len(x) == len(y) == len(p) == n:
        raise error(f"{prefix}event columns differ in length: x {len(x)}, y {len(y)}, t {n}, p {len(p)}")
    for name, v in (("x", x), ("y", y)):
        if v.dtype.kind == "f" and n and not bool(np.all(v == np.round(v))):
            raise error(f"{prefix}{name} must hold integer pixel coordinates, got fractional or NaN values")
    out = np.empty(n, dtype=EVENT_DTYPE)
    out["x"], out["y"], out["t"] = x, y, t
    out["p"] = _signed_polarity(p, error, prefix)
    return out


def _signed_polarity(p: np.ndarray, error: type[ValueError], prefix: str) -> np.ndarray:
    """±1 from polarities all in {0, 1}, all in {-1, +1}, or bool (vectorised, a few passes)."""
    if p.dtype == np.bool_:
        return np.where(p, 1, -1)
    if not len(p):
        return np.zeros(0, dtype=np.int8)
    if p.dtype.kind in "iu":
        lo, hi = int(p.min()), int(p.max())
        bad = None if lo >= -1 and hi <= 1 else (p < -1) | (p > 1)
        negative = lo == -1
    elif p.dtype.kind == "f":
        ok = (p == 1) | (p == 0) | (p == -1)  # False for NaN and fractions
        bad = None if bool(ok.all()) else ~ok
        negative = bool(np.any(p == -1))
    else:
        raise error(f"{prefix}polarity must be 0/1, -1/+1 or bool, got dtype {p.dtype}")
    if bad is not None:
        values = np.unique(p[bad])[:6].tolist()
        raise error(f"{prefix}polarity must be 0/1, -1/+1 or bool, got values {values}")
    if negative and bool(np.any(p == 0)):
        raise error(f"{prefix}polarity mixes the 0/1 and -1/+1 conventions (it holds -1, 0 and 1)")
    # 0/1 and ±1 agree on "positive means ON"; only a 0 needs care: it is OFF in the 0/1 convention
    return np.where(p > 0, 1, -1)


#: factors from a file's time unit to µs
TIME_UNITS = {"s": 1e6, "ms": 1e3, "us": 1.0, "ns": 1e-3}


def to_microseconds(t: Any, scale: float) -> Any:
    """File times times ``scale`` (see ``TIME_UNITS``), as float64 µs rounded to the nanosecond.

    Rounding makes whole-µs stamps stored in seconds come back exact (float seconds carry no
    more than ns precision anyway).

    Example:
        >>> float(to_microseconds(np.float64(0.002113), 1e6))
        2113.0
    """
    t = np.asarray(t, dtype=np.float64)
    return t * scale if scale == 1.0 else np.round(t * scale, 3)


def time_scale(time_unit: str) -> float:
    """The factor from ``time_unit`` (a key of ``TIME_UNITS``) to µs.

    Raises:
        ValueError: for a unit we do not know; the message lists the ones we do.

    Example:
        >>> time_scale("ms")
        1000.0
    """
    if time_unit not in TIME_UNITS:
        raise ValueError(f"time_unit must be one of {sorted(TIME_UNITS)}, got {time_unit!r}")
    return TIME_UNITS[time_unit]


def sorted_by_time(chunk: np.ndarray) -> np.ndarray:
    """``chunk`` itself when already sorted by ``t``, else a stably sorted copy (files that store pieces unsorted)."""
    if len(chunk) > 1 and np.any(chunk["t"][1:] < chunk["t"][:-1]):
        return chunk[np.argsort(chunk["t"], kind="stable")]
    return chunk


def to_unit_image(a: np.ndarray, where: str, channels_last: bool = True, scale: float | None = None) -> np.ndarray:
    """Convert an image to float32 :math:`(C, H, W)` in [0, 1].

    uint8 is divided by 255 and uint16 by 65535; float images are taken as [0, 1] unless ``scale``
    is given. ``(H, W)`` becomes one channel; ``(H, W, 3|4)`` (or ``(3|4, H, W)`` with
    ``channels_last=False``) three channels (alpha dropped).
    """
    a = np.asarray(a)
    if scale is None:
        if a.dtype == np.uint8:
            scale = 1 / 255.0
        elif a.dtype == np.uint16:
            scale = 1 / 65535.0
        elif np.issubdtype(a.dtype, np.floating):
            scale = 1.0
        else:
            raise RecordingError(f"{where}: unsupported pixel type {a.dtype} (expected uint8, uint16 or float)")
    img = a.astype(np.float32) * np.float32(scale)
    if img.ndim == 2:
        img = img[None]
    elif img.ndim == 3 and channels_last and img.shape[-1] in (1, 3, 4):
        img = img[..., : 3 if img.shape[-1] >= 3 else 1].transpose(2, 0, 1)
    elif img.ndim == 3 and not channels_last and img.shape[0] in (1, 3, 4):
        img = img[: 3 if img.shape[0] >= 3 else 1]
    else:
        raise RecordingError(f"{where}: unsupported image shape {a.shape} (expected (H, W), (H, W, 3) or (H, W, 4))")
    if not np.isfinite(img).all():
        raise RecordingError(f"{where}: image has NaN or infinite pixels")
    return np.ascontiguousarray(img)


def iter_events_as_chunks(events: Events | Iterable[Events | np.ndarray]) -> Iterator[np.ndarray]:
    """Normalise one ``Events`` (a single sample) or an iterable of ``Events``/structured chunks to chunks."""
    items = [events] if isinstance(events, (Events, np.ndarray)) else events
    for item in items:
        if isinstance(item, Events):
            if item.batch_size != 1:
                raise ValueError(f"events to write must be one sample, got batch_size {item.batch_size}; "
                                 "use events.sample(i)")
            yield structured_events(item.x.cpu().numpy(), item.y.cpu().numpy(), item.t.cpu().numpy(),
                                    item.p.cpu().numpy())
        elif isinstance(item, np.ndarray) and item.dtype.names and {"x", "y", "t", "p"} <= set(item.dtype.names):
            yield structured_events(item["x"], item["y"], item["t"], item["p"])
        else:
            raise ValueError(f"expected Events or structured arrays with x, y, t, p; got {type(item).__name__}")
