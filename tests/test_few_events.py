"""``evlatcorr.benchmark.few_events`` and ``benchmarks/few_events.py``: the latency error as events thin out."""

from __future__ import annotations

import math

import pytest

from evlatcorr.benchmark.accuracy import make_cases
from evlatcorr.benchmark.few_events import few_events_markdown, few_events_summary, thinned_estimates
from tests.commands import ROOT, run_script


def _row(share, events, truth, estimate, spread=500.0):
    return {"case": "c", "share": share, "events": events, "truth_us": truth, "estimate_us": estimate,
            "abs_error_us": abs(estimate - truth), "spread_us": spread}


def test_the_summary_groups_by_events_and_sets_the_guess_from_the_full_frames():
    rows = [_row(1.0, 5000, 1000.0, 1100.0), _row(1.0, 8000, 3000.0, 3500.0), _row(1.0, 9000, 5000.0, 5200.0),
            _row(0.01, 50, 1000.0, 9000.0, math.nan), _row(0.01, 80, 5000.0, 3000.0, 3000.0)]
    groups = few_events_summary(rows, bins=(0, 100, math.inf))
    assert [g["events"] for g in groups] == [(0, 100), (100, math.inf)]
    few, many = groups
    assert (few["frames"], few["median_abs_error_us"], few["within_1ms"]) == (2, 5000.0, 0.0)
    # the guess answers the full frames' median truth, 3000 us: off by 2000 us on both thinned frames
    assert few["guess_median_abs_error_us"] == 2000.0
    assert few["median_spread_us"] == 3000.0  # the frame the reader did not read (NaN) is left out
    assert (many["frames"], many["median_abs_error_us"], many["within_1ms"]) == (3, 200.0, 1.0)
    table = few_events_markdown(groups)
    assert "| 0-99 | 2 | 5000 us | 0 % | 2000 us | 3000 us |" in table
    assert "| 100 or more | 3 | 200 us | 100 % | 2000 us | 500 us |" in table
    assert few_events_summary([]) == []
    for bins in ((100,), (0, 100, 100), (10, 0)):
        with pytest.raises(ValueError, match="bins must be at least two increasing bounds"):
            few_events_summary(rows, bins=bins)


def test_thinned_estimates_keep_fewer_events_at_a_smaller_share_and_refuse_other_cases():
    cases = make_cases("dev", size=(32, 40))
    constant = next(c for c in cases if c.latency_model == "constant")
    rows = thinned_estimates(constant, shares=(1.0, 0.1))
    assert [r["share"] for r in rows] == [1.0, 0.1] and rows[0]["events"] > rows[1]["events"] > 0
    assert rows[0]["truth_us"] == rows[1]["truth_us"] == pytest.approx(constant.latency_us)
    other = next(c for c in cases if c.latency_model != "constant")
    with pytest.raises(ValueError, match="constant-latency cases"):
        thinned_estimates(other)
    with pytest.raises(ValueError, match=r"shares must lie in \(0, 1\]"):
        thinned_estimates(constant, shares=(0.0,))


def test_the_script_writes_its_table(tmp_path):
    run = run_script("few_events.py", "--split", "dev", "--num", "6", "--size", "32", "40", "--shares", "1", "0.01",
                     "--out", str(tmp_path), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    assert "| events in the window | frames |" in table and "shares kept 1, 0.01" in table
    assert (tmp_path / "results.csv").read_text().startswith(
        "case,share,events,truth_us,estimate_us,abs_error_us,spread_us")
    bad = run_script("few_events.py", "--shares", "2", cwd=tmp_path)
    assert bad.returncode == 2 and "--shares must lie in (0, 1], got [2.0]" in bad.stderr
    assert not list(tmp_path.glob("outputs"))
