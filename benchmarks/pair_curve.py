"""A latency that grows as pixels dim, fitted to two frames' agreement, against one latency for every pixel.

Each case of the accuracy suite (constant latency, per-pixel delay: dim pixels later, the photoreceptor low-pass)
is simulated as two frames with a camera's gap between them (1.25 exposures). The pair gives four corrections of the
first frame: the pair's agreement alone at one latency; the constant corrector given the pair (the learned reader
with the pair's evidence: what ``EventLatencyCorrector()`` does with pairs); the curve ``ψ(L) = a + b · f(L)``
fitted to the pair's agreement (:func:`evlatcorr.pair_curve.fit_pair_curve`, ``--min-gain`` the least relative drop
of the disagreement a slope must earn); and the constant corrector's latency plus that curve's departure from its own
single latency (what ``EventLatencyCorrector(mode="spatial")`` does with pairs). Each is scored against the true
latency map (mean absolute error) and by the first frame's EDI PSNR against ideal events (recovery), and compared
with the constant corrector case by case. ``--threshold-scale`` runs every step with a contrast threshold that far
from the true one (a recording's θ estimated wrong).

    python benchmarks/pair_curve.py --split dev             # 40 cases, ~4 min on 2 cores
    python benchmarks/pair_curve.py --split test            # 48 cases, report only
    python benchmarks/pair_curve.py --split dev_wide --threshold-scale 1.4
    python benchmarks/pair_curve.py --recording cradle_lowlight.aedat4 --threshold 0.52   # a recording's pairs

``--recording`` has no truth: each pair of the recording's consecutive frames (with events, events past the second
exposure) gets the curve as shipped and with no bar and no θ check (``min_gain=0``, ``threshold_scales=()``), and the
shipped fit's time.

Writes ``results.md`` and ``results.csv`` under ``--out``.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from evlatcorr.benchmark.accuracy_cases import simulate_case  # noqa: E402
from evlatcorr.benchmark.compare import edi_psnr, recovery  # noqa: E402
from evlatcorr.correction import EventLatencyCorrector  # noqa: E402
from evlatcorr.pair_curve import DEFAULT_MIN_GAIN, fit_pair_curve  # noqa: E402
from evlatcorr.temporal import frame_evidence  # noqa: E402

FRAME_GAP = 1.25  # the frame interval in exposure times, as benchmarks/pair_consistency.py's
MODELS = {"constant": "constant latency", "intensity_delay": "per-pixel delay", "intensity": "photoreceptor low-pass"}
ESTIMATES = ("one", "corrector", "curve", "sloped")
NAMES = {"one": "the pair's agreement, one latency", "corrector": "the constant corrector with the pair",
         "curve": "the curve fitted to the pair", "sloped": "the corrector's latency, sloped by the curve"}


def case_row(case, min_gain: float, threshold_scale: float = 1.0) -> dict:
    """One case: each correction's latency map error and the first frame's EDI PSNR (every step with the case's
    contrast threshold times ``threshold_scale``: a threshold estimated wrong)."""
    delayed, ideal, seq = simulate_case(case, 2, frame_interval_us=FRAME_GAP * case.exposure_us)
    pair = seq.pairs("delayed", after_us=case.after_us).split()[0]
    first, theta = delayed.split()[0], case.threshold * threshold_scale
    truth = first.meta["true_latency"][0, 0].double()
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # fallbacks show in the figures
        corrected = frame_evidence(EventLatencyCorrector(threshold=theta)(pair))[0][0]
    constant = torch.full_like(truth, corrected)
    started = time.perf_counter()
    try:
        fit = fit_pair_curve(pair, theta, min_gain=min_gain)
    except ValueError:  # the pair tells nothing (blank, or no events past the second exposure): the corrector stands
        fit = None
    fit_s = time.perf_counter() - started
    maps = {"one": constant if fit is None else torch.full_like(truth, fit.single_latency_us), "corrector": constant,
            "curve": constant if fit is None else fit.curve(first.blurry)[0, 0].detach().double()}
    # the curve's departure from its own single latency, about the corrector's
    maps["sloped"] = constant if fit is None else constant + fit.departure(first.blurry)[0, 0].double()
    ideal_db, stamped_db = edi_psnr(ideal.split()[0], theta), edi_psnr(first, theta)
    row = {"case": case.name, "model": case.latency_model, "fitted": fit is not None,
           "slope_us": 0.0 if fit is None else fit.slope_us, "offset_us": math.nan if fit is None else fit.offset_us,
           "gain": math.nan if fit is None else fit.gain, "fit_s": fit_s, "psnr_ideal": ideal_db,
           "psnr_uncorrected": stamped_db, "true_latency_us": float(truth.mean())}
    for name, latency in maps.items():
        latency = latency.clamp(0.0, case.exposure_us)  # as the spatial corrector keeps a map in the search range
        db = edi_psnr(first, theta, latency=latency[None, None].float())
        row[f"{name}_map_error_us"] = float((truth - latency).abs().mean())
        row[f"{name}_psnr"] = db
        row[f"{name}_recovery"] = recovery(db, stamped_db, ideal_db)
    return row


def recording_rows(path: Path, threshold: float) -> list[dict]:
    """Each pair of a recording's consecutive frames: the curve as shipped and unguarded, and the shipped fit's time."""
    from evlatcorr.io import open_recording
    from evlatcorr.restore import has_events, pair_frames, pair_reach_us

    rec = open_recording(path)
    rec.after_us = pair_reach_us(rec)  # to the next exposure's end, and the latencies read past it
    rows = []
    for k, (frame, pair) in enumerate(pair_frames(rec)):
        if pair is None or not has_events(frame):
            continue
        row = {"pair": k, "fit_s": math.nan, "slope_us": math.nan, "offset_us": math.nan, "gain": math.nan,
               "free_slope_us": math.nan, "free_offset_us": math.nan, "free_gain": math.nan,
               "single_latency_us": math.nan, "told_nothing": ""}
        try:
            started = time.perf_counter()
            shipped = fit_pair_curve(pair, threshold)
            row["fit_s"] = time.perf_counter() - started
            free = fit_pair_curve(pair, threshold, min_gain=0.0, threshold_scales=())
        except ValueError as err:  # the pair tells nothing
            rows.append(row | {"told_nothing": str(err)})
            continue
        rows.append(row | {"slope_us": shipped.slope_us, "offset_us": shipped.offset_us, "gain": shipped.gain,
                           "free_slope_us": free.slope_us, "free_offset_us": free.offset_us, "free_gain": free.gain,
                           "single_latency_us": shipped.single_latency_us, "told_nothing": ""})
    return rows


def recording_markdown(rows: list[dict]) -> str:
    lines = ["| pair | single latency | shipped: offset / slope | no bar, no θ check: offset / slope (gain) | fit |",
             "| --- | --- | --- | --- | --- |"]
    for r in rows:
        if r["told_nothing"]:
            lines.append(f"| {r['pair']} | tells nothing | | | |")
            continue
        lines.append(f"| {r['pair']} | {r['single_latency_us']:.0f} µs | {r['offset_us']:.0f} / {r['slope_us']:.0f} µs "
                     f"| {r['free_offset_us']:.0f} / {r['free_slope_us']:.0f} µs ({r['free_gain']:.2%}) | "
                     f"{r['fit_s']:.2f} s |")
    told = [r for r in rows if not r["told_nothing"]]
    times = [r["fit_s"] for r in told]
    return ("\n".join(lines) + f"\n\n{sum(r['slope_us'] > 0 for r in told)} of {len(told)} pairs take a slope as "
            f"shipped, {sum(r['free_slope_us'] > 0 for r in told)} with no bar and no θ check; the shipped fit's "
            f"median time per pair: {statistics.median(times) if times else math.nan:.2f} s.\n")


def to_markdown(rows: list[dict]) -> str:
    def tenth(values: list[float]) -> float:
        return sorted(values)[len(values) // 10] if values else math.nan

    lines = ["| latency model (cases) | correction | map error: median | recovery: median / p10 | EDI PSNR against the "
             "constant corrector: mean / worst / best | cases losing / gaining > 0.5 dB | map error below the "
             "corrector's |", "| --- | --- | --- | --- | --- | --- | --- |"]
    for model, label in MODELS.items():
        group = [r for r in rows if r["model"] == model]
        if not group:
            continue
        slopes = sum(r["slope_us"] > 0 for r in group)
        for name in ESTIMATES:
            rec = [r[f"{name}_recovery"] for r in group if not math.isnan(r[f"{name}_recovery"])]
            change = [r[f"{name}_psnr"] - r["corrector_psnr"] for r in group]
            error = statistics.median(r[f"{name}_map_error_us"] for r in group)
            below = sum(r[f"{name}_map_error_us"] < r["corrector_map_error_us"] - 1 for r in group)
            recs = f"{statistics.median(rec):.0%} / {tenth(rec):.0%}" if rec else ""
            versus = ("" if name == "corrector" else f"{statistics.mean(change):+.2f} / {min(change):+.2f} / "
                      f"{max(change):+.2f} dB")
            counts = "" if name == "corrector" else f"{sum(c < -0.5 for c in change)} / {sum(c > 0.5 for c in change)}"
            what = NAMES[name] + (f" (a slope on {slopes})" if name in ("curve", "sloped") else "")
            lines.append(f"| {label} ({len(group)}) | {what} | {error:.0f} µs | {recs} | {versus} | {counts} | "
                         + ("" if name == "corrector" else f"{below} of {len(group)}") + " |")
    times = [r["fit_s"] for r in rows]
    unfitted = sum(not r["fitted"] for r in rows)
    return ("\n".join(lines) + f"\n\nThe fit's median time per pair: {statistics.median(times):.2f} s (96x128). "
            f"{unfitted} pair(s) told nothing (blank, or no events past the second exposure): the constant "
            "corrector's latency stands there, in every row.\n")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "tuning", ("tuning", "dev", "dev_wide", "test"))
    p.add_argument("--min-gain", type=float, default=DEFAULT_MIN_GAIN,
                   help=f"the least relative drop of the disagreement a slope must earn (default: {DEFAULT_MIN_GAIN})")
    p.add_argument("--threshold-scale", type=float, default=1.0,
                   help="use the true contrast threshold times this, everywhere (a threshold estimated wrong; "
                        "default: 1)")
    p.add_argument("--models", nargs="+", choices=list(MODELS), default=list(MODELS),
                   help="latency models to run (default: all three)")
    p.add_argument("--recording", type=Path, help="a recording's consecutive frames instead of the suite's cases "
                   "(a path, or the name of a shared DAVIS346 recording)")
    p.add_argument("--threshold", type=float, help="the recording's contrast threshold (with --recording)")
    p.add_argument("--out", type=Path, default=Path("outputs/pair_curve"))
    args = p.parse_args(argv)
    if args.recording is not None:
        if args.threshold is None or not (math.isfinite(args.threshold) and args.threshold > 0):
            p.error("--recording needs the recording's --threshold, a positive number")
        path = args.recording if args.recording.is_file() else _setup.shared_recording(str(args.recording))
        if not path.is_file():
            p.error(f"--recording {args.recording}: no such file")
        _setup.check_out_folder(p, args.out)
        rows = recording_rows(path, args.threshold)
        if not rows:
            sys.exit(f"{path}: no pair of consecutive frames with events")
        _setup.write_results(args.out, f"A latency curve fitted to each pair of {path.name} (threshold "
                             f"{args.threshold:g})", recording_markdown(rows), rows)
        return
    _setup.check_case_options(p, args)
    if not (math.isfinite(args.threshold_scale) and args.threshold_scale > 0):
        p.error(f"--threshold-scale must be a positive number, got {args.threshold_scale}")
    if not (math.isfinite(args.min_gain) and args.min_gain >= 0):
        p.error(f"--min-gain must be a non-negative number, got {args.min_gain}")
    rows, note = _setup.evaluate_split(p, args, lambda case: case.latency_model in args.models,
                                       lambda case: case_row(case, args.min_gain, args.threshold_scale),
                                       f"case of {args.models}")
    _setup.write_results(args.out, "A latency curve fitted to two frames' agreement", to_markdown(rows) + note, rows)


if __name__ == "__main__":
    main()
