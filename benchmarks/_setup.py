"""What every script in ``benchmarks/`` does before it imports torch: the repository on ``sys.path``, the CPU
memory settings (2 MB pages, freed memory kept for reuse).

Each script imports it first (``import _setup``: the script's own folder is on ``sys.path``), so the memory
settings (:func:`evlatcorr.pages.prefer_fast_memory`) come before the process's first tensor.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evlatcorr.pages import prefer_fast_memory  # noqa: E402

prefer_fast_memory()


def shared_recording(name: str) -> Path:
    """A shared DAVIS346 recording: ``../shared`` beside the checkout, else ``/work/shared`` (it may not exist)."""
    shared = next((p for p in (Path(__file__).resolve().parents[2] / "shared", Path("/work/shared"))
                   if (p / "data").is_dir()), Path("../shared"))
    return shared / "data" / "davis346" / name


def passive_openmp() -> None:
    """Let idle OpenMP threads sleep (``OMP_WAIT_POLICY=PASSIVE`` unless set): call before torch loads.

    While another process keeps a core busy, OpenMP's busy-waiting threads made the simulator's small-tensor
    steps 3-20x slower on a 2-core VM; passive waiting costs little otherwise. The suite scripts ask for it;
    the timing scripts do not, so their figures keep torch's default.
    """
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def add_case_options(parser: argparse.ArgumentParser, default_split: str, splits: tuple[str, ...] = ("test", "dev"),
                     num_help: str = "first N cases of each split") -> None:
    """``--split``, ``--num`` and ``--size``: which of the accuracy suite's cases a script runs."""
    from evlatcorr.benchmark.accuracy import DEFAULT_SIZE

    parser.add_argument("--split", choices=splits, default=default_split)
    parser.add_argument("--num", type=int, default=None, help=num_help)
    parser.add_argument("--size", type=int, nargs=2, default=DEFAULT_SIZE, metavar=("H", "W"))


def add_constant_case_options(parser: argparse.ArgumentParser) -> None:
    """:func:`add_case_options` for a script that reads the constant-latency cases of a split (tuning by default)."""
    add_case_options(parser, "tuning", splits=("tuning", "dev", "dev_wide", "test"),
                     num_help="first N cases of each split (before keeping the constant-latency ones)")


def constant_cases(parser: argparse.ArgumentParser, args: argparse.Namespace) -> list:
    """The constant-latency cases of ``--split`` (``tuning``: dev and dev_wide) among the first ``--num`` of each, at
    ``--size``; a usage error where there are none."""
    from evlatcorr.benchmark.accuracy import make_cases

    splits = ("dev", "dev_wide") if args.split == "tuning" else (args.split,)
    cases = [c for s in splits for c in make_cases(s, args.num, tuple(args.size)) if c.latency_model == "constant"]
    if not cases:
        parser.error(f"no constant-latency case among the first {args.num} of split {args.split}")
    return cases


# the smallest frame a script simulates: the suite's scenes and sprites need this many pixels a side
MIN_SCENE_SIZE = 16


def check_case_options(parser: argparse.ArgumentParser, args: argparse.Namespace) -> None:
    """The options of :func:`add_case_options` in range: a usage error before the first case, not a traceback."""
    if args.num is not None and args.num < 1:
        parser.error(f"--num must be at least 1, got {args.num}")
    if min(args.size) < MIN_SCENE_SIZE:
        parser.error(f"--size must be at least {MIN_SCENE_SIZE} {MIN_SCENE_SIZE} (the suite's scenes), got "
                     f"{list(args.size)}")


def check_out_folder(parser: argparse.ArgumentParser, folder: Path) -> None:
    """``--out``'s folder made and written to, last of a script's checks: a usage error, not a run lost when its
    results are written at its end."""
    from evlatcorr.io.outputs import check_writable_folder

    try:
        check_writable_folder(folder)
    except ValueError as exc:
        parser.error(f"--out: {exc}")


def add_exposure_option(parser: argparse.ArgumentParser) -> None:
    """``--exposure-us``: every case at another exposure (:func:`cases_at_exposure`)."""
    parser.add_argument("--exposure-us", type=float, default=None, metavar="US",
                        help="every case at this exposure instead of 20 ms, its latencies and the events' run-on "
                             "scaled with it, its motion kept (evlatcorr.benchmark.accuracy.at_exposure)")


def cases_at_exposure(parser: argparse.ArgumentParser, cases: list, exposure_us: float | None) -> list:
    """``cases`` at ``--exposure-us`` (as they are without it); a value that is not positive is a usage error."""
    if exposure_us is None:
        return cases
    if not exposure_us > 0:
        parser.error(f"--exposure-us must be positive, got {exposure_us}")
    from evlatcorr.benchmark.accuracy import at_exposure

    return [at_exposure(case, exposure_us) for case in cases]


def each_simulated(cases: list, evaluate, desc: str) -> tuple[list, str]:
    """``evaluate(case)`` of each case, with a progress bar; a case the simulator refuses (a ValueError, e.g. a zoom
    compounding over a long recording) is left out. Returns the results and a line naming the cases left out ("" if
    none), for the script's table."""
    from tqdm import tqdm

    results, refused = [], []
    for case in tqdm(cases, desc=desc, unit="case"):
        try:
            results.append(evaluate(case))
        except ValueError as err:
            refused.append(f"{case.name} ({err})")
            tqdm.write(f"{case.name}: not simulated: {err}")
    note = f"\n{len(refused)} case(s) not simulated, left out: " + "; ".join(refused) + "\n" if refused else ""
    return results, note


def evaluate_split(parser: argparse.ArgumentParser, args: argparse.Namespace, keep, evaluate,
                   what: str) -> tuple[list, str]:
    """``evaluate(case)`` of the cases of ``args.split`` (``"tuning"``: dev and dev_wide; the first ``args.num`` of
    each) that ``keep(case)`` accepts: a usage error naming ``what`` when there are none, the output folder ``args.out``
    checked first, the script's exit when none could be simulated. Returns :func:`each_simulated`'s results and note."""
    from evlatcorr.benchmark.accuracy import make_cases

    splits = ("dev", "dev_wide") if args.split == "tuning" else (args.split,)
    cases = [c for s in splits for c in make_cases(s, args.num, tuple(args.size)) if keep(c)]
    if not cases:
        parser.error(f"no {what} among the first {args.num} of split {args.split}")
    check_out_folder(parser, args.out)
    rows, note = each_simulated(cases, evaluate, "cases")
    if not rows:
        sys.exit("no case could be simulated: nothing to report")
    return rows, note


def write_results(folder: Path, title: str, body: str, rows: list[dict]) -> None:
    """``results.md`` (the title, the command that ran and ``body``) and ``results.csv`` (``rows``) under ``folder``,
    and the table printed."""
    import csv
    import shlex
    import sys

    command = shlex.join(["python", f"benchmarks/{Path(sys.argv[0]).name}", *sys.argv[1:]])
    text = f"# {title}\n\n`{command}`\n\n{body}"
    (folder / "results.md").write_text(text)
    with open(folder / "results.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print("\n" + text + f"\nwrote {folder / 'results.md'} and results.csv")
