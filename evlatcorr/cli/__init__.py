"""The ``evlatcorr`` command line: correct, deblur, interpolate, simulate and inspect event recordings.

Exit codes: 0 success; 2 bad input (unreadable or unsupported file, bad option, unknown or absent device,
an output that cannot be written or would replace an input); 130 / 143 interrupted (SIGINT / SIGTERM);
1 other errors. A run that fails or is interrupted leaves no output behind and never touches its input.

Each command has its module: :mod:`evlatcorr.cli.correct`, :mod:`evlatcorr.cli.restoration` (deblur and
interpolate); simulate and info are here; :mod:`evlatcorr.cli.parser` holds the arguments and
:mod:`evlatcorr.cli.common` what the commands share.
"""

from __future__ import annotations

import argparse
import signal
import sys
import warnings
from collections.abc import Sequence

from evlatcorr.cli.common import EXIT_BAD_INPUT, EXIT_OK, WarningPrinter, open_input
from evlatcorr.cli.correct import cmd_correct
from evlatcorr.cli.parser import build_parser
from evlatcorr.cli.restoration import cmd_deblur, cmd_interpolate

__all__ = ["main"]


def cmd_simulate(args: argparse.Namespace) -> int:
    from evlatcorr.io import write_sequence
    from evlatcorr.io.outputs import check_hdf5_name
    from evlatcorr.simulate import simulate

    check_hdf5_name(args.output)
    seq = simulate(args.image, num_frames=args.frames, height=args.size[0], width=args.size[1],
                   exposure_us=args.exposure_us, frame_interval_us=args.interval_us, latency=args.latency_model,
                   latency_us=args.latency_us, seed=args.seed)
    write_sequence(args.output, seq)
    print(f"wrote {args.output}: {args.frames} frames {args.size[1]}x{args.size[0]}, "
          f"{len(seq.delayed_events)} events, latency {args.latency_model} "
          f"({float(seq.true_latency.mean()):.0f} us mean)")
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    rec = open_input(args)
    info = rec.info()
    width = max(map(len, info)) + 1
    for key, value in info.items():
        print(f"{key:{width}s}{value}")
    return EXIT_OK


class _Terminated(KeyboardInterrupt):
    """SIGTERM, raised like Ctrl-C so every ``finally`` and temporary-file cleanup runs."""


def _on_sigterm(signum, frame) -> None:  # noqa: ARG001
    raise _Terminated()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the ``evlatcorr`` command with ``argv`` (default: the process's arguments); returns its exit code.

    Example:
        >>> main(["simulate", "rec.h5", "--frames", "2", "--size", "32", "40"])  # doctest: +SKIP
        0
    """
    from evlatcorr.io import RecordingError

    args = build_parser().parse_args(argv)
    command = {"correct": cmd_correct, "deblur": cmd_deblur, "interpolate": cmd_interpolate,
               "simulate": cmd_simulate, "info": cmd_info}
    previous = signal.signal(signal.SIGTERM, _on_sigterm) if _main_thread() else None
    try:
        with warnings.catch_warnings():  # restores the filters and warnings.showwarning on the way out
            warnings.simplefilter("always")  # every warning reaches the printer, which keeps each message once
            printer = WarningPrinter(args.command)
            warnings.showwarning = printer
            try:
                return command[args.command](args)
            finally:  # the frames' repeated warnings, one line a kind, before any error's line
                printer.summarise()
    except (RecordingError, ValueError, OSError) as exc:  # bad input, or an OS error on the user's paths
        print(f"evlatcorr {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt as exc:
        terminated = isinstance(exc, _Terminated)
        print(f"evlatcorr {args.command}: {'terminated' if terminated else 'interrupted'}; no output was written",
              file=sys.stderr)
        return 128 + (signal.SIGTERM if terminated else signal.SIGINT)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def _main_thread() -> bool:
    import threading

    return threading.current_thread() is threading.main_thread()

