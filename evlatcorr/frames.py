"""The batch type that flows through every module: blurry frames, their events, exposures.

:class:`EventFrames` also owns the three batch operations every trainer and data loader needs,
written once here: :meth:`EventFrames.crop`, :meth:`EventFrames.cat` (the collate function) and
:meth:`EventFrames.split` (one-frame batches).
"""

from __future__ import annotations

import copy
import dataclasses
import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from evlatcorr.checks import check_batch_vector, check_exposure, check_image, check_shape, warn_if_coarse_times
from evlatcorr.events import Events

__all__ = ["EventFrames"]

#: optional fields holding one image (or a stack of images) per sample, ``(B, ..., H, W)``
_IMAGE_FIELDS = ("latency", "latent", "sharp", "blurry_next", "target_frames", "output")
#: optional fields holding one vector entry per sample, ``(B,)`` or ``(B, T)``
_VECTOR_FIELDS = ("exposure_start_next", "exposure_end_next", "target_times")


@dataclass
class EventFrames:
    """Blurry frames with the events around their exposures.

    ``EventLatencyCorrector`` and every adapter take and return this type, so
    ``nn.Sequential(EventLatencyCorrector(), model)`` works.

    Args:
        blurry: blurry frames :math:`(B, C, H, W)`, linear intensity in [0, 1], C = 1 or 3.
        events: events of each sample (``events.batch`` indexes the frames). They should
            reach past ``exposure_end`` by the largest latency to be searched.
        exposure_start: exposure start of each frame :math:`(B,)` in µs (held as float64; pass int64 or float64:
            float32 rounds a camera's absolute times by minutes, and a warning says so).
        exposure_end: exposure end of each frame :math:`(B,)` in µs.
        latency: filled by the corrector: latency map :math:`(B, 1, H, W)` in µs.
        latent: filled by the corrector: EDI latent sharp image at mid-exposure :math:`(B, C, H, W)`.
        corrected: filled by the corrector: events with the latency removed.
        sharp: optional ground truth sharp frame at mid-exposure :math:`(B, C, H, W)`.
        blurry_next: optional next blurry frame :math:`(B, C, H, W)` for interpolation.
        exposure_start_next: exposure start of ``blurry_next`` :math:`(B,)` in µs.
        exposure_end_next: exposure end of ``blurry_next`` :math:`(B,)` in µs.
        target_times: optional times :math:`(B, T)` in µs at which frames are wanted.
        target_frames: optional ground truth at ``target_times`` :math:`(B, T, C, H, W)`.
        output: filled by an adapter: restored frames :math:`(B, C, H, W)` or :math:`(B, T, C, H, W)`.
        meta: free-form information (file names, frame indices, ...).

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5.0]), torch.tensor([1]),
        ...             sensor_size=(2, 2))
        >>> batch = EventFrames(torch.rand(1, 1, 2, 2), ev, torch.tensor([0.0]), torch.tensor([10.0]))
        >>> batch.batch_size, batch.sensor_size
        (1, (2, 2))
    """

    blurry: Tensor
    events: Events
    exposure_start: Tensor
    exposure_end: Tensor
    latency: Tensor | None = None
    latent: Tensor | None = None
    corrected: Events | None = None
    sharp: Tensor | None = None
    blurry_next: Tensor | None = None
    exposure_start_next: Tensor | None = None
    exposure_end_next: Tensor | None = None
    target_times: Tensor | None = None
    target_frames: Tensor | None = None
    output: Tensor | None = None
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_image(self.blurry, "blurry")
        if not isinstance(self.events, Events):
            raise ValueError(f"events must be evlatcorr.Events, got {type(self.events).__name__}")
        b, _, h, w = self.blurry.shape
        if self.events.batch_size != b:
            hint = ("; to cut one recording's events into each frame's window, use EventFrames.from_stream"
                    if self.events.batch_size == 1 else "")
            raise ValueError(f"events have batch_size {self.events.batch_size} but blurry has {b} frames{hint}")
        if self.events.sensor_size != (h, w):
            raise ValueError(f"events sensor_size {self.events.sensor_size} does not match blurry (H, W)={(h, w)}")
        self.exposure_start, self.exposure_end = self._checked_exposure(self.exposure_start, self.exposure_end)
        if self.latency is not None:
            check_shape(self.latency, [b, 1, h, w], "latency")
        if self.sharp is not None:
            check_shape(self.sharp, [b, "C", h, w], "sharp")
        if self.blurry_next is not None:
            check_image(self.blurry_next, "blurry_next")
            check_shape(self.blurry_next, list(self.blurry.shape), "blurry_next")
            if self.exposure_start_next is None or self.exposure_end_next is None:
                raise ValueError("blurry_next needs exposure_start_next and exposure_end_next")
            self.exposure_start_next, self.exposure_end_next = self._checked_exposure(
                self.exposure_start_next, self.exposure_end_next, "_next")
        if self.target_times is not None:
            tt = torch.as_tensor(self.target_times, dtype=torch.float64, device=self.blurry.device)
            if tt.dim() == 1:
                tt = tt[:, None]
            check_shape(tt, [b, "T"], "target_times")
            self.target_times = tt
            if self.target_frames is not None:
                check_shape(self.target_frames, [b, tt.shape[1], "C", h, w], "target_frames")

    @classmethod
    def from_stream(cls, blurry: Tensor, events: Events, exposure_start: Any, exposure_end: Any,
                    before_us: float = 0.0, after_us: float | None = None, **fields: Any) -> EventFrames:
        """Frames of one recording with the events of one time-ordered stream, each frame given its own window.

        Frame ``i`` gets the events of ``[exposure_start[i] - before_us, exposure_end[i] + after_us)``, as
        :meth:`evlatcorr.io.Recording.frame` cuts them from a file. The default ``after_us`` (None) is each frame's
        exposure time: the corrector's default search reaches that far past the exposure end. Consecutive
        windows may overlap; their common events go to both frames.

        Args:
            blurry: blurry frames :math:`(B, C, H, W)` in [0, 1].
            events: the recording's events, one sample sorted by time (µs).
            exposure_start: exposure start of each frame :math:`(B,)` in µs.
            exposure_end: exposure end of each frame :math:`(B,)` in µs.
            before_us: how far before each exposure start the window begins.
            after_us: how far past each exposure end the window reaches (None: the exposure time).
            **fields: other fields of :class:`EventFrames` (``sharp``, ``meta``, ...).

        Example:
            >>> ev = Events(torch.zeros(4), torch.zeros(4), torch.tensor([0.0, 15.0, 25.0, 45.0]),
            ...             torch.ones(4), sensor_size=(1, 1))
            >>> batch = EventFrames.from_stream(torch.rand(2, 1, 1, 1), ev, [0.0, 20.0], [10.0, 30.0])
            >>> batch.events.batch.tolist(), batch.events.t.tolist()
            ([0, 0, 1], [0.0, 15.0, 25.0])
        """
        if not isinstance(events, Events):
            raise ValueError(f"events must be evlatcorr.Events, got {type(events).__name__}")
        if not math.isfinite(before_us) or before_us < 0:
            raise ValueError(f"before_us must be a finite number >= 0, got {before_us}")
        if after_us is not None and (not math.isfinite(after_us) or after_us < 0):
            raise ValueError(f"after_us must be None or a finite number >= 0, got {after_us}")
        check_shape(blurry, ["B", "C", "H", "W"], "blurry")
        for times, name in ((exposure_start, "exposure_start"), (exposure_end, "exposure_end")):
            warn_if_coarse_times(times, name)  # at the caller's line: float32 has already rounded them
        start = check_batch_vector(exposure_start, blurry.shape[0], "exposure_start").to(events.device, torch.float64)
        end = check_batch_vector(exposure_end, blurry.shape[0], "exposure_end").to(events.device, torch.float64)
        with warnings.catch_warnings():  # the constructor below warns of short exposures, once
            warnings.simplefilter("ignore")
            check_exposure(start, end)
        after = end - start if after_us is None else torch.full_like(end, after_us)
        windows = events.windows(start - before_us, end + after)
        return cls(blurry, windows.to(blurry.device), start, end, **fields)

    def _checked_exposure(self, start: Any, end: Any, suffix: str = "") -> tuple[Tensor, Tensor]:
        """``exposure_start{suffix}``, ``exposure_end{suffix}`` as float64 :math:`(B,)` on the frames' device."""
        b, device = self.blurry.shape[0], self.blurry.device
        for times, name in ((start, "exposure_start"), (end, "exposure_end")):
            warn_if_coarse_times(times, name + suffix)
        start = check_batch_vector(start, b, f"exposure_start{suffix}").to(device, torch.float64)
        end = check_batch_vector(end, b, f"exposure_end{suffix}").to(device, torch.float64)
        check_exposure(start, end)
        return start, end

    @property
    def batch_size(self) -> int:
        return int(self.blurry.shape[0])

    @property
    def sensor_size(self) -> tuple[int, int]:
        return int(self.blurry.shape[-2]), int(self.blurry.shape[-1])

    @property
    def device(self) -> torch.device:
        return self.blurry.device

    @property
    def exposure_time(self) -> Tensor:
        """Exposure duration of each frame :math:`(B,)` in µs."""
        return self.exposure_end - self.exposure_start

    def replace(self, **changes: Any) -> EventFrames:
        """A copy with some fields replaced (validated again)."""
        return dataclasses.replace(self, **changes)

    def with_outputs(self, **outputs: Any) -> EventFrames:
        """A copy with a stage's outputs filled (``latency``, ``latent``, ``corrected``, ``output``, ``meta``).

        Unlike :meth:`replace`, the inputs are not validated again and the outputs' shapes are checked
        without reading their values, so a corrector or adapter in a GPU pipeline never waits on the device here.

        Example:
            >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5.0]), torch.tensor([1]),
            ...             sensor_size=(2, 2))
            >>> batch = EventFrames(torch.rand(1, 1, 2, 2), ev, torch.tensor([0.0]), torch.tensor([10.0]))
            >>> batch.with_outputs(latency=torch.zeros(1, 1, 2, 2)).latency.shape
            torch.Size([1, 1, 2, 2])
        """
        unknown = set(outputs) - {"latency", "latent", "corrected", "output", "meta"}
        if unknown:
            raise ValueError(f"with_outputs fills latency, latent, corrected, output and meta, not {sorted(unknown)}")
        b, c, h, w = self.blurry.shape
        if outputs.get("latency") is not None:
            check_shape(outputs["latency"], [b, 1, h, w], "latency")
        if outputs.get("latent") is not None:
            check_shape(outputs["latent"], [b, c, h, w], "latent")
        corrected = outputs.get("corrected")
        if corrected is not None and (not isinstance(corrected, Events) or corrected.batch_size != b
                                      or corrected.sensor_size != (h, w)):
            raise ValueError(f"corrected must be Events of batch_size {b} and sensor_size {(h, w)}")
        filled = copy.copy(self)  # a shallow copy: no __post_init__, so nothing is read from the device
        for name, value in outputs.items():
            setattr(filled, name, value)
        return filled

    def to(self, device: torch.device | str, non_blocking: bool = False) -> EventFrames:
        """Move every tensor (and the events) to ``device``; ``non_blocking`` as :meth:`torch.Tensor.to`."""
        changes: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (Tensor, Events)):
                changes[f.name] = v.to(device, non_blocking=non_blocking)
        return dataclasses.replace(self, **changes)

    # batch operations --------------------------------------------------------------------------
    def crop(self, top: int, left: int, height: int, width: int, *, hflip: bool = False) -> EventFrames:
        """A spatial crop, optionally mirrored left-right, of every image field and of the events.

        Events outside the crop (``events`` and ``corrected``) are dropped; the rest keep their times
        and polarities. ``meta`` tensors ending in ``(H, W)`` with 3 or more dimensions (per-pixel
        maps such as ``meta["true_latency"]``) are cropped too; other ``meta`` entries are kept.

        Args:
            top, left: first row and column of the crop.
            height, width: size of the crop; it must lie inside the frame.
            hflip: mirror the crop left-right (images and event columns together).

        Raises:
            ValueError: when the crop does not fit in the frame.

        Example:
            >>> ev = Events(torch.tensor([1, 3]), torch.tensor([0, 2]), torch.tensor([1.0, 2.0]), torch.ones(2),
            ...             sensor_size=(4, 4))
            >>> fr = EventFrames(torch.arange(16.0).view(1, 1, 4, 4) / 16, ev, torch.tensor([0.0]), torch.tensor([5.0]))
            >>> out = fr.crop(1, 2, 3, 2, hflip=True)
            >>> out.sensor_size, out.events.x.tolist(), out.events.y.tolist(), (out.blurry[0, 0, 0] * 16).tolist()
            ((3, 2), [0], [1], [7.0, 6.0])
        """
        h, w = self.sensor_size
        if not (0 <= top and 0 <= left and height >= 1 and width >= 1 and top + height <= h and left + width <= w):
            raise ValueError(f"crop ({top}, {left}, {height}, {width}) does not fit in (H, W)=({h}, {w})")
        box = (top, left, height, width)
        changes: dict[str, Any] = {name: _crop_image(getattr(self, name), box, hflip)
                                   for name in ("blurry", *_IMAGE_FIELDS)}
        changes["events"] = _crop_events(self.events, box, hflip)
        changes["corrected"] = None if self.corrected is None else _crop_events(self.corrected, box, hflip)
        changes["meta"] = {k: _crop_image(v, box, hflip) if _is_pixel_map(v, (h, w)) else v
                           for k, v in self.meta.items()}
        return self.replace(**changes)

    @classmethod
    def cat(cls, items: Sequence[EventFrames]) -> EventFrames:
        """One batch from several batches of one ``(H, W)``: the collate function of the data loaders.

        Every field is kept: tensors are concatenated along the batch dimension and events (``events``,
        ``corrected``) by :meth:`Events.cat`; an optional field must be set on every item or on none.
        In ``meta``, a tensor whose first dimension is the item's batch size, a list as long as it, or a
        tuple of such tensors (e.g. ``etf_curve``) holds one entry per sample and is concatenated (a tuple
        element by element); any other entry describes the whole item
        and is kept when every item has the same value (else dropped: it has no batched form).

        Raises:
            ValueError: no items, items of different ``(H, W)``, or a field set on some items only.

        Example:
            >>> ev = Events(torch.tensor([0]), torch.tensor([1]), torch.tensor([5.0]), torch.ones(1),
            ...             sensor_size=(2, 2))
            >>> one = EventFrames(torch.zeros(1, 1, 2, 2), ev, torch.tensor([0.0]), torch.tensor([10.0]),
            ...                   meta={"frame": [7], "file": "a.h5"})
            >>> two = EventFrames.cat([one, one])
            >>> two.batch_size, two.events.batch.tolist(), two.meta
            (2, [0, 1], {'frame': [7, 7], 'file': 'a.h5'})
        """
        if not items:
            raise ValueError("cannot collate an empty list of EventFrames")
        sizes = {x.sensor_size for x in items}
        if len(sizes) != 1:
            raise ValueError(f"samples must share one (H, W) to be batched, got {sorted(sizes)}; crop them first")
        fields: dict[str, Any] = {name: _cat_optional(name, [getattr(x, name) for x in items])
                                  for name in ("blurry", "exposure_start", "exposure_end", *_IMAGE_FIELDS,
                                               *_VECTOR_FIELDS)}
        fields["events"] = Events.cat([x.events for x in items])
        corrected = [x.corrected for x in items]
        _check_all_or_none("corrected", corrected)
        fields["corrected"] = None if corrected[0] is None else Events.cat(corrected)
        fields["meta"] = _cat_meta(items)
        return cls(**fields)

    def split(self) -> list[EventFrames]:
        """One single-frame ``EventFrames`` per sample, every field kept: the inverse of :meth:`cat`.

        Tensor fields are views of this batch's tensors. ``meta`` entries holding one entry per
        sample (see :meth:`cat`) are sliced; the others are copied to every part.

        Example:
            >>> ev = Events(torch.tensor([0, 1]), torch.tensor([1, 0]), torch.tensor([5.0, 6.0]), torch.ones(2),
            ...             torch.tensor([0, 1]), sensor_size=(2, 2))
            >>> fr = EventFrames(torch.zeros(2, 1, 2, 2), ev, torch.tensor([0.0, 20.0]), torch.tensor([10.0, 30.0]),
            ...                  meta={"frame": [3, 4], "which": "delayed"})
            >>> [(p.exposure_start.tolist(), p.events.x.tolist(), p.meta) for p in fr.split()]
            [([0.0], [0], {'frame': [3], 'which': 'delayed'}), ([20.0], [1], {'frame': [4], 'which': 'delayed'})]
        """
        b = self.batch_size
        parts = []
        for i in range(b):
            changes: dict[str, Any] = {
                name: None if getattr(self, name) is None else getattr(self, name)[i:i + 1]
                for name in ("blurry", "exposure_start", "exposure_end", *_IMAGE_FIELDS, *_VECTOR_FIELDS)}
            changes["events"] = self.events.sample(i)
            changes["corrected"] = None if self.corrected is None else self.corrected.sample(i)
            changes["meta"] = {k: _sample_of(v, i) if _per_sample(v, b) else v for k, v in self.meta.items()}
            parts.append(self.replace(**changes))
        return parts


