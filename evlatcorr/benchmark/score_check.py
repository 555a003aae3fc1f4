"""Whether a sharpness score can find a per-pixel latency at all: the true map's score against the best constant's.

A search over latency maps (the spatial fit, or any richer family) can only return the true map if
the score it minimises rates that map sharper than every constant shift. This check scores, on the
accuracy suite's intensity-dependent cases, the EDI latent of the true map and of every constant
latency whose window holds events (all read from one :class:`~evlatcorr.latency_table.LatencyTable`),
and reports for each score whether the true map wins, by how much, and what both give in EDI PSNR.

Example:
    >>> from evlatcorr.benchmark.accuracy import make_cases
    >>> case = next(c for c in make_cases("dev", size=(32, 48)) if c.latency_model == "intensity_delay")
    >>> row = check_case(case, scores=("sparsity",))
    >>> sorted(row["scores"]["sparsity"])
    ['best_constant_us', 'margin', 'psnr_best_constant', 'true_wins']
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

import torch

from evlatcorr.benchmark.accuracy import Case, simulate_case
from evlatcorr.benchmark.compare import psnr
from evlatcorr.config import SPARSITY_SCORES
from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
from evlatcorr.frames import EventFrames
from evlatcorr.latency_table import LatencyTable
from evlatcorr.sharpness import sharpness_scores
from evlatcorr.spatial import PolynomialLatency

__all__ = ["CHECKED_SCORES", "check_case", "summarize_checks", "checks_to_markdown"]

CHECKED_SCORES = ("etf", *SPARSITY_SCORES)
MAP_MODELS = ("intensity_delay", "intensity")  # the latency models whose truth is a per-pixel map


def check_case(case: Case, simulated: EventFrames | None = None, scores: Sequence[str] = CHECKED_SCORES,
               num_latencies: int = 101) -> dict[str, Any]:
    """Score the true latency map and every constant latency of one case.

    Args:
        case: an accuracy-suite case with a per-pixel latency (:data:`MAP_MODELS`).
        simulated: its delayed frames (``simulate_case(case)[0]``), to reuse a simulation.
        scores: the sharpness scores to check (:func:`~evlatcorr.sharpness.sharpness_scores` names).
        num_latencies: constant latencies tabulated from 0 to the exposure time.

    Returns:
        ``{"name", "latency_model", "psnr_true_map", "scores": {score: {"true_wins", "margin",
        "best_constant_us", "psnr_best_constant"}}}``: ``margin`` is the true map's score over the best
        constant's, minus 1 (negative: the score prefers the true map).
    """
    if case.latency_model not in MAP_MODELS:
        raise ValueError(f"the check needs a per-pixel latency model {MAP_MODELS}, got {case.latency_model!r}")
    frames = simulated if simulated is not None else simulate_case(case)[0]
    exposure = float(frames.exposure_time[0])
    table = LatencyTable.build(frames.events, frames.exposure_start, frames.exposure_end, case.threshold, 0.0,
                               exposure, num_latencies)
    # only constants whose window [start + l, end + l] ends before the last event, as the search scores
    last = float(frames.events.t.max()) - float(frames.exposure_end[0])
    kept = max(1, int(last // table.step) + 1)
    constants = table.low + table.step * torch.arange(min(kept, num_latencies), dtype=torch.float64)
    inverse = torch.exp(-table.log_ratio[0, : len(constants), None])  # (K, 1, H, W)
    true_inverse = torch.exp(-table.read(frames.meta["true_latency"].float()))  # (1, 1, H, W)
    grey = PolynomialLatency.intensity(frames.blurry)
    rated = sharpness_scores(torch.cat([grey * true_inverse, grey * inverse]),
                             torch.zeros(len(constants) + 1), None, tuple(scores), DEFAULT_EPSILON,
                             DEFAULT_WINDOW, DEFAULT_SIGMA_US)  # (M, 1 + K)
    row: dict[str, Any] = {"name": case.name, "latency_model": case.latency_model,
                           "psnr_true_map": psnr(frames.blurry * true_inverse, frames.sharp), "scores": {}}
    for name, values in zip(scores, rated):
        best = int(torch.argmin(values[1:]))
        row["scores"][name] = {
            "true_wins": bool(values[0] < values[1 + best]),
            "margin": float(values[0] / values[1 + best] - 1),
            "best_constant_us": float(constants[best]),
            "psnr_best_constant": psnr(frames.blurry * inverse[best], frames.sharp),
        }
    return row


def summarize_checks(rows: Sequence[Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """Per score and latency model: cases, how many the true map wins, the median margin."""
    summary: dict[str, dict[str, Any]] = {}
    for model in MAP_MODELS:
        sub = [r for r in rows if r["latency_model"] == model]
        for name in (sub[0]["scores"] if sub else ()):
            margins = sorted(r["scores"][name]["margin"] for r in sub)
            wins = sum(r["scores"][name]["true_wins"] for r in sub)
            summary[f"{name}/{model}"] = {"cases": len(sub), "true_wins": wins,
                                          "median_margin": margins[len(margins) // 2]}
    return summary


def checks_to_markdown(rows: Sequence[Mapping[str, Any]]) -> str:
    """The summary, then one line per case and score."""
    lines = ["| score | latency model | cases | true map scores sharper than every constant | median margin |",
             "| --- | --- | --- | --- | --- |"]
    for key, s in summarize_checks(rows).items():
        name, model = key.split("/")
        lines.append(f"| {name} | {model} | {s['cases']} | {s['true_wins']} | {100 * s['median_margin']:+.1f} % |")
    lines += ["", "| case | score | true map wins | margin | best constant µs | PSNR true map | PSNR best constant |",
              "| --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        for name, s in r["scores"].items():
            lines.append(f"| {r['name']} | {name} | {'yes' if s['true_wins'] else 'no'} | {100 * s['margin']:+.1f} % | "
                         f"{s['best_constant_us']:.0f} | {r['psnr_true_map']:.2f} | {s['psnr_best_constant']:.2f} |")
    return "\n".join(lines) + "\n"
