"""Accuracy of latency estimators on the seeded simulated suite (:mod:`evlatcorr.benchmark.accuracy`).

One frame per case (20 ms exposure, events up to 15 ms after its end), photographs and procedural
scenes, translation / random / rotation / zoom / two moving objects, constant, delayed-map and
photoreceptor latency, shot noise, leak, threshold mismatch and refractory period. For each case:
the latency error, EDI PSNR against the sharp mid-exposure frame with ideal, uncorrected and
corrected events, the share of the ideal-vs-uncorrected gap recovered, and for the photoreceptor
model the share of the best constant shift's gain.

    python benchmarks/accuracy.py --split test --mode constant              # 48 cases, 96x128
    python benchmarks/accuracy.py --split dev --num 8 --mode both           # constant and spatial (test-time fit)
    python benchmarks/accuracy.py --split tuning                            # dev + dev_wide: 160 cases to tune on
    python benchmarks/accuracy.py --cases 'test-0*' --estimator mypkg.latency:estimate
    python benchmarks/accuracy.py --estimator path/to/file.py:estimate --mode none

``--estimator module:function`` (or ``file.py:function``) loads ``f(frames) -> latency map
(B, 1, H, W) µs``; ``frames.meta["threshold"]`` holds the case's true contrast threshold (or
``"auto"`` with ``--auto-threshold``). Writes ``results.md``, ``results.csv``, ``results.json`` and
``results.png`` (per estimator: the estimated against the true latency, each case's recovery and share of the best
constant shift's gain, sorted) under ``--out``.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
import fnmatch  # noqa: E402
import platform  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from evlatcorr.benchmark.accuracy import (  # noqa: E402
    Case,
    Estimator,
    corrector_estimator,
    load_estimator,
    make_cases,
    run_suite,
    summarize,
    to_markdown,
    warning_kinds,
    write_results,
)
from evlatcorr.config import SCORES  # noqa: E402


def _given_auto_threshold(estimate: Estimator) -> Estimator:
    """``estimate`` handed ``meta["threshold"] = "auto"`` in place of the case's θ (``--auto-threshold``)."""
    return lambda frames: estimate(frames.replace(meta={**frames.meta, "threshold": "auto"}))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "test", ("test", "dev", "dev_wide", "tuning", "both"))
    p.add_argument("--mode", choices=("constant", "spatial", "both", "none"), default="constant",
                   help="built-in EventLatencyCorrector modes to evaluate ('none': only --estimator)")
    p.add_argument("--estimator", action="append", default=[], metavar="MODULE:FUNCTION",
                   help="an extra estimator f(frames) -> latency map; repeatable")
    p.add_argument("--auto-threshold", action="store_true",
                   help="built-in correctors estimate the threshold (threshold='auto') instead of the true one")
    p.add_argument("--search-range", type=float, nargs=2, default=None, metavar=("LO", "HI"),
                   help="latency search range of the built-in correctors, µs (default: their own, 0 to the exposure)")
    p.add_argument("--score", default=None, choices=SCORES,
                   help="built-in correctors' sharpness score (default: theirs, 'learned': the curve reader, "
                        "evlatcorr.curve_reader; 'consensus': the median of the three sparsity scores' minima)")
    p.add_argument("--ghost-confidence", type=float, default=None, metavar="C",
                   help="built-in correctors: frames whose score confidence is at most C take the ghost cue's "
                        "latency (default: theirs, 0: only frames with no minimum; see evlatcorr.ghost)")
    p.add_argument("--before-us", type=float, default=0.0, metavar="US",
                   help="each frame also keeps this long of events before its exposure, as a recording's stream does "
                        "(default 0: from the exposure start)")
    _setup.add_exposure_option(p)
    p.add_argument("--cases", nargs="+", default=None, metavar="NAME", help="case names or glob patterns")
    p.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's)")
    p.add_argument("--out", type=Path, default=Path("outputs/accuracy"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    if args.threads is not None:
        if args.threads < 1:
            p.error(f"--threads must be >= 1, got {args.threads}")
        torch.set_num_threads(args.threads)

    splits = {"both": ("dev", "test"), "tuning": ("dev", "dev_wide")}.get(args.split, (args.split,))
    cases: list[Case] = [c for s in splits for c in make_cases(s, args.num, tuple(args.size))]
    if args.cases:
        cases = [c for c in cases if any(fnmatch.fnmatchcase(c.name, pat) for pat in args.cases)]
        if not cases:
            p.error(f"no case of split {args.split} matches {args.cases}")
    cases = _setup.cases_at_exposure(p, cases, args.exposure_us)

    threshold_of = (lambda case: "auto") if args.auto_threshold else (lambda case: case.threshold)
    options = {} if args.search_range is None else {"search_range": tuple(args.search_range)}
    if args.ghost_confidence is not None:
        options["ghost_confidence"] = args.ghost_confidence
    if args.score is not None:
        options["score"] = args.score
    modes = {"both": ("constant", "spatial"), "none": ()}.get(args.mode, (args.mode,))
    estimators = {}
    for mode in modes:
        try:  # fail now, not after the first simulation (e.g. spatial without a numeric threshold)
            corrector_estimator(mode, threshold_of(cases[0]), **options)
        except ValueError as err:
            p.error(f"--mode {mode}{' --auto-threshold' if args.auto_threshold else ''}: {err}")
        estimators[mode] = lambda case, mode=mode: corrector_estimator(mode, threshold_of(case), **options)
    for spec in args.estimator:
        try:
            fn = load_estimator(spec)
        except (ValueError, ImportError) as err:
            p.error(f"--estimator {spec}: {err}")
        name = spec.rpartition(":")[2]
        while name in estimators:
            name += "'"
        fn = _given_auto_threshold(fn) if args.auto_threshold else fn
        estimators[name] = lambda case, fn=fn: fn
    if not estimators:
        p.error("nothing to evaluate: --mode none needs --estimator")
    _setup.check_out_folder(p, args.out)

    print(f"{len(cases)} cases ({', '.join(splits)}), {args.size[0]}x{args.size[1]}, estimators: "
          f"{', '.join(estimators)}; torch threads {torch.get_num_threads()}", flush=True)
    t0 = time.perf_counter()
    results = run_suite(cases, estimators, progress=lambda line: print(line, flush=True), before_us=args.before_us)
    total = time.perf_counter() - t0
    summary = summarize(results)
    sim = sum(r["sim_time_s"] for r in results if r["estimator"] == next(iter(estimators)))
    ref = sum(r["reference_time_s"] for r in results if r["estimator"] == next(iter(estimators)))
    est = {name: sum(r["time_s"] for r in results if r["estimator"] == name) for name in estimators}
    warned = sum(bool(r["warnings"]) for r in results)
    kinds = warning_kinds(results)
    before = f" and from {args.before_us:.0f} us before its start" if args.before_us else ""
    scaled = "" if args.exposure_us is None else " (the suite's latencies scaled from its 20 ms exposure)"
    header = "\n".join([
        "# Latency estimator accuracy (simulated suite)", "",
        f"`{shlex.join(['python', 'benchmarks/accuracy.py', *(sys.argv[1:] if argv is None else argv)])}`", "",
        f"- {len(cases)} cases ({', '.join(splits)}) at {args.size[1]}x{args.size[0]} px, one "
        f"{cases[0].exposure_us / 1000:g} ms exposure each, events up to {cases[0].after_us / 1000:g} ms after its "
        f"end{before}{scaled}; EDI with 500 bins and the true threshold.",
        f"- estimators: {', '.join(estimators)}; threshold given to the built-in correctors: "
        f"{'auto' if args.auto_threshold else 'the true one'}; search range: "
        f"{'default (0 to the exposure time)' if args.search_range is None else args.search_range} µs.",
        f"- {warned} of {len(results)} estimates raised warnings"
        + (f", of {len(kinds)} kind{'s' * (len(kinds) > 1)}:" if kinds else "."),
        *(f"  - {count} estimates: \"{example[:300]}\"" for count, example in kinds),
        f"- total {total:.0f} s on {platform.machine()} with {torch.get_num_threads()} torch threads: simulation "
        f"{sim:.0f} s, references (ideal / uncorrected EDI, best-shift scan) {ref:.0f} s, estimation "
        + ", ".join(f"{n} {t:.0f} s" for n, t in est.items()) + ".", "", ""])
    paths = write_results(results, args.out, summary, header)
    print()
    print(header + to_markdown(results, summary))
    print("wrote " + ", ".join(str(p) for p in paths.values()))


if __name__ == "__main__":
    main()
