"""Latency-illuminance curves (paper Sec. 4.1): measure latency from light-off recordings, fit ψ.

- :func:`light_off_latency`: the latency of one recording of a light switched off at a known time:
  the median delay of the first 1% OFF events after the switch.
- :func:`fit_latency_curve`: least-squares fit of ``ψ(L) = Σ a_i f(L)^i`` (K = 5) to measured
  (illuminance, latency) pairs, with ``f(L) = (log L_max − log L) / (log L_max − log L_min)`` (monotone
  decreasing, in [0, 1] over the data, so the powers stay well conditioned); :func:`read_pairs_csv`
  reads the pairs from a CSV and :func:`plot_latency_curve` draws points and curve.
- :func:`simulate_light_off`: light-off recordings from the simulator's photoreceptor model, whose
  latency is known in closed form (for tests and for trying the tools without a lab).

Command line::

    python -m evlatcorr.curves simulate pairs.csv          # (illuminance, latency_us) from the simulator
    python -m evlatcorr.curves fit pairs.csv --order 5 --plot curve.png --out curve.json
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

from evlatcorr.events import Events

__all__ = ["LatencyCurve", "fit_latency_curve", "read_pairs_csv", "plot_latency_curve", "light_off_latency",
           "simulate_light_off", "light_off_theory", "main"]


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

    def to_dict(self) -> dict:
        """JSON-ready form (``f(L) = (log_max − log L) / (log_max − log_min)``)."""
        return {"coefficients": self.coefficients.tolist(), "log_min": self.log_min, "log_max": self.log_max,
                "f": "(log_max - log L) / (log_max - log_min)"}

    @classmethod
    def from_dict(cls, data: dict) -> LatencyCurve:
        return cls(torch.tensor(data["coefficients"], dtype=torch.float64), float(data["log_min"]),
                   float(data["log_max"]))


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
    # a Figure of its own (not pyplot): no global backend switch, nothing left open in the caller's session
    from matplotlib.figure import Figure

    grid = torch.logspace(curve.log_min / math.log(10), curve.log_max / math.log(10), 200, dtype=torch.float64)
    fig = Figure(figsize=(5, 3.5))
    ax = fig.subplots()
    ax.semilogx(illuminance.numpy(), latency_us.numpy() / 1000, "o", label="measured")
    ax.semilogx(grid.numpy(), curve(grid).numpy() / 1000, "-", label=f"K={len(curve.coefficients) - 1} fit")
    ax.set_xlabel("illuminance")
    ax.set_ylabel("latency (ms)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)


def light_off_latency(events: Events, switch_off_us: float | Sequence[float] | Tensor, fraction: float = 0.01,
                      reduce: str = "median") -> float | Tensor:
    """Latency of a light switched off at a known time: the delay of the first OFF events (paper Sec. 4.1).

    Each sample of ``events`` is one repetition (the paper repeats the switch about 80 times per
    illuminance). In each, the delay is the median of the first ``fraction`` (1%) of OFF events
    after the switch; the repetitions are combined by their median, which ignores the odd
    repetition spoiled by noise.

    Args:
        events: the recordings, one batch sample per repetition.
        switch_off_us: when the light went off, µs: one time for all repetitions or one per sample.
        fraction: share of the first OFF events used (paper: 0.01).
        reduce: ``"median"`` (a float, µs) or ``"none"`` (the delay of each repetition :math:`(R,)`).

    Returns:
        the latency in µs.

    Example:
        >>> ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([1500.0, 1700.0, 1900.0]),
        ...             torch.tensor([-1, -1, -1]), sensor_size=(1, 1))
        >>> light_off_latency(ev, 1000.0, fraction=0.5)  # first 2 of 3: median of 500 and 700
        600.0
    """
    if not 0 < fraction <= 1:
        raise ValueError(f"fraction must be in (0, 1], got {fraction}")
    if reduce not in ("median", "none"):
        raise ValueError(f"reduce must be 'median' or 'none', got {reduce!r}")
    reps = events.batch_size
    switch = torch.as_tensor(switch_off_us, dtype=torch.float64).flatten()
    if switch.numel() == 1:
        switch = switch.expand(reps)
    if switch.numel() != reps:
        raise ValueError(f"switch_off_us needs one time or one per repetition ({reps}), got {switch.numel()}")
    delays = []
    for i in range(reps):
        ev = events.sample(i) if reps > 1 else events
        off = ev.t[(ev.p < 0) & (ev.t >= float(switch[i]))]
        if len(off) == 0:
            raise ValueError(f"repetition {i}: no OFF events after {float(switch[i])} us: cannot measure latency")
        first = torch.sort(off).values[: max(1, int(math.ceil(fraction * len(off))))]
        delays.append(float(first.quantile(0.5)) - float(switch[i]))
    out = torch.tensor(delays, dtype=torch.float64)
    return out if reduce == "none" else float(out.quantile(0.5))


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
                       dt_us: float = 5.0, repetitions: int = 1, seed: int = 0) -> list[Events]:
    """A uniform field at each level (intensity in (0, 1]) whose light drops by ``off_factor`` at a known time.

    Events come from the same first-order photoreceptor as ``simulate(latency="intensity")``, whose
    delay after the switch is known in closed form (:func:`light_off_theory`). Each repetition draws
    its own per-pixel threshold mismatch.

    Returns:
        one ``Events`` per level, with ``repetitions`` batch samples.

    Example:
        >>> rec = simulate_light_off([0.5], size=(4, 4), duration_us=20_000.0, repetitions=2)
        >>> rec[0].batch_size
        2
    """
    from evlatcorr.simulation.generator import EventGenerator as _EventGenerator

    if repetitions < 1:
        raise ValueError(f"repetitions must be >= 1, got {repetitions}")
    if not 0 < off_factor < 1:
        raise ValueError(f"off_factor must be in (0, 1) (the light goes down), got {off_factor}")
    for level in levels:
        if not 0 < level <= 1:
            raise ValueError(f"levels must be intensities in (0, 1], got {level}")
    g = torch.Generator().manual_seed(seed)
    height, width = size
    block = repetitions * height
    field = (len(levels) * block, width)  # levels and repetitions stacked along y, split afterwards
    thr = (threshold * (1 + threshold_sigma * torch.randn(field, generator=g))).clamp_min(0.2 * threshold)
    bright = torch.tensor(levels, dtype=torch.float32).repeat_interleave(block)[:, None].expand(field)
    lo, hi = latency_range_us
    filtered = torch.log(bright + 1e-3)
    gen = _EventGenerator(filtered.clone(), thr)
    t = 0.0
    for off in (False, True):  # the same first-order photoreceptor as simulate(latency="intensity")
        intensity = bright * off_factor if off else bright
        gain = 1 - torch.exp(-dt_us / (lo / intensity).clamp(lo, hi))
        target = torch.log(intensity + 1e-3)
        while t < (duration_us if off else switch_off_us):
            new = filtered + gain * (target - filtered)
            gen.step(filtered, new, t, dt_us)
            filtered, t = new, t + dt_us
    ev = gen.events(field, None)
    y = ev.y % height
    sample = torch.div(ev.y, height, rounding_mode="floor")  # level * repetitions + repetition
    out = []
    for i in range(len(levels)):
        mine = torch.div(sample, repetitions, rounding_mode="floor") == i
        out.append(Events(ev.x[mine], y[mine], ev.t[mine], ev.p[mine], sample[mine] - i * repetitions,
                          sensor_size=size, batch_size=repetitions, sort=True))
    return out

def main(argv: Sequence[str] | None = None) -> None:
    """``fit``: K-th order curve from a CSV (+ plot, JSON); ``simulate``: a CSV of simulated light-off pairs."""
    p = argparse.ArgumentParser(prog="python -m evlatcorr.curves", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="command", required=True)
    f = sub.add_parser("fit", help="fit psi(L) to (illuminance, latency_us) pairs of a CSV")
    f.add_argument("csv", type=Path)
    f.add_argument("--order", type=int, default=5)
    f.add_argument("--plot", type=Path, help="PNG of the points and the fitted curve")
    f.add_argument("--out", type=Path, help="JSON of the fitted curve")
    s = sub.add_parser("simulate", help="light-off recordings from the simulator, measured like in the lab")
    s.add_argument("csv", type=Path)
    s.add_argument("--levels", type=float, nargs="+", default=[0.03, 0.05, 0.08, 0.1, 0.15, 0.2, 0.3, 0.5, 0.7, 1.0])
    s.add_argument("--repetitions", type=int, default=5)
    s.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.command == "simulate":
        recordings = simulate_light_off(args.levels, repetitions=args.repetitions, seed=args.seed)
        rows = [(level, light_off_latency(ev, 2000.0)) for level, ev in zip(args.levels, recordings)]
        args.csv.write_text("illuminance,latency_us\n" + "".join(f"{x},{y:.1f}\n" for x, y in rows))
        for x, y in rows:
            print(f"intensity {x:.3f}: latency {y:.0f} us")
        print(f"wrote {args.csv}")
        return
    x, y = read_pairs_csv(args.csv)
    curve = fit_latency_curve(x, y, args.order)
    rms = float((curve(x) - y).pow(2).mean().sqrt())
    coefficients = [round(c, 1) for c in curve.coefficients.tolist()]
    print(f"K={args.order} fit to {len(x)} points: coefficients (us) {coefficients}, RMS residual {rms:.1f} us")
    if args.plot:
        plot_latency_curve(curve, x, y, args.plot)
        print(f"wrote {args.plot}")
    if args.out:
        args.out.write_text(json.dumps({**curve.to_dict(), "rms_us": rms}, indent=2))
        print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
