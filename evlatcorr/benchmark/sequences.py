"""The accuracy suite's cases as sequences of frames: each frame's own latency against the fused one.

A recording's frames share their latency, and :func:`evlatcorr.temporal.fuse_latencies` combines neighbouring
frames' evidence. :func:`evaluate_sequence` simulates a case as ``num_frames`` back-to-back frames, estimates each
frame with the default corrector, fuses the estimates over windows of frames, and scores every frame as the
suite scores one (latency error, EDI PSNR recovery), and the same for the sequence's ideal events (how far from 0,
and what correcting by it costs); :func:`summarize_sequences` aggregates per latency model.

Example:
    >>> from evlatcorr.benchmark.accuracy import make_cases
    >>> case = make_cases("dev")[17]
    >>> rows = evaluate_sequence(case, num_frames=3, windows={"fused ±1": (1, 1)})  # doctest: +SKIP
    >>> sorted({r["estimate"] for r in rows})  # doctest: +SKIP
    ['fused ±1', 'per frame']
"""

from __future__ import annotations

import functools
import math
import statistics
import warnings
from collections.abc import Sequence
from typing import Any

import numpy as np
import torch

from evlatcorr.benchmark.accuracy import NO_GAP_DB, Case, simulate_case
from evlatcorr.benchmark.accuracy_compare import CLEAR_CHANGE_DB, bootstrap_interval
from evlatcorr.benchmark.compare import edi_psnr, recovery
from evlatcorr.pair_curve import fit_pair_curve
from evlatcorr.pair_evidence import DEFAULT_RAMP_NEXT_FACTOR, DEFAULT_RAMP_US, pair_log_odds
from evlatcorr.temporal import DEFAULT_PAIR_REFINE, frame_evidence, fuse_latencies

__all__ = ["evaluate_sequence", "summarize_sequences", "fused_against_own", "DEFAULT_WINDOWS", "IDEAL"]

# the fused estimates scored: (frames before, frames after)
DEFAULT_WINDOWS = {"fused ±2": (2, 2), "fused, past 2 (stream)": (2, 0)}
# the model of the rows of a sequence's ideal events (no latency)
IDEAL = "ideal"
# an ideal frame corrected by an estimate loses more than this much EDI PSNR: counted
LOSING_DB = 0.5


