"""Two consecutive frames' consistency as a latency estimate, with each event the end of a ramp.

Each blurry frame and the events give the latent image at any time (EDI); between two exposures both frames give
it, and at the right latency they agree (:mod:`evlatcorr.consistency`). With step EDI the latency at which they agree
best lies a millisecond or so after the true one (``docs/estimator.md``, "two frames' consistency"): a step holds a
pixel's level until its event, while the scene crossed the threshold gradually, so both frames' latents lag the
scene, and reading the events later makes up for it. Here each event is instead the end of a ramp from the pixel's
previous event, at most ``max_spread_us`` long (:func:`evlatcorr.integral.cumulative_event_grid`'s ``"linear"``
integral): an event after a long quiet is an edge's first crossing, not the end of a change since the last one.
:func:`pair_rows` scans the candidate latencies of one constant-latency case simulated as two frames with a
camera's gap between them, for each ramp length (0: step EDI), beside the default corrector on the first frame.
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
from evlatcorr.frames import EventFrames
from evlatcorr.integral import cumulative_event_grid

__all__ = ["RAMPS_US", "CANDIDATE_STEP_US", "pair_disagreement_curve", "curve_minimum", "pair_rows", "pair_summary",
           "pair_markdown", "recording_rows"]

#: ramp lengths compared, µs (0: step EDI)
RAMPS_US = (0.0, 2000.0, 3000.0, 5000.0)
#: the candidates' spacing, µs (0 to the end of the events)
CANDIDATE_STEP_US = 250.0
#: the frame interval as a multiple of the exposure time (a camera's frames have a gap; as benchmark.threshold's)
FRAME_GAP = 1.25
_FLOOR = 0.02  # log(I + c), as evlatcorr.consistency: the dark pixels' noise does not dominate
_GRID_US = 125.0  # the integral's grid spacing (half the candidates')


def pair_disagreement_curve(pair: EventFrames, threshold: float, candidates: Tensor, max_spread_us: float,
                            grid_us: float = _GRID_US) -> Tensor:
    """For each candidate latency, the mean over pixels of ``|log(I_1(t) + c) − log(I_2(t) + c)|`` (c = 0.02):
    the two frames' EDI latents at ``t``, the middle of the gap between their exposures, from the events read that
    late, each event a ramp of at most ``max_spread_us`` (0: a step).

    Args:
        pair: one pair (``B = 1``): ``blurry``, ``blurry_next``, both exposures and the events over both.
        threshold: contrast threshold θ.
        candidates: :math:`(K,)` latencies, µs.
        max_spread_us: the ramps' longest, µs; 0 for step EDI.
        grid_us: the integral's grid spacing, µs (times are read at the nearest grid point).

    Returns:
        :math:`(K,)` float64.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pair = simulate("camera", num_frames=2, height=24, width=32, latency_us=3000.0, seed=0).pairs()
        >>> curve = pair_disagreement_curve(pair, 0.2, torch.tensor([0.0, 3000.0]), 3000.0)
        >>> bool(curve[1] < curve[0])
        True
    """
    if pair.batch_size != 1 or pair.blurry_next is None:
        raise ValueError("pair_disagreement_curve reads one pair of frames (B = 1, with blurry_next)")
    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number, got {threshold}")
    if not (math.isfinite(max_spread_us) and max_spread_us >= 0 and math.isfinite(grid_us) and grid_us > 0):
        raise ValueError(f"max_spread_us must be 0 or more and grid_us positive, got {max_spread_us} and {grid_us}")
    _check_candidates(candidates)
    s1, e1 = float(pair.exposure_start[0]), float(pair.exposure_end[0])
    s2, e2 = float(pair.exposure_start_next[0]), float(pair.exposure_end_next[0])
    first, second = pair.blurry[0].double().mean(0), pair.blurry_next[0].double().mean(0)
    # events read l late: their integral at t is the stamped events' at t + l, so one grid serves every candidate;
    # each exposure's mean of exp(θ C) is a difference of prefix sums (trapezoids between grid points), and times are
    # taken at the nearest grid point (exact for the suite's exposures, gap and candidates: multiples of the spacing)
    start = s1 - grid_us
    bins = int(math.ceil((e2 + max(float(candidates.max()), 0.0) - start) / grid_us)) + 2
    if max_spread_us > 0:
        grid = cumulative_event_grid(pair.events, start, grid_us, bins, "linear", torch.float64,
                                     max_spread_us=max_spread_us)[0]
    else:
        grid = cumulative_event_grid(pair.events, start, grid_us, bins, "step", torch.float64)[0]
    grid = grid - grid[round(((e1 + s2) / 2 - start) / grid_us)]  # levels about the middle of the gap: no overflow
    weights = torch.exp(threshold * grid)
    sums = weights.cumsum(0)

    def index(t: float) -> int:
        return min(bins, max(0, round((t - start) / grid_us)))

    def mean_weight(a: int, b: int) -> Tensor:  # the mean of exp(θ C) from grid point a to b, trapezoids
        inside = sums[b] - sums[a] + weights[a]
        return (inside - (weights[a] + weights[b]) / 2) / max(b - a, 1)

    out = []
    for latency in candidates.tolist():
        middle = weights[index((e1 + s2) / 2 + latency)]
        logs = []
        for blurry, (a, b) in ((first, (s1, e1)), (second, (s2, e2))):
            latent = blurry * middle / mean_weight(index(a + latency), index(b + latency))
            logs.append(torch.log(latent.clamp_min(0) + _FLOOR))
        out.append((logs[0] - logs[1]).abs().mean())
    return torch.stack(out)


def _check_candidates(candidates: Tensor) -> None:
    if candidates.dim() != 1 or len(candidates) == 0 or not bool(torch.isfinite(candidates).all()):
        raise ValueError(f"candidates must be a non-empty 1-D tensor of finite latencies (us), got shape "
                         f"{tuple(candidates.shape)}")
    if len(candidates) > 1 and not bool((candidates.diff() > 0).all()):
        raise ValueError("candidates must be increasing")


def curve_minimum(candidates: Tensor, curve: Tensor) -> float:
    """The candidate with the lowest value, refined by a parabola through it and its neighbours (µs).

    Example:
        >>> curve_minimum(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.0, 0.0, 1.0]))
        1.0
    """
    _check_candidates(candidates)
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


def pair_rows(case: Case, ramps_us: Sequence[float] = RAMPS_US) -> dict[str, Any]:
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
            curve = pair_disagreement_curve(pair, case.threshold, candidates, ramp)
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
                   grid_us: float = 2 * _GRID_US) -> list[dict[str, Any]]:
    """Each pair of consecutive frames of a recording (no truth): the default corrector's latency for the first frame
    alone and the consistency's for each ramp length (candidates every 250 µs up to the exposure time; the grid
    250 µs apart, so that a DAVIS346 pair fits the default memory budget).

    Returns:
        a row per pair: ``frame``, ``reader_us`` and per ramp ``R`` ``delayed_R_us``.
    """
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.io import open_recording
    from evlatcorr.restore import has_events, pair_frames

    if not (math.isfinite(threshold) and threshold > 0):
        raise ValueError(f"threshold must be a positive number, got {threshold}")
    exposure = max(end - start for start, end, _ in open_recording(path).frame_times())
    reach = 3 * exposure  # the next exposure after a gap of up to an exposure, and the candidates' exposure time
    corrector = EventLatencyCorrector(threshold=threshold)
    candidates = torch.arange(0.0, exposure + 1.0, CANDIDATE_STEP_US, dtype=torch.float64)
    rows = []
    for frame, pair in pair_frames(open_recording(path, after_us=reach)):
        if pair is None or not has_events(frame):
            continue
        with warnings.catch_warnings():  # what the corrector warns of is in its own command's report
            warnings.simplefilter("ignore")
            row: dict[str, Any] = dict(frame=int(frame.meta["frame"]), reader_us=float(corrector(frame).latency.mean()))
        for ramp in ramps_us:
            curve = pair_disagreement_curve(pair, threshold, candidates, ramp, grid_us)
            row[f"delayed_{ramp:g}_us"] = curve_minimum(candidates, curve)
        rows.append(row)
    return rows