def _crop_image(image: Tensor | None, box: tuple[int, int, int, int], hflip: bool) -> Tensor | None:
    if image is None:
        return None
    top, left, height, width = box
    image = image[..., top:top + height, left:left + width]
    return (image.flip(-1) if hflip else image).contiguous()


def _crop_events(events: Events, box: tuple[int, int, int, int], hflip: bool) -> Events:
    top, left, height, width = box
    keep = (events.x >= left) & (events.x < left + width) & (events.y >= top) & (events.y < top + height)
    x = events.x[keep] - left
    return Events(width - 1 - x if hflip else x, events.y[keep] - top, events.t[keep], events.p[keep],
                  events.batch[keep], sensor_size=(height, width), batch_size=events.batch_size)


def _is_pixel_map(value: Any, size: tuple[int, int]) -> bool:
    return isinstance(value, Tensor) and value.dim() >= 3 and tuple(value.shape[-2:]) == size


def _per_sample(value: Any, batch_size: int) -> bool:
    """Whether a ``meta`` entry holds one entry per sample: a tensor ``(B, ...)``, a list of B, or a tuple of such
    tensors (e.g. the corrector's ``etf_curve``, candidates and scores)."""
    if isinstance(value, Tensor):
        return value.dim() >= 1 and value.shape[0] == batch_size
    if isinstance(value, tuple):
        return bool(value) and all(isinstance(v, Tensor) and _per_sample(v, batch_size) for v in value)
    return isinstance(value, list) and len(value) == batch_size


