"""Two consecutive frames' consistency as a latency estimate, with each event the end of a ramp.

Each blurry frame and the events give the latent image at any time (EDI); between two exposures both frames give
it, and at the right latency they agree (:mod:`evlatcorr.consistency`). With step EDI the latency at which they agree
best lies a millisecond or so after the true one (``docs/estimator.md``, "two frames' consistency"): a step holds a
pixel's level until its event, while the scene crossed the threshold gradually, so both frames' latents lag the
scene, and reading the events later makes up for it. Here each event is instead the end of a ramp from the pixel's
previous event, at most ``max_spread_us`` long and, by default, at most twice the interval to the pixel's next event
(:func:`evlatcorr.integral.cumulative_event_grid`'s ``"linear"`` integral): an event after a long quiet is an edge's
first crossing, not the end of a change since the last one (:func:`evlatcorr.pair_evidence.pair_disagreement_curve`).
:func:`pair_rows` scans the candidate latencies of one constant-latency case simulated as two frames with a camera's
gap between them, for each ramp length (0: step EDI), beside the default corrector on the first frame.
"""

from __future__ import annotations

import math
import statistics
import warnings
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

from evlatcorr.benchmark.accuracy_cases import Case, simulate_case
from evlatcorr.pair_evidence import DEFAULT_RAMP_NEXT_FACTOR, check_candidates, pair_disagreement_curve

__all__ = ["RAMPS_US", "CANDIDATE_STEP_US", "pair_disagreement_curve", "curve_minimum", "pair_rows", "pair_summary",
           "pair_markdown", "recording_rows"]

#: ramp lengths compared, µs (0: step EDI; 10 ms is the shipped cap)
RAMPS_US = (0.0, 5000.0, 10000.0, 20000.0)
#: the candidates' spacing, µs (0 to the end of the events)
CANDIDATE_STEP_US = 250.0
#: the frame interval as a multiple of the exposure time (a camera's frames have a gap; as benchmark.threshold's)
FRAME_GAP = 1.25


def curve_minimum(candidates: Tensor, curve: Tensor) -> float:
    """The candidate with the lowest value, refined by a parabola through it and its neighbours (µs).

    Example:
        >>> curve_minimum(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.0, 0.0, 1.0]))
        1.0
    """
    check_candidates(candidates)
    if curve.shape != candidates.shape:
        raise ValueError(f"curve must hold one value per candidate, got {tuple(curve.shape)} for "
                         f"{tuple(candidates.shape)}")
    k = int(curve.argmin())
    if 0 < k < len(curve) - 1:
        y0, y1, y2 = (float(v) for v in curve[k - 1:k + 2])
        curvature = y0 - 2 * y1 + y2
        if curvature > 0:
            return float(candidates[k]) + 0.5 * (y0 - y2) / curvature * float(candidates[k + 1] - candidates[k])
    return float(candidates[k])


