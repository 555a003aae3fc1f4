"""Event simulator with known latency, from the photographs scikit-image ships.

A photograph is seen by a camera under a random smooth motion (translation with a gentle
wobble, a slow rotation and zoom, rendered with Kornia warps). At small time steps the
simulator renders the colour frame, takes its luminance, and emits an event each time the
log-luminance of a pixel crosses a multiple of the contrast threshold since its last event,
with the crossing time interpolated linearly inside the step (as ESIM does). Blurry frames are
the mean of the colour frames over each exposure.

Latency models (``latency=``):

- ``"none"``: delayed events are the ideal events.
- ``"constant"``: delayed events are the ideal events stamped ``latency_us`` later.
- ``"intensity_delay"``: each ideal event is delayed by ``τ`` (the formula below) at its pixel,
  evaluated on the blurry frame nearest in time: a clean per-pixel ground truth for evaluating
  latency maps, without the filter's smoothing.
- ``"intensity"``: each pixel's photoreceptor is a first-order low-pass filter on the
  log-luminance whose time constant is inversely proportional to the pixel's intensity,
  ``τ = clip(latency_range_us[0] / I, *latency_range_us)`` with ``I`` the linear intensity in
  [0, 1] (as in v2e and IEBCS): bright pixels (I = 1) lag by ≈ 0.5 ms, dim ones up to 10 ms. The
  delayed events are those of the filtered signal. A first-order filter following a ramp lags
  it by exactly ``τ``, so the true latency map reported is ``τ`` at the pixel's intensity
  averaged over the exposure (the blurry frame's luminance): the quantity a method can estimate.

Everything random comes from one ``torch.Generator`` seeded by ``seed``.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import kornia
import numpy as np
import torch
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = [
    "PHOTOGRAPHS_TRAIN",
    "PHOTOGRAPHS_TEST",
    "load_photograph",
    "simulate",
    "simulate_dataset",
    "SimulatedSequence",
]

# scikit-image photographs stored inside the package (no download). Disjoint splits.
_FILES = {
    "astronaut": "astronaut.png", "coffee": "coffee.png", "chelsea": "chelsea.png", "rocket": "rocket.jpg",
    "camera": "camera.png", "motorcycle_right": "motorcycle_right.png", "brick": "brick.png",
    "gravel": "gravel.png", "motorcycle_left": "motorcycle_left.png", "hubble_deep_field": "hubble_deep_field.jpg",
    "retina": "retina.jpg", "immunohistochemistry": "ihc.png", "moon": "moon.png", "coins": "coins.png",
    "page": "page.png", "text": "text.png", "grass": "grass.png", "cell": "cell.png",
}
PHOTOGRAPHS_TEST = ("astronaut", "coffee", "chelsea", "rocket", "camera", "motorcycle_right", "brick", "gravel")
PHOTOGRAPHS_TRAIN = ("motorcycle_left", "hubble_deep_field", "retina", "immunohistochemistry", "moon", "coins",
                     "page", "text", "grass", "cell")
_LATENCY_MODELS = ("none", "constant", "intensity", "intensity_delay")
_LOG_EPS = 1e-3  # log(I + eps): dark pixels do not fire on noise-level changes


def load_photograph(name: str) -> Tensor:
    """A scikit-image photograph as linear RGB :math:`(3, H, W)` in [0, 1] (grey repeated to 3 channels).

    Example:
        >>> load_photograph("camera").shape
        torch.Size([3, 512, 512])
    """
    if name not in _FILES:
        raise ValueError(f"unknown photograph {name!r}; choose from {sorted(_FILES)}")
    import skimage.data
    import skimage.io

    path = os.path.join(os.path.dirname(skimage.data.__file__), _FILES[name])
    img = np.asarray(skimage.io.imread(path))
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    img = img[..., :3].astype(np.float32)
    img /= 255.0 if img.max() > 1.0 else 1.0
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).contiguous()


@dataclass
class SimulatedSequence:
    """Ground truth and inputs of one simulated sequence of ``F`` frames.

    Attributes:
        blurry: :math:`(F, 3, H, W)` mean of the frames over each exposure, in [0, 1].
        sharp: :math:`(F, 3, H, W)` frames at mid-exposure.
        exposure_start: :math:`(F,)` µs (float64).
        exposure_end: :math:`(F,)` µs.
        ideal_events: events with exact timestamps (one sample, the whole sequence).
        delayed_events: the same scene's events with latency.
        true_latency: :math:`(F, 1, H, W)` µs.
        target_times: :math:`(T,)` µs, times of ``target_frames`` (the gaps' midpoints, then any requested).
        target_frames: :math:`(T, 3, H, W)` sharp frames at ``target_times``.
        threshold: contrast threshold used.
        seed: the seed.
        config: every simulation parameter.
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

    @property
    def num_frames(self) -> int:
        return int(self.blurry.shape[0])

    def _events(self, which: str) -> Events:
        if which not in ("delayed", "ideal"):
            raise ValueError(f"which must be 'delayed' or 'ideal', got {which!r}")
        return self.delayed_events if which == "delayed" else self.ideal_events

    def _windows(self, events: Events, starts: Tensor, ends: Tensor) -> Events:
        parts = [events.window(float(s), float(e)) for s, e in zip(starts, ends)]
        return Events.cat(parts)

    def frames(self, which: str = "delayed", before_us: float = 0.0, after_us: float | None = None) -> EventFrames:
        """Deblurring batch: one sample per frame, events of ``[start - before, end + after)``.

        ``after_us`` defaults to the exposure time, the default latency search range.
        """
        after = float(self.config["exposure_us"]) if after_us is None else after_us
        events = self._windows(self._events(which), self.exposure_start - before_us, self.exposure_end + after)
        return EventFrames(self.blurry, events, self.exposure_start, self.exposure_end, sharp=self.sharp,
                           meta={"which": which, "true_latency": self.true_latency})

    def pairs(self, which: str = "delayed", before_us: float = 0.0, after_us: float | None = None) -> EventFrames:
        """Interpolation batch: sample ``i`` pairs frame ``i`` and ``i + 1``; target = the gap's midpoint."""
        if self.num_frames < 2:
            raise ValueError("pairs() needs a sequence of at least 2 frames")
        after = float(self.config["exposure_us"]) if after_us is None else after_us
        events = self._windows(self._events(which), self.exposure_start[:-1] - before_us,
                               self.exposure_end[1:] + after)
        p = self.num_frames - 1
        return EventFrames(
            self.blurry[:-1], events, self.exposure_start[:-1], self.exposure_end[:-1],
            blurry_next=self.blurry[1:], exposure_start_next=self.exposure_start[1:],
            exposure_end_next=self.exposure_end[1:], target_times=self.target_times[:p, None],
            target_frames=self.target_frames[:p, None], sharp=self.sharp[:-1],
            meta={"which": which, "true_latency": self.true_latency[:-1]},
        )


class _Camera:
    """A smooth random camera trajectory over a photograph, rendered with Kornia."""

    def __init__(self, photo: Tensor, height: int, width: int, speed_px_per_ms: float, duration_us: float,
                 generator: torch.Generator) -> None:
        g = generator
        rnd = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
        angle = float(rnd(1)) * 2 * math.pi
        speed = speed_px_per_ms * (0.8 + 0.4 * float(rnd(1))) / 1000.0  # px/µs
        self.velocity = (speed * math.cos(angle), speed * math.sin(angle))
        # wobble: one slow sinusoid per axis, amplitude up to 15% of the drift over a period
        self.wobble = [(float(rnd(1)) * 0.15 * speed * 40_000, 30_000 + 50_000 * float(rnd(1)),
                        2 * math.pi * float(rnd(1))) for _ in range(2)]
        self.spin = (float(rnd(1)) - 0.5) * 2 * 0.2e-6  # rad/µs (≤ 0.2 mrad/ms)
        self.zoom_rate = (float(rnd(1)) - 0.5) * 2 * 2e-6  # relative scale/ms-ish, tiny
        travel = speed * duration_us + 2 * 0.15 * speed * 40_000
        need = math.hypot(height, width) + 2 * travel + 8
        scale = max(1.0, need / min(photo.shape[-2:]))
        self.photo = torch.nn.functional.interpolate(photo[None], scale_factor=scale, mode="bilinear",
                                                     align_corners=False, antialias=False).clamp(0, 1)
        self.center = (self.photo.shape[-1] / 2.0, self.photo.shape[-2] / 2.0)
        self.size = (height, width)
        self.duration = duration_us

    def render(self, t: float) -> Tensor:
        """Colour frame :math:`(3, H, W)` at time ``t`` (µs from the start)."""
        dx = self.velocity[0] * (t - self.duration / 2)
        dy = self.velocity[1] * (t - self.duration / 2)
        (ax, px, fx), (ay, py, fy) = self.wobble
        dx += ax * math.sin(2 * math.pi * t / px + fx)
        dy += ay * math.sin(2 * math.pi * t / py + fy)
        rot = self.spin * (t - self.duration / 2)
        zoom = 1.0 + self.zoom_rate * (t - self.duration / 2) / 1000.0
        cx, cy = self.center[0] + dx, self.center[1] + dy
        h, w = self.size
        c, s = math.cos(rot) * zoom, math.sin(rot) * zoom
        # destination = A (source - centre) + view centre
        m = torch.tensor([[[c, -s, (w - 1) / 2 - (c * cx - s * cy)],
                           [s, c, (h - 1) / 2 - (s * cx + c * cy)]]], dtype=self.photo.dtype,
                         device=self.photo.device)
        out = kornia.geometry.transform.warp_affine(self.photo, m, dsize=(h, w), mode="bilinear",
                                                    padding_mode="reflection", align_corners=True)
        return out[0].clamp(0, 1)


class _EventGenerator:
    """ESIM-style threshold crossings of a log signal, per pixel, step by step."""

    def __init__(self, log_start: Tensor, thresholds: Tensor) -> None:
        self.ref = log_start.clone()
        self.thr = thresholds
        self.chunks: list[tuple[Tensor, Tensor, Tensor]] = []  # (flat pixel, t, p)

    def step(self, log_prev: Tensor, log_cur: Tensor, t_prev: float, dt: float) -> None:
        diff = log_cur - self.ref
        count = torch.floor(diff.abs() / self.thr)
        fired = torch.nonzero(count.flatten() > 0).flatten()
        if fired.numel() == 0:
            return
        n = count.flatten()[fired].long()
        sign = torch.sign(diff.flatten()[fired])
        pix = torch.repeat_interleave(fired, n)
        sgn = torch.repeat_interleave(sign, n)
        start = torch.cumsum(n, 0) - n
        k = torch.arange(int(n.sum()), device=n.device) - torch.repeat_interleave(start, n) + 1
        level = self.ref.flatten()[pix] + sgn * k * self.thr.flatten()[pix]
        lp, lc = log_prev.flatten()[pix], log_cur.flatten()[pix]
        frac = ((level - lp) / (lc - lp).where((lc - lp).abs() > 1e-12, torch.ones_like(lc))).clamp(0, 1)
        self.chunks.append((pix, t_prev + frac.double() * dt, sgn.to(torch.int8)))
        ref = self.ref.flatten()
        ref[fired] += sign * n * self.thr.flatten()[fired]

    def events(self, sensor_size: tuple[int, int], extra: tuple[Tensor, Tensor, Tensor] | None) -> Events:
        chunks = self.chunks + ([extra] if extra is not None else [])
        _, width = sensor_size
        if chunks:
            pix = torch.cat([c[0] for c in chunks])
            t = torch.cat([c[1] for c in chunks])
            p = torch.cat([c[2] for c in chunks])
        else:
            pix, t, p = (torch.zeros(0, dtype=torch.long), torch.zeros(0, dtype=torch.float64),
                         torch.zeros(0, dtype=torch.int8))
        return Events(pix % width, pix // width, t, p, sensor_size=sensor_size, sort=True)


def _luminance(rgb: Tensor) -> Tensor:
    return (0.299 * rgb[0] + 0.587 * rgb[1] + 0.114 * rgb[2]).clamp_min(0)


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
    speed_px_per_ms: float = 1.0,
    brightness: float = 1.0,
    margin_us: float | None = None,
    target_times: Sequence[float] | None = None,
    dt_us: float | None = None,
    seed: int = 0,
    device: str | torch.device = "cpu",
) -> SimulatedSequence:
    """Simulate blurry frames and their ideal and delayed events.

    Args:
        image: a photograph name (:data:`PHOTOGRAPHS_TRAIN`, :data:`PHOTOGRAPHS_TEST`) or an RGB
            tensor :math:`(3, H, W)` in [0, 1].
        num_frames: number of consecutive exposures ``F``.
        height: sensor height ``H``.
        width: sensor width ``W``.
        exposure_us: exposure time of each frame.
        frame_interval_us: time between exposure starts (≥ exposure).
        latency: ``"none"``, ``"constant"``, ``"intensity"`` or ``"intensity_delay"`` (see the module docstring).
        latency_us: the constant latency.
        latency_range_us: ``(bright, dim)`` latency limits of the intensity model.
        threshold: contrast threshold (log units).
        threshold_sigma: relative per-pixel threshold mismatch (Gaussian std).
        noise_rate_hz: shot-noise events per pixel per second (random polarity), in both streams.
        speed_px_per_ms: mean image speed; 1 px/ms blurs 20 px in a 20 ms exposure.
        brightness: multiplies the scene's linear intensity (dim scenes are late scenes).
        margin_us: events before the first exposure; after the last one the simulation runs
            ``exposure_us`` plus the largest latency (so the default latency search sees every late event).
        target_times: extra times (µs) for ground-truth sharp frames; the gaps' midpoints come first.
        dt_us: time step; default keeps the motion ≤ 0.25 px per step, at most 200 µs.
        seed: random seed (motion, mismatch, noise).
        device: where to simulate.

    Returns:
        a :class:`SimulatedSequence`.

    Example:
        >>> seq = simulate("camera", num_frames=1, height=32, width=40, exposure_us=5000.0, seed=1)
        >>> seq.blurry.shape, seq.true_latency.unique().tolist()
        (torch.Size([1, 3, 32, 40]), [4000.0])
    """
    if latency not in _LATENCY_MODELS:
        raise ValueError(f"latency must be one of {_LATENCY_MODELS}, got {latency!r}")
    if exposure_us <= 0:
        raise ValueError(f"exposure_us must be positive, got {exposure_us}")
    if frame_interval_us < exposure_us:
        raise ValueError(f"frame_interval_us ({frame_interval_us}) must be >= exposure_us ({exposure_us})")
    if threshold <= 0:
        raise ValueError(f"threshold must be positive, got {threshold}")
    if num_frames < 1 or height < 2 or width < 2:
        raise ValueError(f"need num_frames >= 1 and a sensor of at least 2x2, got {num_frames}, {height}x{width}")
    if latency == "constant" and latency_us < 0:
        raise ValueError(f"latency_us must be >= 0, got {latency_us}")
    lo_lat, hi_lat = latency_range_us
    if latency.startswith("intensity") and not 0 < lo_lat <= hi_lat:
        raise ValueError(f"latency_range_us must be 0 < bright <= dim, got {latency_range_us}")
    if brightness <= 0 or speed_px_per_ms < 0 or noise_rate_hz < 0 or threshold_sigma < 0:
        raise ValueError("brightness must be positive and speed, noise rate, threshold_sigma non-negative")

    device = torch.device(device)
    g = torch.Generator().manual_seed(seed)
    photo = load_photograph(image) if isinstance(image, str) else image.float()
    if photo.dim() != 3 or photo.shape[0] != 3:
        raise ValueError(f"image must be a photograph name or an RGB tensor (3, H, W), got {tuple(photo.shape)}")
    max_latency = {"none": 0.0, "constant": latency_us, "intensity": hi_lat, "intensity_delay": hi_lat}[latency]
    before = exposure_us if margin_us is None else margin_us
    starts = torch.arange(num_frames, dtype=torch.float64) * frame_interval_us + before
    ends = starts + exposure_us
    t_end = float(ends[-1]) + exposure_us + max_latency + 1000.0
    gaps = ((ends[:-1] + starts[1:]) / 2).tolist()
    wanted = gaps + [float(t) for t in (target_times or [])]

    camera = _Camera(photo.to(device), height, width, speed_px_per_ms, t_end, g)
    dt = dt_us if dt_us is not None else min(200.0, 0.25 / max(speed_px_per_ms * 1.2 / 1000.0, 1e-9))
    steps = int(math.ceil(t_end / dt))

    thresholds = torch.full((height, width), threshold)
    if threshold_sigma > 0:
        thresholds = thresholds * (1 + threshold_sigma * torch.randn(height, width, generator=g))
        thresholds = thresholds.clamp_min(0.2 * threshold)
    thresholds = thresholds.to(device)

    def log_of(rgb: Tensor) -> tuple[Tensor, Tensor]:
        lum = _luminance(rgb) * brightness
        return torch.log(lum + _LOG_EPS), lum

    frame0 = camera.render(0.0)
    log_prev, lum_prev = log_of(frame0)
    ideal = _EventGenerator(log_prev, thresholds)
    filtered = log_prev.clone()
    delayed = _EventGenerator(log_prev, thresholds) if latency == "intensity" else None
    sums = torch.zeros(num_frames, 3, height, width, device=device)
    counts = torch.zeros(num_frames, device=device)
    starts_l, ends_l = starts.tolist(), ends.tolist()

    def accumulate(frame: Tensor, t: float) -> None:
        for i, (s, e) in enumerate(zip(starts_l, ends_l)):
            if s <= t <= e:
                sums[i] += frame
                counts[i] += 1

    accumulate(frame0, 0.0)
    t_prev = 0.0
    for k in range(1, steps + 1):
        t = min(k * dt, t_end)
        frame = camera.render(t)
        log_cur, lum_cur = log_of(frame)
        ideal.step(log_prev, log_cur, t_prev, t - t_prev)
        if delayed is not None:
            tau = (lo_lat / lum_cur.clamp_min(1e-6)).clamp(lo_lat, hi_lat)
            new_filtered = filtered + (1 - torch.exp(-(t - t_prev) / tau)) * (log_cur - filtered)
            delayed.step(filtered, new_filtered, t_prev, t - t_prev)
            filtered = new_filtered
        accumulate(frame, t)
        log_prev, t_prev = log_cur, t

    # sample each exposure finely even if dt is coarse relative to it
    for i in range(num_frames):
        if counts[i] < 8:
            for t in torch.linspace(starts_l[i], ends_l[i], 16).tolist():
                sums[i] += camera.render(t)
                counts[i] += 1
    blurry = (sums / counts.view(-1, 1, 1, 1)) * brightness
    sharp = torch.stack([camera.render((s + e) / 2) for s, e in zip(starts_l, ends_l)]) * brightness
    targets = (torch.stack([camera.render(t) for t in wanted]) * brightness if wanted
               else torch.zeros(0, 3, height, width, device=device))

    noise = None
    if noise_rate_hz > 0:
        n = int(torch.poisson(torch.tensor(noise_rate_hz * t_end * 1e-6 * height * width, dtype=torch.float64),
                              generator=g))
        noise = (torch.randint(0, height * width, (n,), generator=g).to(device),
                 (torch.rand(n, generator=g, dtype=torch.float64) * t_end).to(device),
                 (torch.randint(0, 2, (n,), generator=g) * 2 - 1).to(torch.int8).to(device))
    ideal_events = ideal.events((height, width), noise)
    if latency == "intensity":
        assert delayed is not None
        delayed_events = delayed.events((height, width), noise)
        lum_blur = (0.299 * blurry[:, 0] + 0.587 * blurry[:, 1] + 0.114 * blurry[:, 2]).unsqueeze(1)
        true_latency = (lo_lat / lum_blur.clamp_min(1e-6)).clamp(lo_lat, hi_lat)
    elif latency == "intensity_delay":
        lum_blur = (0.299 * blurry[:, 0] + 0.587 * blurry[:, 1] + 0.114 * blurry[:, 2]).unsqueeze(1)
        true_latency = (lo_lat / lum_blur.clamp_min(1e-6)).clamp(lo_lat, hi_lat)
        # each signal event is delayed by the map of the frame nearest in time, at its pixel
        signal = ideal.events((height, width), None)
        mids = ((starts + ends) / 2).to(device)
        nearest = (signal.t[:, None] - mids[None]).abs().argmin(1)
        delay = true_latency[:, 0].flatten(1)[nearest, signal.y * width + signal.x].double()
        parts = [Events._trusted(signal.x, signal.y, signal.t + delay, signal.p, signal.batch, (height, width), 1)]
        if noise is not None:
            parts.append(Events._trusted(noise[0] % width, noise[0] // width, noise[1], noise[2],
                                         torch.zeros_like(noise[0]), (height, width), 1))
        cat = Events.cat(parts)
        delayed_events = Events(cat.x, cat.y, cat.t, cat.p, sensor_size=(height, width), sort=True)
    else:
        lat = latency_us if latency == "constant" else 0.0
        if noise is not None and lat:
            # noise is not delayed: add it after shifting the signal events
            signal = ideal.events((height, width), None)
            shifted = Events._trusted(signal.x, signal.y, signal.t + lat, signal.p, signal.batch,
                                      signal.sensor_size, 1)
            delayed_events = Events.cat([shifted, Events._trusted(noise[0] % width, noise[0] // width, noise[1],
                                                                  noise[2], torch.zeros_like(noise[0]),
                                                                  (height, width), 1)])
            delayed_events = Events(delayed_events.x, delayed_events.y, delayed_events.t, delayed_events.p,
                                    sensor_size=(height, width), sort=True)
        else:
            delayed_events = Events._trusted(ideal_events.x, ideal_events.y, ideal_events.t + lat, ideal_events.p,
                                             ideal_events.batch, (height, width), 1)
        true_latency = torch.full((num_frames, 1, height, width), lat, device=device)

    config = dict(image=image if isinstance(image, str) else "tensor", num_frames=num_frames, height=height,
                  width=width, exposure_us=exposure_us, frame_interval_us=frame_interval_us, latency=latency,
                  latency_us=latency_us, latency_range_us=tuple(latency_range_us), threshold=threshold,
                  threshold_sigma=threshold_sigma, noise_rate_hz=noise_rate_hz, speed_px_per_ms=speed_px_per_ms,
                  brightness=brightness, margin_us=before, dt_us=dt, seed=seed)
    return SimulatedSequence(
        blurry=blurry.clamp(0, 1), sharp=sharp.clamp(0, 1), exposure_start=starts.to(device),
        exposure_end=ends.to(device), ideal_events=ideal_events, delayed_events=delayed_events,
        true_latency=true_latency.float(), target_times=torch.tensor(wanted, dtype=torch.float64, device=device),
        target_frames=targets.clamp(0, 1), threshold=threshold, seed=seed, config=config,
    )


def simulate_dataset(names: Sequence[str], *, seed: int = 0, **kwargs: Any) -> list[SimulatedSequence]:
    """One sequence per photograph, each with its own motion (seed + index)."""
    return [simulate(name, seed=seed + i, **kwargs) for i, name in enumerate(names)]
