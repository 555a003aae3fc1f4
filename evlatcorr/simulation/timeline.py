"""The simulation's time axis: exposures, the time step, the photoreceptor's warm-up and the target times."""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from evlatcorr.simulation.latency import largest_latency
from evlatcorr.simulation.settings import Settings

__all__ = ["Timeline", "make_timeline"]

_MAX_DT_US = 200.0  # longest time step, whatever the motion
_STEP_PX = 0.3  # longest image motion per step


@dataclass(frozen=True)
class Timeline:
    """Times in µs; the events start at 0 and steps ``k = -n_warm .. n_main`` are at :meth:`time_at`.

    Attributes:
        starts: :math:`(F,)` exposure starts (float64, CPU).
        ends: :math:`(F,)` exposure ends.
        margin: events simulated before the first exposure and (plus the largest latency) after the last.
        t_end: end of the events.
        dt: time step.
        n_main: steps from 0 to ``t_end`` (the last one is shortened to end exactly there).
        n_warm: steps of the photoreceptor's warm-up before 0.
        targets: :math:`(T,)` times of the ground-truth sharp frames (gaps' midpoints, then those requested).
    """

    starts: Tensor
    ends: Tensor
    margin: float
    t_end: float
    dt: float
    n_main: int
    n_warm: int
    targets: Tensor

    def time_at(self, k: int) -> float:
        """Time of step ``k``."""
        return self.t_end if k == self.n_main else k * self.dt

    @property
    def mids(self) -> Tensor:
        """Mid-exposure times :math:`(F,)`."""
        return (self.starts + self.ends) / 2

    def span(self) -> tuple[float, float]:
        """First and last time the camera is looked at: warm-up, events and target times."""
        wanted = self.targets
        return (min(-self.n_warm * self.dt, float(wanted.min()) if wanted.numel() else 0.0),
                max(self.t_end, float(wanted.max()) if wanted.numel() else 0.0))

    def span_from_zero(self) -> tuple[float, float]:
        """:meth:`span` without the warm-up (a zoom grows exponentially: sizing for it would waste memory)."""
        wanted = self.targets
        return (min(0.0, float(wanted.min()) if wanted.numel() else 0.0), self.span()[1])


def make_timeline(settings: Settings) -> Timeline:
    """Exposures after ``margin``, events until ``margin`` plus the largest latency after the last one.

    The default step moves the image by at most ``0.3`` px (and is at most 200 µs); the
    ``"intensity"`` model warms up for ``4 τ_max`` so its filter starts in its steady state.
    """
    s = settings
    hi_lat = s.latency_range_us[1]
    max_latency = largest_latency(s.latency, s.latency_us, hi_lat)
    margin = float(s.exposure_us) if s.margin_us is None else float(s.margin_us)
    starts = torch.arange(s.num_frames, dtype=torch.float64) * float(s.frame_interval_us) + margin
    ends = starts + float(s.exposure_us)
    t_end = float(ends[-1]) + margin + max_latency
    dt = float(s.dt_us) if s.dt_us is not None else min(_MAX_DT_US, _STEP_PX / max(s.speed / 1000.0, 1e-12))
    n_main = max(1, math.ceil(t_end / dt - 1e-6))
    n_warm = math.ceil(4 * hi_lat / dt) if s.latency == "intensity" else 0
    gaps = ((ends[:-1] + starts[1:]) / 2)
    targets = torch.cat([gaps, s.target_times])
    return Timeline(starts, ends, margin, t_end, dt, n_main, n_warm, targets)