def _stackable(tuples: Sequence[tuple[Tensor, ...]]) -> bool:
    """Whether per-sample tuples of tensors concatenate element by element (one length, one shape past dim 0)."""
    return len({tuple(t.shape[1:] for t in value) for value in tuples}) == 1


def _sample_of(value: Any, i: int) -> Any:
    """Sample ``i`` of a per-sample ``meta`` entry (:func:`_per_sample`), as a batch of one."""
    return tuple(v[i:i + 1] for v in value) if isinstance(value, tuple) else value[i:i + 1]


def _check_all_or_none(name: str, values: Sequence[Any]) -> None:
    missing = sum(v is None for v in values)
    if 0 < missing < len(values):
        raise ValueError(f"cannot batch samples where {name} is set on some and missing on others")


def _cat_optional(name: str, values: list[Tensor | None]) -> Tensor | None:
    _check_all_or_none(name, values)
    return None if values[0] is None else torch.cat(values)


def _same(a: Any, b: Any) -> bool:
    if isinstance(a, Tensor) or isinstance(b, Tensor):
        return isinstance(a, Tensor) and isinstance(b, Tensor) and a.device == b.device and torch.equal(a, b)
    try:
        return a is b or bool(a == b)
    except (TypeError, ValueError, RuntimeError):  # e.g. arrays, whose == is element-wise
        return False


def _cat_meta(items: Sequence[EventFrames]) -> dict[str, Any]:
    meta: dict[str, Any] = {}
    for key in items[0].meta:
        if not all(key in x.meta for x in items):
            continue
        values = [x.meta[key] for x in items]
        if all(_per_sample(v, x.batch_size) for v, x in zip(values, items)):
            kind = type(values[0]) if not isinstance(values[0], Tensor) else Tensor
            if all(isinstance(v, kind) for v in values) and (kind is not tuple or _stackable(values)):
                meta[key] = (torch.cat(values) if kind is Tensor else
                             tuple(torch.cat(parts) for parts in zip(*values)) if kind is tuple else
                             [e for v in values for e in v])
                continue
        if all(_same(values[0], v) for v in values[1:]):
            meta[key] = values[0]
    return meta
