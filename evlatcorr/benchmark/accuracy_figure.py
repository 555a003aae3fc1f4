"""The accuracy suite's figure (:mod:`evlatcorr.benchmark.accuracy`): what its tables say, at a glance.

One row of panels per estimator: the estimated against the true latency of the constant-latency cases, each case's
recovery of its EDI PSNR gap (constant latency and per-pixel delay), and the share of the best constant shift's gain
of each case whose latency varies with intensity (photoreceptor and per-pixel delay), sorted, with the suite's goals
drawn in.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["plot_results"]

_SHOWN_PERCENT = (-50.0, 150.0)  # recoveries beyond are drawn at the edge: a case at -300 % would flatten the others


def plot_results(results: Sequence[Mapping[str, Any]], path: str | Path) -> Path:
    """Write the figure of ``results`` (the rows of :func:`evlatcorr.benchmark.accuracy.run_suite`) to ``path``.

    Cases whose estimator failed are left out; constant-latency cases without a PSNR gap (where the latency does not
    change EDI's image) are drawn hollow.

    Returns:
        ``path``.

    Raises:
        ValueError: when no row has an estimate to draw.
    """
    from matplotlib.figure import Figure

    rows = [r for r in results if not r.get("error") and _finite(r.get("est_latency_us"))]
    if not rows:
        raise ValueError("no estimates to draw: every case failed or none was run")
    estimators = list(dict.fromkeys(r["estimator"] for r in rows))
    fig = Figure(figsize=(13.5, 3.6 * len(estimators)))
    axes = fig.subplots(len(estimators), 3, squeeze=False)
    for (scatter, recovery, share), name in zip(axes, estimators):
        mine = [r for r in rows if r["estimator"] == name]
        _latency_scatter(scatter, [r for r in mine if r["latency_model"] == "constant"], name)
        _sorted_percent(recovery, {"constant latency": _values(mine, "constant", "recovery"),
                                   "per-pixel delay": _values(mine, "intensity_delay", "recovery")},
                        f"{name}: recovery of the EDI PSNR gap", (90.0, 50.0))
        _sorted_percent(share, {"photoreceptor": _values(mine, "intensity", "best_shift_share"),
                                "per-pixel delay": _values(mine, "intensity_delay", "best_shift_share")},
                        f"{name}: share of the best constant shift's gain", (90.0,))
    splits = ", ".join(dict.fromkeys(r["split"] for r in rows))
    fig.suptitle(f"latency estimators on the accuracy suite ({splits}; {len(rows)} estimates)", fontsize=10)
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=80)
    return path


def _finite(value: Any) -> bool:
    return isinstance(value, (int, float)) and math.isfinite(value)


def _values(rows: Sequence[Mapping[str, Any]], model: str, key: str) -> list[float]:
    return [100.0 * r[key] for r in rows if r["latency_model"] == model and _finite(r.get(key))]


def _latency_scatter(ax, rows: Sequence[Mapping[str, Any]], name: str) -> None:
    """The estimated against the true latency (ms), the diagonal and a band of ±1 ms around it."""
    true = [r["true_latency_us"] / 1000 for r in rows]
    estimated = [r["est_latency_us"] / 1000 for r in rows]
    top = 1.05 * max([*true, *estimated, 1.0])  # a margin, so that the largest latencies are not on the frame
    ax.fill_between([0, top], [-1, top - 1], [1, top + 1], color="0.9", label="±1 ms")
    ax.plot([0, top], [0, top], color="0.5", lw=0.8)
    gap = [not r.get("no_gap") for r in rows]
    ax.scatter([t for t, g in zip(true, gap) if g], [e for e, g in zip(estimated, gap) if g], s=14, color="C0",
               label="constant latency")
    ax.scatter([t for t, g in zip(true, gap) if not g], [e for e, g in zip(estimated, gap) if not g], s=14,
               facecolors="none", edgecolors="C0", label="no PSNR gap")
    ax.set(xlim=(0, top), ylim=(0, top), xlabel="true latency (ms)", ylabel="estimated latency (ms)",
           title=f"{name}: {len(rows)} constant-latency cases")
    ax.title.set_fontsize(9)
    ax.legend(fontsize=7, loc="upper left")


def _sorted_percent(ax, series: Mapping[str, list[float]], title: str, goals: Sequence[float]) -> None:
    """Each series sorted, its cases spread over [0, 1], clipped to the shown range; the goals as dashed lines."""
    low, high = _SHOWN_PERCENT
    for k, (label, values) in enumerate(series.items()):
        if values:
            ranked = sorted(min(max(v, low), high) for v in values)
            place = [(i + 0.5) / len(ranked) for i in range(len(ranked))]
            ax.plot(place, ranked, "o-", ms=3, lw=0.8, color=f"C{k}", label=f"{label} ({len(ranked)})")
    for goal in goals:
        ax.axhline(goal, color="0.5", ls="--", lw=0.8)
    ax.set(xlim=(0, 1), ylim=(low - 5, high + 5), xlabel="share of the cases, worst first", ylabel="%", title=title)
    ax.title.set_fontsize(9)
    if any(series.values()):
        ax.legend(fontsize=7, loc="lower right")
