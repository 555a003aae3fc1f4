"""How much of a network's loss to latency an estimate recovers: the accuracy suite's cases scored by a network.

The accuracy suite scores estimates with EDI, whose sharpest image is reached when the events are read
somewhat later than their true latency (step EDI's own lag). A network trained on ideal events may want the
true latency instead. This check runs a restoration network (EFNet by default, shipped weights) on each
case's ideal, delayed and corrected events and reports the network's PSNR recovery per estimator:
``(corrected − delayed) / (ideal − delayed)``.

Example:
    >>> from evlatcorr.benchmark.accuracy import make_cases
    >>> from evlatcorr.restore import build_model
    >>> case = make_cases("dev", size=(32, 48))[5]
    >>> row = check_case(case, {"none": lambda frames: 0.0}, build_model("efnet"))
    >>> sorted(row["estimators"]["none"])
    ['latency_us', 'psnr', 'recovery']
"""

from __future__ import annotations

import math
import statistics
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import torch
from torch import nn

from evlatcorr.benchmark.accuracy import Case, _as_map, simulate_case
from evlatcorr.benchmark.compare import NO_GAP_DB, psnr, recovery
from evlatcorr.frames import EventFrames

__all__ = ["check_case", "summarize_checks", "checks_to_markdown"]

Estimator = Callable[[EventFrames], Any]


def check_case(case: Case, estimators: Mapping[str, Estimator], network: nn.Module,
               simulated: tuple[EventFrames, EventFrames, Any] | None = None) -> dict[str, Any]:
    """The network's PSNR on one case with ideal, delayed and each estimator's corrected events.

    Args:
        case: an accuracy-suite case.
        estimators: name → ``f(frames) -> latency`` (as :func:`~evlatcorr.benchmark.accuracy.evaluate_case`'s;
            ``frames.meta["threshold"]`` holds the case's threshold).
        network: a restoration adapter taking :class:`EventFrames` (reads ``corrected`` when set).
        simulated: ``simulate_case(case)``, to reuse a simulation.

    Returns:
        ``{"name", "latency_model", "true_latency_us", "psnr_ideal", "psnr_delayed", "estimators": {name:
        {"latency_us", "psnr", "recovery"}}}``; ``recovery`` is NaN when the ideal events beat the delayed ones by
        no more than :data:`~evlatcorr.benchmark.compare.NO_GAP_DB`.
    """
    delayed, ideal, _ = simulated if simulated is not None else simulate_case(case)
    frames = delayed.replace(meta={**delayed.meta, "threshold": case.threshold})
    with torch.no_grad():
        psnr_ideal = psnr(network(ideal).output, ideal.sharp)
        psnr_delayed = psnr(network(delayed).output, delayed.sharp)
    row: dict[str, Any] = {"name": case.name, "latency_model": case.latency_model,
                           "true_latency_us": float(delayed.meta["true_latency"].mean()),
                           "psnr_ideal": psnr_ideal, "psnr_delayed": psnr_delayed, "estimators": {}}
    for name, estimate in estimators.items():
        latency = _as_map(estimate(frames), delayed)
        corrected = delayed.with_outputs(latency=latency.float(), corrected=delayed.events.shift(latency))
        with torch.no_grad():
            value = psnr(network(corrected).output, delayed.sharp)
        row["estimators"][name] = {"latency_us": float(latency.mean()), "psnr": value,
                                   "recovery": recovery(value, psnr_delayed, psnr_ideal, NO_GAP_DB)}
    return row


def summarize_checks(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, float]]:
    """Per estimator and latency model (and ``"all"``): cases with a gap, median and worst network recovery."""
    summary: dict[str, dict[str, float]] = {}
    names = list(rows[0]["estimators"]) if rows else []
    for model in ("constant", "intensity_delay", "intensity", "all"):
        sub = [r for r in rows if model == "all" or r["latency_model"] == model]
        for name in names:
            values = [v for r in sub if not math.isnan(v := r["estimators"][name]["recovery"])]  # NaN: no gap
            if values:
                summary[f"{name}/{model}"] = {"cases": len(values), "median_recovery": statistics.median(values),
                                              "worst_recovery": min(values)}
    return summary


def checks_to_markdown(rows: Sequence[Mapping[str, Any]], network_name: str) -> str:
    """The summary, then one line per case."""
    lines = [f"| estimator | latency model | cases with a gap | median {network_name} recovery | worst |",
             "| --- | --- | --- | --- | --- |"]
    for key, s in summarize_checks(rows).items():
        name, model = key.split("/")
        lines.append(f"| {name} | {model} | {s['cases']} | {100 * s['median_recovery']:.0f}% | "
                     f"{100 * s['worst_recovery']:.0f}% |")
    names = list(rows[0]["estimators"]) if rows else []
    lines += ["", "| case | true µs | PSNR ideal | PSNR delayed | "
              + " | ".join(f"{n}: µs / PSNR / recovery" for n in names) + " |",
              "| --- | --- | --- | --- | " + " | ".join("---" for _ in names) + " |"]
    for r in rows:
        cells = []
        for n in names:
            e = r["estimators"][n]
            gain = "no gap" if math.isnan(e["recovery"]) else f"{100 * e['recovery']:.0f}%"
            cells.append(f"{e['latency_us']:.0f} / {e['psnr']:.2f} / {gain}")
        lines.append(f"| {r['name']} | {r['true_latency_us']:.0f} | {r['psnr_ideal']:.2f} | {r['psnr_delayed']:.2f} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"
