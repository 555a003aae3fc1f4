"""The one training command line, with a subcommand per trainer: ``python -m evlatcorr.lightning {latency,restore}``.

Each subcommand module (:mod:`~evlatcorr.lightning.latency_command`,
:mod:`~evlatcorr.lightning.restore_command`) gives ``SUMMARY``, ``DESCRIPTION``, ``add_arguments``,
``check`` and ``run``; this module builds the parsers and dispatches. :func:`run_command` runs one
subcommand under another program name (``python -m evlatcorr.train`` and
``python -m evlatcorr.training`` are kept that way).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from types import ModuleType
from typing import Any

from evlatcorr.lightning import latency_command, restore_command
from evlatcorr.lightning.arguments import CommandParser

__all__ = ["PROG", "COMMANDS", "build_parser", "main", "run_command"]

PROG = "python -m evlatcorr.lightning"

DESCRIPTION = """Training with Lightning, on one CPU or many GPUs (--devices N --strategy ddp).

  latency   trains the latency polynomial self-supervised, on simulated scenes or a recording
  restore   trains or fine-tunes a restoration network (EFNet, GEM, REFID), optionally with a corrector

`python -m evlatcorr.lightning COMMAND --help` shows a command's options.
"""

#: subcommand name -> the module that implements it
COMMANDS: dict[str, ModuleType] = {"latency": latency_command, "restore": restore_command}


def build_parser(prog: str = PROG) -> CommandParser:
    """The parser of the whole command line, one subparser per entry of :data:`COMMANDS`.

    Example:
        >>> args = build_parser().parse_args(["latency", "--epochs", "1"])
        >>> args.command, args.epochs
        ('latency', 1)
    """
    parser = CommandParser(prog=prog, description=DESCRIPTION, formatter_class=argparse.RawDescriptionHelpFormatter)
    subparsers = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=CommandParser)
    for name, command in COMMANDS.items():
        sub = subparsers.add_parser(name, help=command.SUMMARY, description=command.DESCRIPTION,
                                    formatter_class=argparse.RawDescriptionHelpFormatter)
        command.add_arguments(sub)
        sub.set_defaults(command_parser=sub)
    return parser


def main(argv: Sequence[str] | None = None) -> Any:
    """Run ``python -m evlatcorr.lightning COMMAND ...``; returns what the subcommand returns."""
    argv = list(sys.argv[1:] if argv is None else argv)
    args = build_parser().parse_args(argv)
    return _dispatch(args.command, args, args.command_parser, f"{PROG} {' '.join(argv)}")


def run_command(name: str, argv: Sequence[str] | None = None, prog: str | None = None) -> Any:
    """Run one subcommand with its own program name in usage, errors and the recorded command.

    Example:
        >>> run_command("restore", ["--help"], prog="python -m evlatcorr.train")  # doctest: +SKIP
    """
    command = COMMANDS[name]
    argv = list(sys.argv[1:] if argv is None else argv)
    prog = prog or f"{PROG} {name}"
    parser = CommandParser(prog=prog, description=command.DESCRIPTION,
                           formatter_class=argparse.RawDescriptionHelpFormatter)
    command.add_arguments(parser)
    args = parser.parse_args(argv)
    return _dispatch(name, args, parser, f"{prog} {' '.join(argv)}")


def _dispatch(name: str, args: argparse.Namespace, parser: argparse.ArgumentParser, command_line: str) -> Any:
    command = COMMANDS[name]
    command.check(args, parser)
    args.command_line = command_line.rstrip()
    args.error_label = parser.prog.removeprefix("python -m ")  # "evlatcorr.train: error: ..." as before
    return command.run(args)
