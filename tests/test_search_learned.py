"""``score="learned"`` in the search (:mod:`evlatcorr.search_learned`): the curves it reads, the reader's pick."""

import math

import pytest
import torch

import evlatcorr.search_learned as search_learned
from evlatcorr import EventFrames, EventLatencyCorrector, Events
from evlatcorr.benchmark.accuracy import make_cases, simulate_case
from evlatcorr.curve_reader import NUM_FEATURES
from evlatcorr.sample_warnings import SampleWarning
from evlatcorr.search import search_constant_latency
from evlatcorr.search_learned import candidate_curves
from tests.conftest import random_events, textured_frames


def test_learned_score_known_answer_on_a_suite_case():
    # dev-28: two objects over static grass, dark, 7.2 ms, shot noise, leak and refractory period; the default
    # consensus is 4.8 ms early on it (the objects' ghosts barely change a whole-image score); the reader's
    # estimate is measured at +1030 us
    case = make_cases("dev")[28]
    delayed, _, _ = simulate_case(case)
    res = search_constant_latency(delayed.blurry, delayed.events, delayed.exposure_start, delayed.exposure_end,
                                  case.threshold, score="learned")
    assert abs(res.latency.item() - case.latency_us) <= 1500.0
    assert res.source == ["reader"] and math.isfinite(res.confidence.item())


class _PlantedReader(torch.nn.Module):
    """Stands in for the shipped ensemble: fixed log-probabilities, masked where no candidate could be scored."""

    def __init__(self, log_p: torch.Tensor) -> None:
        super().__init__()
        self.log_p = torch.nn.Parameter(log_p, requires_grad=False)

    def forward(self, curves, valid):
        return self.log_p.to(curves.dtype)[None].masked_fill(~valid, -1e4)


@pytest.mark.parametrize("mode", [3, 9])  # an inner candidate; the last one whose window holds events
def test_learned_estimate_is_the_centre_of_the_reader_probability_near_its_pick(monkeypatch, mode):
    # 11 candidates 0..100 us; the events stop just before 200 us, so the window of l = 100 reaches past them
    ev = random_events(3000, (8, 9), (0.0, 200.0), seed=6)
    blurry = textured_frames(1, 1, 8, 9, seed=6)
    log_p = torch.full((11,), -30.0)
    log_p[mode] = 0.0
    weights = {mode - 2: -3.0, mode - 1: -1.0, mode + 1: -0.5, mode + 2: -2.0}
    for k, v in weights.items():
        if 0 <= k < 11:
            log_p[k] = v
    log_p[0 if mode > 5 else 10] = -0.2  # a second mode far away: not averaged in
    monkeypatch.setattr(search_learned, "_curve_reader_on", lambda device: _PlantedReader(log_p))
    args = (blurry, ev, torch.zeros(1), torch.full((1,), 100.0), 0.2)
    res = search_constant_latency(*args, num_bins=50, num_candidates=11, score="learned")
    assert bool(torch.isfinite(res.etf[0, 9])) and not bool(torch.isfinite(res.etf[0, 10]))
    # as many neighbours on both sides: none at the last valid candidate (the estimate never needs events past the
    # last one), so a pick at an edge is not pulled inwards
    near = list(range(mode - 2, mode + 3)) if mode == 3 else [mode]
    p = torch.softmax(log_p[near].double(), 0)
    expected = float((p * res.candidates[0, near].double()).sum())
    assert res.source == ["sharpness"] or res.source == ["reader"]
    assert res.latency.item() == pytest.approx(expected, abs=1e-9)
    assert expected != pytest.approx(float(res.candidates[0, mode])) or mode == 9
    # without refinement the estimate is the likeliest candidate itself
    pick = search_constant_latency(*args, num_bins=50, num_candidates=11, score="learned", refine=False)
    assert pick.latency.item() == pytest.approx(float(res.candidates[0, mode]))


