"""Two accuracy runs, case by case: is the change better, or within what the suite's cases can tell?

    python benchmarks/accuracy.py --split tuning --out runs/before          # at the base commit
    python benchmarks/accuracy.py --split tuning --out runs/after           # with the change
    python benchmarks/compare_accuracy.py runs/before runs/after
    python benchmarks/compare_accuracy.py runs/a runs/a --estimator constant --other-estimator my_estimator

For each latency model, over the cases both runs scored: the mean EDI PSNR change with a bootstrap 95 % interval,
the cases gaining or losing more than 0.5 dB, and each run's median error
(:mod:`evlatcorr.benchmark.accuracy_compare`). A run with several estimators compares them the same way in its own
``results.md``, each against the first.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path

# isort: split

import argparse  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.accuracy_compare import compare_runs, comparison_markdown, load_results  # noqa: E402


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("base", type=Path, help="the run compared against: its --out folder or results.json")
    p.add_argument("other", type=Path, help="the run compared: its --out folder or results.json")
    p.add_argument("--estimator", default=None, help="the estimator of the base run (default: its only one, or "
                                                     "'constant')")
    p.add_argument("--other-estimator", default=None, help="the estimator of the other run (default: --estimator)")
    p.add_argument("--seed", type=int, default=0, help="the bootstrap's seed")
    args = p.parse_args(argv)
    try:
        base, other = load_results(args.base), load_results(args.other)
    except ValueError as exc:
        p.error(str(exc))
    base_name = args.estimator or _default_estimator(p, base, args.base)
    other_name = args.other_estimator or base_name
    labels = (f"{args.base}:{base_name}", f"{args.other}:{other_name}")
    try:
        groups = compare_runs(base, other, base_name, other_name, labels, args.seed)
    except ValueError as exc:
        p.error(str(exc))
    print(comparison_markdown(groups))
    return 0


def _default_estimator(p: argparse.ArgumentParser, rows: list[dict], path: Path) -> str:
    names = list(dict.fromkeys(r["estimator"] for r in rows))
    if len(names) == 1:
        return names[0]
    if "constant" in names:
        return "constant"
    p.error(f"{path} holds several estimators ({', '.join(names)}): choose one with --estimator")
    raise AssertionError  # p.error exits


if __name__ == "__main__":
    sys.exit(main())
