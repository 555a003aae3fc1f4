"""The ``evlatcorr`` command and the scripts under ``benchmarks/``, run in the test's own process.

A fresh interpreter spends seconds importing torch and Lightning, which a hundred command-line tests would pay each
time; these helpers run the same entry points here and answer as :func:`subprocess.run` does (the exit code, the
text on stdout and on stderr, a traceback on stderr and exit 1 for an uncaught exception). A few tests still start a
real process: the entry points themselves (``python -m evlatcorr``, ``python benchmarks/x.py``), signals, and other
processes' environments.
"""

from __future__ import annotations

import contextlib
import io
import os
import runpy
import subprocess
import sys
import traceback
import warnings
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def run_command(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``evlatcorr ARGS`` in folder ``cwd``, as :func:`subprocess.run` with ``capture_output=True, text=True``
    answers it."""
    from evlatcorr.__main__ import main

    return _in_process(lambda: main(list(args)), ["evlatcorr", *args], cwd)


def run_script(script: str, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``python benchmarks/SCRIPT ARGS`` in folder ``cwd``, as :func:`subprocess.run` answers it."""
    path = ROOT / "benchmarks" / script
    if str(path.parent) not in sys.path:  # where the scripts find their shared setup, as when run from a shell
        sys.path.insert(0, str(path.parent))
    argv = [str(path), *args]

    def script_main() -> None:
        saved = sys.argv
        sys.argv = argv
        try:
            runpy.run_path(str(path), run_name="__main__")
        finally:
            sys.argv = saved

    return _in_process(script_main, argv, cwd)


def _in_process(entry: Callable[[], int | None], argv: list[str], cwd: Path) -> subprocess.CompletedProcess:
    import torch

    out, err = io.StringIO(), io.StringIO()
    before, threads = os.getcwd(), torch.get_num_threads()  # a script may set its own thread count
    os.chdir(cwd)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            # warnings printed as a new interpreter prints them (pytest would record them instead); changing the
            # filters also forgets which warnings an earlier run has already shown
            warnings.simplefilter("default")
            warnings.showwarning = _print_warning
            try:
                code = entry()
            except SystemExit as exc:
                code = _exit_code(exc.code)
            except Exception:  # noqa: BLE001 - what an uncaught exception does to a process
                traceback.print_exc()
                code = 1
    finally:
        os.chdir(before)
        torch.set_num_threads(threads)
    return subprocess.CompletedProcess(argv, 0 if code is None else code, out.getvalue(), err.getvalue())


def _exit_code(code: object) -> int:
    """The status :func:`sys.exit` gives a process for ``code`` (a message is printed to stderr, status 1)."""
    if code is None or isinstance(code, int):
        return code or 0
    print(code, file=sys.stderr)
    return 1


def _print_warning(message, category, filename, lineno, file=None, line=None) -> None:
    sys.stderr.write(warnings.formatwarning(message, category, filename, lineno, line))
