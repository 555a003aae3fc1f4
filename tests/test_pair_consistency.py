"""``evlatcorr.benchmark.pair_consistency`` and ``benchmarks/pair_consistency.py``: two frames' consistency as a
latency estimate, step EDI against events as ramps."""

from __future__ import annotations

import math

import pytest
import torch

from evlatcorr.benchmark.accuracy import make_cases
from evlatcorr.benchmark.pair_consistency import curve_minimum, pair_disagreement_curve, pair_rows, pair_summary
from evlatcorr.frames import EventFrames
from evlatcorr.pair_evidence import DEFAULT_RAMP_US
from evlatcorr.simulate import simulate
from tests.commands import ROOT, run_script


def test_ramps_take_off_the_step_lag_on_ideal_events():
    # a dev case (shapes rotating, 7.34 ms): with step EDI the two frames agree best about 0.7 ms late even with
    # ideal events; with each event a ramp (the shipped rule: up to 10 ms and twice the interval to the pixel's next
    # event) they agree best at 0, and the delayed events' at the truth
    case = next(c for c in make_cases("dev") if c.name.startswith("dev-05-"))
    row = pair_rows(case, (0.0, DEFAULT_RAMP_US))
    ramp = f"{DEFAULT_RAMP_US:g}"
    assert row["ideal_0_us"] > 400.0 and row[f"ideal_{ramp}_us"] < 150.0
    assert abs(row[f"delayed_{ramp}_us"] - case.latency_us) < 150.0 < row["delayed_0_us"] - case.latency_us
    assert math.isfinite(row["reader_us"])
    # the cap alone spreads the first event of each edge's burst over 10 ms, and the pair agrees best early
    assert pair_rows(case, (DEFAULT_RAMP_US,), None)[f"delayed_{ramp}_us"] < case.latency_us - 500.0
    with pytest.raises(ValueError, match="constant-latency cases"):
        pair_rows(next(c for c in make_cases("dev") if c.latency_model != "constant"))


def test_the_curve_reads_one_pair():
    seq = simulate("camera", num_frames=3, height=24, width=32, latency_us=2000.0, seed=0)
    with pytest.raises(ValueError, match="one pair of frames"):
        pair_disagreement_curve(seq.pairs(), 0.2, torch.tensor([0.0]), 0.0)  # two pairs
    one = seq.frames().split()[0]
    assert isinstance(one, EventFrames)
    with pytest.raises(ValueError, match="one pair of frames"):
        pair_disagreement_curve(one, 0.2, torch.tensor([0.0]), 0.0)  # no next frame
    pair = seq.pairs().split()[0]
    for theta, candidates, ramp, match in ((0.0, torch.tensor([0.0]), 0.0, "threshold must be a positive"),
                                           (0.2, torch.tensor([]), 0.0, "non-empty 1-D tensor"),
                                           (0.2, torch.tensor([100.0, 0.0]), 0.0, "increasing"),
                                           (0.2, torch.tensor([0.0]), -1.0, "max_spread_us must be 0 or more")):
        with pytest.raises(ValueError, match=match):
            pair_disagreement_curve(pair, theta, candidates, ramp)
    with pytest.raises(ValueError, match="one value per candidate"):
        curve_minimum(torch.tensor([0.0, 1.0]), torch.tensor([1.0]))
    # the parabola's vertex between candidates: y = (x - 1.25)^2 sampled at 0, 1, 2
    assert curve_minimum(torch.tensor([0.0, 1.0, 2.0]), torch.tensor([1.5625, 0.0625, 0.5625])) == pytest.approx(1.25)


def test_the_summary_on_known_rows():
    rows = [dict(truth_us=1000.0, reader_us=1400.0, delayed_0_us=2000.0, ideal_0_us=600.0, delayed_3000_us=900.0,
                 ideal_3000_us=0.0),
            dict(truth_us=5000.0, reader_us=4000.0, delayed_0_us=6000.0, ideal_0_us=800.0, delayed_3000_us=5200.0,
                 ideal_3000_us=100.0)]
    summary = {s["estimator"]: s for s in pair_summary(rows, (0.0, 3000.0))}
    reader = summary["default corrector, first frame"]
    assert (reader["median_abs_error_us"], reader["worst_abs_error_us"], reader["within_500us"]) == (700.0, 1000.0, 0.5)
    ramp = summary["consistency, ramps up to 3000 us"]
    assert (ramp["median_abs_error_us"], ramp["median_signed_error_us"], ramp["ideal_median_abs_us"]) == (150.0, 50.0,
                                                                                                            50.0)
    both = summary["mean of the corrector and the consistency, ramps up to 3000 us"]
    assert both["median_abs_error_us"] == pytest.approx((150.0 + 400.0) / 2)
    assert math.isnan(both["ideal_median_abs_us"]) and pair_summary([]) == []
    # where the consistency found no minimum the fallback row takes the corrector alone
    rows[1]["delayed_3000_at_reach"] = True
    fallback = {s["estimator"]: s for s in pair_summary(rows, (3000.0,))}[
        "mean of the two, the corrector alone where the consistency has no minimum"]
    assert fallback["median_abs_error_us"] == pytest.approx((150.0 + 1000.0) / 2)


def test_the_script_writes_its_table(tmp_path):
    run = run_script("pair_consistency.py", "--split", "dev", "--num", "6", "--size", "32", "40", "--ramps-us", "0",
                     "3000", "--out", str(tmp_path), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "results.md").read_text()
    assert "| consistency, ramps up to 3000 us |" in table and "--ramps-us 0 3000" in table
    assert (tmp_path / "results.csv").read_text().startswith("case,truth_us,reader_us,delayed_0_us")
    assert "each ramp at most 2x the interval to its pixel's next event" in table
    bad = run_script("pair_consistency.py", "--ramps-us", "-1", cwd=tmp_path)
    assert bad.returncode == 2 and "--ramps-us must be 0 or more, got [-1.0]" in bad.stderr
    bad = run_script("pair_consistency.py", "--next-factor", "-1", cwd=tmp_path)
    assert bad.returncode == 2 and "--next-factor must be 0 or more, got -1.0" in bad.stderr


def test_the_script_reads_a_recording_s_pairs(tmp_path):
    from evlatcorr.benchmark.accuracy_cases import simulate_case
    from evlatcorr.io import write_sequence

    case = next(c for c in make_cases("dev", size=(32, 40)) if c.latency_model == "constant")
    _, _, seq = simulate_case(case, 3, frame_interval_us=1.25 * case.exposure_us)
    write_sequence(tmp_path / "rec.h5", seq)
    run = run_script("pair_consistency.py", "--recording", str(tmp_path / "rec.h5"), "--threshold",
                     str(case.threshold), "--ramps-us", "0", "3000", "--out", str(tmp_path / "out"), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    table = (tmp_path / "out" / "results.md").read_text()
    assert "rec.h5, 2 pairs of consecutive frames" in table and "| median |" in table
    assert "| frame | default corrector, the frame alone | consistency, step EDI |" in table
    bad = run_script("pair_consistency.py", "--recording", str(tmp_path / "rec.h5"), cwd=tmp_path)
    assert bad.returncode == 2 and "--recording needs the recording's --threshold" in bad.stderr
    missing = run_script("pair_consistency.py", "--recording", str(tmp_path / "none.h5"), "--threshold", "0.2",
                         cwd=tmp_path)
    assert missing.returncode == 2 and "none.h5: no such file" in missing.stderr