def evaluate_sequence(case: Case, num_frames: int = 6, windows: dict[str, tuple] | None = None,
                      ideal: bool = True, pair_weights: Sequence[float] = (), frame_gap: float = 1.0,
                      ramp_us: float = DEFAULT_RAMP_US,
                      ramp_next_factor: float | None = DEFAULT_RAMP_NEXT_FACTOR,
                      slope: bool = False,
                      pair_refines: Sequence[float | None] = (DEFAULT_PAIR_REFINE,)) -> list[dict[str, Any]]:
    """Every frame of a case simulated as a sequence, scored with its own latency and with each fused one.

    Args:
        case: the suite's case (its scene, motion, latency and noise models).
        num_frames: frames in the sequence (at least 1).
        windows: name -> ``(before, after)`` frames for :func:`~evlatcorr.temporal.fuse_latencies`, or ``(before,
            after, no_latency_mass)``; default :data:`DEFAULT_WINDOWS`.
        ideal: also estimate the same sequence's ideal events (no latency: what a recording in bright light gives),
            as rows of model :data:`IDEAL`.
        pair_weights: for each weight ``w``, also ``"fused ±2, pairs w"``, ``"per frame, with its pair w"`` and
            ``"fused, past 2 (stream), pairs w"``: 2 frames either side, none or 2 before, with each pair of
            consecutive frames' agreement (:func:`evlatcorr.pair_evidence.pair_log_odds` at weight ``w``, ramps up to
            ``ramp_us``) added to the first frame's evidence.
        frame_gap: time from one exposure's start to the next, in exposure times (1: back to back; a camera's
            frames have a gap).
        ramp_us: the pairs' ramps' longest, µs (0: steps).
        ramp_next_factor: the ramps' longest as a multiple of the interval to the pixel's next event (None: none).
        slope: with ``pair_weights``, also each ``"fused ±2, pairs w"`` with the sequence's slope over intensity
            (``"fused ±2, pairs w, sloped"``): one curve fitted to all its pairs' agreement
            (:func:`evlatcorr.pair_curve.fit_pair_curve`), each frame's map the fused latency plus the curve's
            departure from its single latency at the frame's intensities (what ``evlatcorr correct --mode spatial``
            does); its ``latency_us`` is the map's mean.
        pair_refines: with ``pair_weights``, each pair-fused estimate at each of these ``pair_refine`` of
            :func:`~evlatcorr.temporal.fuse_latencies` (how many times the pairs count near the fused latency; 1 or
            None: not at all); the default's estimates keep their names, the others end in ``", refine r"``.

    Returns:
        one row per frame and estimate (``"per frame"`` and each window): ``case``, ``model``, ``frame``,
        ``estimate``, ``latency_us``, ``true_latency_us`` (mean of the map), ``error_us`` (estimate − mean truth),
        ``psnr_ideal``, ``psnr_uncorrected``, ``psnr_corrected`` and ``recovery`` (NaN without a gap). A frame
        with no events gets no rows. The ideal events' rows have a true latency of 0, ``psnr_uncorrected`` equal to
        ``psnr_ideal`` (their EDI PSNR as they are), ``psnr_corrected`` that of the events corrected by the
        estimate, and no recovery (NaN).

    Raises:
        ValueError: for a weight that is not positive, a gap under 1, a negative ramp, a factor that is not
            positive or a ``pair_refines`` under 1.
    """
    windows = DEFAULT_WINDOWS if windows is None else windows
    if any(not (isinstance(w, (int, float)) and math.isfinite(w) and w > 0) for w in pair_weights):
        raise ValueError(f"pair_weights must be positive numbers, got {list(pair_weights)}")
    if not (math.isfinite(frame_gap) and frame_gap >= 1):
        raise ValueError(f"frame_gap must be 1 or more (frames do not overlap), got {frame_gap}")
    if not (math.isfinite(ramp_us) and ramp_us >= 0):
        raise ValueError(f"ramp_us must be 0 or more, got {ramp_us}")
    if ramp_next_factor is not None and not (math.isfinite(ramp_next_factor) and ramp_next_factor > 0):
        raise ValueError(f"ramp_next_factor must be positive or None, got {ramp_next_factor}")
    if not pair_refines or any(r is not None and not (math.isfinite(r) and r >= 1) for r in pair_refines):
        raise ValueError(f"pair_refines must be numbers >= 1 or None, at least one, got {list(pair_refines)}")
    ramps = (ramp_us, ramp_next_factor)
    delayed, ideal_events, seq = simulate_case(case, num_frames, frame_interval_us=frame_gap * case.exposure_us)
    frames, ideal_frames = delayed.split(), ideal_events.split()

    def pairs(which: str) -> list:
        if not pair_weights or num_frames < 2:
            return []
        return seq.pairs(which, after_us=case.after_us).split()

    def sloped(which: str, sequence: list, estimates: dict) -> dict[str, torch.Tensor | None]:
        """Each estimate's departure maps per frame (None: the estimate as it is)."""
        out: dict[str, Any] = {name: None for name in estimates}
        if not (slope and pair_weights and num_frames >= 2):
            return out
        try:
            fit = fit_pair_curve(seq.pairs(which, after_us=case.after_us), case.threshold)
        except ValueError:  # no pair tells anything: no slope
            fit = None
        has_slope = fit is not None and fit.slope_us > 0  # without a slope the maps are the fused latencies
        departures = [fit.departure(frame.blurry).double() if has_slope else None for frame in sequence]
        for name in list(estimates):
            if name.startswith("fused ±2, pairs"):
                estimates[f"{name}, sloped"] = estimates[name]
                out[f"{name}, sloped"] = departures
        return out

    rows = []
    kept, estimates = _estimates(frames, case.threshold, windows, pairs("delayed"), pair_weights, ramps,
                                  pair_refines)
    maps = sloped("delayed", frames, estimates)
    for n, i in enumerate(kept):
        frame = frames[i]
        true = float(frame.meta["true_latency"].mean())
        psnr_ideal, psnr_uncorrected = edi_psnr(ideal_frames[i], case.threshold), edi_psnr(frame, case.threshold)
        for name, values in estimates.items():
            value = _latency(values[n], maps[name], i, case.exposure_us)
            psnr = edi_psnr(frame, case.threshold, latency=value)
            value = float(torch.as_tensor(value).mean())
            rows.append(dict(case=case.name, model=case.latency_model, frame=i, estimate=name, latency_us=value,
                             true_latency_us=true, error_us=value - true, psnr_ideal=psnr_ideal,
                             psnr_uncorrected=psnr_uncorrected, psnr_corrected=psnr,
                             recovery=recovery(psnr, psnr_uncorrected, psnr_ideal, NO_GAP_DB)))
    if ideal:
        kept, estimates = _estimates(ideal_frames, case.threshold, windows, pairs("ideal"), pair_weights,
                                      ramps, pair_refines)
        maps = sloped("ideal", ideal_frames, estimates)
        for n, i in enumerate(kept):
            psnr_ideal = edi_psnr(ideal_frames[i], case.threshold)
            for name, values in estimates.items():
                value = _latency(values[n], maps[name], i, case.exposure_us)
                psnr = edi_psnr(ideal_frames[i], case.threshold, latency=value)
                value = float(torch.as_tensor(value).mean())
                rows.append(dict(case=case.name, model=IDEAL, frame=i, estimate=name, latency_us=value,
                                 true_latency_us=0.0, error_us=value, psnr_ideal=psnr_ideal,
                                 psnr_uncorrected=psnr_ideal, psnr_corrected=psnr, recovery=math.nan))
    return rows


