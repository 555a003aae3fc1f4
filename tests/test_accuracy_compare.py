from __future__ import annotations

import json
import math

import pytest

from evlatcorr.benchmark.accuracy import run_suite, summarize, to_markdown, write_results
from evlatcorr.benchmark.accuracy_compare import (
    bootstrap_interval,
    compare_runs,
    comparison_markdown,
    load_results,
    paired_comparison,
)
from tests.commands import run_script


def row(estimator: str, name: str, psnr: float, model: str = "constant", error_us: float = 100.0, **extra) -> dict:
    return {"estimator": estimator, "split": "dev", "name": name, "latency_model": model, "psnr_corrected": psnr,
            "latency_abs_error_us": error_us, "ideal_psnr_change_db": -0.1, **extra}


def test_bootstrap_interval_known_answers():
    assert bootstrap_interval([0.3] * 5) == pytest.approx((0.3, 0.3))
    assert all(math.isnan(v) for v in bootstrap_interval([1.0]))
    assert bootstrap_interval([0.1, 0.5, 0.2, 0.4]) == bootstrap_interval([0.1, 0.5, 0.2, 0.4])  # seeded
    low, high = bootstrap_interval([1.0, 1.2, 0.8, 1.1, 0.9, 1.0])
    assert 0.8 < low < 1.0 < high < 1.2
    low, high = bootstrap_interval([-1.0, 1.0, -0.5, 0.5, -0.2, 0.2])  # a change of either sign: 0 inside
    assert low < 0.0 < high
    with pytest.raises(ValueError, match="level must lie in"):
        bootstrap_interval([1.0, 2.0], level=1.0)
    # the median's interval: an outlier moves the mean's, barely the median's
    skewed = [1.0, 1.0, 1.1, 0.9, 1.0, 1.05, 0.95, 50.0]
    assert bootstrap_interval(skewed, statistic="median")[1] < 1.2 < bootstrap_interval(skewed)[1]
    assert bootstrap_interval([2.0, math.nan, 2.0], statistic="median") == (2.0, 2.0)  # NaN left out
    with pytest.raises(ValueError, match="statistic must be"):
        bootstrap_interval([1.0, 2.0], statistic="mode")
    with pytest.raises(ValueError, match="resamples must be a whole number >= 1, got 0"):
        bootstrap_interval([1.0, 2.0], resamples=0)


def test_paired_comparison_pairs_cases_and_counts_clear_changes():
    rows = [row("a", "c0", 30.0), row("b", "c0", 31.0),              # +1.0: gaining
            row("a", "c1", 30.0), row("b", "c1", 29.0),              # -1.0: losing
            row("a", "c2", 30.0), row("b", "c2", 30.2),              # +0.2
            row("a", "m0", 25.0, "intensity", 900.0), row("b", "m0", 26.0, "intensity", 700.0),
            row("a", "c3", 30.0), row("b", "c3", math.nan, error="raised"),  # b failed: not paired
            row("a", "c4", 30.0)]                                    # b never ran it
    groups = {g["latency_model"]: g for g in paired_comparison(rows, "a", "b")}
    assert list(groups) == ["constant", "intensity", "all"]
    const = groups["constant"]
    assert const["cases"] == 3 and (const["gaining"], const["losing"]) == (1, 1)
    assert const["mean_psnr_change_db"] == pytest.approx(0.2 / 3)
    assert const["psnr_change_low_db"] < const["mean_psnr_change_db"] < const["psnr_change_high_db"]
    assert groups["intensity"]["baseline_median_abs_error_us"] == 900.0
    assert groups["intensity"]["other_median_abs_error_us"] == 700.0
    assert groups["all"]["cases"] == 4 and groups["all"]["gaining"] == 2
    assert groups["all"]["other_mean_ideal_psnr_change_db"] == pytest.approx(-0.1)
    table = comparison_markdown(list(groups.values()))
    assert "## b against a, case by case" in table and "| constant | 3 | +0.067 (" in table


def test_paired_comparison_refuses_what_it_cannot_compare():
    rows = [row("a", "c0", 30.0), row("b", "c1", 30.0)]
    with pytest.raises(ValueError, match="no rows of estimator 'z'"):
        paired_comparison(rows, "a", "z")
    with pytest.raises(ValueError, match="share no case"):
        paired_comparison(rows, "a", "b")


