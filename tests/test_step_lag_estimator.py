from __future__ import annotations

from pathlib import Path

import torch

from evlatcorr import EventLatencyCorrector
from evlatcorr.benchmark.accuracy import evaluate_case, load_estimator, simulate_case
from tests.test_accuracy import tiny_case

PLUGIN = Path(__file__).resolve().parents[1] / "benchmarks" / "estimators" / "step_lag.py"


def test_step_lag_is_half_the_median_interval_between_a_pixel_s_events():
    module_estimate = load_estimator(f"{PLUGIN}:estimate")
    step_lag = module_estimate.__globals__["step_lag"]
    from evlatcorr import EventFrames, Events

    # pixel (0, 0): events 100 us apart, pixel (0, 1): 300 us apart; gaps (100, 100, 300), median 100, lag 50
    x = torch.tensor([0, 0, 0, 1, 1])
    t = torch.tensor([100.0, 200.0, 300.0, 50.0, 350.0])
    order = torch.argsort(t)
    events = Events(x[order], torch.zeros(5, dtype=torch.long), t[order], torch.ones(5), sensor_size=(1, 2))
    frames = EventFrames(torch.full((1, 1, 1, 2), 0.5), events, torch.tensor([0.0]), torch.tensor([1000.0]))
    assert step_lag(frames, torch.tensor([0.0])).tolist() == [50.0]
    # the window read 250 us late holds one event per pixel: no interval, no lag
    assert step_lag(frames, torch.tensor([250.0])).tolist() == [0.0]


def test_the_estimator_moves_the_corrector_s_latency_earlier_and_scores_in_the_suite():
    case = tiny_case()  # constant 4000 us
    delayed = simulate_case(case)[0]
    frames = delayed.replace(meta={**delayed.meta, "threshold": case.threshold})
    estimate = load_estimator(f"{PLUGIN}:estimate")
    lagged = estimate(frames)
    plain = EventLatencyCorrector(threshold=case.threshold)(frames).latency
    lag = estimate.__globals__["step_lag"](frames, plain[:, 0, 0, 0].double())
    assert lagged.shape == plain.shape and 0.0 < float(lag[0]) < 1000.0
    torch.testing.assert_close(lagged, (plain - float(lag[0])).clamp_min(0.0))
    row = evaluate_case(case, estimate)
    assert row["error"] == "" and abs(row["est_latency_us"] - float(lagged[0, 0, 0, 0])) < 1e-3


def test_the_consensus_plugin_is_the_corrector_with_the_previous_default_score():
    case = tiny_case()
    delayed = simulate_case(case)[0]
    frames = delayed.replace(meta={**delayed.meta, "threshold": case.threshold})
    plugin = Path(__file__).resolve().parents[1] / "benchmarks" / "estimators" / "consensus.py"
    latency = load_estimator(f"{plugin}:estimate")(frames)
    expected = EventLatencyCorrector(threshold=case.threshold, score="consensus")(frames).latency
    torch.testing.assert_close(latency, expected)
