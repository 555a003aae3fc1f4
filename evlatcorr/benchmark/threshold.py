"""How well a recording's contrast threshold θ is estimated, and what its error costs.

EDI needs the camera's θ, and a real recording does not say it: by default ``evlatcorr correct``, ``deblur`` and
``interpolate`` estimate one θ for the recording from its first frames
(:func:`evlatcorr.restore.recording_threshold`: two-frame consistency). Here each of the accuracy suite's cases is
simulated as a short recording with a θ drawn for it over what cameras are set to (log-uniform over
:data:`THRESHOLD_RANGE`; the suite's own θ spans only 0.15-0.3), with a gap between exposures as a camera has, and
written as a file; the recording's θ is estimated as the command line does, and compared with the truth. What the
error costs is measured too: the EDI PSNR of the recording's ideal events (no latency) with the estimated θ against
the true one, and, for constant latency, the default corrector's latency error with each.
"""

from __future__ import annotations

import dataclasses
import math
import statistics
import tempfile
import time
import warnings
from pathlib import Path
from typing import Any

import torch

from evlatcorr.benchmark.accuracy_cases import Case, simulate_case
from evlatcorr.benchmark.accuracy_compare import bootstrap_interval
from evlatcorr.benchmark.compare import edi_psnr, psnr

__all__ = ["THRESHOLD_RANGE", "FRAME_GAP", "case_with_drawn_threshold", "evaluate_threshold", "summarize_thresholds"]

#: the range θ is drawn from, log-uniformly (DAVIS cameras at their usual biases to a low-light recording's 0.52)
THRESHOLD_RANGE = (0.1, 0.6)
#: the frame interval as a multiple of the exposure time (a camera's frames have a gap; 25 ms for 20 ms exposures)
FRAME_GAP = 1.25
#: relative errors counted as "close" in the summary
CLOSE = (0.15, 0.3)
#: EDI with the true θ must beat the blurry frame by this much for θ to matter to the image (dB): where events are
#: few (a dark or slow scene) the blurry frame is nearly sharp, any θ gives about the same image, and θ is not
#: identifiable, so its error there says nothing
MATTERS_DB = 1.0


def case_with_drawn_threshold(case: Case) -> Case:
    """``case`` with its θ drawn log-uniformly over :data:`THRESHOLD_RANGE` from its own seed (the same on every
    machine); its per-pixel mismatch stays relative to it.

    Example:
        >>> from evlatcorr.benchmark.accuracy import make_cases
        >>> case = case_with_drawn_threshold(make_cases("dev", 1)[0])
        >>> 0.1 <= case.threshold <= 0.6
        True
    """
    generator = torch.Generator().manual_seed(case.seed * 7919 + 17)
    u = float(torch.rand((), generator=generator, dtype=torch.float64))
    low, high = THRESHOLD_RANGE
    return dataclasses.replace(case, threshold=round(math.exp(math.log(low) + u * math.log(high / low)), 4))


def evaluate_threshold(case: Case, num_frames: int = 6, folder: str | Path | None = None) -> dict[str, Any]:
    """One recording's θ estimated as the command line does it, against the truth, and what the error costs.

    Args:
        case: the suite's case; its θ is redrawn (:func:`case_with_drawn_threshold`).
        num_frames: frames in the recording (the estimate looks at the first 12 pairs).
        folder: where the recording's file is written (default: a temporary folder, removed after).

    Returns:
        a row: ``case``, ``latency_model``, ``threshold`` (true), ``estimate`` (NaN where the recording has no pair
        of frames with events), ``ratio`` (estimate / true), ``psnr_blurry`` (the blurry frames against the sharp
        ones), ``psnr_true_theta`` and ``psnr_estimated_theta`` (the ideal events' EDI PSNR; each a mean over the
        frames with events), ``psnr_loss_db`` (the true θ's less the estimate's), ``matters`` (EDI with the true θ
        beats the blurry frames by :data:`MATTERS_DB`), ``gain_kept`` (the share of that gain the estimated θ keeps;
        NaN where it does not matter),
        ``latency_error_true_theta_us`` and ``latency_error_estimated_theta_us`` (constant latency: the default
        corrector's mean absolute error over the frames; NaN for the other models) and ``seconds`` (the estimate's
        time).
    """
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.io import H5Recording, write_sequence
    from evlatcorr.restore import has_events, recording_threshold

    case = case_with_drawn_threshold(case)
    delayed, ideal, seq = simulate_case(case, num_frames, frame_interval_us=FRAME_GAP * case.exposure_us)
    with tempfile.TemporaryDirectory(dir=folder) as tmp, warnings.catch_warnings():
        warnings.simplefilter("ignore")  # events missing past the last frame, fallbacks: counted, not printed
        path = Path(tmp) / f"{case.name}.h5"
        write_sequence(path, seq)
        t0 = time.perf_counter()
        estimate = recording_threshold(H5Recording(path))
        seconds = time.perf_counter() - t0
    theta = case.threshold
    row: dict[str, Any] = dict(case=case.name, latency_model=case.latency_model, threshold=theta,
                               estimate=math.nan if estimate is None else estimate, seconds=seconds)
    row["ratio"] = row["estimate"] / theta
    frames = [i for i, frame in enumerate(ideal.split()) if len(frame.events)]
    if estimate is None or not frames:
        return row | dict(psnr_blurry=math.nan, psnr_true_theta=math.nan, psnr_estimated_theta=math.nan,
                          psnr_loss_db=math.nan, matters=False, gain_kept=math.nan,
                          latency_error_true_theta_us=math.nan, latency_error_estimated_theta_us=math.nan)
    ideal_frames, delayed_frames = ideal.split(), delayed.split()
    blurry_psnr = statistics.fmean(psnr(ideal_frames[i].blurry, ideal_frames[i].sharp) for i in frames)
    true_psnr = statistics.fmean(edi_psnr(ideal_frames[i], theta) for i in frames)
    estimated_psnr = statistics.fmean(edi_psnr(ideal_frames[i], estimate) for i in frames)
    matters = true_psnr - blurry_psnr > MATTERS_DB
    row.update(psnr_blurry=blurry_psnr, psnr_true_theta=true_psnr, psnr_estimated_theta=estimated_psnr,
               psnr_loss_db=true_psnr - estimated_psnr, matters=matters,
               gain_kept=(estimated_psnr - blurry_psnr) / (true_psnr - blurry_psnr) if matters else math.nan)
    errors = {"true_theta": math.nan, "estimated_theta": math.nan}
    searched = [frame for frame in delayed_frames if has_events(frame)]  # late events may leave a frame none
    if case.latency_model == "constant" and searched:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            for name, value in (("true_theta", theta), ("estimated_theta", estimate)):
                corrector = EventLatencyCorrector(threshold=value)
                errors[name] = statistics.fmean(abs(float(corrector(frame).latency.mean()) - case.latency_us)
                                                for frame in searched)
    row.update(latency_error_true_theta_us=errors["true_theta"],
               latency_error_estimated_theta_us=errors["estimated_theta"])
    return row