def test_candidate_curves_match_what_the_search_reads():
    case = make_cases("dev")[10]
    delayed, _, _ = simulate_case(case)
    latencies, curves, valid = candidate_curves(delayed.blurry, delayed.events, float(delayed.exposure_start[0]),
                                                float(delayed.exposure_end[0]), case.threshold)
    assert curves.shape == (NUM_FEATURES, len(latencies)) and valid.shape == latencies.shape
    assert latencies[0] == 0.0 and latencies[-1] == pytest.approx(case.exposure_us)
    assert bool(valid[0]) and not bool(valid[-1])  # events stop 15 ms after the 20 ms exposure
    with pytest.raises(ValueError, match="one frame"):
        candidate_curves(delayed.blurry.expand(2, -1, -1, -1), delayed.events, 0.0, 1.0, 0.2)


def test_candidate_curves_reach_below_zero_where_the_events_start_earlier():
    case = make_cases("dev")[10]
    plain, _, _ = simulate_case(case)
    early, _, _ = simulate_case(case, before_us=2000.0)
    start, end = float(plain.exposure_start[0]), float(plain.exposure_end[0])
    assert float(early.events.t.min()) < start - 1500.0 <= start <= float(plain.events.t.min())
    latencies, curves, valid = candidate_curves(plain.blurry, plain.events, start, end, case.threshold)
    below, curves_below, valid_below = candidate_curves(early.blurry, early.events, start, end, case.threshold,
                                                        before_us=2000.0)
    # ten more candidates at the same spacing, down to -2 ms, each window holding events
    assert len(below) == len(latencies) + 10 and below[0] == -2000.0
    torch.testing.assert_close(below[10:], latencies)
    assert curves_below.shape == (NUM_FEATURES, len(below)) and bool(valid_below[:11].all())
    assert torch.equal(valid_below[10:], valid)
    for bad in (-1.0, case.exposure_us + 1.0, math.nan):
        with pytest.raises(ValueError, match="before_us"):
            candidate_curves(early.blurry, early.events, start, end, case.threshold, before_us=bad)


def test_learned_score_reads_the_binned_table_too():
    case = make_cases("dev")[28]
    delayed, _, _ = simulate_case(case)
    args = (delayed.blurry, delayed.events, delayed.exposure_start, delayed.exposure_end, case.threshold)
    binned = search_constant_latency(*args, score="learned", method="binned")
    continuous = search_constant_latency(*args, score="learned")
    assert abs(binned.latency.item() - continuous.latency.item()) <= 200.0  # one coarse candidate


def _planted_search(monkeypatch, log_p, search_range, events_until=200.0):
    """The search over a small random frame (exposure 0-100 us, 11 default candidates) with a planted reader."""
    ev = random_events(3000, (8, 9), (0.0, events_until), seed=6)
    blurry = textured_frames(1, 1, 8, 9, seed=6)
    monkeypatch.setattr(search_learned, "_curve_reader_on", lambda device: _PlantedReader(log_p))
    return search_constant_latency(blurry, ev, torch.zeros(1), torch.full((1,), 100.0), 0.2, num_bins=50,
                                   num_candidates=11, score="learned", search_range=search_range)


def test_learned_search_range_restricts_the_reader_to_it(monkeypatch):
    # the reader likes 80 us best and 30 us second; told the latency lies in 20-50 us it answers near 30 us, from the
    # curves over 0 to the exposure time it was trained on
    log_p = torch.full((11,), -30.0)
    log_p[[2, 3, 4, 7, 8, 9]] = torch.tensor([-2.0, -1.0, -1.5, -0.5, 0.0, -0.5])
    res = _planted_search(monkeypatch, log_p, (20.0, 50.0))
    torch.testing.assert_close(res.candidates[0], torch.linspace(0.0, 100.0, 11, dtype=torch.float64))
    p = torch.softmax(log_p[2:5].double(), 0)  # the pick (30 us) and one neighbour each side
    assert res.latency.item() == pytest.approx(float((p * torch.tensor([20.0, 30.0, 40.0])).sum()), abs=1e-9)
    own = res.log_probability[0]  # what the frame says for fusing: only the range's candidates
    assert bool(torch.isfinite(own[2:6]).all()) and not bool(torch.isfinite(own[[0, 1, 6, 7, 8]]).any())
    # three quarters of the reader's probability lies outside the range: its likeliest latency there is reported
    assert res.outside_range.tolist() == [80.0]
    # 0 to the exposure time is the default range itself
    default = _planted_search(monkeypatch, log_p, None)
    assert _planted_search(monkeypatch, log_p, (0.0, 100.0)).latency.item() == default.latency.item()
    assert default.latency.item() == pytest.approx(80.0, abs=1.0)
    assert math.isnan(default.outside_range.item())
    # a range that keeps more than half of it: nothing to report
    assert math.isnan(_planted_search(monkeypatch, log_p, (20.0, 80.0)).outside_range.item())


