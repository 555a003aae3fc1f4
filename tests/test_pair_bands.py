"""``benchmarks/pair_bands.py``: a latency per brightness band from two frames' agreement, on the per-pixel delay
cases."""

from __future__ import annotations

import csv

from tests.commands import ROOT, run_script


def test_the_script_writes_its_table(tmp_path):
    run = run_script("pair_bands.py", "--split", "dev", "--num", "8", "--size", "32", "40", "--weights", "1", "inf",
                     "--out", str(tmp_path), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    assert "3 per-pixel delay cases" in table and "| the pair's one latency |" in table
    assert "| a latency per band, weight 1 |" in table and "| a latency per band, weight inf |" in table
    rows = list(csv.DictReader(open(tmp_path / "results.csv")))
    assert len(rows) == 3 and {"pair_map_error_us", "w1_map_error_us", "winf_psnr_change_db"} <= set(rows[0])
    # one band is the whole sensor: its latency is the pair's
    one = run_script("pair_bands.py", "--split", "dev", "--num", "8", "--size", "32", "40", "--bands", "1",
                     "--weights", "inf", "--out", str(tmp_path / "one"), cwd=ROOT)
    assert one.returncode == 0, one.stderr
    for row in csv.DictReader(open(tmp_path / "one" / "results.csv")):
        assert row["winf_map_error_us"] == row["pair_map_error_us"] and float(row["winf_psnr_change_db"]) == 0.0


def test_bad_arguments_are_refused(tmp_path):
    for args, message in ((["--bands", "0"], "--bands must be at least 1"),
                          (["--weights", "0"], "--weights must be positive"),
                          (["--split", "test", "--num", "1"], "no per-pixel delay case among the first 1")):
        run = run_script("pair_bands.py", *args, cwd=tmp_path)
        assert run.returncode == 2 and message in run.stderr and "Traceback" not in run.stderr
    assert not list(tmp_path.iterdir())
