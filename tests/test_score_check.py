from __future__ import annotations

import pytest

from evlatcorr.benchmark.score_check import check_case, checks_to_markdown, summarize_checks
from tests.test_accuracy import tiny_case

SCORES = ("etf", "sparsity")


@pytest.fixture(scope="module")
def delay_row():
    # dim pixels later: 0.5 ms at full brightness up to 6 ms
    return check_case(tiny_case(latency_model="intensity_delay", latency_us=0.0), scores=SCORES)


def test_the_true_map_restores_at_least_as_well_as_any_score_s_constant(delay_row):
    assert set(delay_row["scores"]) == set(SCORES)
    for s in delay_row["scores"].values():
        assert 0.0 <= s["best_constant_us"] <= 10_000.0
        assert s["true_wins"] == (s["margin"] < 0)
        # the per-pixel truth is the better reconstruction, whatever a score prefers
        assert delay_row["psnr_true_map"] >= s["psnr_best_constant"] - 0.1


def test_summary_counts_the_cases_each_score_gets_right(delay_row):
    other = {**delay_row, "name": "other", "scores": {
        n: {**s, "true_wins": not s["true_wins"], "margin": -s["margin"]} for n, s in delay_row["scores"].items()}}
    summary = summarize_checks([delay_row, other])
    assert set(summary) == {f"{n}/intensity_delay" for n in SCORES}
    assert all(s["cases"] == 2 and s["true_wins"] == 1 for s in summary.values())
    text = checks_to_markdown([delay_row, other])
    assert text.count("| tiny |") == len(SCORES) and "| etf | intensity_delay | 2 | 1 |" in text


def test_a_constant_latency_case_is_refused():
    with pytest.raises(ValueError, match="per-pixel latency"):
        check_case(tiny_case())
