"""Two frames' consistency as a latency estimate, step EDI against events as ramps: see
:mod:`evlatcorr.benchmark.pair_consistency`.

Each constant-latency case of the suite is simulated as two frames with a camera's gap between them; the latency at
which the two frames' EDI latents agree best in the gap is found for each ramp length (0: step EDI), on the delayed
and on the ideal events, beside the default corrector on the first frame alone.

    python benchmarks/pair_consistency.py                       # the 80 constant-latency tuning cases, ~10 minutes
    python benchmarks/pair_consistency.py --split dev --num 10 --ramps-us 0 3000
    python benchmarks/pair_consistency.py --split dev --ramps-us 5000 10000 --next-factor 0   # the ramps capped alone

``--recording PATH --threshold θ`` does the same on each pair of a recording's consecutive frames (no truth there:
the two estimates side by side, and their medians):

    python benchmarks/pair_consistency.py --recording cradle_lowlight.aedat4 --threshold 0.52
"""

from __future__ import annotations

import _setup  # first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
import csv  # noqa: E402
import shlex  # noqa: E402
import statistics  # noqa: E402
import sys  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.pair_consistency import (  # noqa: E402
    RAMPS_US,
    pair_markdown,
    pair_rows,
    pair_summary,
    recording_rows,
)
from evlatcorr.pair_evidence import DEFAULT_RAMP_NEXT_FACTOR  # noqa: E402


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_constant_case_options(p)
    p.add_argument("--ramps-us", type=float, nargs="+", default=list(RAMPS_US),
                   help="ramp lengths to compare, us (0: step EDI)")
    p.add_argument("--next-factor", type=float, default=DEFAULT_RAMP_NEXT_FACTOR, metavar="FACTOR",
                   help="each ramp also no longer than FACTOR times the interval to its pixel's next event (default: "
                        f"{DEFAULT_RAMP_NEXT_FACTOR:g}, as the shipped pair evidence; 0: the cap alone)")
    p.add_argument("--recording", type=Path, help="a recording's consecutive frames instead of the suite's cases")
    p.add_argument("--threshold", type=float, help="the recording's contrast threshold (with --recording)")
    p.add_argument("--out", type=Path, default=Path("outputs/pair_consistency"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    if not args.next_factor >= 0:
        p.error(f"--next-factor must be 0 or more, got {args.next_factor}")
    if not all(r >= 0 for r in args.ramps_us):
        p.error(f"--ramps-us must be 0 or more, got {args.ramps_us}")
    command = shlex.join(["python", "benchmarks/pair_consistency.py", *sys.argv[1:]])
    rule = (f"; each ramp at most {args.next_factor:g}x the interval to its pixel's next event" if args.next_factor
            else "; the ramps capped alone")
    if args.recording is not None:
        if args.threshold is None or not args.threshold > 0:
            p.error("--recording needs the recording's --threshold, a positive number")
        if not args.recording.is_file():
            p.error(f"--recording {args.recording}: no such file")
        _setup.check_out_folder(p, args.out)
        rows = recording_rows(str(args.recording), args.threshold, args.ramps_us, next_factor=args.next_factor or None)
        title = f"{args.recording.name}, {len(rows)} pairs of consecutive frames, threshold {args.threshold:g}{rule}"
        _write(args.out, rows, title, command, _recording_markdown(rows, args.ramps_us))
        return
    cases = _setup.constant_cases(p, args)
    _setup.check_out_folder(p, args.out)
    with warnings.catch_warnings():  # the corrector's warnings (events that stop, fallbacks): the table says enough
        warnings.simplefilter("ignore")
        rows, note = _setup.each_simulated(cases, lambda case: pair_rows(case, args.ramps_us, args.next_factor or None),
                                           "cases")
    title = f"{args.split} split, {len(rows)} constant-latency cases{rule}"
    _write(args.out, rows, title, command, pair_markdown(pair_summary(rows, args.ramps_us)) + note)


def _recording_markdown(rows: list[dict], ramps_us: list[float]) -> str:
    """A recording's pairs: the corrector's and each ramp's consistency latency per frame, then their medians."""
    names = ["step EDI" if r == 0 else f"ramps up to {r:g} us" for r in ramps_us]
    keys = ["reader_us", *(f"delayed_{r:g}_us" for r in ramps_us)]
    lines = ["| frame | default corrector, the frame alone | " + " | ".join(f"consistency, {n}" for n in names) + " |",
             "| --- " * (len(keys) + 1) + "|"]
    lines += [f"| {row['frame']} | " + " | ".join(f"{row[k]:.0f} us" for k in keys) + " |" for row in rows]
    if rows:
        lines.append("| median | " + " | ".join(f"{statistics.median(row[k] for row in rows):.0f} us" for k in keys)
                     + " |")
    return "\n".join(lines) + "\n"


def _write(out: Path, rows: list[dict], title: str, command: str, table: str) -> None:
    with open(out / "results.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]) if rows else ["case"])
        writer.writeheader()
        writer.writerows(rows)
    text = f"# Two frames' consistency as a latency estimate ({title})\n\n`{command}`\n\n" + table
    (out / "results.md").write_text(text)
    print("\n" + text + f"\nwrote {out / 'results.md'} and results.csv")


if __name__ == "__main__":
    main()
