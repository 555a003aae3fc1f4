"""Camera motion: smooth trajectories (drift, wobble, rotation, zoom) and the moving view of a photograph."""

from __future__ import annotations

import math

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from evlatcorr.simulation.photographs import luminance

__all__ = ["MOTIONS", "Camera", "Trajectory"]

MOTIONS = ("random", "rotation", "zoom")  # named motions; a (vx, vy) tuple is a constant translation
# the most pixels the photograph is upsampled to (1 GB as float32 RGB + luminance): past it the path over the
# timeline (a zoom compounding over a long sequence) is refused rather than allocated
MAX_PHOTO_PIXELS = 64_000_000


class Trajectory:
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
            self._draw_random(max_speed_px_per_ms / 1000.0, radius, generator)
        else:
            self.drift = (float(motion[0]) / 1000.0, float(motion[1]) / 1000.0)

    def _draw_random(self, vmax: float, radius: float, generator: torch.Generator) -> None:
        """The ``"random"`` motion, ``vmax`` in px/µs (the draws' order fixes the motion a seed gives)."""
        u = torch.rand(17, generator=generator, dtype=torch.float64).tolist()
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


class Camera:
    """Renders the view of a photograph along a trajectory with Kornia (source coordinates = photo pixels).

    The photograph is upsampled when the path over ``span`` (µs) would see past its edges.
    """

    def __init__(self, photo: Tensor, height: int, width: int, trajectory: Trajectory, span: tuple[float, float]):
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
            if size[0] * size[1] > MAX_PHOTO_PIXELS:
                raise ValueError(f"the motion over {(span[1] - span[0]) / 1000:.0f} ms sees {self.scale:.3g}x past "
                                 f"the photograph's edges (it would be upsampled to {size[1]}x{size[0]} pixels, over "
                                 f"{MAX_PHOTO_PIXELS // 1_000_000} M): simulate fewer or shorter frames, or a slower "
                                 "motion")
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
