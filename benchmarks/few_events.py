"""How few events still tell a latency? The suite's constant-latency cases with their events thinned at random.

Each case's events are kept with each share of ``--shares`` and the default corrector estimates the latency from what
is left; the errors are grouped by the events left in the frame's exposure and search window, beside the error of a
guess that knows only the cases' typical latency. See :mod:`evlatcorr.benchmark.few_events`;
:data:`evlatcorr.checks.FEW_EVENTS` comes from this table.

    python benchmarks/few_events.py                  # the 80 constant-latency tuning cases, about 2 minutes
    python benchmarks/few_events.py --split dev --num 10
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
import csv  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.few_events import (  # noqa: E402
    DEFAULT_SHARES,
    few_events_markdown,
    few_events_summary,
    thinned_estimates,
)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_constant_case_options(p)
    p.add_argument("--shares", type=float, nargs="+", default=list(DEFAULT_SHARES),
                   help="shares of each case's events kept, in (0, 1]")
    p.add_argument("--out", type=Path, default=Path("outputs/few_events"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    if not all(0.0 < s <= 1.0 for s in args.shares):
        p.error(f"--shares must lie in (0, 1], got {args.shares}")
    cases = _setup.constant_cases(p, args)
    _setup.check_out_folder(p, args.out)
    rows, note = _setup.each_simulated(cases, lambda case: thinned_estimates(case, args.shares), "cases")
    rows = [row for case_rows in rows for row in case_rows]
    with open(args.out / "results.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["case"])
        writer.writeheader()
        writer.writerows(rows)
    text = (f"# Latency error by events in the window ({args.split} split, {len(cases)} constant-latency cases, "
            f"shares kept {', '.join(f'{s:g}' for s in args.shares)})\n\n"
            + few_events_markdown(few_events_summary(rows)) + note)
    (args.out / "results.md").write_text(text)
    print("\n" + text + f"\nwrote {args.out / 'results.md'} and results.csv")


if __name__ == "__main__":
    main()
