from __future__ import annotations

import pytest
import torch

from evlatcorr.benchmark.accuracy import load_estimator, make_cases, simulate_case
from evlatcorr.correction import EventLatencyCorrector
from evlatcorr.frames import EventFrames
from tests.test_accuracy import tiny_case

TILES = "benchmarks/estimators/tiles.py"


def test_tiles_whole_frame_read_is_the_corrector_s_reader_estimate():
    delayed = simulate_case(tiny_case())[0]
    delayed.meta["threshold"] = 0.2
    corrected = EventLatencyCorrector(threshold=0.2)(delayed)
    assert corrected.meta["latency_source"][0] in ("sharpness", "reader")
    whole = load_estimator(f"{TILES}:estimate_whole")(delayed)
    assert whole.shape == (1, 1, *delayed.blurry.shape[-2:])
    torch.testing.assert_close(whole, corrected.latency.to(whole), atol=0.05, rtol=0)


@pytest.fixture(scope="module")
def text_case():
    # a dev case the reader gets right (text translating at 1.2 px/ms, a constant 10.86 ms): tiles of a 96x128
    # frame are large enough to read
    case = next(c for c in make_cases("dev") if c.name.startswith("dev-17-"))
    delayed = simulate_case(case)[0]
    delayed.meta["threshold"] = case.threshold
    return case, delayed


def test_tiles_fused_estimate_lies_where_the_events_are_and_near_the_truth(text_case):
    case, delayed = text_case
    fused = float(load_estimator(f"{TILES}:estimate")(delayed).unique())
    last = float(delayed.events.t.max() - delayed.exposure_end[0])
    assert 0.0 <= fused <= last
    assert abs(fused - case.latency_us) < 500.0


def test_tile_latency_map_covers_the_frame_with_the_tiles_estimates(text_case):
    case, delayed = text_case
    latency = load_estimator(f"{TILES}:estimate_map_3x3")(delayed)
    assert latency.shape == (1, 1, 96, 128) and torch.isfinite(latency).all()
    # one latency for every pixel here: each tile's estimate is near it
    assert float((latency - case.latency_us).abs().max()) < 1500.0


def test_tiles_refuse_a_batch_and_tiles_too_small_to_read(text_case):
    tile_log_probabilities = load_estimator(f"{TILES}:tile_log_probabilities")
    tile_latency_map = load_estimator(f"{TILES}:tile_latency_map")
    _, delayed = text_case
    with pytest.raises(ValueError, match="one frame"):
        tile_log_probabilities(EventFrames.cat([delayed, delayed]))
    for grid in ((0, 2), (40, 2), (2, 2.5)):
        with pytest.raises(ValueError, match="at least 3x3 pixels"):
            tile_latency_map(delayed, grid)
