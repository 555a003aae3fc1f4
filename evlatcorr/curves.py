"""Latency-illuminance curves (paper Sec. 4.1): measure latency from light-off recordings, fit ψ.

- :func:`light_off_latency`: the latency of one recording of a light switched off at a known time:
  the median delay of the first 1% OFF events after the switch.
- :func:`fit_latency_curve`: least-squares fit of ``ψ(L) = Σ a_i f(L)^i`` (K = 5) to measured
  (illuminance, latency) pairs, with ``f(L) = (log L_max − log L) / (log L_max − log L_min)`` (monotone
  decreasing, in [0, 1] over the data, so the powers stay well conditioned); :func:`read_pairs_csv`
  reads the pairs from a CSV and :func:`plot_latency_curve` draws points and curve.
- :func:`simulate_light_off`: light-off recordings from the simulator's photoreceptor model, whose
  latency is known in closed form (for tests and for trying the tools without a lab).
"""

from __future__ import annotations

import csv
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from evlatcorr.events import Events

__all__ = ["LatencyCurve", "fit_latency_curve", "read_pairs_csv", "plot_latency_curve", "light_off_latency",
           "simulate_light_off", "light_off_theory"]


@dataclass
class LatencyCurve:
    """A fitted ``ψ(L)``: coefficients over ``f(L)`` and the log-illuminance range of the fit."""

    coefficients: Tensor
    log_min: float
    log_max: float

    def transform(self, illuminance: Tensor) -> Tensor:
        return (self.log_max - torch.log(torch.as_tensor(illuminance, dtype=torch.float64))) / (
            self.log_max - self.log_min)

    def __call__(self, illuminance: Tensor | Sequence[float]) -> Tensor:
        f = self.transform(torch.as_tensor(illuminance, dtype=torch.float64))
        return (f[..., None] ** torch.arange(len(self.coefficients), dtype=torch.float64) * self.coefficients).sum(-1)


def fit_latency_curve(illuminance: Sequence[float] | Tensor, latency_us: Sequence[float] | Tensor,
                      order: int = 5) -> LatencyCurve:
    """Least-squares K-th order fit of latency (µs) against illuminance (lux or any positive unit).

    Example:
        >>> lux = torch.tensor([0.5, 1.0, 5.0, 20.0, 100.0, 1000.0])
        >>> curve = fit_latency_curve(lux, 1000.0 / lux, order=3)
        >>> bool(curve(torch.tensor([2.0])) > curve(torch.tensor([50.0])))
        True
    """
    x = torch.as_tensor(illuminance, dtype=torch.float64).flatten()
    y = torch.as_tensor(latency_us, dtype=torch.float64).flatten()
    if order < 0:
        raise ValueError(f"order K must be >= 0, got {order}")
    if x.shape != y.shape or len(x) == 0:
        raise ValueError(f"illuminance and latency_us must be non-empty and of equal length, got {len(x)}, {len(y)}")
    if bool((x <= 0).any()) or not bool(torch.isfinite(y).all()):
        raise ValueError("illuminance must be positive and latencies finite")
    if len(x) <= order:
        raise ValueError(f"a K={order} fit needs more than {order} points, got {len(x)}")
    log_min, log_max = float(x.log().min()), float(x.log().max())
    if log_max == log_min:
        raise ValueError("all illuminance values are equal: nothing to fit")
    curve = LatencyCurve(torch.zeros(order + 1, dtype=torch.float64), log_min, log_max)
    design = curve.transform(x)[:, None] ** torch.arange(order + 1, dtype=torch.float64)
    curve.coefficients = torch.linalg.lstsq(design, y[:, None]).solution[:, 0]
    return curve


