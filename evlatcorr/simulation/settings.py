"""The arguments of :func:`~evlatcorr.simulate.simulate`: checked once, at the boundary, and normalised."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor

from evlatcorr.simulation.latency import LATENCY_MODELS, MAX_LATENCY_US
from evlatcorr.simulation.motion import MOTIONS
from evlatcorr.simulation.objects import ObjectSpec, check_objects

__all__ = ["Settings", "check_settings"]


@dataclass(frozen=True)
class Settings:
    """Checked simulation arguments: numbers as floats, ``motion`` a name or a ``(vx, vy)`` float pair.

    ``speed`` is the fastest image motion, px/ms, that sets the time step; ``image``, ``margin_us``,
    ``dt_us``, ``seed`` and ``device`` are as given.
    """

    image: str | Tensor
    num_frames: int
    height: int
    width: int
    exposure_us: float
    frame_interval_us: float
    latency: str
    latency_us: float
    latency_range_us: tuple[float, float]
    threshold: float
    threshold_sigma: float
    noise_rate_hz: float
    max_speed_px_per_ms: float
    motion: str | tuple[float, float]
    speed: float
    brightness: float
    margin_us: float | None
    target_times: Tensor
    dt_us: float | None
    seed: int
    device: str | torch.device
    objects: list[ObjectSpec] | None
    leak_rate_hz: float
    refractory_us: float


_NUMBERS = ("exposure_us", "frame_interval_us", "latency_us", "threshold", "threshold_sigma", "noise_rate_hz",
            "max_speed_px_per_ms", "brightness", "leak_rate_hz", "refractory_us")
_NON_NEGATIVE = ("threshold_sigma", "noise_rate_hz", "max_speed_px_per_ms", "leak_rate_hz", "refractory_us")


def check_settings(image: str | Tensor, **kwargs: Any) -> Settings:
    """Check every keyword argument of ``simulate`` (``ValueError`` naming the first bad one) into :class:`Settings`.

    The image itself is checked when it is loaded.
    """
    if kwargs["latency"] not in LATENCY_MODELS:
        raise ValueError(f"latency must be one of {LATENCY_MODELS}, got {kwargs['latency']!r}")
    num_frames, height, width = kwargs["num_frames"], kwargs["height"], kwargs["width"]
    if not isinstance(num_frames, int) or num_frames < 1:
        raise ValueError(f"num_frames must be a positive integer, got {num_frames}")
    if not isinstance(height, int) or not isinstance(width, int) or height < 2 or width < 2:
        raise ValueError(f"height and width must be integers >= 2, got {height}x{width}")
    numbers = _finite_numbers({key: kwargs[key] for key in _NUMBERS})
    _check_ranges(numbers, kwargs["latency_range_us"])
    motion, speed = _check_motion(kwargs["motion"], numbers["max_speed_px_per_ms"])
    margin_us, dt_us = kwargs["margin_us"], kwargs["dt_us"]
    if margin_us is not None and not (math.isfinite(margin_us) and margin_us >= 0):
        raise ValueError(f"margin_us must be >= 0, got {margin_us}")
    if dt_us is not None and not (math.isfinite(dt_us) and dt_us > 0):
        raise ValueError(f"dt_us must be positive, got {dt_us}")
    target_times = kwargs["target_times"]
    extra_times = torch.as_tensor([] if target_times is None else target_times, dtype=torch.float64).flatten().cpu()
    if not bool(torch.isfinite(extra_times).all()):
        raise ValueError("target_times must be finite")
    specs = None
    if kwargs["objects"] is not None:
        specs = check_objects(kwargs["objects"])
        if motion != "random" and motion != (0.0, 0.0):
            raise ValueError(f"objects move over a static background: leave motion at its default, got {motion!r}")
        motion = (0.0, 0.0)
        speed = max([math.hypot(*o.velocity) for o in specs], default=0.0)
    latency_range = (float(kwargs["latency_range_us"][0]), float(kwargs["latency_range_us"][1]))
    return Settings(image=image, num_frames=num_frames, height=height, width=width, latency=kwargs["latency"],
                    latency_range_us=latency_range, motion=motion, speed=speed, margin_us=margin_us,
                    target_times=extra_times, dt_us=dt_us, seed=kwargs["seed"], device=kwargs["device"],
                    objects=specs, **numbers)


def _finite_numbers(values: dict[str, Any]) -> dict[str, float]:
    """``values`` as floats, in their order; a ``ValueError`` names the first that is not a finite number."""
    numbers = dict(values)
    for key, value in values.items():
        try:
            numbers[key] = float(value)
        except (TypeError, ValueError):
            raise ValueError(f"{key} must be a finite number, got {value!r}") from None
        if not math.isfinite(numbers[key]):
            raise ValueError(f"{key} must be a finite number, got {value!r}")
    return numbers


def _check_ranges(numbers: dict[str, float], latency_range_us: Sequence[float]) -> None:
    """Each number, and the ``(bright, dim)`` latency range, within its physical range."""
    exposure_us = numbers["exposure_us"]
    if exposure_us <= 0:
        raise ValueError(f"exposure_us must be positive, got {exposure_us}")
    if numbers["frame_interval_us"] < exposure_us:
        raise ValueError(f"frame_interval_us ({numbers['frame_interval_us']}) must be >= exposure_us ({exposure_us})")
    if numbers["threshold"] <= 0:
        raise ValueError(f"threshold must be positive, got {numbers['threshold']}")
    if not 0 <= numbers["latency_us"] <= MAX_LATENCY_US:
        raise ValueError(f"latency_us must be in [0, {MAX_LATENCY_US:.0f}] (event-camera latencies are µs to tens of "
                         f"ms; the sequence is simulated that much longer), got {numbers['latency_us']}")
    if (len(latency_range_us) != 2 or not 0 < float(latency_range_us[0]) <= float(latency_range_us[1])
            <= MAX_LATENCY_US):
        raise ValueError(f"latency_range_us must be (bright, dim) with 0 < bright <= dim <= {MAX_LATENCY_US:.0f}, "
                         f"got {latency_range_us}")
    for key in _NON_NEGATIVE:
        if numbers[key] < 0:
            raise ValueError(f"{key} must be >= 0, got {numbers[key]}")
    if numbers["brightness"] <= 0:
        raise ValueError(f"brightness must be positive, got {numbers['brightness']}")


def _check_motion(motion: Any, max_speed_px_per_ms: float) -> tuple[str | tuple[float, float], float]:
    """A motion name or a finite ``(vx, vy)`` px/ms as floats, with the image speed it sets, px/ms."""
    if isinstance(motion, str):
        if motion not in MOTIONS:
            raise ValueError(f"motion must be one of {MOTIONS} or a (vx, vy) translation in px/ms, got {motion!r}")
        return motion, float(max_speed_px_per_ms)
    try:
        velocity = (float(motion[0]), float(motion[1])) if len(motion) == 2 else ()
    except (TypeError, ValueError):
        velocity = ()
    if len(velocity) != 2 or not all(math.isfinite(v) for v in velocity):
        raise ValueError(f"motion must be one of {MOTIONS} or a (vx, vy) translation in px/ms, got {motion!r}")
    return velocity, math.hypot(*velocity)

