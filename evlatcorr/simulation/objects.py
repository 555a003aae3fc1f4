"""Moving objects: :class:`ObjectSpec`, their soft-edged sprites, and a still view with sprites composited over it."""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import kornia
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from evlatcorr.simulation.motion import Camera, Trajectory
from evlatcorr.simulation.photographs import image_tensor, load_photograph, luminance

__all__ = ["OBJECT_SHAPES", "ObjectCamera", "ObjectSpec", "check_objects", "object_camera", "sprite_name"]

OBJECT_SHAPES = ("disc", "rect")


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


class ObjectCamera:
    """A static background with sprites composited over it (alpha over), same interface as :class:`Camera`.

    Args:
        background: colour :math:`(3, h, w)`; the static view of it is rendered as by a still camera.
        sprites: premultiplied ``(R α, G α, B α, Y α, α)`` images :math:`(5, h_i, w_i)`, drawn in order
            (later ones on top).
        motions: ``(x0, y0, vx, vy)`` per sprite: the sprite's centre ``(x0, y0) + (vx, vy) t`` on the
            sensor at time ``t`` (px, px/µs).
    """

    def __init__(self, background: Tensor, height: int, width: int, sprites: Sequence[Tensor],
                 motions: Sequence[tuple[float, float, float, float]]) -> None:
        still = Camera(background, height, width, Trajectory((0.0, 0.0), 0.0, 1.0, 0.0, torch.Generator()),
                       (0.0, 0.0))
        self.size = (height, width)
        self.scale = still.scale
        self.background = still.rgby_at(0.0)[None]  # (1, 4, H, W)
        self.rgby = self.background  # dtype / device, as Camera
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


def object_camera(background: Tensor, height: int, width: int, specs: Sequence[ObjectSpec], brightness: float,
                  device: torch.device) -> ObjectCamera:
    """The :class:`ObjectCamera` of checked ``specs`` (velocities px/ms) over ``background``, on ``device``."""
    sprites = [_sprite(o, brightness, device) for o in specs]
    motions = [(o.position[0] - o.velocity[0] / 1000.0 * o.time_us, o.position[1] - o.velocity[1] / 1000.0
                * o.time_us, o.velocity[0] / 1000.0, o.velocity[1] / 1000.0) for o in specs]
    return ObjectCamera(background, height, width, sprites, motions)


def _sprite_rgb(spec: ObjectSpec) -> Tensor:
    """The sprite's colour :math:`(3, h, w)` at the object's ``size``, centre-cropped to its aspect ratio."""
    from evlatcorr.scenes import procedural_scene

    h, w = spec.size
    if isinstance(spec.sprite, tuple):
        kind, seed = spec.sprite
        rgb = procedural_scene(kind, max(h, 8), max(w, 8), seed)
    else:
        rgb = load_photograph(spec.sprite) if isinstance(spec.sprite, str) else image_tensor(spec.sprite)
    ph, pw = rgb.shape[-2:]
    if ph * w > pw * h:  # centre crop to the object's aspect ratio
        ch = max(1, round(pw * h / w))
        rgb = rgb[:, (ph - ch) // 2:(ph - ch) // 2 + ch]
    else:
        cw = max(1, round(ph * w / h))
        rgb = rgb[:, :, (pw - cw) // 2:(pw - cw) // 2 + cw]
    if tuple(rgb.shape[-2:]) != (h, w):
        rgb = F.interpolate(rgb[None], size=(h, w), mode="bilinear", align_corners=False, antialias=True)[0]
    return rgb


def _sprite(spec: ObjectSpec, brightness: float, device: torch.device) -> Tensor:
    """Premultiplied ``(R α, G α, B α, Y α, α)`` image :math:`(5, h + 4, w + 4)` of an object (2 px clear border)."""
    h, w = spec.size
    rgb = (_sprite_rgb(spec).to(device) * float(brightness)).clamp(0, 1)
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


def sprite_name(sprite: str | tuple[str, int] | Tensor) -> str | list[Any]:
    """JSON-serialisable description of a sprite: its name, ``[kind, seed]`` or ``"tensor"``."""
    return sprite if isinstance(sprite, str) else list(sprite) if isinstance(sprite, tuple) else "tensor"


def check_objects(objects: Sequence[ObjectSpec]) -> list[ObjectSpec]:
    """Checked copies of ``objects``: sizes as ints, positions, velocities and times as floats (``ValueError``)."""
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
        out.append(ObjectSpec(_check_sprite(i, spec.sprite), size, pos, vel, spec.shape, time_us))
    return out


def _check_sprite(i: int, sprite: Any) -> str | tuple[str, int] | Tensor:
    """``objects[i].sprite`` checked; a procedural scene is normalised to ``(str kind, int seed)``."""
    if isinstance(sprite, (tuple, list)):
        from evlatcorr.scenes import PROCEDURAL_SCENES

        if (len(sprite) != 2 or sprite[0] not in PROCEDURAL_SCENES or isinstance(sprite[1], bool)
                or not isinstance(sprite[1], (int, np.integer))):
            raise ValueError(f"objects[{i}].sprite as a procedural scene must be (kind, seed) with kind in "
                             f"{PROCEDURAL_SCENES} and an integer seed, got {sprite!r}")
        return (str(sprite[0]), int(sprite[1]))
    if not isinstance(sprite, (str, Tensor)):
        raise ValueError(f"objects[{i}].sprite must be a photograph name, a procedural (kind, seed) or an "
                         f"image tensor, got {type(sprite).__name__}")
    return sprite