def read_pairs_csv(path: str | Path) -> tuple[Tensor, Tensor]:
    """Read ``illuminance`` and ``latency_us`` columns of a CSV (header names are required)."""
    with open(path, newline="") as fh:
        reader = csv.DictReader(fh)
        if reader.fieldnames is None or not {"illuminance", "latency_us"} <= set(reader.fieldnames):
            raise ValueError(f"{path}: needs the columns illuminance and latency_us, got {reader.fieldnames}")
        rows = [(float(r["illuminance"]), float(r["latency_us"])) for r in reader]
    if not rows:
        raise ValueError(f"{path}: no rows")
    x, y = zip(*rows)
    return torch.tensor(x, dtype=torch.float64), torch.tensor(y, dtype=torch.float64)


def plot_latency_curve(curve: LatencyCurve, illuminance: Tensor, latency_us: Tensor, path: str | Path) -> None:
    """Measured points and the fitted curve, log illuminance axis, to a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = torch.logspace(curve.log_min / math.log(10), curve.log_max / math.log(10), 200, dtype=torch.float64)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.semilogx(illuminance.numpy(), latency_us.numpy() / 1000, "o", label="measured")
    ax.semilogx(grid.numpy(), curve(grid).numpy() / 1000, "-", label=f"K={len(curve.coefficients) - 1} fit")
    ax.set_xlabel("illuminance")
    ax.set_ylabel("latency (ms)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def light_off_latency(events: Events, switch_off_us: float, fraction: float = 0.01) -> float:
    """Median delay (µs) of the first ``fraction`` of OFF events after the light goes off at ``switch_off_us``."""
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    off = events.t[(events.p < 0) & (events.t >= switch_off_us)]
    if len(off) == 0:
        raise ValueError(f"no OFF events after {switch_off_us} us: cannot measure latency")
    first = torch.sort(off).values[: max(1, int(math.ceil(fraction * len(off))))]
    return float(first.median()) - switch_off_us


def light_off_theory(level: float, off_factor: float, threshold: float,
                     latency_range_us: tuple[float, float]) -> float:
    """Delay of the first OFF event of the simulator's photoreceptor after the light drops by ``off_factor``.

    The filtered log intensity relaxes with ``τ = clip(lo / I_after)`` towards the new level, so it
    falls by one threshold after ``−τ ln(1 − θ / Δ)``, ``Δ`` the log drop.
    """
    eps = 1e-3
    drop = math.log(level + eps) - math.log(level * off_factor + eps)
    tau = min(max(latency_range_us[0] / (level * off_factor), latency_range_us[0]), latency_range_us[1])
    return -tau * math.log(1 - threshold / drop)


def simulate_light_off(levels: Sequence[float], switch_off_us: float = 2000.0, duration_us: float = 40_000.0,
                       off_factor: float = 0.25, size: tuple[int, int] = (16, 16), threshold: float = 0.2,
                       threshold_sigma: float = 0.03, latency_range_us: tuple[float, float] = (500.0, 10_000.0),
                       dt_us: float = 5.0, seed: int = 0) -> list[Events]:
    """A uniform field at each level (intensity in (0, 1]) whose light drops by ``off_factor`` at a known time.

    Events come from the same first-order photoreceptor as ``simulate(latency="intensity")``.
    """
    from evlatcorr.simulate import _EventGenerator

    g = torch.Generator().manual_seed(seed)
    out = []
    for level in levels:
        if not 0 < level <= 1:
            raise ValueError(f"levels must be intensities in (0, 1], got {level}")
        thr = (threshold * (1 + threshold_sigma * torch.randn(size, generator=g))).clamp_min(0.2 * threshold)
        before = math.log(level + 1e-3)
        filtered = torch.full(size, before)
        gen = _EventGenerator(filtered.clone(), thr)
        t = 0.0
        while t < duration_us:
            intensity = level if t < switch_off_us else level * off_factor
            tau = min(max(latency_range_us[0] / intensity, latency_range_us[0]), latency_range_us[1])
            target = torch.full(size, math.log(intensity + 1e-3))
            new = filtered + (1 - math.exp(-dt_us / tau)) * (target - filtered)
            gen.step(filtered, new, t, dt_us)
            filtered, t = new, t + dt_us
        out.append(gen.events(size, None))
    return out