def pair_rows(case: Case, ramps_us: Sequence[float] = RAMPS_US,
              next_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> dict[str, Any]:
    """One constant-latency case simulated as two frames with a camera's gap: the consistency's latency for each
    ramp length, on the delayed and on the ideal events, beside the default corrector's on the first frame.

    Returns:
        a row: ``case``, ``truth_us``, ``reader_us`` (the default corrector, the first frame alone), and per ramp
        ``R`` ``delayed_R_us`` and ``ideal_R_us`` (the ideal events' estimate: 0 is right), with
        ``delayed_R_at_reach`` and ``ideal_R_at_reach`` (the curve's lowest point within a candidate of the events'
        reach: no minimum).
    """
    from evlatcorr.correction import EventLatencyCorrector

    if case.latency_model != "constant":
        raise ValueError(f"pair_rows reads constant-latency cases, got {case.name} ({case.latency_model})")
    delayed, _, seq = simulate_case(case, 2, frame_interval_us=FRAME_GAP * case.exposure_us)
    row: dict[str, Any] = dict(case=case.name, truth_us=case.latency_us)
    with warnings.catch_warnings():  # the suite's events stop 15 ms after the exposure: the search says so each time
        warnings.simplefilter("ignore")
        reader = EventLatencyCorrector(threshold=case.threshold)(delayed.split()[0])
    row["reader_us"] = float(reader.latency.mean())
    for which in ("delayed", "ideal"):
        pair = seq.pairs(which, after_us=case.after_us)
        reach = float(pair.events.t.max() - pair.exposure_end_next[0])  # a window never runs past the last event
        candidates = torch.arange(0.0, max(reach, 0.0) + 1.0, CANDIDATE_STEP_US, dtype=torch.float64)
        for ramp in ramps_us:
            curve = pair_disagreement_curve(pair, case.threshold, candidates, ramp, next_spread_factor=next_factor)
            row[f"{which}_{ramp:g}_us"] = curve_minimum(candidates, curve)
            # no minimum before the events run out: the curve fell over the whole range (a frame latency does not
            # change, or too few events), as the sharpness scores' did before the reader's fallbacks
            row[f"{which}_{ramp:g}_at_reach"] = int(curve.argmin()) >= len(candidates) - 2
    return row


def pair_summary(rows: list[dict[str, Any]], ramps_us: Sequence[float] = RAMPS_US) -> list[dict[str, Any]]:
    """Per estimator (the default corrector on the first frame; the consistency at each ramp length; the mean of
    the corrector's and the consistency's at each ramp, and the same with the corrector alone where the consistency
    found no minimum before the events' reach): the median absolute and signed error, the 90th percentile
    and the worst absolute error, the share within 500 µs, and the ideal events' median absolute estimate.

    Example:
        >>> rows = [dict(truth_us=1000.0, reader_us=1400.0, delayed_0_us=2000.0, ideal_0_us=600.0)]
        >>> [(s["estimator"], s["median_abs_error_us"]) for s in pair_summary(rows, (0.0,))][:3]
        [('default corrector, first frame', 400.0), ('consistency, step EDI', 1000.0), ('mean of the two', 700.0)]
    """
    if not rows:
        return []
    estimators: list[tuple[str, list[float], list[float] | None]] = [
        ("default corrector, first frame", [r["reader_us"] for r in rows], None)]
    for ramp in ramps_us:
        name = "step EDI" if ramp == 0 else f"ramps up to {ramp:g} us"
        own = [r[f"delayed_{ramp:g}_us"] for r in rows]
        ideal = [r[f"ideal_{ramp:g}_us"] for r in rows]
        estimators.append((f"consistency, {name}", own, ideal))
        both = "mean of the two" if len(ramps_us) == 1 else f"mean of the corrector and the consistency, {name}"
        estimators.append((both, [(a + r["reader_us"]) / 2 for a, r in zip(own, rows)], None))
        estimators.append((f"{both}, the corrector alone where the consistency has no minimum",
                           [r["reader_us"] if r.get(f"delayed_{ramp:g}_at_reach") else (a + r["reader_us"]) / 2
                            for a, r in zip(own, rows)], None))
    out = []
    truth = [r["truth_us"] for r in rows]
    for name, estimates, ideal in estimators:
        errors = [e - t for e, t in zip(estimates, truth)]
        absolute = sorted(abs(e) for e in errors)
        out.append({"estimator": name, "cases": len(rows), "median_abs_error_us": statistics.median(absolute),
                    "median_signed_error_us": statistics.median(errors),
                    "p90_abs_error_us": absolute[math.ceil(0.9 * len(absolute)) - 1],
                    "worst_abs_error_us": absolute[-1],
                    "within_500us": sum(a <= 500.0 for a in absolute) / len(absolute),
                    "ideal_median_abs_us": statistics.median(abs(v) for v in ideal) if ideal else math.nan})
    return out


def pair_markdown(summary: list[dict[str, Any]]) -> str:
    """:func:`pair_summary`'s rows as a markdown table."""
    lines = ["| estimator | cases | median abs. error | median signed error | p90 / worst abs. error | within 500 us | "
             "ideal events: median abs. estimate |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for s in summary:
        ideal = "" if math.isnan(s["ideal_median_abs_us"]) else f"{s['ideal_median_abs_us']:.0f} us"
        lines.append(f"| {s['estimator']} | {s['cases']} | {s['median_abs_error_us']:.0f} us | "
                     f"{s['median_signed_error_us']:+.0f} us | {s['p90_abs_error_us']:.0f} / "
                     f"{s['worst_abs_error_us']:.0f} us | {100 * s['within_500us']:.0f} % | {ideal} |")
    return "\n".join(lines) + "\n"


def recording_rows(path: str, threshold: float, ramps_us: Sequence[float] = RAMPS_US,
                   grid_us: float = 250.0,
                   next_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR) -> list[dict[str, Any]]:
    """Each pair of consecutive frames of a recording (no truth): the default corrector's latency for the first frame
    alone and the consistency's for each ramp length (candidates every 250 µs up to the exposure time; the grid
    250 µs apart, as docs/estimator.md's figures were measured).

    Returns:
        a row per pair: ``frame``, ``reader_us`` and per ramp ``R`` ``delayed_R_us``.
    """
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.io import open_recording
    from evlatcorr.restore import has_events, pair_frames, pair_reach_us

    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number, got {threshold}")
    rec = open_recording(path)
    exposure = max(end - start for start, end, _ in rec.frame_times())
    rec.after_us = pair_reach_us(rec)  # to the next exposure's end, and the candidates past it
    corrector = EventLatencyCorrector(threshold=threshold)
    candidates = torch.arange(0.0, exposure + 1.0, CANDIDATE_STEP_US, dtype=torch.float64)
    rows = []
    for frame, pair in pair_frames(rec):
        if pair is None or not has_events(frame):
            continue
        with warnings.catch_warnings():  # what the corrector warns of is in its own command's report
            warnings.simplefilter("ignore")
            row: dict[str, Any] = dict(frame=int(frame.meta["frame"]), reader_us=float(corrector(frame).latency.mean()))
        for ramp in ramps_us:
            curve = pair_disagreement_curve(pair, threshold, candidates, ramp, grid_us, next_factor)
            row[f"delayed_{ramp:g}_us"] = curve_minimum(candidates, curve)
        rows.append(row)
    return rows
