"""The :func:`simulate` entry point: checks its arguments, then films, steps, delays and packs one sequence."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from evlatcorr.events import Events
from evlatcorr.simulation.generator import pixel_thresholds
from evlatcorr.simulation.latency import delay_events, true_latency_map
from evlatcorr.simulation.motion import Camera, Trajectory
from evlatcorr.simulation.noise import NoiseEvents, apply_refractory, background_noise, merge_noise
from evlatcorr.simulation.objects import ObjectCamera, ObjectSpec, object_camera, sprite_name
from evlatcorr.simulation.photographs import source_image
from evlatcorr.simulation.sequence import SimulatedSequence
from evlatcorr.simulation.settings import Settings, check_settings
from evlatcorr.simulation.stepping import Exposures, Stepped, step_through
from evlatcorr.simulation.timeline import Timeline, make_timeline

__all__ = ["simulate", "simulate_dataset"]


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
    """Simulate blurry colour frames and their ideal and delayed events (see :mod:`evlatcorr.simulate`).

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
    s = check_settings(
        image, num_frames=num_frames, height=height, width=width, exposure_us=exposure_us,
        frame_interval_us=frame_interval_us, latency=latency, latency_us=latency_us,
        latency_range_us=latency_range_us, threshold=threshold, threshold_sigma=threshold_sigma,
        noise_rate_hz=noise_rate_hz, max_speed_px_per_ms=max_speed_px_per_ms, motion=motion, brightness=brightness,
        margin_us=margin_us, target_times=target_times, dt_us=dt_us, seed=seed, device=device, objects=objects,
        leak_rate_hz=leak_rate_hz, refractory_us=refractory_us)
    photo = source_image(image)
    device = torch.device(device)
    g = torch.Generator().manual_seed(int(seed))  # drawn from in a fixed order: motion, thresholds, noise
    timeline = make_timeline(s)
    camera = _camera(s, photo, timeline, g, device)
    thresholds = pixel_thresholds(s.height, s.width, s.threshold, s.threshold_sigma, g, device)
    photoreceptor = s.latency_range_us if s.latency == "intensity" else None
    stepped = step_through(camera, timeline, Exposures(timeline.starts, timeline.ends, (s.height, s.width), device),
                           thresholds, photoreceptor)
    blurry = stepped.exposures.blurry(s.exposure_us)
    sharp = camera.render(timeline.mids)
    targets = camera.render(timeline.targets)
    noise = background_noise(s.height, s.width, timeline.t_end, s.noise_rate_hz, s.leak_rate_hz, g, device)
    ideal_events, delayed_events, true_latency = _streams(s, stepped, blurry, timeline.mids.to(device), noise)
    return SimulatedSequence(
        blurry=blurry, sharp=sharp, exposure_start=timeline.starts.to(device),
        exposure_end=timeline.ends.to(device), ideal_events=ideal_events, delayed_events=delayed_events,
        true_latency=true_latency.float(), target_times=timeline.targets.to(device), target_frames=targets,
        threshold=float(s.threshold), seed=int(seed), config=_config(s, timeline, camera.scale),
        threshold_map=thresholds[None, None], renderer=camera.render,
    )


def _camera(s: Settings, photo: Tensor, timeline: Timeline, g: torch.Generator,
            device: torch.device) -> Camera | ObjectCamera:
    """The moving view of ``photo``, or a still view of it with the objects moving over it."""
    radius = 0.5 * math.hypot(s.height - 1, s.width - 1)
    trajectory = Trajectory(s.motion, float(s.max_speed_px_per_ms), max(radius, 1.0), timeline.t_end / 2, g)
    photo = (photo.to(device) * float(s.brightness)).clamp(0, 1)
    if s.objects is not None:
        return object_camera(photo, s.height, s.width, s.objects, s.brightness, device)
    # a zoom's scale is exponential in time: size the photograph for the events' timeline, not the warm-up's
    span = timeline.span_from_zero() if s.motion == "zoom" else timeline.span()
    return Camera(photo, s.height, s.width, trajectory, span)


def _streams(s: Settings, stepped: Stepped, blurry: Tensor, mids: Tensor,
             noise: NoiseEvents | None) -> tuple[Events, Events, Tensor]:
    """Ideal and delayed events (noise merged, refractory period applied) and the true latency map."""
    sensor = (s.height, s.width)
    signal = stepped.ideal.events(sensor, None)
    ideal_events = merge_noise(signal, noise)
    true_latency = true_latency_map(s.latency, blurry, s.latency_us, *s.latency_range_us)
    if stepped.delayed is not None:  # the photoreceptor's filtered signal
        delayed_signal = stepped.delayed.events(sensor, None)
    else:
        delayed_signal = delay_events(s.latency, signal, true_latency, mids, s.latency_us)
    delayed_events = merge_noise(delayed_signal, noise)
    if s.refractory_us > 0:
        ideal_events = apply_refractory(ideal_events, s.refractory_us)
        delayed_events = apply_refractory(delayed_events, s.refractory_us)
    return ideal_events, delayed_events, true_latency


def _config(s: Settings, timeline: Timeline, photo_scale: float) -> dict[str, Any]:
    """Every simulation parameter, JSON-serialisable (stored with the sequence, e.g. in HDF5 files)."""
    lo_lat, hi_lat = s.latency_range_us
    return dict(
        image=s.image if isinstance(s.image, str) else "tensor", num_frames=s.num_frames, height=s.height,
        width=s.width, exposure_us=float(s.exposure_us), frame_interval_us=float(s.frame_interval_us),
        latency=s.latency, latency_us=float(s.latency_us), latency_range_us=[lo_lat, hi_lat],
        threshold=float(s.threshold), threshold_sigma=float(s.threshold_sigma),
        noise_rate_hz=float(s.noise_rate_hz), max_speed_px_per_ms=float(s.max_speed_px_per_ms),
        motion=s.motion if isinstance(s.motion, str) else [float(v) for v in s.motion],
        brightness=float(s.brightness), margin_us=timeline.margin, dt_us=timeline.dt, t_end_us=timeline.t_end,
        warmup_us=timeline.n_warm * timeline.dt, photo_scale=photo_scale, seed=int(s.seed),
        leak_rate_hz=float(s.leak_rate_hz), refractory_us=float(s.refractory_us),
        objects=None if s.objects is None else [
            dict(sprite=sprite_name(o.sprite), size=list(o.size), position=list(o.position),
                 velocity=list(o.velocity), shape=o.shape, time_us=o.time_us) for o in s.objects])


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
