"""The result of a simulation: :class:`SimulatedSequence`, its frames, events and ground truth, and batches of it."""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = ["SimulatedSequence"]


@dataclass(eq=False)
class SimulatedSequence:
    """Ground truth and inputs of one simulated sequence of ``F`` frames.

    Attributes:
        blurry: :math:`(F, 3, H, W)` mean of the colour frames over each exposure, in [0, 1].
        sharp: :math:`(F, 3, H, W)` frames at mid-exposure.
        exposure_start: :math:`(F,)` µs (float64).
        exposure_end: :math:`(F,)` µs.
        ideal_events: events with exact timestamps (one sample, the whole sequence, time-sorted).
        delayed_events: the same scene's events with latency (one sample, time-sorted).
        true_latency: :math:`(F, 1, H, W)` µs.
        target_times: :math:`(T,)` µs, times of ``target_frames`` (the gaps' midpoints, then any requested).
        target_frames: :math:`(T, 3, H, W)` sharp frames at ``target_times``.
        threshold: contrast threshold used (the mean when ``threshold_sigma > 0``).
        seed: the seed.
        config: every simulation parameter (JSON-serialisable).
        threshold_map: :math:`(1, 1, H, W)` per-pixel thresholds (``None`` when read from a file).
        renderer: renders sharp frames at given times (µs) as :math:`(T, 3, H, W)`; ``None`` when
            read from a file. Use :meth:`render`.
    """

    blurry: Tensor
    sharp: Tensor
    exposure_start: Tensor
    exposure_end: Tensor
    ideal_events: Events
    delayed_events: Events
    true_latency: Tensor
    target_times: Tensor
    target_frames: Tensor
    threshold: float
    seed: int
    config: dict[str, Any] = field(default_factory=dict)
    threshold_map: Tensor | None = None
    renderer: Callable[[Tensor], Tensor] | None = field(default=None, repr=False)

    @property
    def num_frames(self) -> int:
        return int(self.blurry.shape[0])

    @property
    def sensor_size(self) -> tuple[int, int]:
        """``(H, W)``: the events', which the frames share."""
        return self.ideal_events.sensor_size

    def render(self, times: Sequence[float] | Tensor) -> Tensor:
        """Sharp colour frames :math:`(T, 3, H, W)` at ``times`` (µs), from the simulated camera.

        Example:
            >>> from evlatcorr.simulate import simulate
            >>> seq = simulate("camera", num_frames=1, height=16, width=20, exposure_us=2000.0)
            >>> seq.render([0.0, 1000.0]).shape
            torch.Size([2, 3, 16, 20])
        """
        if self.renderer is None:
            raise ValueError("this sequence cannot render new frames (it was read from a file); "
                             "only its stored target_times are available")
        t = torch.as_tensor(times, dtype=torch.float64).flatten().cpu()
        if not bool(torch.isfinite(t).all()):
            raise ValueError("times must be finite")
        return self.renderer(t)

    def _events(self, which: str) -> Events:
        if which not in ("delayed", "ideal"):
            raise ValueError(f"which must be 'delayed' or 'ideal', got {which!r}")
        return self.delayed_events if which == "delayed" else self.ideal_events

    @staticmethod
    def _windows(events: Events, starts: Tensor, ends: Tensor) -> Events:
        return Events.cat([events.window(float(s), float(e)) for s, e in zip(starts, ends)])

    def _margins(self, before_us: float, after_us: float | None) -> tuple[float, Tensor]:
        exposure = (self.exposure_end - self.exposure_start).to(torch.float64)
        after = exposure if after_us is None else torch.full_like(exposure, float(after_us))
        if not (math.isfinite(before_us) and before_us >= 0) or not bool(((after >= 0) & after.isfinite()).all()):
            raise ValueError(f"before_us and after_us must be finite and >= 0, got {before_us}, {after_us}")
        return float(before_us), after

    def frames(self, which: str = "delayed", before_us: float = 0.0, after_us: float | None = None) -> EventFrames:
        """Deblurring batch: one sample per frame (``B = F``), events of ``[start - before, end + after)``.

        Args:
            which: ``"delayed"`` (with latency) or ``"ideal"`` events.
            before_us: events kept before each exposure start, µs.
            after_us: events kept after each exposure end, µs; defaults to the exposure time, the
                default latency search range (the simulation covers it plus the largest latency).

        Returns:
            :class:`EventFrames` with ``blurry``, ``events``, exposures and ``sharp`` (mid-exposure);
            ``meta`` holds ``which``, ``true_latency`` :math:`(F, 1, H, W)` and ``frame_index``.

        Example:
            >>> from evlatcorr.simulate import simulate
            >>> seq = simulate("camera", num_frames=2, height=16, width=20, exposure_us=2000.0)
            >>> seq.frames("delayed").batch_size
            2
        """
        events = self._events(which)
        before, after = self._margins(before_us, after_us)
        windowed = self._windows(events, self.exposure_start - before, self.exposure_end + after)
        return EventFrames(self.blurry, windowed, self.exposure_start, self.exposure_end, sharp=self.sharp,
                           meta={"which": which, "true_latency": self.true_latency,
                                 "frame_index": list(range(self.num_frames)),
                                 "latency_model": self.config.get("latency")})

    def pair_times(self, times_per_pair: int = 1) -> Tensor:
        """Target times :math:`(F - 1, T)` µs: ``T`` evenly spaced times strictly between the mid-exposures
        of frames ``i`` and ``i + 1`` (for ``T = 1`` the midpoint of the gap between the exposures)."""
        if not isinstance(times_per_pair, int) or times_per_pair < 1:
            raise ValueError(f"times_per_pair must be a positive integer, got {times_per_pair}")
        mid = ((self.exposure_start + self.exposure_end) / 2).to(torch.float64).cpu()
        frac = torch.arange(1, times_per_pair + 1, dtype=torch.float64) / (times_per_pair + 1)
        return mid[:-1, None] + frac[None] * (mid[1:] - mid[:-1])[:, None]

    def pairs(self, which: str = "delayed", times_per_pair: int = 1, before_us: float = 0.0,
              after_us: float | None = None) -> EventFrames:
        """Interpolation batch: sample ``i`` (``B = F - 1``) pairs frame ``i`` and frame ``i + 1``.

        Args:
            which: ``"delayed"`` or ``"ideal"`` events.
            times_per_pair: number ``T`` of target times per pair, evenly spaced between the two
                mid-exposures (see :meth:`pair_times`); their ground truth frames are rendered
                (``T = 1`` uses the stored gap midpoints, so it also works on sequences read from a file).
            before_us: events kept before the first exposure's start, µs.
            after_us: events kept after the second exposure's end, µs (default: the exposure time).

        Returns:
            :class:`EventFrames` with ``blurry`` (frame i), ``blurry_next`` (frame i + 1), both exposures,
            the events of ``[start_i - before, end_{i+1} + after)``, ``sharp`` (frame i at mid-exposure),
            ``target_times`` :math:`(F-1, T)` and ``target_frames`` :math:`(F-1, T, 3, H, W)`.

        Example:
            >>> from evlatcorr.simulate import simulate
            >>> seq = simulate("camera", num_frames=3, height=16, width=20, exposure_us=2000.0)
            >>> p = seq.pairs("ideal", times_per_pair=3)
            >>> p.batch_size, tuple(p.target_frames.shape)
            (2, (2, 3, 3, 16, 20))
        """
        if self.num_frames < 2:
            raise ValueError("pairs() needs a sequence of at least 2 frames")
        events = self._events(which)
        times = self.pair_times(times_per_pair)
        n, t_per = times.shape
        stored = self.target_times.to(torch.float64).cpu()
        if stored.numel() >= n and torch.allclose(stored[:n, None], times, rtol=0, atol=1e-6) and t_per == 1:
            targets = self.target_frames[:n, None]
        else:
            targets = self.render(times.flatten()).view(n, t_per, *self.blurry.shape[1:])
        before, after = self._margins(before_us, after_us)
        windowed = self._windows(events, self.exposure_start[:-1] - before, self.exposure_end[1:] + after[1:])
        return EventFrames(
            self.blurry[:-1], windowed, self.exposure_start[:-1], self.exposure_end[:-1],
            blurry_next=self.blurry[1:], exposure_start_next=self.exposure_start[1:],
            exposure_end_next=self.exposure_end[1:], target_times=times.to(self.blurry.device),
            target_frames=targets.to(self.blurry.device), sharp=self.sharp[:-1],
            meta={"which": which, "true_latency": self.true_latency[:-1], "frame_index": list(range(n)),
                  "true_latency_next": self.true_latency[1:], "latency_model": self.config.get("latency")},
        )
