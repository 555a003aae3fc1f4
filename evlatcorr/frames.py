"""The batch type that flows through every module: blurry frames, their events, exposures."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from evlatcorr.checks import check_batch_vector, check_exposure, check_image, check_shape
from evlatcorr.events import Events

__all__ = ["EventFrames"]


@dataclass
class EventFrames:
    """Blurry frames with the events around their exposures.

    ``EventLatencyCorrector`` and every adapter take and return this type, so
    ``nn.Sequential(EventLatencyCorrector(), model)`` works.

    Args:
        blurry: blurry frames :math:`(B, C, H, W)`, linear intensity in [0, 1], C = 1 or 3.
        events: events of each sample (``events.batch`` indexes the frames). They should
            reach past ``exposure_end`` by the largest latency to be searched.
        exposure_start: exposure start of each frame :math:`(B,)` in µs (float64).
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
            raise ValueError(f"events have batch_size {self.events.batch_size} but blurry has {b} frames")
        if self.events.sensor_size != (h, w):
            raise ValueError(f"events sensor_size {self.events.sensor_size} does not match blurry (H, W)={(h, w)}")
        self.exposure_start = check_batch_vector(self.exposure_start, b, "exposure_start").to(
            self.blurry.device, torch.float64)
        self.exposure_end = check_batch_vector(self.exposure_end, b, "exposure_end").to(
            self.blurry.device, torch.float64)
        check_exposure(self.exposure_start, self.exposure_end)
        if self.latency is not None:
            check_shape(self.latency, [b, 1, h, w], "latency")
        if self.sharp is not None:
            check_shape(self.sharp, [b, "C", h, w], "sharp")
        if self.blurry_next is not None:
            check_image(self.blurry_next, "blurry_next")
            check_shape(self.blurry_next, list(self.blurry.shape), "blurry_next")
            if self.exposure_start_next is None or self.exposure_end_next is None:
                raise ValueError("blurry_next needs exposure_start_next and exposure_end_next")
            self.exposure_start_next = check_batch_vector(self.exposure_start_next, b, "exposure_start_next").to(
                self.blurry.device, torch.float64)
            self.exposure_end_next = check_batch_vector(self.exposure_end_next, b, "exposure_end_next").to(
                self.blurry.device, torch.float64)
            check_exposure(self.exposure_start_next, self.exposure_end_next)
        if self.target_times is not None:
            tt = torch.as_tensor(self.target_times, dtype=torch.float64, device=self.blurry.device)
            if tt.dim() == 1:
                tt = tt[:, None]
            check_shape(tt, [b, "T"], "target_times")
            self.target_times = tt
            if self.target_frames is not None:
                check_shape(self.target_frames, [b, tt.shape[1], "C", h, w], "target_frames")

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

    def to(self, device: torch.device | str) -> EventFrames:
        """Move every tensor (and the events) to ``device``."""
        changes: dict[str, Any] = {}
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if isinstance(v, (Tensor, Events)):
                changes[f.name] = v.to(device)
        return dataclasses.replace(self, **changes)