def summarize_thresholds(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """The rows' aggregate: cases, cases estimated, median / p90 / worst relative error of θ, the share within
    :data:`CLOSE`, the median and highest ratio estimate / true θ, the EDI PSNR the error costs (median / p90 /
    worst), the share of EDI's gain over the blurry frame that the estimate keeps (median / p10 / worst, where θ
    matters) and for constant latency the default corrector's median error with the true and the estimated θ.
    The two medians a reader compares with a goal come with a seeded bootstrap 95 % interval over the recordings
    (``median_relative_error_interval``, ``median_gain_kept_interval``; NaN for fewer than two): a few dozen
    recordings leave a median a few points either way.

    Example:
        >>> rows = [dict(threshold=0.2, estimate=0.22, ratio=1.1, psnr_loss_db=0.1, latency_error_true_theta_us=300.0,
        ...              latency_error_estimated_theta_us=320.0)] * 2
        >>> summary = summarize_thresholds(rows)
        >>> summary["median_relative_error"], summary["within_15%"]
        (0.1, 1.0)
    """
    done = [r for r in rows if math.isfinite(r["estimate"])]
    summary: dict[str, Any] = {"cases": len(rows), "estimated": len(done)}
    if not done:
        return summary
    errors = sorted(abs(r["ratio"] - 1.0) for r in done)
    ratios = sorted(r["ratio"] for r in done)
    losses = sorted(r["psnr_loss_db"] for r in done if math.isfinite(r["psnr_loss_db"]))
    summary.update(median_relative_error=round(_quantile(errors, 0.5), 4),
                   median_relative_error_interval=bootstrap_interval(errors, statistic="median"),
                   p90_relative_error=_quantile(errors, 0.9),
                   worst_relative_error=errors[-1], lowest_ratio=ratios[0], median_ratio=_quantile(ratios, 0.5),
                   highest_ratio=ratios[-1])
    for close in CLOSE:
        summary[f"within_{close:.0%}"] = sum(e <= close for e in errors) / len(errors)
    if losses:
        summary.update(median_psnr_loss_db=_quantile(losses, 0.5), p90_psnr_loss_db=_quantile(losses, 0.9),
                       worst_psnr_loss_db=losses[-1])
    kept = sorted(r["gain_kept"] for r in done if math.isfinite(r.get("gain_kept", math.nan)))
    if kept:
        summary.update(median_gain_kept=_quantile(kept, 0.5),
                       median_gain_kept_interval=bootstrap_interval(kept, statistic="median"),
                       p10_gain_kept=_quantile(kept, 0.1),
                       worst_gain_kept=kept[0])
    constant = [r for r in done if math.isfinite(r.get("latency_error_true_theta_us", math.nan))]
    if constant:
        summary.update(
            constant_cases=len(constant),
            median_latency_error_true_theta_us=statistics.median(r["latency_error_true_theta_us"] for r in constant),
            median_latency_error_estimated_theta_us=statistics.median(r["latency_error_estimated_theta_us"]
                                                                      for r in constant))
    return summary


def _quantile(values: list[float], q: float) -> float:
    """The ``q`` quantile of sorted ``values`` (linear between neighbours)."""
    position = q * (len(values) - 1)
    low = math.floor(position)
    high = min(low + 1, len(values) - 1)
    return values[low] + (values[high] - values[low]) * (position - low)
