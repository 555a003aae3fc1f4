"""How few events still tell a latency? The accuracy suite's constant-latency cases with their events thinned.

A frame of a still scene, or a dark one, holds a few dozen events where a moving one holds tens of thousands. Each
case's delayed events are kept at random with a share ``f`` (one uniform draw per event, seeded, so a smaller share
keeps a subset of a larger one's events), the default corrector estimates the latency from what is left, and its
error is grouped by the events left in the frame's exposure and search window. Where the median error reaches what a
guess that knows only the cases' typical latency makes, the events no longer tell the latency:
:data:`evlatcorr.checks.FEW_EVENTS` is set from this table.

Thinning keeps the contrast threshold θ of the case, so each event left stands for the same step of log intensity
as before: the frame reads as a scene with fewer and weaker changes, as a still or dark one is.
"""

from __future__ import annotations

import math
import statistics
import warnings
from collections.abc import Sequence

import torch

from evlatcorr.benchmark.accuracy_cases import Case, simulate_case

__all__ = ["DEFAULT_SHARES", "EVENT_BINS", "thinned_estimates", "few_events_summary", "few_events_markdown"]

#: the shares of each case's events kept
DEFAULT_SHARES = (1.0, 0.1, 0.03, 0.01, 0.003, 0.001, 0.0003)
#: the groups of events left in the window the table reports
EVENT_BINS = (0, 10, 30, 100, 300, 1000, 3000, 10000, math.inf)


def thinned_estimates(case: Case, shares: Sequence[float] = DEFAULT_SHARES, seed: int = 0) -> list[dict]:
    """The default corrector's latency for one constant-latency ``case`` with its events thinned to each share.

    Returns:
        one row per share with events left: ``case``, ``share``, ``events`` (in ``[exposure_start, exposure_end +
        exposure time)``, the window the search reads), ``truth_us``, ``estimate_us``, ``abs_error_us`` and the
        learned reader's ``spread_us`` (how unsure it is; NaN where it did not read the frame).

    Example:
        >>> from evlatcorr.benchmark.accuracy import make_cases
        >>> case = next(c for c in make_cases("dev", size=(32, 40)) if c.latency_model == "constant")
        >>> rows = thinned_estimates(case, shares=(1.0, 0.01))
        >>> [row["share"] for row in rows], rows[0]["events"] > rows[1]["events"]
        ([1.0, 0.01], True)
    """
    from evlatcorr.correction import EventLatencyCorrector

    if case.latency_model != "constant":
        raise ValueError(f"thinned_estimates reads constant-latency cases, got {case.name} ({case.latency_model})")
    if not shares or not all(0.0 < s <= 1.0 for s in shares):
        raise ValueError(f"shares must lie in (0, 1], got {list(shares)}")
    delayed, _, _ = simulate_case(case)
    truth = float(delayed.meta["true_latency"].mean())
    events = delayed.events
    draw = torch.rand(len(events), generator=torch.Generator().manual_seed(seed))
    start, end = float(delayed.exposure_start[0]), float(delayed.exposure_end[0] + delayed.exposure_time[0])
    corrector = EventLatencyCorrector(threshold=case.threshold)
    rows = []
    for share in shares:
        kept = events.select(draw < share)
        in_window = int(((kept.t >= start) & (kept.t < end)).sum())
        if in_window == 0:  # nothing left to estimate from
            continue
        with warnings.catch_warnings():  # the few-events warning is what this measures
            warnings.simplefilter("ignore")
            out = corrector(delayed.replace(events=kept))
        estimate = float(out.latency.mean())
        rows.append({"case": case.name, "share": share, "events": in_window, "truth_us": truth,
                     "estimate_us": estimate, "abs_error_us": abs(estimate - truth),
                     "spread_us": float(out.meta["latency_spread_us"][0])})
    return rows


def few_events_summary(rows: list[dict], bins: Sequence[float] = EVENT_BINS) -> list[dict]:
    """The rows grouped by events in the window: the estimates' median absolute error, their share within 1 ms,
    the median error of the guess that answers every frame with the median true latency of all the cases, and the
    reader's median spread (over the frames it read).

    Raises:
        ValueError: when ``bins`` are not at least two increasing bounds.
    """
    if len(bins) < 2 or any(not low < high for low, high in zip(bins[:-1], bins[1:])):
        raise ValueError(f"bins must be at least two increasing bounds, got {list(bins)}")
    if not rows:
        return []
    guess = statistics.median(row["truth_us"] for row in rows if row["share"] == max(r["share"] for r in rows))
    groups = []
    for low, high in zip(bins[:-1], bins[1:]):
        group = [row for row in rows if low <= row["events"] < high]
        if group:
            groups.append({"events": (low, high), "frames": len(group),
                           "median_abs_error_us": statistics.median(row["abs_error_us"] for row in group),
                           "within_1ms": sum(row["abs_error_us"] < 1000.0 for row in group) / len(group),
                           "guess_median_abs_error_us": statistics.median(abs(row["truth_us"] - guess)
                                                                          for row in group),
                           "median_spread_us": _median_of_numbers([row.get("spread_us", math.nan)
                                                                   for row in group])})
    return groups


def _median_of_numbers(values: list[float]) -> float:
    numbers = [v for v in values if not math.isnan(v)]
    return statistics.median(numbers) if numbers else math.nan


def few_events_markdown(groups: list[dict]) -> str:
    """:func:`few_events_summary`'s groups as a markdown table."""
    lines = ["| events in the window | frames | median abs. error | within 1 ms | the typical-latency guess's median "
             "abs. error | the reader's spread, median |", "| --- | --- | --- | --- | --- | --- |"]
    for g in groups:
        low, high = g["events"]
        span = f"{low:g} or more" if math.isinf(high) else f"{low:g}-{high - 1:g}"
        lines.append(f"| {span} | {g['frames']} | {g['median_abs_error_us']:.0f} us | {100 * g['within_1ms']:.0f} % "
                     f"| {g['guess_median_abs_error_us']:.0f} us | {g['median_spread_us']:.0f} us |")
    return "\n".join(lines) + "\n"
