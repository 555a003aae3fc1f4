"""Latency over sequences of frames: each frame's own estimate against the estimate fused with its neighbours'.

The accuracy suite's cases (:mod:`evlatcorr.benchmark.accuracy`) simulated as ``--frames`` back-to-back frames of
one recording (:mod:`evlatcorr.benchmark.sequences`). Every frame is estimated with the default corrector, then
:func:`evlatcorr.temporal.fuse_latencies` combines the learned reader's evidence of 2 frames either side
(``fused ±2``) or of the 2 frames before (a stream); ``fused ±2, pairs 10`` adds each pair of consecutive frames'
agreement (:mod:`evlatcorr.pair_evidence`), as ``evlatcorr correct`` fuses a recording. Each frame is scored as
the suite scores one: latency error (constant latency), EDI PSNR recovery. The same sequences' ideal events (no
latency, as a recording in bright light gives) are estimated too (``--no-ideal`` skips them): how far from 0 each
estimate lies and what correcting them by it does to their EDI PSNR. Each fused estimate is also compared with every
frame's own, case by case, with a bootstrap interval over the cases.

    python benchmarks/sequence_accuracy.py --split tuning              # dev + dev_wide: 160 sequences
    python benchmarks/sequence_accuracy.py --split test --frames 6     # report only
    python benchmarks/sequence_accuracy.py --split tuning --no-latency-mass 0 0.1   # also without the rule, and at 0.1
    python benchmarks/sequence_accuracy.py --split test --exposure-us 40000 # every case at a 40 ms exposure
    python benchmarks/sequence_accuracy.py --split dev --pair-weights 3 10 30 --frame-gap 1.25  # a camera's gap

Writes ``results.md``, ``results.csv`` and ``results.json`` under ``--out``.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.accuracy import make_cases  # noqa: E402
from evlatcorr.benchmark.sequences import (  # noqa: E402
    DEFAULT_WINDOWS,
    IDEAL,
    LOSING_DB,
    evaluate_sequence,
    fused_against_own,
    summarize_sequences,
)
from evlatcorr.pair_evidence import DEFAULT_PAIR_WEIGHT, DEFAULT_RAMP_NEXT_FACTOR, DEFAULT_RAMP_US  # noqa: E402
from evlatcorr.temporal import DEFAULT_NO_LATENCY_MASS, DEFAULT_PAIR_REFINE  # noqa: E402

MODELS = {"constant": "constant latency", "intensity": "photoreceptor low-pass", "intensity_delay": "per-pixel delay"}


def to_markdown(summary: dict, command: str, seconds: float, paired: list[dict] | None = None) -> str:
    lines = [f"`{command}` ({seconds / 60:.1f} min)", "",
             "| estimate | latency model | frames (with a gap) | abs. error: median / p90 / worst | "
             "recovery: median / p10 / worst | frames recovering < 50 % |", "| --- | --- | --- | --- | --- | --- |"]
    ideal = []
    for estimate, models in summary.items():
        for model, s in models.items():
            if model == IDEAL:
                ideal.append(f"| {estimate} | {s['frames']} | {s['median_abs_error_us']:.0f} µs; {s['within_150us']} | "
                             f"{s['mean_psnr_change_db']:+.2f} / {s['worst_psnr_change_db']:+.2f} dB | "
                             f"{s['losing_frames']} |")
                continue
            error = (f"{s['median_abs_error_us']:.0f} / {s['p90_abs_error_us']:.0f} / {s['worst_abs_error_us']:.0f} µs"
                     if "median_abs_error_us" in s else "")
            gain = (f"{s['median_recovery']:.0%} / {s['p10_recovery']:.0%} / {s['worst_recovery']:.0%}"
                    if "median_recovery" in s else "")
            below = f"{s['below_half']} of {s['frames_with_gap']}" if "below_half" in s else ""
            lines.append(f"| {estimate} | {MODELS.get(model, model)} | {s['frames']} ({s['frames_with_gap']}) | "
                         f"{error} | {gain} | {below} |")
    if ideal:
        lines += ["", "The same sequences' ideal events (no latency, as in bright light), corrected by the estimate:",
                  "",
                  "| estimate | frames | median abs. estimate; within 150 µs | EDI PSNR change: mean / worst | "
                  f"frames losing > {LOSING_DB} dB |", "| --- | --- | --- | --- | --- |", *ideal]
    if paired:
        lines += ["", "Each fused estimate against every frame's own, case by case: EDI PSNR change (fused − own) "
                  "averaged over a case's frames, then over the cases, with a bootstrap 95 % interval that resamples "
                  "cases (an interval that holds 0 is within what the cases tell):", "",
                  "| estimate | latency model | cases (frames) | mean PSNR change dB (95 % interval) | "
                  "cases gaining / losing > 0.5 dB |", "| --- | --- | --- | --- | --- |"]
        for g in paired:
            lines.append(f"| {g['estimate']} | {MODELS.get(g['model'], g['model'])} | {g['cases']} ({g['frames']}) | "
                         f"{g['mean_psnr_change_db']:+.3f} ({_db(g['psnr_change_low_db'])} to "
                         f"{_db(g['psnr_change_high_db'])}) | {g['cases_gaining']} / {g['cases_losing']} |")
    return "\n".join(lines) + "\n"


def _db(value: float) -> str:
    return "–" if math.isnan(value) else f"{value:+.3f}"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "tuning", ("test", "dev", "dev_wide", "tuning"), num_help="first N cases of each split")
    p.add_argument("--frames", type=int, default=6, help="frames per sequence (default: 6)")
    p.add_argument("--models", nargs="+", choices=tuple(MODELS), default=list(MODELS),
                   help="latency models to run (default: all)")
    p.add_argument("--no-latency-mass", type=float, nargs="+", default=[], metavar="SHARE",
                   help="also score 'fused ±2' with fuse_latencies(no_latency_mass=SHARE): 0 where the fused "
                        "probability keeps more than that share on no latency (0: without that rule; the default "
                        f"windows use {DEFAULT_NO_LATENCY_MASS})")
    p.add_argument("--pair-weights", type=float, nargs="*", default=[DEFAULT_PAIR_WEIGHT], metavar="W",
                   help="also score 'fused ±2' with each pair of consecutive frames' agreement "
                        "(evlatcorr.pair_evidence.pair_log_odds, as evlatcorr correct fuses them) at these weights "
                        f"(default: {DEFAULT_PAIR_WEIGHT:g}; none: without)")
    p.add_argument("--pair-ramp-us", type=float, default=DEFAULT_RAMP_US,
                   help=f"the pairs' ramps' longest, us (default: {DEFAULT_RAMP_US:g})")
    p.add_argument("--pair-ramp-next", type=float, default=DEFAULT_RAMP_NEXT_FACTOR, metavar="FACTOR",
                   help="the pairs' ramps' longest as a multiple of the interval to the pixel's next event (default: "
                        f"{DEFAULT_RAMP_NEXT_FACTOR:g}; 0: no such limit)")
    p.add_argument("--pair-refine", type=float, nargs="+", default=[DEFAULT_PAIR_REFINE], metavar="R",
                   help="score the pair-fused estimates with fuse_latencies(pair_refine=R) for each R: near the fused "
                        "latency the pairs count R times (default: "
                        f"{DEFAULT_PAIR_REFINE:g}; 1: not refined; estimates at other R are named '..., refine R')")
    p.add_argument("--frame-gap", type=float, default=1.0,
                   help="time from one exposure's start to the next, in exposure times (default: 1, back to back)")
    p.add_argument("--slope", action="store_true",
                   help="also score each 'fused ±2, pairs W' with the sequence's slope over intensity fitted to its "
                        "pairs (evlatcorr.pair_curve; what evlatcorr correct --mode spatial does)")
    p.add_argument("--no-ideal", action="store_true",
                   help="skip the sequences' ideal events (estimated by default: what bright light gives)")
    _setup.add_exposure_option(p)
    p.add_argument("--out", type=Path, default=Path("outputs/sequences"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    if args.frames < 2:  # one frame has no neighbours: its fused estimates would be its own
        p.error(f"--frames must be at least 2 (fusing needs a frame's neighbours), got {args.frames}")
    if any(not (math.isfinite(w) and w > 0) for w in args.pair_weights):
        p.error(f"--pair-weights must be positive, got {args.pair_weights}")
    if any(not (math.isfinite(r) and r >= 1) for r in args.pair_refine):
        p.error(f"--pair-refine must be 1 or more, got {args.pair_refine}")
    if not (math.isfinite(args.frame_gap) and args.frame_gap >= 1):
        p.error(f"--frame-gap must be 1 or more (frames do not overlap), got {args.frame_gap}")
    if not (math.isfinite(args.pair_ramp_us) and args.pair_ramp_us >= 0):
        p.error(f"--pair-ramp-us must be 0 or more, got {args.pair_ramp_us}")
    if not (math.isfinite(args.pair_ramp_next) and args.pair_ramp_next >= 0):
        p.error(f"--pair-ramp-next must be 0 or more, got {args.pair_ramp_next}")
    if any(not 0 <= share < 1 for share in args.no_latency_mass):
        p.error(f"--no-latency-mass must be in [0, 1), got {args.no_latency_mass}")
    windows = dict(DEFAULT_WINDOWS) | {
        (f"fused ±2, 0 where p(0) > {share:g}" if share else "fused ±2, without the no-latency rule"):
            (2, 2, share or None) for share in args.no_latency_mass}
    splits = {"tuning": ("dev", "dev_wide")}.get(args.split, (args.split,))
    cases = [c for s in splits for c in make_cases(s, args.num, tuple(args.size)) if c.latency_model in args.models]
    cases = _setup.cases_at_exposure(p, cases, args.exposure_us)
    _setup.check_out_folder(p, args.out)
    t0 = time.perf_counter()
    per_case, unsimulated = _setup.each_simulated(
        cases, lambda case: evaluate_sequence(case, args.frames, windows, ideal=not args.no_ideal,
                                              pair_weights=args.pair_weights, frame_gap=args.frame_gap,
                                              ramp_us=args.pair_ramp_us,
                                              ramp_next_factor=args.pair_ramp_next or None, slope=args.slope,
                                              pair_refines=args.pair_refine),
        "sequences")
    rows = [row for case_rows in per_case for row in case_rows]
    seconds = time.perf_counter() - t0
    if not rows:
        sys.exit("no frame had events: nothing to report")
    summary = summarize_sequences(rows)
    paired = fused_against_own(rows)
    command = shlex.join(["python", "benchmarks/sequence_accuracy.py", *(sys.argv[1:] if argv is None else argv)])
    table = to_markdown(summary, command, seconds, paired) + unsimulated
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.md").write_text(table)
    (args.out / "results.json").write_text(json.dumps({"command": command, "summary": summary,
                                                       "fused_against_own": paired}, indent=1))
    with open(args.out / "results.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(table)
    print(f"wrote {args.out}/results.md, results.csv, results.json")


if __name__ == "__main__":
    main()
