"""``benchmarks/pair_curve.py``: a latency curve fitted to two frames' agreement, against one latency, on the suite."""

from __future__ import annotations

import csv

import pytest

from tests.commands import ROOT, run_script


def test_the_script_writes_its_table(tmp_path):
    run = run_script("pair_curve.py", "--split", "dev", "--num", "6", "--size", "32", "40", "--models", "constant",
                     "intensity_delay", "--out", str(tmp_path), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    for row in ("| constant latency (", "| per-pixel delay (", "the constant corrector with the pair |",
                "the corrector's latency, sloped by the curve (a slope on "):
        assert row in table, table
    rows = list(csv.DictReader(open(tmp_path / "results.csv")))
    assert {r["model"] for r in rows} == {"constant", "intensity_delay"}
    for r in rows:
        # without a slope the sloped map is the corrector's latency, and the curve the pair's one latency
        if float(r["slope_us"]) == 0:
            assert r["sloped_psnr"] == r["corrector_psnr"] and r["curve_psnr"] == r["one_psnr"]


def test_bad_arguments_are_refused(tmp_path):
    for args, message in ((["--min-gain", "-1"], "--min-gain must be a non-negative number"),
                          (["--threshold-scale", "0"], "--threshold-scale must be a positive number"),
                          (["--recording", "missing.aedat4", "--threshold", "0.5"],
                           "--recording missing.aedat4: no such file"),
                          (["--recording", "x.aedat4"], "--recording needs the recording's --threshold"),
                          (["--split", "test", "--num", "1", "--models", "intensity"],
                           "no case of ['intensity'] among the first 1")):
        run = run_script("pair_curve.py", *args, cwd=tmp_path)
        assert run.returncode == 2 and message in run.stderr and "Traceback" not in run.stderr
    assert not list(tmp_path.iterdir())


@pytest.mark.slow
def test_a_recordings_pairs_are_read_without_truth(tmp_path):
    # the shared low-light recording: each pair's curve as shipped and unguarded, and the fit's time
    from tests.conftest import shared_data_dir

    if not (shared_data_dir() / "davis346" / "cradle_lowlight.aedat4").is_file():
        pytest.skip("shared DAVIS recordings absent")
    run = run_script("pair_curve.py", "--recording", "cradle_lowlight.aedat4", "--threshold", "0.52", "--out",
                     str(tmp_path), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    rows = list(csv.DictReader(open(tmp_path / "results.csv")))
    told = [r for r in rows if not r["told_nothing"]]
    assert len(rows) == 12 and len(told) == 11
    assert all(float(r["slope_us"]) == 0.0 and float(r["fit_s"]) > 0 for r in told)
    assert sum(float(r["free_slope_us"]) > 0 for r in told) <= 1
    assert "0 of 11 pairs take a slope as shipped" in (tmp_path / "results.md").read_text()
