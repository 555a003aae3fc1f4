from __future__ import annotations

import math

import pytest
import torch

from evlatcorr.benchmark.network_check import check_case, checks_to_markdown, summarize_checks
from evlatcorr.restore import build_model
from tests.test_accuracy import tiny_case


@pytest.fixture(scope="module")
def row():
    # a constant 4000 us: no shift gives the delayed events' output exactly, the true shift the ideal timing
    return check_case(tiny_case(), {"none": lambda frames: 0.0, "truth": lambda frames: 4000.0}, build_model("efnet"))


def test_no_shift_recovers_nothing_and_the_true_latency_recovers_most(row):
    none, truth = row["estimators"]["none"], row["estimators"]["truth"]
    assert row["psnr_ideal"] > row["psnr_delayed"] + 1.0  # the network loses to the latency
    assert none["latency_us"] == 0.0 and none["psnr"] == row["psnr_delayed"] and none["recovery"] == 0.0
    assert truth["latency_us"] == 4000.0 and truth["recovery"] > 0.5


def test_summary_and_markdown(row):
    flat = {**row, "name": "flat", "psnr_ideal": row["psnr_delayed"],
            "estimators": {n: {**e, "recovery": math.nan} for n, e in row["estimators"].items()}}
    summary = summarize_checks([row, flat])
    assert summary["none/constant"] == {"cases": 1, "median_recovery": 0.0, "worst_recovery": 0.0}
    assert set(summary) == {"none/constant", "truth/constant", "none/all", "truth/all"}
    text = checks_to_markdown([row, flat], "efnet")
    assert "| none | constant | 1 | 0% | 0% |" in text and "/ no gap |" in text and text.count("| tiny |") == 1


def test_an_estimator_with_a_wrong_shape_is_refused():
    with pytest.raises(ValueError, match=r"latency map of shape \(1, 1, 32, 40\)"):
        check_case(tiny_case(), {"bad": lambda frames: torch.zeros(2, 3)}, build_model("efnet"))


def test_the_script_skips_a_case_it_cannot_estimate_and_keeps_every_estimator(tmp_path):
    from tests.commands import ROOT, run_script

    module = tmp_path / "refuses.py"
    module.write_text("def estimate(frames):\n    raise ValueError('no events in its window')\n\n\n"
                      "def none(frames):\n    return 0.0\n")
    out = tmp_path / "check.md"
    script = ["network_check.py", "--split", "dev", "--size", "32", "40"]
    run = run_script(*script, "--num", "1", "--estimator", f"{module}:estimate", "--out", str(out), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    assert "skipped (no events in its window)" in run.stdout
    assert "Skipped (an estimator could not estimate): dev-00-" in out.read_text()
    # two estimators from one module each keep their own column
    run = run_script(*script, "--num", "2", "--models", "intensity", "--estimator", f"{module}:none",
                     "--estimator", f"{module}:none", "--out", str(out), cwd=ROOT)
    assert run.returncode == 0, run.stderr
    assert "| refuses: µs / PSNR / recovery | refuses': µs / PSNR / recovery |" in out.read_text()
    # the suite's streams stop 15 ms after the exposure, which the corrector warns of on every case: one line per
    # kind in the report, not a warning per case on the console
    assert "Warnings the estimates raised, by kind:\n\n- 1 of 1 cases: \"events of sample 0 end at" in out.read_text()
    assert "SampleWarning" not in run.stderr
