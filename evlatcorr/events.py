"""A batched, flat event container.

Events of several samples live in flat tensors ``x, y, t, p`` plus a per-event sample index
``batch`` (like PyTorch Geometric), so variable counts per sample need no padding and every
per-pixel reduction is one scatter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from evlatcorr.checks import check_batch_vector, check_shape, warn_if_coarse_times

__all__ = ["Events", "polarity_to_signed"]

EVENT_DTYPE = np.dtype([("x", np.int16), ("y", np.int16), ("t", np.int64), ("p", np.int8)])


def polarity_to_signed(p: Tensor | np.ndarray) -> Tensor:
    """Convert polarities given as {0, 1}, {-1, +1} or bool to ±1 (int8).

    Example:
        >>> polarity_to_signed(torch.tensor([0, 1, 1])).tolist()
        [-1, 1, 1]
    """
    p = torch.as_tensor(p)
    if p.dtype == torch.bool:
        return torch.where(p, 1, -1).to(torch.int8)
    if p.is_floating_point():
        if not bool(torch.isfinite(p).all()) or not bool((p == p.round()).all()):
            raise ValueError("p (polarity) must hold integers {0,1} or {-1,+1}, got non-integer values")
    if p.numel() == 0:
        return p.to(torch.int8)
    values = set(torch.unique(p).tolist())
    if values <= {0, 1}:
        return (p.to(torch.int8) * 2 - 1).to(torch.int8)
    if values <= {-1, 1}:
        return p.to(torch.int8)
    raise ValueError(f"p (polarity) must be in {{0,1}}, {{-1,+1}} or bool, got values {sorted(values)[:6]}")


class Events:
    """A batch of events in flat tensors.

    Args:
        x: column of each event :math:`(N,)`, in ``[0, W)``.
        y: row of each event :math:`(N,)`, in ``[0, H)``.
        t: timestamp of each event :math:`(N,)` in microseconds (held as float64). Pass int64 or float64: float32
            rounds times beyond about 8 s by more than 1 µs, and a camera's absolute timestamps by minutes (a
            warning says so).
        p: polarity :math:`(N,)` given as {0,1}, {-1,+1} or bool; held as ±1 (int8).
        batch: sample index of each event :math:`(N,)`; all zeros when omitted.
        sensor_size: ``(H, W)`` of the sensor.
        batch_size: number of samples; defaults to ``batch.max() + 1`` (1 with no events).
        sort: sort events by (sample, time) instead of raising when they are not sorted.

    Events must be sorted by sample and, within each sample, by time (pass ``sort=True`` to
    have them sorted).

    Example:
        >>> ev = Events(torch.tensor([1, 2]), torch.tensor([0, 3]), torch.tensor([10.0, 25.0]),
        ...             torch.tensor([1, 0]), sensor_size=(4, 5))
        >>> ev
        Events(num_events=2, batch_size=1, sensor_size=(4, 5), t=[10.0, 25.0] us)
        >>> ev.p.tolist()
        [1, -1]
    """

    def __init__(
        self,
        x: Tensor | np.ndarray,
        y: Tensor | np.ndarray,
        t: Tensor | np.ndarray,
        p: Tensor | np.ndarray,
        batch: Tensor | np.ndarray | None = None,
        sensor_size: tuple[int, int] = (260, 346),
        batch_size: int | None = None,
        sort: bool = False,
    ) -> None:
        x, y, t, p = (torch.as_tensor(v) for v in (x, y, t, p))
        for name, v in (("x", x), ("y", y), ("t", t), ("p", p)):
            if v.dim() != 1:
                raise ValueError(f"{name} must be a 1-D tensor of events, got shape {tuple(v.shape)}")
        n = t.shape[0]
        for name, v in (("x", x), ("y", y), ("p", p)):
            if v.shape[0] != n:
                raise ValueError(f"x, y, t and p must have the same length; t has {n}, {name} has {v.shape[0]}")
        if len(sensor_size) != 2 or min(int(s) for s in sensor_size) <= 0:
            raise ValueError(f"sensor_size must be a positive (H, W), got {sensor_size}")
        self.sensor_size = (int(sensor_size[0]), int(sensor_size[1]))
        height, width = self.sensor_size
        if x.is_floating_point() or y.is_floating_point():
            if not bool((x == x.round()).all() and (y == y.round()).all()):
                raise ValueError("x and y must be integer pixel coordinates")
        x, y = x.long(), y.long()
        if n and (int(x.min()) < 0 or int(x.max()) >= width):
            raise ValueError(f"x must be in [0, {width}) for sensor_size (H, W)={self.sensor_size}, "
                             f"got values in [{int(x.min())}, {int(x.max())}]")
        if n and (int(y.min()) < 0 or int(y.max()) >= height):
            raise ValueError(f"y must be in [0, {height}) for sensor_size (H, W)={self.sensor_size}, "
                             f"got values in [{int(y.min())}, {int(y.max())}]")
        warn_if_coarse_times(t, "t (timestamps)")
        t = t.to(torch.float64)
        if not bool(torch.isfinite(t).all()):
            raise ValueError("t (timestamps) has NaN or infinite values")
        p = polarity_to_signed(p).to(x.device)
        if batch is None:
            batch = torch.zeros(n, dtype=torch.long, device=x.device)
        else:
            batch = torch.as_tensor(batch).long()
            if batch.shape != (n,):
                raise ValueError(f"batch must have one sample index per event ({n},), got {tuple(batch.shape)}")
            if n and int(batch.min()) < 0:
                raise ValueError("batch indices must be non-negative")
        inferred = int(batch.max()) + 1 if n else 1
        if batch_size is None:
            batch_size = inferred
        elif batch_size < inferred:
            raise ValueError(f"batch_size={batch_size} but events refer to sample {inferred - 1}")
        self.batch_size = int(batch_size)
        if n > 1:
            order_ok = bool(((batch[1:] > batch[:-1]) | ((batch[1:] == batch[:-1]) & (t[1:] >= t[:-1]))).all())
            if not order_ok:
                if not sort:
                    raise ValueError(
                        "events must be sorted by sample (batch) and, within a sample, by timestamp t; "
                        "pass sort=True to sort them"
                    )
                order = _sort_order(batch, t)
                x, y, t, p, batch = x[order], y[order], t[order], p[order], batch[order]
        self.x, self.y, self.t, self.p, self.batch = x, y, t, p, batch

    # construction -------------------------------------------------------------------------
    @classmethod
    def from_canonical(cls, x: Tensor, y: Tensor, t: Tensor, p: Tensor, batch: Tensor,
                       sensor_size: tuple[int, int], batch_size: int) -> Events:
        """Build without any check or copy from tensors already in the canonical form of an :class:`Events`.

        For code that derives the tensors from other events (shifted times, a mask, a re-sort), where the
        constructor's checks would only read the data again (on a GPU, a device sync each). Nothing is
        validated: ``x, y`` int64 in the sensor, ``t`` float64 µs, ``p`` int8 ±1, ``batch`` int64, sorted by
        ``(batch, t)``, are the caller's promise.

        Example:
            >>> ev = Events(torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([1.0, 2.0]),
            ...             torch.tensor([1, 0]), sensor_size=(1, 2))
            >>> later = Events.from_canonical(ev.x, ev.y, ev.t + 5.0, ev.p, ev.batch, ev.sensor_size, ev.batch_size)
            >>> later.t.tolist(), later.p.tolist()
            ([6.0, 7.0], [1, -1])
        """
        ev = cls.__new__(cls)
        ev.x, ev.y, ev.t, ev.p, ev.batch = x, y, t, p, batch
        ev.sensor_size, ev.batch_size = sensor_size, batch_size
        return ev

    @classmethod
    def from_numpy(cls, array: np.ndarray, sensor_size: tuple[int, int], batch: np.ndarray | None = None,
                   sort: bool = False) -> Events:
        """Build from a numpy structured array with fields ``x, y, t, p`` (t in microseconds).

        Example:
            >>> arr = np.zeros(3, dtype=[("x", "i2"), ("y", "i2"), ("t", "i8"), ("p", "i1")])
            >>> arr["t"] = [1, 2, 3]; arr["p"] = [0, 1, 1]
            >>> len(Events.from_numpy(arr, sensor_size=(2, 2)))
            3
        """
        if array.dtype.names is None or not {"x", "y", "t", "p"} <= set(array.dtype.names):
            raise ValueError(f"array must be a structured array with fields x, y, t, p; got dtype {array.dtype}")
        return cls(
            torch.from_numpy(np.ascontiguousarray(array["x"]).astype(np.int64)),
            torch.from_numpy(np.ascontiguousarray(array["y"]).astype(np.int64)),
            torch.from_numpy(np.ascontiguousarray(array["t"]).astype(np.float64)),
            torch.from_numpy(np.ascontiguousarray(array["p"]).astype(np.int8)),
            None if batch is None else torch.from_numpy(np.asarray(batch, dtype=np.int64)),
            sensor_size=sensor_size,
            sort=sort,
        )

    def to_numpy(self) -> np.ndarray:
        """Return a structured array with fields ``x, y`` (int16), ``t`` (int64 µs, rounded), ``p`` (±1 int8).

        The sample index is dropped; use :meth:`sample` first for one sample of a batch.
        """
        out = np.empty(len(self), dtype=EVENT_DTYPE)
        out["x"] = self.x.cpu().numpy()
        out["y"] = self.y.cpu().numpy()
        out["t"] = np.round(self.t.cpu().numpy()).astype(np.int64)
        out["p"] = self.p.cpu().numpy()
        return out

    @classmethod
    def cat(cls, samples: Sequence[Events]) -> Events:
        """Stack single- or multi-sample event sets into one batch (sample indices are offset)."""
        if not samples:
            raise ValueError("cat needs at least one Events")
        sizes = {s.sensor_size for s in samples}
        if len(sizes) != 1:
            raise ValueError(f"all Events must share one sensor_size, got {sorted(sizes)}")
        offsets, total = [], 0
        for s in samples:
            offsets.append(total)
            total += s.batch_size
        device = samples[0].t.device
        return cls.from_canonical(
            torch.cat([s.x.to(device) for s in samples]),
            torch.cat([s.y.to(device) for s in samples]),
            torch.cat([s.t.to(device) for s in samples]),
            torch.cat([s.p.to(device) for s in samples]),
            torch.cat([s.batch.to(device) + o for s, o in zip(samples, offsets)]),
            samples[0].sensor_size,
            total,
        )

    # basic protocol ------------------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.t.shape[0])

    def __repr__(self) -> str:
        span = f"[{float(self.t.min()):.1f}, {float(self.t.max()):.1f}] us" if len(self) else "[]"
        return (f"Events(num_events={len(self)}, batch_size={self.batch_size}, "
                f"sensor_size={self.sensor_size}, t={span})")

    @property
    def device(self) -> torch.device:
        return self.t.device

    def to(self, device: torch.device | str, non_blocking: bool = False) -> Events:
        """Move all tensors to ``device``; ``non_blocking`` as :meth:`torch.Tensor.to`."""
        moved = (v.to(device, non_blocking=non_blocking) for v in (self.x, self.y, self.t, self.p, self.batch))
        x, y, t, p, batch = moved
        return Events.from_canonical(x, y, t, p, batch, self.sensor_size, self.batch_size)

    def select(self, mask: Tensor) -> Events:
        """Keep the events where the boolean ``mask`` :math:`(N,)` is true (order is preserved)."""
        if mask.shape != self.t.shape or mask.dtype != torch.bool:
            raise ValueError(f"mask must be a bool tensor of shape {tuple(self.t.shape)}, got "
                             f"{mask.dtype} {tuple(mask.shape)}")
        return Events.from_canonical(self.x[mask], self.y[mask], self.t[mask], self.p[mask], self.batch[mask],
                                     self.sensor_size, self.batch_size)

    def sample(self, index: int) -> Events:
        """The events of one sample, as a batch of size 1."""
        if not 0 <= index < self.batch_size:
            raise ValueError(f"sample index must be in [0, {self.batch_size}), got {index}")
        # events are sorted by sample: one contiguous slice (a mask would copy through all samples' events)
        lo, hi = torch.searchsorted(self.batch, torch.tensor([index, index + 1], device=self.device)).tolist()
        return Events.from_canonical(self.x[lo:hi], self.y[lo:hi], self.t[lo:hi], self.p[lo:hi],
                                     torch.zeros_like(self.batch[lo:hi]), self.sensor_size, 1)

    def counts(self) -> Tensor:
        """Number of events per sample :math:`(B,)`."""
        return torch.bincount(self.batch, minlength=self.batch_size)

    def last_times(self) -> Tensor:
        """Each sample's last event time :math:`(B,)` float64 µs, ``-inf`` for a sample with no events.

        Events are sorted by sample and time, so it is the time just before each sample's end: one binary search
        per sample (a max-reduction onto one value per sample would serialise its atomics on a GPU).

        Example:
            >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([1.0, 4.0, 2.0]), torch.ones(3),
            ...             sensor_size=(1, 1), batch=torch.tensor([0, 0, 2]), batch_size=3)
            >>> ev.last_times().tolist()
            [4.0, -inf, 2.0]
        """
        if not len(self):
            return torch.full((self.batch_size,), -math.inf, dtype=torch.float64, device=self.device)
        bounds = self.sample_bounds()
        starts, ends = bounds[:-1], bounds[1:]
        last = self.t.to(torch.float64).index_select(0, (ends - 1).clamp(min=0))
        return torch.where(ends > starts, last, -math.inf)

    def sample_bounds(self) -> Tensor:
        """Where each sample's events start, and the end :math:`(B + 1,)`: sample ``b`` is
        ``[bounds[b], bounds[b + 1])`` (events are sorted by sample: one binary search per sample).

        Example:
            >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([1.0, 4.0, 2.0]), torch.ones(3),
            ...             sensor_size=(1, 1), batch=torch.tensor([0, 0, 2]), batch_size=3)
            >>> ev.sample_bounds().tolist()
            [0, 2, 2, 3]
        """
        samples = torch.arange(self.batch_size + 1, device=self.device, dtype=self.batch.dtype)
        return torch.searchsorted(self.batch, samples)

    def pixel_index(self) -> Tensor:
        """Flat index ``(b * H + y) * W + x`` of each event into a :math:`(B, H, W)` grid."""
        height, width = self.sensor_size
        return (self.batch * height + self.y) * width + self.x

    # time operations -----------------------------------------------------------------------
    def since(self, start: Tensor | float) -> Events:
        """Events with ``t >= start[b]`` for their sample ``b`` (µs, a scalar or :math:`(B,)`).

        Example:
            >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([0.0, 5.0, 10.0]),
            ...             torch.ones(3), sensor_size=(1, 1))
            >>> ev.since(5.0).t.tolist()
            [5.0, 10.0]
        """
        start = check_batch_vector(start, self.batch_size, "start").to(self.device, torch.float64)
        return self.select(self.t >= start[self.batch])

    def window(self, start: Tensor | float, end: Tensor | float) -> Events:
        """Events with ``start[b] <= t < end[b]`` for their sample ``b`` (µs, scalars or :math:`(B,)`).

        Example:
            >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([0.0, 5.0, 10.0]),
            ...             torch.ones(3), sensor_size=(1, 1))
            >>> ev.window(5.0, 10.0).t.tolist()
            [5.0]
        """
        start = check_batch_vector(start, self.batch_size, "start").to(self.device, torch.float64)
        end = check_batch_vector(end, self.batch_size, "end").to(self.device, torch.float64)
        if bool((end < start).any()):
            raise ValueError("window end must not be before its start")
        return self.select((self.t >= start[self.batch]) & (self.t < end[self.batch]))

    def windows(self, start: Tensor, end: Tensor) -> Events:
        """Cut one time-ordered stream (a single sample) into windows: sample ``i`` holds the events with
        ``start[i] <= t < end[i]`` (µs, :math:`(B,)`). Windows may overlap; an event in several is copied into each.

        One binary search per window bound and one gather, with no loop over windows or events (on a GPU, one
        host read: the total count, to size the output).

        Example:
            >>> ev = Events(torch.zeros(4), torch.zeros(4), torch.tensor([0.0, 5.0, 10.0, 15.0]),
            ...             torch.ones(4), sensor_size=(1, 1))
            >>> cut = ev.windows(torch.tensor([0.0, 5.0]), torch.tensor([10.0, 20.0]))
            >>> cut.batch.tolist(), cut.t.tolist()
            ([0, 0, 1, 1, 1], [0.0, 5.0, 5.0, 10.0, 15.0])
        """
        if self.batch_size != 1:
            raise ValueError(f"windows cuts one stream (batch_size 1), got batch_size {self.batch_size}")
        start = torch.as_tensor(start, dtype=torch.float64, device=self.device)
        end = torch.as_tensor(end, dtype=torch.float64, device=self.device)
        if start.dim() != 1 or start.shape != end.shape:
            raise ValueError(f"start and end must be 1-D of the same length, got {tuple(start.shape)} and "
                             f"{tuple(end.shape)}")
        if bool((end < start).any()):
            raise ValueError("window end must not be before its start")
        first = torch.searchsorted(self.t, start)
        counts = torch.searchsorted(self.t, end) - first
        batch = torch.repeat_interleave(torch.arange(start.shape[0], device=self.device), counts)
        # event k of the output is event first[b] + (k - offset[b]) of the stream, offset[b] = where window b begins
        offset = torch.cumsum(counts, 0) - counts
        index = torch.arange(batch.shape[0], device=self.device) - offset[batch] + first[batch]
        return Events.from_canonical(self.x[index], self.y[index], self.t[index], self.p[index], batch,
                                     self.sensor_size, int(start.shape[0]))

    def latency_at_events(self, latency: Tensor | float) -> Tensor:
        """The latency (µs) that applies to each event, from a scalar, a :math:`(B,)` vector or a
        :math:`(B, 1, H, W)` map, as a float64 tensor :math:`(N,)`."""
        latency = torch.as_tensor(latency, dtype=torch.float64, device=self.device)
        if latency.dim() == 4:
            check_shape(latency, [self.batch_size, 1, *self.sensor_size], "latency")
            if not bool(torch.isfinite(latency).all()):
                raise ValueError("latency map has NaN or infinite values")
            return latency.to(torch.float64).flatten()[self.pixel_index()]
        latency = check_batch_vector(latency, self.batch_size, "latency").to(self.device, torch.float64)
        return latency[self.batch]

    def shift(self, latency: Tensor | float) -> Events:
        """Correct a latency: ``t' = t - latency`` at each event's pixel.

        Args:
            latency: µs; a scalar, one value per sample :math:`(B,)`, or a per-pixel map
                :math:`(B, 1, H, W)`. Positive means the events were stamped late.

        Returns:
            the corrected events, re-sorted by time within each sample.

        Example:
            >>> ev = Events(torch.tensor([0, 1]), torch.zeros(2), torch.tensor([10.0, 20.0]),
            ...             torch.ones(2), sensor_size=(1, 2))
            >>> ev.shift(torch.tensor([[[[15.0, 0.0]]]])).t.tolist()
            [-5.0, 20.0]
        """
        per_event = self.latency_at_events(latency)
        t = self.t - per_event
        latency = torch.as_tensor(latency)
        if latency.dim() < 4:  # one latency per sample keeps each sample's time order: nothing to sort
            return Events.from_canonical(self.x, self.y, t, self.p, self.batch, self.sensor_size, self.batch_size)
        order = _sort_order(self.batch, t)
        return Events.from_canonical(self.x[order], self.y[order], t[order], self.p[order], self.batch[order],
                                     self.sensor_size, self.batch_size)


def _sort_order(batch: Tensor, t: Tensor) -> Tensor:
    """Stable order by (batch, t)."""
    order = torch.argsort(t, stable=True)
    return order[torch.argsort(batch[order], stable=True)]