def test_an_estimate_held_at_the_range_edge_is_reported_not_silent(monkeypatch):
    # the reader is sure of 80 us; told 20-50 us the corrector answers within the range and says why
    log_p = torch.full((11,), -30.0)
    log_p[8] = 0.0
    ev = random_events(3000, (8, 9), (0.0, 200.0), seed=6)
    frames = EventFrames(textured_frames(2, 1, 8, 9, seed=6),
                         Events.cat([ev, ev]), torch.zeros(2), torch.full((2,), 100.0))
    monkeypatch.setattr(search_learned, "_curve_reader_on", lambda device: _PlantedReader(log_p))
    corrector = EventLatencyCorrector(threshold=0.2, num_bins=50, num_candidates=11, search_range=(20.0, 50.0))
    with pytest.warns(SampleWarning, match=r"samples \[0, 1\]: the learned reader finds the latency likeliest at "
                                           r"80, 80 us, outside search_range 20-50 us") as caught:
        out = corrector(frames)
    assert all(20.0 <= v <= 50.0 for v in out.latency.flatten().tolist())
    assert out.meta["latency_outside_range_us"].tolist() == [80.0, 80.0]
    held = next(w.message for w in caught if isinstance(w.message, SampleWarning))
    assert held.kind == "outside_range" and held.samples == (0, 1)
    assert held.naming(["frame 7", "frame 8"]).startswith("frames 7, 8: the learned reader")


def test_a_range_narrower_than_10_us_is_named_with_its_decimals(monkeypatch):
    log_p = torch.full((11,), -30.0)
    log_p[8] = 0.0
    monkeypatch.setattr(search_learned, "_curve_reader_on", lambda device: _PlantedReader(log_p))
    ev = random_events(3000, (8, 9), (0.0, 200.0), seed=6)
    frames = EventFrames(textured_frames(1, 1, 8, 9), ev, torch.zeros(1), torch.full((1,), 100.0))
    corrector = EventLatencyCorrector(threshold=0.2, num_bins=50, num_candidates=11, search_range=(33.25, 37.5))
    with pytest.warns(SampleWarning, match=r"outside search_range 33\.25-37\.50 us"):
        corrector(frames)


def test_learned_search_range_narrower_than_the_candidates_spacing(monkeypatch):
    log_p = torch.full((11,), -30.0)
    log_p[8] = 0.0
    res = _planted_search(monkeypatch, log_p, (33.0, 37.0))  # between the candidates 30 and 40 us
    assert 33.0 <= res.latency.item() <= 37.0 and not bool(res.fallback[0])


def test_learned_search_range_past_the_events_falls_back_to_its_low_end(monkeypatch):
    # the events stop at 150 us: no window of 60-100 us (ending at 160-200 us) holds the whole exposure's events
    res = _planted_search(monkeypatch, torch.zeros(11), (60.0, 100.0), events_until=150.0)
    assert res.latency.item() == 60.0 and bool(res.fallback[0]) and res.source == ["fallback"]


def test_learned_search_range_beyond_the_exposure_warns(monkeypatch):
    with pytest.warns(UserWarning, match="trained on"):
        res = _planted_search(monkeypatch, torch.zeros(13), (0.0, 150.0), events_until=300.0)  # 13 candidates
    assert float(res.candidates[0, -1]) == pytest.approx(150.0)  # read as given


def test_answer_block_snaps_outwards_to_the_candidates():
    latencies = torch.arange(0.0, 101.0, 10.0, dtype=torch.float64)
    assert torch.nonzero(search_learned._answer_block(latencies, 20.0, 50.0)).flatten().tolist() == [2, 3, 4, 5]
    assert torch.nonzero(search_learned._answer_block(latencies, 33.0, 37.0)).flatten().tolist() == [3, 4]
    assert bool(search_learned._answer_block(latencies, 0.0, 100.0).all())
