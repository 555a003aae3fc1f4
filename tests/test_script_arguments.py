"""The benchmark scripts refuse bad arguments as argparse does: exit 2 and one line, never a traceback."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.commands import ROOT, run_script


@pytest.mark.parametrize("script, args, message", [
    ("speed.py", ["--part", "search", "--device", "tpu"], "--device must be cpu or cuda, got 'tpu'"),
    ("accuracy.py", ["--split", "test", "--threads", "0"], "--threads must be >= 1, got 0"),
    ("accuracy.py", ["--split", "test", "--exposure-us", "-5"], "--exposure-us must be positive, got -5.0"),
    ("sequence_accuracy.py", ["--exposure-us", "0"], "--exposure-us must be positive, got 0.0"),
    ("threshold.py", ["--exposure-us", "-1"], "--exposure-us must be positive, got -1.0"),
    ("demo.py", ["--latency-us", "-3"], "latency_us must be in [0, 1000000]"),
    ("real_data.py", ["--threshold", "-1"], "--threshold must be a positive number, got -1.0"),
    ("profile_search.py", ["--device", "tpu"], "--device must be cpu or cuda, got 'tpu'"),
    ("threshold.py", ["--frames", "1"], "--frames must be at least 2 (θ is estimated from pairs of frames), got 1"),
    ("threshold.py", ["--num", "0"], "--num must be at least 1, got 0"),
    ("compare_accuracy.py", ["missing", "missing"], "missing: cannot read an accuracy run's results"),
    # tracebacks once (an empty case list, a size the scenes refuse, a count of 0)
    ("accuracy.py", ["--num", "0"], "--num must be at least 1"),
    ("accuracy.py", ["--size", "3", "3"], "--size must be at least 16 16"),
    ("speed.py", ["--repeats", "0"], "--repeats must be >= 1"),
    ("demo.py", ["--size", "3", "3"], "--size must be at least 16 16"),
    ("spatial.py", ["--order", "-1"], "--order >= 0"),
    ("train_curve_reader.py", ["--members", "0"], "--members, --epochs, --channels and --layers must be >= 1"),
    ("train_tile_reader.py", ["--workers", "0"], "--workers, --members and --epochs must be >= 1"),
    ("real_data.py", ["--frames", "99"], "--frames [99]: the recording has 13 frames"),
])
def test_bad_arguments_exit_2_with_one_line(script, args, message, tmp_path):
    run = run_script(script, *args, cwd=tmp_path)
    assert run.returncode == 2, run.stderr
    assert message in run.stderr and "Traceback" not in run.stderr
    assert not list(tmp_path.iterdir())  # nothing written


@pytest.mark.parametrize("script, args", [
    ("accuracy.py", ["--split", "dev", "--num", "1"]),
    ("sequence_accuracy.py", ["--split", "dev", "--num", "1"]),
    ("threshold.py", ["--split", "dev", "--num", "1"]),
    ("real_data.py", []),
])
def test_an_out_folder_that_cannot_be_written_is_refused_before_the_first_case(script, args, tmp_path):
    # found at the start, not when the results are written at the end of the run
    (tmp_path / "file").write_text("")
    run = run_script(script, *args, "--out", str(tmp_path / "file" / "out"), cwd=tmp_path)
    assert run.returncode == 2, run.stderr
    assert f"{script}: error: --out: " in run.stderr and "cannot be written" in run.stderr


def test_a_script_run_from_the_shell_exits_2_with_one_line(tmp_path):
    # the tests above run the scripts in this process; this one starts Python as a user's shell does
    run = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "accuracy.py"), "--num", "0"],
                         capture_output=True, text=True, cwd=tmp_path, timeout=300)
    assert run.returncode == 2 and "--num must be at least 1" in run.stderr and "Traceback" not in run.stderr
    assert not list(tmp_path.iterdir())
