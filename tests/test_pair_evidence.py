"""``evlatcorr.pair_evidence``: two consecutive frames' agreement as log-odds of their latency, and
``fuse_latencies(pair_log_odds=...)`` taking it beside the reader's evidence."""

from __future__ import annotations

import math

import pytest
import torch

from evlatcorr import checks
from evlatcorr.pair_evidence import pair_disagreement_curve, pair_disagreement_maps, pair_log_odds
from evlatcorr.simulate import simulate
from evlatcorr.temporal import fuse_latencies

CANDIDATES = torch.arange(0.0, 8001.0, 250.0, dtype=torch.float64)


def _pairs(latency_us: float, seed: int = 0):
    return simulate("camera", num_frames=2, height=24, width=32, latency_us=latency_us, seed=seed)


@pytest.mark.parametrize("latency_us", [0.0, 3000.0])
def test_the_log_odds_peak_at_the_true_latency(latency_us):
    # ideal events too: with each event a ramp the pair agrees best at no latency, where step EDI's lag put it late
    seq = _pairs(latency_us)
    which = "ideal" if latency_us == 0 else "delayed"
    log_odds = pair_log_odds(seq.pairs(which).split()[0], 0.2, CANDIDATES)
    assert log_odds is not None and log_odds.shape == CANDIDATES.shape and log_odds.dtype == torch.float64
    assert float(log_odds.max()) == 0.0
    assert abs(float(CANDIDATES[log_odds.argmax()]) - latency_us) <= 250.0
    # the weight scales the log-odds
    double = pair_log_odds(seq.pairs(which).split()[0], 0.2, CANDIDATES, weight=20.0)
    torch.testing.assert_close(double, 2 * log_odds)


def test_unreadable_candidates_get_no_evidence_and_too_few_give_none():
    seq = _pairs(3000.0)
    pair = seq.pairs(after_us=5000.0).split()[0]  # events 5 ms past the second exposure
    last = float(pair.events.t.max() - pair.exposure_end_next[0])
    log_odds = pair_log_odds(pair, 0.2, CANDIDATES)
    beyond = CANDIDATES > last
    assert bool(beyond.any())
    read = log_odds[~beyond]
    assert torch.equal(log_odds[beyond], torch.full_like(log_odds[beyond], float(read.median())))
    # events that stop 300 us after the second exposure: two candidates readable, nothing said
    end = float(pair.exposure_end_next[0]) + 300.0
    short = pair.replace(events=pair.events.select(pair.events.t < end))
    assert pair_log_odds(short, 0.2, CANDIDATES) is None
    # events that stop before the agreement's best (3 ms): the disagreement still falls at the last read candidate
    early = pair.replace(events=pair.events.select(pair.events.t < float(pair.exposure_end_next[0]) + 1800.0))
    assert pair_log_odds(early, 0.2, CANDIDATES) is None


def test_a_small_memory_budget_reads_the_sensor_in_bands_with_the_same_curve(monkeypatch):
    pair = _pairs(3000.0).pairs().split()[0]
    whole = pair_disagreement_curve(pair, 0.2, CANDIDATES)
    for rows in (1, 7):  # the grid's 428 points, 32 pixels a row, 56 bytes a point: a quarter of the budget
        monkeypatch.setattr(checks, "MEMORY_BUDGET_BYTES", 4 * rows * 428 * 32 * 56)
        torch.testing.assert_close(pair_disagreement_curve(pair, 0.2, CANDIDATES), whole, rtol=1e-12, atol=1e-12)
    monkeypatch.setattr(checks, "MEMORY_BUDGET_BYTES", 4 * 200 * 32 * 56)  # a row of 428 points does not fit: coarser
    coarse = pair_disagreement_curve(pair, 0.2, CANDIDATES)
    assert not torch.allclose(coarse, whole) and abs(float(CANDIDATES[coarse.argmin()]) - 3000.0) <= 500.0
    monkeypatch.setattr(checks, "MEMORY_BUDGET_BYTES", 1)  # not even the coarsest grid: refused, as every grid over
    with pytest.raises(ValueError, match="over the memory budget"):
        pair_disagreement_curve(pair, 0.2, CANDIDATES)
    assert abs(float(CANDIDATES[whole.argmin()]) - 3000.0) <= 250.0