def _latency(value: torch.Tensor, departures: list | None, frame: int, high: float) -> float | torch.Tensor:
    """A frame's estimate: its fused latency, or with ``departures`` that plus the frame's departure map, held inside
    0 to ``high`` (µs) as spatial mode holds its maps inside the search range."""
    if departures is None or departures[frame] is None:
        return float(value)
    return (float(value) + departures[frame]).clamp(0.0, high)


def _estimates(frames: list, threshold: float, windows: dict[str, tuple], pairs: Sequence = (),
               pair_weights: Sequence[float] = (), ramps: tuple[float, float | None] = (DEFAULT_RAMP_US, None),
               pair_refines: Sequence[float | None] = (DEFAULT_PAIR_REFINE,)
               ) -> tuple[list[int], dict[str, torch.Tensor]]:
    """The default corrector's latency of each frame with events (their indices), alone (``"per frame"``), fused
    over each window, and fused with the pairs' agreement at each weight and refinement (``pairs[i]``: frames i and
    i + 1)."""
    from evlatcorr.correction import EventLatencyCorrector

    corrector = EventLatencyCorrector(threshold=threshold)
    own, candidates, log_p, kept = [], [], [], []
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fallbacks are counted in the figures, not printed per frame
        for i, frame in enumerate(frames):
            if len(frame.events) == 0:
                continue
            latency, cand, row = frame_evidence(corrector(frame))[0]
            own.append(latency)
            candidates.append(cand)
            log_p.append(row)
            kept.append(i)
    if not kept:
        return [], {}
    latency = torch.tensor(own, dtype=torch.float64)
    estimates = {"per frame": latency}
    for name, window in windows.items():
        estimates[name] = fuse_latencies(latency, candidates, log_p, *window)
    if pair_weights:
        # weight 1, then scaled: the log-odds are proportional to the weight
        unit = [pair_log_odds(pairs[i], threshold, cand, ramps[0], 1.0, ramps[1]) if i < len(pairs) else None
                for i, cand in zip(kept, candidates)]
        for w in pair_weights:
            weighted = [None if u is None else w * u for u in unit]
            for refine in pair_refines:
                tail = "" if refine == DEFAULT_PAIR_REFINE else f", refine {refine or 1:g}"
                fused = functools.partial(fuse_latencies, latency, candidates, log_p, pair_log_odds=weighted,
                                          pair_refine=refine)
                estimates[f"fused ±2, pairs {w:g}{tail}"] = fused(2, 2)
                # one pair alone (a pair-reading network behind the corrector): the frame's evidence and its pair's
                estimates[f"per frame, with its pair {w:g}{tail}"] = fused(0, 0)
                # a stream of pairs (interpolation, REFID): each frame has its own pair, not the later frames'
                estimates[f"fused, past 2 (stream), pairs {w:g}{tail}"] = fused(2, 0)
    return kept, estimates


