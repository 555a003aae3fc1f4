"""Event simulator with known latency, from the photographs scikit-image ships.

A photograph is seen by a camera under a random smooth motion: a drift in a random direction with
a gentle wobble (sums of low-frequency sinusoids), a small rotation and a small zoom, rendered
with Kornia's ``warp_affine``. At small time steps (≤ 0.3 px of image motion per step) the
simulator renders the luminance ``Y = 0.299 R + 0.587 G + 0.114 B`` and emits an event each time
``log(Y + 1e-3)`` of a pixel crosses a multiple of the contrast threshold away from its last
event's level, the crossing time interpolated linearly inside the step (as ESIM does). Colour is
kept for the frames: blurry frames are the time average of the colour frames over each exposure
(exact for frames varying linearly between steps), sharp frames are rendered at mid-exposure and
at any requested time.

Latency models (``latency=``):

- ``"none"``: delayed events are the ideal events.
- ``"constant"``: delayed events are the ideal events stamped ``latency_us`` later.
- ``"intensity"``: each pixel's photoreceptor is a first-order low-pass filter on the log-luminance
  whose time constant is inversely proportional to the pixel's linear intensity ``I`` in [0, 1]
  (as in v2e and IEBCS), ``τ = clip(latency_range_us[0] / I, *latency_range_us)``: bright pixels
  (I = 1) lag by ``latency_range_us[0]`` (0.5 ms by default), dim ones up to
  ``latency_range_us[1]`` (10 ms). The filter is updated exactly for an input that is linear
  between steps, and it is run over a warm-up of ``4 τ_max`` before the first event so it starts
  in its steady state. The delayed events are the threshold crossings of the *filtered* signal;
  the ideal events those of the unfiltered one. A first-order filter following a ramp lags it by
  exactly ``τ`` (and, for any monotone change, the level-crossing times lag by ``τ`` on average),
  so the true latency map reported is ``τ`` at the pixel's intensity averaged over the exposure,
  i.e. computed from the blurry frame's luminance: the quantity a method can estimate from it.
- ``"intensity_delay"``: each ideal event is delayed by that same map (of the frame nearest in
  time) at its pixel: an exact per-pixel ground truth, without the filter's smoothing.

Motion (``motion=``): ``"random"`` (above), a constant translation ``(vx, vy)`` px/ms, ``"rotation"``
(about the view's centre) or ``"zoom"`` (about the view's centre), both at ``max_speed_px_per_ms``
at the view's corners, in a random direction. With ``objects=`` (:class:`ObjectSpec`) the camera is
static and sprites with soft-edged masks move at constant velocities over the background.

Noise, the same in both streams (ideal and delayed differ only by the latency):

- ``noise_rate_hz``: shot noise, Poisson events of random polarity at uniform times, undelayed;
- ``leak_rate_hz``: leak events, ON events repeating at each pixel with a period drawn around
  ``1 / leak_rate_hz`` (lognormal rates) and a random phase, undelayed;
- ``threshold_sigma``: per-pixel contrast-threshold mismatch;
- ``refractory_us``: an event is dropped when the previous event of its pixel (in the stream's own
  times, noise included) is less than ``refractory_us`` earlier (see :func:`apply_refractory`).

Everything random comes from one ``torch.Generator`` seeded by ``seed``, so a seed gives identical
events.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = [
    "PHOTOGRAPHS_TRAIN",
    "PHOTOGRAPHS_TEST",
    "LATENCY_MODELS",
    "MOTIONS",
    "ObjectSpec",
    "apply_refractory",
    "load_photograph",
    "luminance",
    "simulate",
    "simulate_dataset",
    "SimulatedSequence",
]

# Largest latency simulated, µs: the sequence runs this much past its last exposure (memory grows with it).
MAX_LATENCY_US = 1_000_000.0

# scikit-image photographs stored inside the package (no download). Disjoint splits.
_FILES = {
    "astronaut": "astronaut.png", "coffee": "coffee.png", "chelsea": "chelsea.png", "rocket": "rocket.jpg",
    "camera": "camera.png", "motorcycle_right": "motorcycle_right.png", "brick": "brick.png",
    "gravel": "gravel.png", "motorcycle_left": "motorcycle_left.png", "hubble_deep_field": "hubble_deep_field.jpg",
    "retina": "retina.jpg", "immunohistochemistry": "ihc.png", "moon": "moon.png", "coins": "coins.png",
    "page": "page.png", "text": "text.png", "grass": "grass.png", "cell": "cell.png",
}
_ALIASES = {"ihc": "immunohistochemistry"}
PHOTOGRAPHS_TEST = ("astronaut", "coffee", "chelsea", "rocket", "camera", "motorcycle_right", "brick", "gravel")
PHOTOGRAPHS_TRAIN = ("motorcycle_left", "hubble_deep_field", "retina", "immunohistochemistry", "moon", "coins",
                     "page", "text", "grass", "cell")
LATENCY_MODELS = ("none", "constant", "intensity", "intensity_delay")
MOTIONS = ("random", "rotation", "zoom")  # named motions; a (vx, vy) tuple is a constant translation
OBJECT_SHAPES = ("disc", "rect")
_LEAK_SPREAD = 0.5  # std of log(rate) of the per-pixel leak rates
_LOG_EPS = 1e-3  # log(Y + eps): dark pixels do not fire on noise-level changes
_MAX_DT_US = 200.0  # longest time step, whatever the motion
_STEP_PX = 0.3  # longest image motion per step


def luminance(rgb: Tensor) -> Tensor:
    """Luminance ``0.299 R + 0.587 G + 0.114 B`` of images :math:`(..., 3, H, W)` as :math:`(..., 1, H, W)`.

    Example:
        >>> luminance(torch.ones(2, 3, 4, 5)).shape
        torch.Size([2, 1, 4, 5])
    """
    if rgb.dim() < 3 or rgb.shape[-3] != 3:
        raise ValueError(f"rgb must have shape (..., 3, H, W), got {tuple(rgb.shape)}")
    return 0.299 * rgb[..., 0:1, :, :] + 0.587 * rgb[..., 1:2, :, :] + 0.114 * rgb[..., 2:3, :, :]


def load_photograph(name: str, gain: float = 1.0) -> Tensor:
    """A scikit-image photograph as linear RGB :math:`(3, H, W)` in [0, 1] (grey repeated to 3 channels).

    The 8-bit values are taken as linear intensities (no gamma), scaled by ``gain`` and clipped to
    [0, 1], so ``gain < 1`` gives a dim scene.

    Args:
        name: one of :data:`PHOTOGRAPHS_TRAIN` or :data:`PHOTOGRAPHS_TEST` (``"ihc"`` is accepted too).
        gain: intensity scale, > 0.

    Example:
        >>> load_photograph("camera").shape
        torch.Size([3, 512, 512])
    """
    key = _ALIASES.get(name, name) if isinstance(name, str) else name
    if key not in _FILES:
        raise ValueError(f"unknown photograph {name!r}; choose from {sorted(_FILES)}")
    if not gain > 0 or not math.isfinite(gain):
        raise ValueError(f"gain must be a positive number, got {gain}")
    import skimage.data
    import skimage.io

    path = os.path.join(os.path.dirname(skimage.data.__file__), _FILES[key])
    img = np.asarray(skimage.io.imread(path))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3]
    scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
    out = torch.from_numpy(np.ascontiguousarray(img.astype(np.float32) / scale)).permute(2, 0, 1).contiguous()
    return (out * gain).clamp_(0.0, 1.0)


@dataclass(frozen=True)
class ObjectSpec:
    """A sprite moving at a constant velocity over a static background (``simulate(objects=...)``).

    Attributes:
        sprite: a photograph name (:data:`PHOTOGRAPHS_TRAIN`, :data:`PHOTOGRAPHS_TEST`), a procedural
            scene ``(kind, seed)`` (:func:`evlatcorr.scenes.procedural_scene`, drawn at ``size``) or an
            image :math:`(3, h, w)`, :math:`(1, h, w)` or :math:`(h, w)` in [0, 1]; photographs and
            images are centre-cropped to the aspect ratio of ``size`` and resized to it.
        size: ``(h, w)`` of the object on the sensor, px (≥ 2).
        position: ``(x, y)`` of the object's centre on the sensor (px, may be outside it) at ``time_us``.
        velocity: ``(vx, vy)`` px/ms.
        shape: opacity mask: ``"disc"`` (the ellipse inscribed in ``size``) or ``"rect"`` (a rectangle
            with corners rounded by a quarter of its shorter side); its edge is antialiased over 1 px.
        time_us: the time at which the centre is at ``position``, µs (default: the first event's, 0).

    Example:
        >>> coins = ObjectSpec("coins", size=(20, 30), position=(10.0, 12.0), velocity=(1.0, 0.0))
        >>> board = ObjectSpec(("checkerboard", 3), size=(16, 16), position=(30.0, 12.0), shape="rect")
        >>> coins.shape, board.velocity
        ('disc', (0.0, 0.0))
    """

    sprite: str | tuple[str, int] | Tensor
    size: tuple[int, int]
    position: tuple[float, float]
    velocity: tuple[float, float] = (0.0, 0.0)
    shape: str = "disc"
    time_us: float = 0.0


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
        return int(self.blurry.shape[-2]), int(self.blurry.shape[-1])

    def render(self, times: Sequence[float] | Tensor) -> Tensor:
        """Sharp colour frames :math:`(T, 3, H, W)` at ``times`` (µs), from the simulated camera.

        Example:
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


class _Trajectory:
    """A smooth camera trajectory: content displacement (px), rotation (rad) and log-zoom as functions of time.

    ``motion="random"``: a drift of 55-68 % of ``max_speed`` in a random direction, two sinusoids per
    axis (periods 40-120 ms, at most 12 % of ``max_speed`` per axis), a rotation and a zoom whose
    speeds at the view's corners stay under 8 % and 7 % of ``max_speed``: no point of the view
    moves faster than ``max_speed`` (to within the ~1 % zoom). A ``(vx, vy)`` tuple (px/ms) gives a
    pure constant translation. ``"rotation"`` and ``"zoom"``: a constant rotation (rad/µs) or rate of
    log-zoom (1/µs) about the view's centre of ``max_speed / radius``, a random sign: points at the
    view's corners move at ``max_speed``. Everything is relative to ``t_center`` (the view is
    centred on the photograph then).
    """

    def __init__(self, motion: str | tuple[float, float], max_speed_px_per_ms: float, radius: float,
                 t_center: float, generator: torch.Generator) -> None:
        self.t_center = t_center
        self.translations: list[tuple[float, float, float, float]] = []  # (vx, vy, period, phase) sinusoids
        self.rotations: list[tuple[float, float, float]] = []  # (amplitude rad/µs, period, phase)
        self.zooms: list[tuple[float, float, float]] = []
        self.spin = 0.0
        self.zoom_rate = 0.0
        if motion in ("rotation", "zoom"):
            self.drift = (0.0, 0.0)
            sign = 1.0 if float(torch.rand((), generator=generator, dtype=torch.float64)) < 0.5 else -1.0
            rate = sign * max_speed_px_per_ms / 1000.0 / radius
            if motion == "rotation":
                self.spin = rate
            else:
                self.zoom_rate = rate
        elif isinstance(motion, str):
            u = torch.rand(17, generator=generator, dtype=torch.float64).tolist()
            vmax = max_speed_px_per_ms / 1000.0  # px/µs
            angle, drift = 2 * math.pi * u[0], vmax * (0.55 + 0.13 * u[1])
            self.drift = (drift * math.cos(angle), drift * math.sin(angle))
            for axis in range(2):
                for k in range(2):
                    a, p, ph = u[2 + 6 * axis + 3 * k: 5 + 6 * axis + 3 * k]
                    amp = vmax * 0.06 * (0.5 + 0.5 * a)
                    self.translations.append((amp if axis == 0 else 0.0, amp if axis == 1 else 0.0,
                                              40_000.0 + 80_000.0 * p, 2 * math.pi * ph))
            # rotation: |spin| + |oscillation| <= 0.04 + 0.04 of vmax at the view's corners
            self.spin = (2 * u[14] - 1) * 0.04 * vmax / radius
            self.rotations.append((0.04 * vmax / radius, 60_000.0 + 60_000.0 * u[15], 2 * math.pi * u[16]))
            zu = torch.rand(3, generator=generator, dtype=torch.float64).tolist()
            self.zooms.append((0.07 * vmax / radius * (0.5 + 0.5 * zu[0]), 50_000.0 + 70_000.0 * zu[1],
                               2 * math.pi * zu[2]))
        else:
            self.drift = (float(motion[0]) / 1000.0, float(motion[1]) / 1000.0)

    @staticmethod
    def _integral(amp: float, period: float, phase: float, t: Tensor, t0: float) -> Tensor:
        """∫_{t0}^{t} amp cos(2π s / period + phase) ds."""
        w = 2 * math.pi / period
        return amp / w * (torch.sin(w * t + phase) - math.sin(w * t0 + phase))

    def pose(self, t: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Content displacement ``dx, dy`` (px), rotation (rad) and log-zoom at times ``t`` :math:`(N,)` µs."""
        t = t.to(torch.float64)
        rel = t - self.t_center
        dx, dy = self.drift[0] * rel, self.drift[1] * rel
        for vx, vy, period, phase in self.translations:
            if vx:
                dx = dx + self._integral(vx, period, phase, t, self.t_center)
            if vy:
                dy = dy + self._integral(vy, period, phase, t, self.t_center)
        rot = self.spin * rel
        for amp, period, phase in self.rotations:
            rot = rot + self._integral(amp, period, phase, t, self.t_center)
        zoom = self.zoom_rate * rel
        for amp, period, phase in self.zooms:
            zoom = zoom + self._integral(amp, period, phase, t, self.t_center)
        return dx, dy, rot, zoom


class _Camera:
    """Renders the view of a photograph along a trajectory with Kornia (source coordinates = photo pixels)."""

    def __init__(self, photo: Tensor, height: int, width: int, trajectory: _Trajectory, span: tuple[float, float]):
        self.size = (height, width)
        self.trajectory = trajectory
        radius = 0.5 * math.hypot(height - 1, width - 1)
        grid = torch.linspace(span[0], span[1], 2001, dtype=torch.float64)
        dx, dy, _, zoom = trajectory.pose(grid)
        shrink = math.exp(-float(zoom.min()))  # source extent of one sensor pixel at the smallest zoom
        need_w = 2 * (float(dx.abs().max()) * shrink + radius * shrink) + 6
        need_h = 2 * (float(dy.abs().max()) * shrink + radius * shrink) + 6
        ph, pw = photo.shape[-2:]
        self.scale = max(1.0, need_w / pw, need_h / ph)
        if self.scale > 1.0:
            size = (math.ceil(ph * self.scale), math.ceil(pw * self.scale))
            photo = F.interpolate(photo[None], size=size, mode="bilinear", align_corners=False)[0].clamp(0, 1)
        self.rgby = torch.cat([photo, luminance(photo)], 0)[None].contiguous()  # (1, 4, h, w)
        self.lum = self.rgby[:, 3:4].contiguous()
        self.center = ((self.rgby.shape[-1] - 1) / 2.0, (self.rgby.shape[-2] - 1) / 2.0)

    def matrices(self, t: Tensor) -> Tensor:
        """Source-to-sensor affine matrices :math:`(N, 2, 3)` at times ``t`` :math:`(N,)`."""
        dx, dy, rot, logzoom = self.trajectory.pose(t)
        z = torch.exp(logzoom)
        c, s = torch.cos(rot) * z, torch.sin(rot) * z
        # the view's centre in the photograph: content displaced by +d appears displaced by +d on the sensor
        cx, cy = self.center[0] - dx / z, self.center[1] - dy / z
        h, w = self.size
        m = torch.stack([torch.stack([c, -s, (w - 1) / 2 - (c * cx - s * cy)], -1),
                         torch.stack([s, c, (h - 1) / 2 - (s * cx + c * cy)], -1)], -2)
        return m.to(self.rgby)

    def _warp(self, src: Tensor, t: Tensor) -> Tensor:
        m = self.matrices(t)
        return kornia.geometry.transform.warp_affine(src.expand(m.shape[0], -1, -1, -1), m, dsize=self.size,
                                                     mode="bilinear", padding_mode="reflection",
                                                     align_corners=True)

    def luminance_at(self, t: float) -> Tensor:
        """Luminance :math:`(H, W)` at time ``t``."""
        return self._warp(self.lum, torch.tensor([t], dtype=torch.float64))[0, 0]

    def rgby_at(self, t: float) -> Tensor:
        """Colour and luminance :math:`(4, H, W)` at time ``t``."""
        return self._warp(self.rgby, torch.tensor([t], dtype=torch.float64))[0]

    def render(self, times: Tensor, chunk: int = 16) -> Tensor:
        """Colour frames :math:`(T, 3, H, W)` at ``times`` µs."""
        times = torch.as_tensor(times, dtype=torch.float64).flatten().cpu()
        if times.numel() == 0:
            return torch.zeros(0, 3, *self.size, dtype=self.rgby.dtype, device=self.rgby.device)
        rgb = self.rgby[:, :3]
        return torch.cat([self._warp(rgb, times[i:i + chunk]) for i in range(0, times.numel(), chunk)]).clamp(0, 1)


class _ObjectCamera:
    """A static background with sprites composited over it (alpha over), same interface as :class:`_Camera`.

    Args:
        background: colour :math:`(3, h, w)`; the static view of it is rendered as by a still camera.
        sprites: premultiplied ``(R α, G α, B α, Y α, α)`` images :math:`(5, h_i, w_i)`, drawn in order
            (later ones on top).
        motions: ``(x0, y0, vx, vy)`` per sprite: the sprite's centre ``(x0, y0) + (vx, vy) t`` on the
            sensor at time ``t`` (px, px/µs).
    """

    def __init__(self, background: Tensor, height: int, width: int, sprites: Sequence[Tensor],
                 motions: Sequence[tuple[float, float, float, float]]) -> None:
        still = _Camera(background, height, width, _Trajectory((0.0, 0.0), 0.0, 1.0, 0.0, torch.Generator()),
                        (0.0, 0.0))
        self.size = (height, width)
        self.scale = still.scale
        self.background = still.rgby_at(0.0)[None]  # (1, 4, H, W)
        self.rgby = self.background  # dtype / device, as _Camera
        self.sprites = [s[None].to(self.background) for s in sprites]
        self.motions = list(motions)

    def _compose(self, t: Tensor, channels: slice) -> Tensor:
        t = t.to(torch.float64)
        out = self.background[:, channels].expand(t.numel(), -1, -1, -1)
        for sprite, (x0, y0, vx, vy) in zip(self.sprites, self.motions):
            h, w = sprite.shape[-2:]
            tx = x0 + vx * t - (w - 1) / 2  # where the sprite's pixel (0, 0) lands on the sensor
            ty = y0 + vy * t - (h - 1) / 2
            one, zero = torch.ones_like(t), torch.zeros_like(t)
            m = torch.stack([torch.stack([one, zero, tx], -1), torch.stack([zero, one, ty], -1)], -2).to(sprite)
            src = torch.cat([sprite[:, channels], sprite[:, 4:5]], 1).expand(t.numel(), -1, -1, -1)
            warped = kornia.geometry.transform.warp_affine(src, m, dsize=self.size, mode="bilinear",
                                                           padding_mode="zeros", align_corners=True)
            out = warped[:, :-1] + (1 - warped[:, -1:]) * out
        return out

    def luminance_at(self, t: float) -> Tensor:
        """Luminance :math:`(H, W)` at time ``t``."""
        return self._compose(torch.tensor([t], dtype=torch.float64), slice(3, 4))[0, 0]

    def rgby_at(self, t: float) -> Tensor:
        """Colour and luminance :math:`(4, H, W)` at time ``t``."""
        return self._compose(torch.tensor([t], dtype=torch.float64), slice(0, 4))[0]

    def render(self, times: Tensor, chunk: int = 16) -> Tensor:
        """Colour frames :math:`(T, 3, H, W)` at ``times`` µs."""
        times = torch.as_tensor(times, dtype=torch.float64).flatten().cpu()
        if times.numel() == 0:
            return torch.zeros(0, 3, *self.size, dtype=self.rgby.dtype, device=self.rgby.device)
        return torch.cat([self._compose(times[i:i + chunk], slice(0, 3))
                          for i in range(0, times.numel(), chunk)]).clamp(0, 1)


def _sprite(spec: ObjectSpec, brightness: float, device: torch.device) -> Tensor:
    """Premultiplied ``(R α, G α, B α, Y α, α)`` image :math:`(5, h + 4, w + 4)` of an object (2 px clear border)."""
    from evlatcorr.scenes import procedural_scene

    h, w = spec.size
    if isinstance(spec.sprite, tuple):
        kind, seed = spec.sprite
        rgb = procedural_scene(kind, max(h, 8), max(w, 8), seed)
    else:
        rgb = load_photograph(spec.sprite) if isinstance(spec.sprite, str) else _image_tensor(spec.sprite)
    ph, pw = rgb.shape[-2:]
    if ph * w > pw * h:  # centre crop to the object's aspect ratio
        ch = max(1, round(pw * h / w))
        rgb = rgb[:, (ph - ch) // 2:(ph - ch) // 2 + ch]
    else:
        cw = max(1, round(ph * w / h))
        rgb = rgb[:, :, (pw - cw) // 2:(pw - cw) // 2 + cw]
    if tuple(rgb.shape[-2:]) != (h, w):
        rgb = F.interpolate(rgb[None], size=(h, w), mode="bilinear", align_corners=False, antialias=True)[0]
    rgb = (rgb.to(device) * float(brightness)).clamp(0, 1)
    # signed distance (px, negative inside) to the mask's edge, then a 1 px antialiased ramp
    y = torch.arange(h + 4, dtype=torch.float64, device=device)[:, None] - (h + 3) / 2
    x = torch.arange(w + 4, dtype=torch.float64, device=device)[None, :] - (w + 3) / 2
    a, b = w / 2, h / 2
    if spec.shape == "disc":
        sd = (torch.sqrt((x / a) ** 2 + (y / b) ** 2) - 1) * min(a, b)
    else:
        r = min(a, b) / 2
        qx, qy = x.abs() - (a - r), y.abs() - (b - r)
        sd = torch.sqrt(qx.clamp_min(0) ** 2 + qy.clamp_min(0) ** 2) + torch.maximum(qx, qy).clamp_max(0) - r
    alpha = (0.5 - sd).clamp(0, 1).to(rgb)[None]
    rgby = F.pad(torch.cat([rgb, luminance(rgb)], 0), (2, 2, 2, 2))
    return torch.cat([rgby * alpha, alpha], 0)


def _sprite_name(sprite: str | tuple[str, int] | Tensor) -> str | list[Any]:
    """JSON-serialisable description of a sprite: its name, ``[kind, seed]`` or ``"tensor"``."""
    return sprite if isinstance(sprite, str) else list(sprite) if isinstance(sprite, tuple) else "tensor"


def _check_objects(objects: Sequence[ObjectSpec]) -> list[ObjectSpec]:
    if isinstance(objects, ObjectSpec) or not isinstance(objects, Sequence):
        raise ValueError(f"objects must be a sequence of ObjectSpec, got {type(objects).__name__}")
    out = []
    for i, spec in enumerate(objects):
        if not isinstance(spec, ObjectSpec):
            raise ValueError(f"objects[{i}] must be an ObjectSpec, got {type(spec).__name__}")
        try:
            size = (int(spec.size[0]), int(spec.size[1])) if len(spec.size) == 2 else ()
            pos = tuple(float(v) for v in spec.position)
            vel = tuple(float(v) for v in spec.velocity)
            time_us = float(spec.time_us)
        except (TypeError, ValueError):
            raise ValueError(f"objects[{i}] needs size (h, w), position (x, y), velocity (vx, vy) and time_us "
                             f"as numbers, got {spec!r}") from None
        if len(size) != 2 or min(size) < 2 or tuple(spec.size) != size:
            raise ValueError(f"objects[{i}].size must be two integers >= 2, got {spec.size}")
        if len(pos) != 2 or len(vel) != 2 or not all(math.isfinite(v) for v in (*pos, *vel, time_us)):
            raise ValueError(f"objects[{i}] position, velocity and time_us must be finite (x, y), (vx, vy) and "
                             f"a number, got {spec.position}, {spec.velocity}, {spec.time_us}")
        if spec.shape not in OBJECT_SHAPES:
            raise ValueError(f"objects[{i}].shape must be one of {OBJECT_SHAPES}, got {spec.shape!r}")
        sprite = spec.sprite
        if isinstance(sprite, (tuple, list)):
            from evlatcorr.scenes import PROCEDURAL_SCENES

            if (len(sprite) != 2 or sprite[0] not in PROCEDURAL_SCENES or isinstance(sprite[1], bool)
                    or not isinstance(sprite[1], (int, np.integer))):
                raise ValueError(f"objects[{i}].sprite as a procedural scene must be (kind, seed) with kind in "
                                 f"{PROCEDURAL_SCENES} and an integer seed, got {sprite!r}")
            sprite = (str(sprite[0]), int(sprite[1]))
        elif not isinstance(sprite, (str, Tensor)):
            raise ValueError(f"objects[{i}].sprite must be a photograph name, a procedural (kind, seed) or an "
                             f"image tensor, got {type(sprite).__name__}")
        out.append(ObjectSpec(sprite, size, pos, vel, spec.shape, time_us))
    return out


class _EventGenerator:
    """ESIM-style threshold crossings of a log signal, per pixel, step by step.

    Args:
        log_start: the signal :math:`(H, W)` at the start; it is each pixel's first reference level.
        thresholds: contrast threshold per pixel :math:`(H, W)` (or broadcastable).
    """

    def __init__(self, log_start: Tensor, thresholds: Tensor) -> None:
        self.ref = log_start.clone()
        self.thr = torch.as_tensor(thresholds, dtype=log_start.dtype, device=log_start.device).expand_as(
            log_start).contiguous()
        self.chunks: list[tuple[Tensor, Tensor, Tensor]] = []  # (flat pixel, t, p)

    def step(self, log_prev: Tensor, log_cur: Tensor, t_prev: float, dt: float) -> None:
        """Emit the crossings of a signal going linearly from ``log_prev`` (at ``t_prev``) to ``log_cur`` (``+ dt``)."""
        diff = (log_cur - self.ref).flatten()
        thr = self.thr.flatten()
        count = torch.floor(diff.abs() / thr)
        fired = torch.nonzero(count > 0).flatten()
        if fired.numel() == 0:
            return
        n = count[fired].long()
        sign = torch.sign(diff[fired])
        pix = torch.repeat_interleave(fired, n)
        sgn = torch.repeat_interleave(sign, n)
        first = torch.cumsum(n, 0) - n
        k = torch.arange(pix.numel(), device=n.device) - torch.repeat_interleave(first, n) + 1
        ref = self.ref.view(-1)
        level = ref[pix] + sgn * k * thr[pix]
        lp, lc = log_prev.flatten()[pix], log_cur.flatten()[pix]
        step = lc - lp
        frac = ((level - lp) / step.where(step.abs() > 1e-12, torch.ones_like(step))).clamp(0, 1)
        self.chunks.append((pix, t_prev + frac.double() * dt, sgn.to(torch.int8)))
        ref[fired] += sign * n * thr[fired]

    def events(self, sensor_size: tuple[int, int], extra: tuple[Tensor, Tensor, Tensor] | None) -> Events:
        """All events so far (plus ``extra`` = (flat pixel, t, p) ones) as one time-sorted sample."""
        chunks = self.chunks + ([extra] if extra is not None else [])
        _, width = sensor_size
        device = self.ref.device
        if chunks:
            pix = torch.cat([c[0].to(device) for c in chunks])
            t = torch.cat([c[1].to(device) for c in chunks])
            p = torch.cat([c[2].to(device) for c in chunks])
        else:
            pix = torch.zeros(0, dtype=torch.long, device=device)
            t = torch.zeros(0, dtype=torch.float64, device=device)
            p = torch.zeros(0, dtype=torch.int8, device=device)
        order = torch.argsort(t, stable=True)
        pix, t, p = pix[order], t[order], p[order]
        return Events._trusted(pix % width, pix // width, t, p, torch.zeros_like(pix), sensor_size, 1)


def _merge(signal: Events, noise: tuple[Tensor, Tensor, Tensor] | None) -> Events:
    """Signal events plus (flat pixel, t, p) noise events, time-sorted, one sample."""
    if noise is None or noise[0].numel() == 0:
        return signal
    width = signal.sensor_size[1]
    pix = torch.cat([signal.y * width + signal.x, noise[0]])
    t = torch.cat([signal.t, noise[1]])
    p = torch.cat([signal.p, noise[2]])
    order = torch.argsort(t, stable=True)
    pix, t, p = pix[order], t[order], p[order]
    return Events._trusted(pix % width, pix // width, t, p, torch.zeros_like(pix), signal.sensor_size, 1)


def apply_refractory(events: Events, refractory_us: float) -> Events:
    """Drop each event whose pixel had an event less than ``refractory_us`` before it (a vectorised dead time).

    The previous event counts whether it was kept or dropped, so this drops at least as many events
    as a true dead time after each *kept* event (a pixel firing steadily faster than 1 /
    ``refractory_us`` keeps only its first event), and kept events of a pixel are always at least
    ``refractory_us`` apart. The change that happens during the dead time is lost, not emitted late.

    Args:
        events: events of one or more samples (pixels are per sample), time-sorted within each.
        refractory_us: dead time, µs (≥ 0; 0 keeps everything).

    Returns:
        the kept events, in their order.

    Example:
        >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([0.0, 50.0, 300.0]), torch.ones(3),
        ...             sensor_size=(1, 1))
        >>> apply_refractory(ev, 100.0).t.tolist()
        [0.0, 300.0]
    """
    refractory_us = float(refractory_us)
    if not (math.isfinite(refractory_us) and refractory_us >= 0):
        raise ValueError(f"refractory_us must be >= 0, got {refractory_us}")
    if refractory_us == 0 or len(events) < 2:
        return events
    pix = events.pixel_index()
    order = torch.argsort(pix, stable=True)  # by pixel, in time order within each pixel
    pix_o, t_o = pix[order], events.t[order]
    close = (pix_o[1:] == pix_o[:-1]) & (t_o[1:] - t_o[:-1] < refractory_us)
    keep = torch.ones_like(pix, dtype=torch.bool)
    keep[order[1:][close]] = False
    return events.select(keep)


def _leak_events(height: int, width: int, t_end: float, rate_hz: float,
                 g: torch.Generator) -> tuple[Tensor, Tensor, Tensor]:
    """Leak events (flat pixel, t, p = +1) in ``[0, t_end)``: per-pixel periodic at a lognormal rate, random phase."""
    n_pix = height * width
    rates = float(rate_hz) * torch.exp(_LEAK_SPREAD * torch.randn(n_pix, generator=g, dtype=torch.float64)
                                       - _LEAK_SPREAD**2 / 2)  # Hz, mean rate_hz
    period = 1e6 / rates  # µs
    first = torch.rand(n_pix, generator=g, dtype=torch.float64) * period
    count = torch.where(first < t_end, torch.floor((t_end - first) / period) + 1, torch.zeros_like(first)).long()
    pix = torch.repeat_interleave(torch.arange(n_pix), count)
    k = torch.arange(pix.numel()) - torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    t = first[pix] + k.double() * period[pix]
    t = t.clamp_max(math.nextafter(t_end, 0.0))  # rounding
    return pix, t, torch.ones(pix.numel(), dtype=torch.int8)


def _image_tensor(image: Tensor) -> Tensor:
    if not isinstance(image, Tensor):
        raise ValueError(f"image must be a photograph name or a tensor, got {type(image).__name__}")
    if image.dim() == 2:
        image = image[None]
    if image.dim() != 3 or image.shape[0] not in (1, 3) or min(image.shape[-2:]) < 2:
        raise ValueError(f"image must be an RGB (3, H, W) or grey (1, H, W) / (H, W) tensor, got {tuple(image.shape)}")
    if not image.is_floating_point():
        raise ValueError(f"image must be a floating point tensor in [0, 1], got {image.dtype}")
    if not bool(torch.isfinite(image).all()) or float(image.min()) < 0 or float(image.max()) > 1:
        raise ValueError("image must hold finite linear intensities in [0, 1]")
    return image.float().expand(3, -1, -1).contiguous()


def simulate(
    image: str | Tensor,
    *,
    num_frames: int = 2,
    height: int = 260,
    width: int = 346,
    exposure_us: float = 20_000.0,
    frame_interval_us: float = 25_000.0,
    latency: str = "constant",
    latency_us: float = 4000.0,
    latency_range_us: tuple[float, float] = (500.0, 10_000.0),
    threshold: float = 0.2,
    threshold_sigma: float = 0.0,
    noise_rate_hz: float = 0.0,
    max_speed_px_per_ms: float = 1.5,
    motion: str | tuple[float, float] = "random",
    brightness: float = 1.0,
    margin_us: float | None = None,
    target_times: Sequence[float] | Tensor | None = None,
    dt_us: float | None = None,
    seed: int = 0,
    device: str | torch.device = "cpu",
    objects: Sequence[ObjectSpec] | None = None,
    leak_rate_hz: float = 0.0,
    refractory_us: float = 0.0,
) -> SimulatedSequence:
    """Simulate blurry colour frames and their ideal and delayed events (see the module docstring).

    The timeline starts at 0 µs with the first event; exposure ``i`` is
    ``[margin + i * frame_interval, margin + i * frame_interval + exposure)`` and the events end
    ``margin`` plus the model's largest latency after the last exposure, so every frame has delayed
    events up to ``exposure_end + margin`` of any latency up to the largest (the default latency
    search range is the exposure time, the default margin).

    Args:
        image: a photograph name (:data:`PHOTOGRAPHS_TRAIN`, :data:`PHOTOGRAPHS_TEST`) or an image
            tensor :math:`(3, H, W)`, :math:`(1, H, W)` or :math:`(H, W)` of linear intensities in [0, 1].
            It is upsampled when smaller than the camera's path needs.
        num_frames: number of consecutive exposures ``F``.
        height: sensor height ``H``.
        width: sensor width ``W``.
        exposure_us: exposure time of each frame, µs.
        frame_interval_us: time between exposure starts (≥ exposure), µs.
        latency: ``"none"``, ``"constant"``, ``"intensity"`` or ``"intensity_delay"``.
        latency_us: the constant latency, µs.
        latency_range_us: ``(bright, dim)`` time constants of the intensity models, µs;
            ``τ = clip(bright / I, bright, dim)``.
        threshold: contrast threshold (log units).
        threshold_sigma: per-pixel threshold mismatch, relative: thresholds are
            ``threshold * (1 + threshold_sigma * N(0, 1))``, clipped at ``0.2 * threshold``.
        noise_rate_hz: shot-noise events per pixel per second (Poisson, random polarity, uniform
            times), in both streams.
        max_speed_px_per_ms: largest image speed anywhere in the view (random motion); the default
            blurs a 20 ms exposure by about 15-25 px. For ``"rotation"`` and ``"zoom"``, the speed at
            the view's corners.
        motion: ``"random"`` (smooth random drift, wobble, rotation, zoom), ``"rotation"`` or
            ``"zoom"`` (constant, about the view's centre, random sign), or a constant translation
            ``(vx, vy)`` of the image content in px/ms (then ``max_speed_px_per_ms`` is ignored).
            With ``"zoom"`` the photograph is sized for the view from 0 µs on: during the
            ``"intensity"`` filter's warm-up the view may reach past it (mirrored content).
        brightness: multiplies the photograph's (and the objects') intensity before anything else
            (clipped to [0, 1]); dim scenes have late events under the intensity models.
        margin_us: events simulated before the first exposure, µs (default ``exposure_us``); after the
            last exposure they run ``margin_us`` plus the model's largest latency (``latency_us``,
            ``latency_range_us[1]`` or 0).
        target_times: extra times (µs) for ground-truth sharp frames; the gaps' midpoints come first.
        dt_us: time step; default ``min(200, 0.3 / max_speed)`` µs so the image moves ≤ 0.3 px per step.
        seed: random seed (motion, threshold mismatch, noise).
        device: where to simulate.
        objects: sprites (:class:`ObjectSpec`) composited, in order, over the photograph seen by a
            static camera (``motion`` must then be left at its default or be ``(0, 0)``); the step
            follows the fastest object (``max_speed_px_per_ms`` is ignored).
        leak_rate_hz: mean rate of leak events (ON, roughly periodic per pixel, rates lognormal
            around it with a log-std of 0.5, random phases), in both streams, undelayed.
        refractory_us: per-pixel dead time, µs, applied to each stream in its own times (noise
            included) by :func:`apply_refractory`.

    Returns:
        a :class:`SimulatedSequence`.

    Example:
        >>> seq = simulate("camera", num_frames=1, height=32, width=40, exposure_us=5000.0, seed=1)
        >>> seq.blurry.shape, seq.true_latency.unique().tolist()
        (torch.Size([1, 3, 32, 40]), [4000.0])
        >>> batch = seq.frames("delayed")  # EventFrames for EventLatencyCorrector
    """
    # validation ---------------------------------------------------------------------------------
    if latency not in LATENCY_MODELS:
        raise ValueError(f"latency must be one of {LATENCY_MODELS}, got {latency!r}")
    if not isinstance(num_frames, int) or num_frames < 1:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames}")
    if not isinstance(height, int) or not isinstance(width, int) or height < 2 or width < 2:
        raise ValueError(f"height and width must be integers >= 2, got {height}x{width}")
    numbers = dict(exposure_us=exposure_us, frame_interval_us=frame_interval_us, latency_us=latency_us,
                   threshold=threshold, threshold_sigma=threshold_sigma, noise_rate_hz=noise_rate_hz,
                   max_speed_px_per_ms=max_speed_px_per_ms, brightness=brightness, leak_rate_hz=leak_rate_hz,
                   refractory_us=refractory_us)
    for key, value in numbers.items():
        try:
            numbers[key] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{key} must be a finite number, got {value!r}") from None
        if not math.isfinite(numbers[key]):
            raise ValueError(f"{key} must be a finite number, got {value!r}")
    exposure_us, frame_interval_us, latency_us, threshold, threshold_sigma, noise_rate_hz, max_speed_px_per_ms, \
        brightness, leak_rate_hz, refractory_us = numbers.values()
    if exposure_us <= 0:
        raise ValueError(f"exposure_us must be positive, got {exposure_us}")
    if frame_interval_us < exposure_us:
        raise ValueError(f"frame_interval_us ({frame_interval_us}) must be >= exposure_us ({exposure_us})")
    if threshold <= 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    if not 0 <= latency_us <= MAX_LATENCY_US:
        raise ValueError(f"latency_us must be in [0, {MAX_LATENCY_US:.0f}] (event-camera latencies are µs to tens of "
                         f"ms; the sequence is simulated that much longer), got {latency_us}")
    if (len(latency_range_us) != 2 or not 0 < float(latency_range_us[0]) <= float(latency_range_us[1])
            <= MAX_LATENCY_US):
        raise ValueError(f"latency_range_us must be (bright, dim) with 0 < bright <= dim <= {MAX_LATENCY_US:.0f}, "
                         f"got {latency_range_us}")
    for key in ("threshold_sigma", "noise_rate_hz", "max_speed_px_per_ms", "leak_rate_hz", "refractory_us"):
        if numbers[key] < 0:
            raise ValueError(f"{key} must be >= 0, got {numbers[key]}")
    if brightness <= 0:
        raise ValueError(f"brightness must be positive, got {brightness}")
    if isinstance(motion, str):
        if motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS} or a (vx, vy) translation in px/ms, got {motion!r}")
        speed = float(max_speed_px_per_ms)
    else:
        try:
            velocity = (float(motion[0]), float(motion[1])) if len(motion) == 2 else ()
        except (TypeError, ValueError):
            velocity = ()
        if len(velocity) != 2 or not all(math.isfinite(v) for v in velocity):
            raise ValueError(f"motion must be one of {MOTIONS} or a (vx, vy) translation in px/ms, got {motion!r}")
        motion = velocity
        speed = math.hypot(*velocity)
    if margin_us is not None and not (math.isfinite(margin_us) and margin_us >= 0):
        raise ValueError(f"margin_us must be >= 0, got {margin_us}")
    if dt_us is not None and not (math.isfinite(dt_us) and dt_us > 0):
        raise ValueError(f"dt_us must be positive, got {dt_us}")
    extra_times = torch.as_tensor([] if target_times is None else target_times, dtype=torch.float64).flatten().cpu()
    if not bool(torch.isfinite(extra_times).all()):
        raise ValueError("target_times must be finite")
    specs = None
    if objects is not None:
        specs = _check_objects(objects)
        if motion != "random" and motion != (0.0, 0.0):
            raise ValueError(f"objects move over a static background: leave motion at its default, got {motion!r}")
        motion = (0.0, 0.0)
        speed = max([math.hypot(*o.velocity) for o in specs], default=0.0)
    if isinstance(image, str):
        photo = load_photograph(image)
    else:
        photo = _image_tensor(image)

    # timeline -----------------------------------------------------------------------------------
    device = torch.device(device)
    g = torch.Generator().manual_seed(int(seed))
    lo_lat, hi_lat = float(latency_range_us[0]), float(latency_range_us[1])
    max_latency = {"none": 0.0, "constant": float(latency_us), "intensity": hi_lat, "intensity_delay": hi_lat}[latency]
    margin = float(exposure_us) if margin_us is None else float(margin_us)
    starts = torch.arange(num_frames, dtype=torch.float64) * float(frame_interval_us) + margin
    ends = starts + float(exposure_us)
    t_end = float(ends[-1]) + margin + max_latency
    dt = float(dt_us) if dt_us is not None else min(_MAX_DT_US, _STEP_PX / max(speed / 1000.0, 1e-12))
    n_main = max(1, math.ceil(t_end / dt - 1e-6))
    n_warm = math.ceil(4 * hi_lat / dt) if latency == "intensity" else 0
    gaps = ((ends[:-1] + starts[1:]) / 2)
    wanted = torch.cat([gaps, extra_times])

    radius = 0.5 * math.hypot(height - 1, width - 1)
    trajectory = _Trajectory(motion, float(max_speed_px_per_ms), max(radius, 1.0), t_end / 2, g)
    span = (min(-n_warm * dt, float(wanted.min()) if wanted.numel() else 0.0),
            max(t_end, float(wanted.max()) if wanted.numel() else 0.0))
    photo = (photo.to(device) * float(brightness)).clamp(0, 1)
    camera: _Camera | _ObjectCamera
    if specs is not None:
        sprites = [_sprite(o, brightness, device) for o in specs]
        motions = [(o.position[0] - o.velocity[0] / 1000.0 * o.time_us, o.position[1] - o.velocity[1] / 1000.0
                    * o.time_us, o.velocity[0] / 1000.0, o.velocity[1] / 1000.0) for o in specs]
        camera = _ObjectCamera(photo, height, width, sprites, motions)
    else:
        # a zoom's scale is exponential in time: size the photograph for the events' timeline, not the warm-up's
        sized = (min(0.0, float(wanted.min()) if wanted.numel() else 0.0), span[1]) if motion == "zoom" else span
        camera = _Camera(photo, height, width, trajectory, sized)

    thresholds = torch.full((height, width), float(threshold), dtype=torch.float32)
    if threshold_sigma > 0:
        mismatch = 1 + float(threshold_sigma) * torch.randn(height, width, generator=g)
        thresholds = (thresholds * mismatch).clamp_min(0.2 * float(threshold))
    thresholds = thresholds.to(device)

    # time stepping ------------------------------------------------------------------------------
    def time_at(k: int) -> float:
        return t_end if k == n_main else k * dt

    def log_of(lum: Tensor) -> Tensor:
        return torch.log(lum.clamp_min(0) + _LOG_EPS)

    starts_l, ends_l = starts.tolist(), ends.tolist()
    sums = torch.zeros(num_frames, 3, height, width, device=device)
    intensity_filter = latency == "intensity"
    lum_prev = camera.luminance_at(time_at(-n_warm))
    log_prev = log_of(lum_prev)
    filtered = log_prev.clone()
    ideal = delayed = None
    rgb_prev: Tensor | None = None
    t_prev = time_at(-n_warm)
    if n_warm == 0:
        ideal = _EventGenerator(log_prev, thresholds)
        delayed = _EventGenerator(filtered, thresholds) if intensity_filter else None
    for k in range(-n_warm + 1, n_main + 1):
        t = time_at(k)
        step = t - t_prev
        overlaps = [i for i in range(num_frames) if t > starts_l[i] and t_prev < ends_l[i]]
        if overlaps:
            rgby = camera.rgby_at(t)
            rgb, lum = rgby[:3], rgby[3]
            if rgb_prev is None:
                rgb_prev = camera.rgby_at(t_prev)[:3]
            for i in overlaps:
                a, b = max(t_prev, starts_l[i]), min(t, ends_l[i])
                m = ((a + b) / 2 - t_prev) / step
                sums[i] += (b - a) * ((1 - m) * rgb_prev + m * rgb)
        else:
            rgb, lum = None, camera.luminance_at(t)
        log_cur = log_of(lum)
        if intensity_filter:
            # exact first-order low-pass update for an input linear over the step
            tau = (lo_lat / (0.5 * (lum + lum_prev)).clamp_min(1e-12)).clamp(lo_lat, hi_lat)
            slope_tau = (log_cur - log_prev) / step * tau
            new_filtered = log_cur - slope_tau + (filtered - log_prev + slope_tau) * torch.exp(-step / tau)
            if delayed is not None:
                delayed.step(filtered, new_filtered, t_prev, step)
            filtered = new_filtered
        if ideal is not None:
            ideal.step(log_prev, log_cur, t_prev, step)
        if k == 0:  # end of the warm-up: the event streams start here
            ideal = _EventGenerator(log_cur, thresholds)
            delayed = _EventGenerator(filtered, thresholds) if intensity_filter else None
        log_prev, lum_prev, rgb_prev, t_prev = log_cur, lum, rgb, t
    assert ideal is not None  # n_main >= 1, so the streams exist

    # frames -------------------------------------------------------------------------------------
    blurry = (sums / float(exposure_us)).clamp(0, 1)
    sharp = camera.render((starts + ends) / 2)
    targets = camera.render(wanted)

    # noise, latency -----------------------------------------------------------------------------
    noise = None
    if noise_rate_hz > 0:
        mean = torch.tensor(float(noise_rate_hz) * t_end * 1e-6 * height * width, dtype=torch.float64)
        n = int(torch.poisson(mean, generator=g))
        noise = (torch.randint(0, height * width, (n,), generator=g).to(device),
                 (torch.rand(n, generator=g, dtype=torch.float64) * t_end).to(device),
                 (torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8).to(device))
    if leak_rate_hz > 0:
        leak = tuple(v.to(device) for v in _leak_events(height, width, t_end, leak_rate_hz, g))
        noise = leak if noise is None else tuple(torch.cat([a, b]) for a, b in zip(noise, leak))
    sensor = (height, width)
    signal = ideal.events(sensor, None)
    ideal_events = _merge(signal, noise)
    lum_blur = luminance(blurry)
    tau_map = (lo_lat / lum_blur.clamp_min(1e-12)).clamp(lo_lat, hi_lat)
    if latency == "intensity":
        assert delayed is not None
        delayed_events = _merge(delayed.events(sensor, None), noise)
        true_latency = tau_map
    elif latency == "intensity_delay":
        true_latency = tau_map
        mids = ((starts + ends) / 2).to(device)
        nearest = torch.searchsorted((mids[1:] + mids[:-1]) / 2, signal.t)  # frame whose mid-exposure is nearest
        delay = true_latency[:, 0].flatten(1)[nearest, signal.y * width + signal.x].double()
        shifted = Events._trusted(signal.x, signal.y, signal.t + delay, signal.p, signal.batch, sensor, 1)
        order = torch.argsort(shifted.t, stable=True)
        shifted = Events._trusted(shifted.x[order], shifted.y[order], shifted.t[order], shifted.p[order],
                                  shifted.batch, sensor, 1)
        delayed_events = _merge(shifted, noise)
    else:
        lat = float(latency_us) if latency == "constant" else 0.0
        shifted = Events._trusted(signal.x, signal.y, signal.t + lat, signal.p, signal.batch, sensor, 1)
        delayed_events = _merge(shifted, noise)
        true_latency = torch.full((num_frames, 1, height, width), lat, device=device)

    if refractory_us > 0:
        ideal_events = apply_refractory(ideal_events, refractory_us)
        delayed_events = apply_refractory(delayed_events, refractory_us)

    config = dict(image=image if isinstance(image, str) else "tensor", num_frames=num_frames, height=height,
                  width=width, exposure_us=float(exposure_us), frame_interval_us=float(frame_interval_us),
                  latency=latency, latency_us=float(latency_us), latency_range_us=[lo_lat, hi_lat],
                  threshold=float(threshold), threshold_sigma=float(threshold_sigma),
                  noise_rate_hz=float(noise_rate_hz), max_speed_px_per_ms=float(max_speed_px_per_ms),
                  motion=motion if isinstance(motion, str) else [float(v) for v in motion],
                  brightness=float(brightness), margin_us=margin, dt_us=dt, t_end_us=t_end,
                  warmup_us=n_warm * dt, photo_scale=camera.scale, seed=int(seed), leak_rate_hz=float(leak_rate_hz),
                  refractory_us=float(refractory_us),
                  objects=None if specs is None else [
                      dict(sprite=_sprite_name(o.sprite), size=list(o.size), position=list(o.position),
                           velocity=list(o.velocity), shape=o.shape, time_us=o.time_us) for o in specs])
    return SimulatedSequence(
        blurry=blurry, sharp=sharp, exposure_start=starts.to(device), exposure_end=ends.to(device),
        ideal_events=ideal_events, delayed_events=delayed_events, true_latency=true_latency.float(),
        target_times=wanted.to(device), target_frames=targets, threshold=float(threshold), seed=int(seed),
        config=config, threshold_map=thresholds[None, None], renderer=camera.render,
    )


def simulate_dataset(names: Sequence[str], *, seed: int = 0, **kwargs: Any) -> list[SimulatedSequence]:
    """One sequence per photograph, each with its own motion (seed ``seed + index``).

    Example:
        >>> seqs = simulate_dataset(["camera", "coins"], num_frames=1, height=16, width=20, exposure_us=2000.0)
        >>> [s.seed for s in seqs]
        [0, 1]
    """
    if isinstance(names, str) or not names:
        raise ValueError(f"names must be a non-empty sequence of photograph names, got {names!r}")
    return [simulate(name, seed=seed + i, **kwargs) for i, name in enumerate(names)]