def test_the_maps_are_the_curve_pixel_by_pixel(monkeypatch):
    seq = _pairs(3000.0)
    pair = seq.pairs().split()[0]
    maps = pair_disagreement_maps(pair, 0.2, CANDIDATES)
    assert maps.shape == (len(CANDIDATES), 24, 32) and maps.dtype == torch.float32
    torch.testing.assert_close(maps.double().mean((1, 2)), pair_disagreement_curve(pair, 0.2, CANDIDATES), rtol=1e-6,
                               atol=0)
    monkeypatch.setattr(checks, "MEMORY_BUDGET_BYTES", 4 * 7 * 428 * 32 * 56)  # bands of 7 rows: the same maps
    torch.testing.assert_close(pair_disagreement_maps(pair, 0.2, CANDIDATES), maps, rtol=0, atol=0)
    with pytest.raises(ValueError, match="pair_disagreement_maps reads one pair"):
        pair_disagreement_maps(seq.frames(), 0.2, CANDIDATES)
    with pytest.raises(ValueError, match="non-empty 1-D tensor"):
        pair_disagreement_maps(pair, 0.2, torch.tensor(1.0))


def test_only_pixels_with_events_are_integrated_and_the_maps_are_the_whole_sensors():
    # the maps from one grid over the whole sensor, by hand: each frame's latent at the gap's middle is its blurry
    # frame times exp(θ C(mid + l)) over its exposure's mean of exp(θ C(t + l)) (trapezoids, times at grid points);
    # a pixel without events keeps its blurry frame at every candidate
    from evlatcorr.integral import cumulative_event_grid
    from evlatcorr.pair_evidence import DEFAULT_RAMP_NEXT_FACTOR, DEFAULT_RAMP_US

    seq = _pairs(3000.0)
    pair = seq.pairs().split()[0]
    keep = pair.events.x < 20  # the right third of the sensor has no events
    pair = pair.replace(events=pair.events.select(keep))
    s1, e1, s2, e2 = (float(v[0]) for v in (pair.exposure_start, pair.exposure_end, pair.exposure_start_next,
                                            pair.exposure_end_next))
    step = 125.0
    start, bins = s1 - step, int(math.ceil((e2 + float(CANDIDATES.max()) - s1 + step) / step)) + 2
    grid = cumulative_event_grid(pair.events, start, step, bins, "linear", torch.float64,
                                 max_spread_us=DEFAULT_RAMP_US, next_spread_factor=DEFAULT_RAMP_NEXT_FACTOR)[0]
    weights = (0.2 * (grid - grid[round(((e1 + s2) / 2 - start) / step)])).exp()
    sums = weights.cumsum(0) - weights / 2

    def at(t):
        return ((t + CANDIDATES - start) / step).round().long().clamp(0, bins)

    logs = []
    for blurry, (a, b) in ((pair.blurry, (at(s1), at(e1))), (pair.blurry_next, (at(s2), at(e2)))):
        mean = (sums[b] - sums[a]) / (b - a)[:, None, None]
        latent = blurry[0].mean(0).double() * weights[at((e1 + s2) / 2)] / mean
        logs.append(torch.log(latent.clamp_min(0) + 0.02))
    maps = pair_disagreement_maps(pair, 0.2, CANDIDATES)
    torch.testing.assert_close(maps.double(), (logs[0] - logs[1]).abs(), rtol=1e-4, atol=1e-5)
    still = (logs[0] - logs[1]).abs()[:, :, 20:]
    assert bool((still == still[:1]).all())  # no events: the same at every candidate


