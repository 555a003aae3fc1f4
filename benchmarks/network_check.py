"""A network's PSNR recovery with each estimator's corrected events, on the accuracy suite's cases.

The accuracy suite (``benchmarks/accuracy.py``) scores estimates by EDI. This runs a restoration network
(shipped weights, trained on ideal events) on each case's ideal, delayed and corrected events instead, and
reports its recovery ``(corrected − delayed) / (ideal − delayed)`` per estimator. See
:mod:`evlatcorr.benchmark.network_check`.

    python benchmarks/network_check.py --split test --models constant          # EFNet, the default corrector
    python benchmarks/network_check.py --split test --models constant \\
        --estimator benchmarks/estimators/step_lag.py:estimate                  # ... and another estimator
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.accuracy import (  # noqa: E402
    LATENCY_MODELS,
    corrector_estimator,
    load_estimator,
    make_cases,
    warning_kinds,
)
from evlatcorr.benchmark.network_check import check_case, checks_to_markdown  # noqa: E402
from evlatcorr.restore import build_model  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "test", ("test", "dev", "dev_wide"), num_help="first N cases of the split")
    p.add_argument("--models", nargs="+", choices=LATENCY_MODELS, default=list(LATENCY_MODELS),
                   help="latency models of the cases kept")
    p.add_argument("--network", choices=("efnet", "gem"), default="efnet", help="shipped weights")
    p.add_argument("--estimator", action="append", default=[], metavar="MODULE:FUNCTION",
                   help="an estimator f(frames) -> latency map besides the default corrector; repeatable")
    p.add_argument("--out", type=Path, default=Path("outputs/network_check.md"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    cases = [c for c in make_cases(args.split, args.num, tuple(args.size)) if c.latency_model in args.models]
    if not cases:
        p.error(f"no case of split {args.split} with latency models {args.models}")
    extra = {}
    for spec in args.estimator:
        try:
            fn = load_estimator(spec)
        except (ValueError, ImportError) as err:
            p.error(f"--estimator {spec}: {err}")
        name = Path(spec.rpartition(":")[0]).stem or spec
        while name in extra or name == "constant":  # two estimators of one module each keep their column
            name += "'"
        extra[name] = fn
    _setup.check_out_folder(p, args.out.parent)
    network = build_model(args.network)
    rows, skipped, raised = [], [], []
    t0 = time.perf_counter()
    for i, case in enumerate(cases, 1):
        estimators = {"constant": corrector_estimator("constant", case.threshold), **extra}
        try:
            # the estimators' warnings, counted by kind at the end: one per case would bury the progress lines
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                rows.append(check_case(case, estimators, network))
            raised.append({"warnings": [str(w.message) for w in caught]})
        except ValueError as err:  # e.g. a case with no events in its window: nothing to estimate
            skipped.append(case.name)
            print(f"[{i}/{len(cases)}] {case.name}: skipped ({err})", flush=True)
            continue
        r = rows[-1]
        print(f"[{i}/{len(cases)}] {case.name}: {args.network} PSNR ideal {r['psnr_ideal']:.2f} delayed "
              f"{r['psnr_delayed']:.2f}; " + ", ".join(f"{n} {e['latency_us']:.0f} us {e['psnr']:.2f}"
                                                      for n, e in r["estimators"].items()), flush=True)
    kinds = "".join(f"- {count} of {len(raised)} cases: \"{message}\"\n" for count, message in warning_kinds(raised))
    text = (f"# {args.network} recovery with corrected events ({args.split} split, {len(rows)} cases, "
            f"{time.perf_counter() - t0:.0f} s)\n\n"
            + (f"Skipped (an estimator could not estimate): {', '.join(skipped)}.\n\n" if skipped else "")
            + (f"Warnings the estimates raised, by kind:\n\n{kinds}\n" if kinds else "")
            + checks_to_markdown(rows, args.network))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    print("\n" + text + f"\nwrote {args.out}")


if __name__ == "__main__":
    main()