def test_suite_report_compares_each_estimator_with_the_first(tmp_path):
    from tests.test_accuracy import tiny_case

    truth = lambda case: lambda frames: frames.meta["true_latency"]  # noqa: E731
    none = lambda case: lambda frames: frames.meta["true_latency"] * 0  # noqa: E731
    results = run_suite([tiny_case()], {"truth": truth, "none": none}, progress=None)
    summary = summarize(results)
    (groups,) = summary["paired"]
    every = groups[-1]
    assert (every["baseline"], every["other"], every["cases"]) == ("truth", "none", 1)
    # not correcting loses what the true latency recovers
    assert every["mean_psnr_change_db"] == pytest.approx(results[1]["psnr_corrected"] - results[0]["psnr_corrected"])
    assert every["mean_psnr_change_db"] < -1.0 and every["losing"] == 1
    report = to_markdown(results, summary)
    assert "## none against truth, case by case" in report
    # one case: its median has no interval (two are needed), and the report says nothing it cannot tell
    assert all(math.isnan(v) for v in summary["groups"][0]["median_abs_error_interval_us"])
    assert "## How sure the medians are" not in report
    # the run written and read back compares with itself, or another run, by case
    write_results(results, tmp_path / "run")
    rows = load_results(tmp_path / "run")
    assert len(rows) == 2
    (same,) = [g for g in compare_runs(rows, rows, "truth", "truth") if g["latency_model"] == "all"]
    assert (same["cases"], same["mean_psnr_change_db"], same["gaining"], same["losing"]) == (1, 0.0, 0, 0)
    with pytest.raises(ValueError, match="the two runs need two labels"):
        compare_runs(rows, rows, "truth", "truth", labels=("run", "run"))
    script = run_script("compare_accuracy.py", str(tmp_path / "run"), str(tmp_path / "run" / "results.json"),
                        "--estimator", "truth", "--other-estimator", "none", cwd=tmp_path)
    assert script.returncode == 0, script.stderr
    assert "case by case" in script.stdout and "| all | 1 |" in script.stdout
    # two estimators, none chosen, and no "constant" among them: the script asks which
    script = run_script("compare_accuracy.py", str(tmp_path / "run"), str(tmp_path / "run"), cwd=tmp_path)
    assert script.returncode == 2 and "choose one with --estimator" in script.stderr


def test_load_results_refuses_what_is_not_a_run(tmp_path):
    with pytest.raises(ValueError, match="cannot read an accuracy run"):
        load_results(tmp_path / "missing.json")
    (tmp_path / "other.json").write_text(json.dumps({"table": []}))
    with pytest.raises(ValueError, match="holds no accuracy-suite rows"):
        load_results(tmp_path / "other.json")


def test_summary_gives_the_headline_medians_their_intervals():
    # the fields the report's case table reads, as a run fills them
    case = dict(no_gap=False, best_shift_us=0.0, true_latency_us=0.0, est_latency_us=0.0, latency_error_us=0.0,
                time_s=0.1, noise_models="", psnr_ideal=31.0, psnr_uncorrected=25.0, psnr_best_shift=31.0)
    rows = [row("a", f"c{i}", 30.0, error_us=100.0 * (i + 1), recovery=0.8 + 0.02 * i, best_shift_share=math.nan,
                **case) for i in range(9)]
    rows += [row("a", f"p{i}", 30.0, "intensity", recovery=math.nan, best_shift_share=0.7 + 0.05 * i, **case)
             for i in range(5)]
    groups = {g["latency_model"]: g for g in summarize(rows)["groups"]}
    const = groups["constant"]
    assert const["median_abs_error_us"] == 500.0
    low, high = const["median_abs_error_interval_us"]
    assert 100.0 <= low < 500.0 < high <= 900.0
    low, high = groups["intensity"]["median_best_shift_share_interval"]
    assert 0.7 <= low < 0.8 < high <= 0.9
    report = to_markdown(rows)
    assert "| a | dev | constant | 9 | median abs error | 500 µs (" in report
    assert "| a | dev | intensity | 5 | median share of the best shift | 80% (" in report