def test_a_pair_with_a_black_saturated_or_flat_frame_tells_nothing():
    # a lens cap or a flash: such a frame agrees with its neighbour at no latency (a black next frame agreed best
    # where the first frame's latent was darkest, 4.5 ms for a true 3 ms), and the frame keeps its own estimate
    pair = _pairs(3000.0).pairs("delayed", after_us=25000.0).split()[0]
    assert pair_log_odds(pair, 0.2, CANDIDATES) is not None
    for blank in (torch.zeros_like(pair.blurry), torch.ones_like(pair.blurry), torch.full_like(pair.blurry, 0.5)):
        assert pair_log_odds(pair.replace(blurry_next=blank), 0.2, CANDIDATES) is None
        assert pair_log_odds(pair.replace(blurry=blank), 0.2, CANDIDATES) is None


def test_bad_inputs_are_refused():
    seq = _pairs(3000.0)
    pair = seq.pairs().split()[0]
    with pytest.raises(ValueError, match="one pair of frames"):
        pair_log_odds(seq.frames(), 0.2, CANDIDATES)
    with pytest.raises(ValueError, match="weight must be a positive"):
        pair_log_odds(pair, 0.2, CANDIDATES, weight=0.0)
    with pytest.raises(ValueError, match="threshold must be positive"):
        pair_log_odds(pair, 0.0, CANDIDATES)
    with pytest.raises(ValueError, match="increasing"):
        pair_log_odds(pair, 0.2, CANDIDATES.flip(0))
    with pytest.raises(ValueError, match="grid_us must be positive"):
        pair_disagreement_curve(pair, 0.2, CANDIDATES, grid_us=0.0)
    with pytest.raises(ValueError, match="next_spread_factor must be positive or None"):
        pair_log_odds(pair, 0.2, CANDIDATES, next_spread_factor=0.0)


def _belief(mean: float, sigma: float) -> torch.Tensor:
    return torch.log_softmax(-((CANDIDATES - mean) / sigma) ** 2, 0)


def test_fuse_latencies_adds_a_pairs_log_odds_to_its_first_frame():
    log_p = torch.stack([_belief(4000.0, 3000.0)] * 3)  # three unsure frames
    own = torch.full((3,), 4000.0, dtype=torch.float64)
    alone = fuse_latencies(own, CANDIDATES, log_p, 1, 1, no_latency_mass=None)
    pair = -20.0 * torch.log1p(((CANDIDATES - 2000.0) / 1000.0) ** 2)  # a sharp agreement at 2 ms
    fused = fuse_latencies(own, CANDIDATES, log_p, 1, 1, no_latency_mass=None, pair_log_odds=[pair, pair, None])
    assert torch.allclose(alone, own, atol=1.0)
    assert bool((fused - 2000.0).abs().max() < 300.0)
    # no pair evidence anywhere: the same as without
    none = fuse_latencies(own, CANDIDATES, log_p, 1, 1, no_latency_mass=None, pair_log_odds=[None] * 3)
    assert torch.equal(none, alone)
    with pytest.raises(ValueError, match="one row per frame"):
        fuse_latencies(own, CANDIDATES, log_p, pair_log_odds=[pair])
    with pytest.raises(ValueError, match="pair_log_odds must be finite, one per candidate"):
        fuse_latencies(own, CANDIDATES, log_p, pair_log_odds=[pair[:-1], None, None])
    with pytest.raises(ValueError, match="pair_log_odds must be finite"):
        fuse_latencies(own, CANDIDATES, log_p, pair_log_odds=[torch.full_like(pair, -math.inf), None, None])


@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, True, "10"])
def test_the_search_settings_refuse_a_bad_pair_weight(bad):
    from evlatcorr.config import SearchConfig
    from evlatcorr.correction import EventLatencyCorrector

    assert SearchConfig().pair_weight == 10.0 and SearchConfig(pair_weight=0).pair_weight == 0
    with pytest.raises(ValueError, match="pair_weight must be a finite number >= 0"):
        SearchConfig(pair_weight=bad)
    with pytest.raises(ValueError, match="pair_weight must be a finite number >= 0"):
        EventLatencyCorrector(pair_weight=bad)
