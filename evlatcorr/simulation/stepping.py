"""The time-stepping loop: the camera's view, step by step, into the exposures, the photoreceptor and the events."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch
from torch import Tensor

from evlatcorr.simulation.generator import EventGenerator, log_intensity
from evlatcorr.simulation.latency import Photoreceptor
from evlatcorr.simulation.timeline import Timeline

__all__ = ["Exposures", "Stepped", "View", "step_through"]


class View(Protocol):
    """What the loop needs of a camera (:class:`~evlatcorr.simulation.motion.Camera` or an object camera)."""

    def luminance_at(self, t: float) -> Tensor: ...

    def rgby_at(self, t: float) -> Tensor: ...


class Exposures:
    """Sums the colour over each exposure, exactly for frames varying linearly between steps.

    Args:
        starts: exposure starts :math:`(F,)` µs.
        ends: exposure ends :math:`(F,)` µs.
        size: ``(H, W)``.
        device: where the sums live.
    """

    def __init__(self, starts: Tensor, ends: Tensor, size: tuple[int, int], device: torch.device) -> None:
        self.starts, self.ends = starts.tolist(), ends.tolist()
        self.sums = torch.zeros(len(self.starts), 3, *size, device=device)

    def open_during(self, t_prev: float, t: float) -> list[int]:
        """Indices of the exposures that overlap the step ``(t_prev, t)``."""
        return [i for i in range(len(self.starts)) if t > self.starts[i] and t_prev < self.ends[i]]

    def add(self, frames: list[int], t_prev: float, t: float, rgb_prev: Tensor, rgb: Tensor) -> None:
        """Integrate colour going linearly from ``rgb_prev`` to ``rgb`` over the step into each of ``frames``."""
        step = t - t_prev
        for i in frames:
            a, b = max(t_prev, self.starts[i]), min(t, self.ends[i])
            m = ((a + b) / 2 - t_prev) / step  # the overlap's midpoint, as a fraction of the step
            self.sums[i] += (b - a) * ((1 - m) * rgb_prev + m * rgb)

    def blurry(self, exposure_us: float) -> Tensor:
        """Mean colour over each exposure :math:`(F, 3, H, W)`, in [0, 1]."""
        return (self.sums / float(exposure_us)).clamp(0, 1)


@dataclass
class Stepped:
    """What the loop produced: exposure sums, and the ideal and (``"intensity"`` model) filtered events."""

    exposures: Exposures
    ideal: EventGenerator
    delayed: EventGenerator | None


def step_through(camera: View, timeline: Timeline, exposures: Exposures, thresholds: Tensor,
                 photoreceptor: tuple[float, float] | None) -> Stepped:
    """Run the camera from the warm-up's start to ``timeline.t_end``.

    Args:
        camera: the view.
        timeline: the steps.
        exposures: filled in place.
        thresholds: contrast thresholds :math:`(H, W)`.
        photoreceptor: ``(bright_us, dim_us)`` to filter the signal of a delayed stream
            (the ``"intensity"`` model), else ``None``.
    """
    t_prev = timeline.time_at(-timeline.n_warm)
    lum_prev = camera.luminance_at(t_prev)
    log_prev = log_intensity(lum_prev)
    receptor = None if photoreceptor is None else Photoreceptor(log_prev, *photoreceptor)
    streams = None if timeline.n_warm else _start_streams(log_prev, receptor, thresholds)
    rgb_prev: Tensor | None = None
    for k in range(-timeline.n_warm + 1, timeline.n_main + 1):
        t = timeline.time_at(k)
        step = t - t_prev
        rgb, lum = _look(camera, exposures, t_prev, t, rgb_prev)
        log_cur = log_intensity(lum)
        if receptor is not None:
            filtered = receptor.level
            receptor.advance(log_prev, log_cur, lum_prev, lum, step)
            if streams is not None and streams[1] is not None:
                streams[1].step(filtered, receptor.level, t_prev, step)
        if streams is not None:
            streams[0].step(log_prev, log_cur, t_prev, step)
        if k == 0:  # end of the warm-up: the event streams start here
            streams = _start_streams(log_cur, receptor, thresholds)
        log_prev, lum_prev, rgb_prev, t_prev = log_cur, lum, rgb, t
    if streams is None:  # cannot happen: n_main >= 1, so step 0 or the start opened the streams
        raise RuntimeError("the event streams were never started")
    return Stepped(exposures, *streams)


def _start_streams(log_now: Tensor, receptor: Photoreceptor | None,
                   thresholds: Tensor) -> tuple[EventGenerator, EventGenerator | None]:
    """Ideal and (with a photoreceptor) delayed generators, referenced to the signals at this instant."""
    delayed = None if receptor is None else EventGenerator(receptor.level, thresholds)
    return EventGenerator(log_now, thresholds), delayed


def _look(camera: View, exposures: Exposures, t_prev: float, t: float,
          rgb_prev: Tensor | None) -> tuple[Tensor | None, Tensor]:
    """Colour (``None`` when no exposure is open: only luminance is rendered) and luminance at ``t``.

    The colour over the step is integrated into the open exposures on the way.
    """
    frames = exposures.open_during(t_prev, t)
    if not frames:
        return None, camera.luminance_at(t)
    rgby = camera.rgby_at(t)
    rgb, lum = rgby[:3], rgby[3]
    if rgb_prev is None:
        rgb_prev = camera.rgby_at(t_prev)[:3]
    exposures.add(frames, t_prev, t, rgb_prev, rgb)
    return rgb, lum