def summarize_sequences(rows: list[dict[str, Any]]) -> dict[str, dict[str, dict[str, float]]]:
    """Per estimate and latency model: frames, the median / 90th percentile / worst absolute error (constant
    latency only, µs), the median / 10th percentile / worst recovery and how many frames recover less than half of
    their gap (frames with a gap only); for the ideal events (:data:`IDEAL`), the median absolute estimate, how many
    are within 150 µs of 0, and the mean and worst change of EDI PSNR that correcting by them makes, and on how many
    frames it loses more than :data:`LOSING_DB`."""
    out: dict[str, dict[str, dict[str, float]]] = {}
    for estimate in dict.fromkeys(r["estimate"] for r in rows):
        out[estimate] = {}
        for model in dict.fromkeys(r["model"] for r in rows):
            sel = [r for r in rows if r["estimate"] == estimate and r["model"] == model]
            errors = [abs(r["error_us"]) for r in sel]
            gains = [r["recovery"] for r in sel if not math.isnan(r["recovery"])]
            stats: dict[str, float] = {"frames": len(sel), "frames_with_gap": len(gains)}
            if model == "constant" and errors:
                stats.update(median_abs_error_us=statistics.median(errors),
                             p90_abs_error_us=float(np.percentile(errors, 90)), worst_abs_error_us=max(errors))
            if gains:
                stats.update(median_recovery=statistics.median(gains), p10_recovery=float(np.percentile(gains, 10)),
                             worst_recovery=min(gains), below_half=sum(g < 0.5 for g in gains))
            if model == IDEAL and sel:
                changes = [r["psnr_corrected"] - r["psnr_uncorrected"] for r in sel]
                stats.update(median_abs_error_us=statistics.median(errors),
                             within_150us=sum(e <= 150.0 for e in errors),
                             mean_psnr_change_db=statistics.fmean(changes), worst_psnr_change_db=min(changes),
                             losing_frames=sum(c < -LOSING_DB for c in changes))
            out[estimate][model] = stats
    return out


def fused_against_own(rows: list[dict[str, Any]], seed: int = 0) -> list[dict[str, Any]]:
    """Each fused estimate against every frame's own (``"per frame"``), case by case: does fusing help, beyond what
    the cases can tell?

    A case's frames share its scene, motion and latency, so they are not independent draws: the EDI PSNR change
    (fused − own) is averaged over each case's frames, and the cases' means over the cases, with a seeded bootstrap
    95 % interval that resamples cases.

    Returns:
        one dict per fused estimate and latency model (the ideal events' rows too, as :data:`IDEAL`): ``estimate``,
        ``model``, ``cases``, ``frames``, ``mean_psnr_change_db``, ``psnr_change_low_db``, ``psnr_change_high_db``,
        and ``cases_gaining`` / ``cases_losing`` (a case's mean moving more than 0.5 dB).

    Example:
        >>> rows = [dict(case=c, model="constant", frame=f, estimate=e, psnr_corrected=30.0 + (e != "per frame"))
        ...         for c in ("a", "b") for f in range(3) for e in ("per frame", "fused ±2")]
        >>> [(g["cases"], g["frames"], g["mean_psnr_change_db"]) for g in fused_against_own(rows)]
        [(2, 6, 1.0)]
    """
    own = {(r["case"], r["model"], r["frame"]): r["psnr_corrected"] for r in rows if r["estimate"] == "per frame"}
    groups = []
    for estimate in dict.fromkeys(r["estimate"] for r in rows if r["estimate"] != "per frame"):
        for model in dict.fromkeys(r["model"] for r in rows):
            per_case: dict[str, list[float]] = {}
            for r in rows:
                key = (r["case"], r["model"], r["frame"])
                if r["estimate"] == estimate and r["model"] == model and key in own:
                    per_case.setdefault(r["case"], []).append(r["psnr_corrected"] - own[key])
            if not per_case:
                continue
            means = [statistics.fmean(changes) for changes in per_case.values()]
            low, high = bootstrap_interval(means, seed=seed)
            groups.append({"estimate": estimate, "model": model, "cases": len(means),
                           "frames": sum(len(changes) for changes in per_case.values()),
                           "mean_psnr_change_db": statistics.fmean(means), "psnr_change_low_db": low,
                           "psnr_change_high_db": high, "cases_gaining": sum(m > CLEAR_CHANGE_DB for m in means),
                           "cases_losing": sum(m < -CLEAR_CHANGE_DB for m in means)})
    return groups
