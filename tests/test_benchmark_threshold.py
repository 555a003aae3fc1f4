from __future__ import annotations

import dataclasses
import json
import math

import pytest

from evlatcorr.benchmark.accuracy import make_cases
from evlatcorr.benchmark.accuracy_cases import simulate_case
from evlatcorr.benchmark.threshold import (
    MATTERS_DB,
    THRESHOLD_RANGE,
    case_with_drawn_threshold,
    evaluate_threshold,
    summarize_thresholds,
)
from tests.commands import run_script
from tests.test_accuracy import tiny_case


def test_each_case_draws_its_own_threshold_the_same_every_time():
    cases = make_cases("test")
    drawn = [case_with_drawn_threshold(c).threshold for c in cases]
    assert drawn == [case_with_drawn_threshold(c).threshold for c in cases]
    assert all(THRESHOLD_RANGE[0] <= t <= THRESHOLD_RANGE[1] for t in drawn)
    assert min(drawn) < 0.15 and max(drawn) > 0.45  # the range is covered, not the suite's 0.15-0.3
    changed = case_with_drawn_threshold(cases[0])
    assert dataclasses.replace(changed, threshold=cases[0].threshold) == cases[0]  # nothing else changes


def test_frames_with_a_gap_between_exposures():
    case = tiny_case()
    delayed, _, _ = simulate_case(case, 3, frame_interval_us=1.25 * case.exposure_us)
    assert (delayed.exposure_start[1:] - delayed.exposure_start[:-1]).tolist() == [12_500.0, 12_500.0]
    assert (delayed.exposure_end - delayed.exposure_start).tolist() == [10_000.0] * 3
    with pytest.raises(ValueError, match="frame_interval_us must be at least the exposure time"):
        simulate_case(case, 2, frame_interval_us=5000.0)


def test_a_textured_recording_gets_its_threshold_and_keeps_edis_gain(tmp_path):
    # a moving checkerboard: θ is identifiable, and the estimate is what the command line would use
    row = evaluate_threshold(tiny_case(), num_frames=4, folder=tmp_path)
    theta = row["threshold"]
    assert theta == case_with_drawn_threshold(tiny_case()).threshold
    assert row["matters"] and row["psnr_true_theta"] > row["psnr_blurry"] + MATTERS_DB
    assert 0.8 < row["ratio"] < 1.25, row  # measured: 1.06 (θ 0.1435, estimate 0.152)
    assert row["gain_kept"] > 0.9 and abs(row["psnr_loss_db"]) < 0.5  # measured: 99.7 %, 0.04 dB
    assert row["latency_error_estimated_theta_us"] < 500.0  # measured: 11 us
    assert math.isfinite(row["latency_error_true_theta_us"])
    assert not list(tmp_path.iterdir())  # the recording's file is removed


def test_summary_counts_and_quantiles():
    rows = [dict(threshold=0.2, estimate=0.2 * r, ratio=r, psnr_loss_db=loss, gain_kept=kept,
                 latency_error_true_theta_us=300.0, latency_error_estimated_theta_us=400.0)
            for r, loss, kept in ((1.1, 0.1, 0.95), (0.5, 2.0, 0.4), (1.2, 0.3, math.nan))]
    rows.append(dict(threshold=0.2, estimate=math.nan, ratio=math.nan, psnr_loss_db=math.nan, gain_kept=math.nan))
    s = summarize_thresholds(rows)
    assert (s["cases"], s["estimated"], s["constant_cases"]) == (4, 3, 3)
    assert s["median_relative_error"] == pytest.approx(0.2) and s["worst_relative_error"] == pytest.approx(0.5)
    assert s["within_15%"] == pytest.approx(1 / 3) and s["within_30%"] == pytest.approx(2 / 3)
    assert (s["lowest_ratio"], s["highest_ratio"]) == (0.5, 1.2)
    assert s["worst_gain_kept"] == 0.4 and s["median_gain_kept"] == pytest.approx(0.675)
    assert s["median_latency_error_estimated_theta_us"] == 400.0
    assert summarize_thresholds([rows[-1]]) == {"cases": 1, "estimated": 0}


def test_the_medians_come_with_a_bootstrap_interval():
    errors = [0.02, 0.05, 0.06, 0.1, 0.4, 0.03, 0.08]
    rows = [dict(threshold=0.2, estimate=0.2 * (1 + e), ratio=1 + e, psnr_loss_db=0.1, gain_kept=1 - e)
            for e in errors]
    s = summarize_thresholds(rows)
    low, high = s["median_relative_error_interval"]
    assert low <= s["median_relative_error"] <= high and min(errors) <= low and high <= max(errors)
    low, high = s["median_gain_kept_interval"]
    assert low <= s["median_gain_kept"] <= high
    assert summarize_thresholds(rows) == s  # seeded
    one = summarize_thresholds(rows[:1])
    assert all(math.isnan(v) for v in one["median_relative_error_interval"] + one["median_gain_kept_interval"])


@pytest.mark.slow
def test_the_script_reports_a_small_split(tmp_path):
    run = run_script("threshold.py", "--split", "dev", "--num", "2", "--size", "32", "40", "--frames", "3",
                     "--out", str(tmp_path / "out"), cwd=tmp_path)
    assert run.returncode == 0, run.stderr
    results = json.loads((tmp_path / "out" / "results.json").read_text())
    assert [r["case"] for r in results["rows"]] == [c.name for c in make_cases("dev", 2, (32, 40))]
    assert results["summary"]["all"]["cases"] == 2
    table = (tmp_path / "out" / "results.md").read_text()
    assert table.startswith("`python benchmarks/threshold.py --split dev --num 2") and "| all (2) |" in table
    assert "θ error: median (95 % interval)" in table
    assert (tmp_path / "out" / "results.png").stat().st_size > 10_000
