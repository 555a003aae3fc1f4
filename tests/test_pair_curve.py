"""``evlatcorr.pair_curve``: a latency growing as pixels dim, fitted to two frames' agreement."""

from __future__ import annotations

import pytest
import torch

from evlatcorr.benchmark.compare import psnr
from evlatcorr.correction import EventLatencyCorrector, SlopedLatencyCorrector
from evlatcorr.pair_curve import fit_pair_curve, pair_curve_table
from evlatcorr.pair_evidence import pair_disagreement_curve, pair_disagreement_maps
from evlatcorr.simulate import simulate
from evlatcorr.spatial import PolynomialLatency, save_curve

OFFSETS = torch.arange(0.0, 8001.0, 500.0, dtype=torch.float64)


@pytest.fixture(scope="module")
def constant_pair():
    return simulate("camera", num_frames=2, height=48, width=64, latency_us=3000.0, seed=0).pairs().split()[0]


@pytest.fixture(scope="module")
def dim_later():
    # dim pixels later: 0.5 ms at white to 8 ms at black (the simulator's per-pixel delay)
    return simulate("astronaut", num_frames=3, height=48, width=64, latency="intensity_delay",
                    latency_range_us=(500.0, 8000.0), max_speed_px_per_ms=1.0, seed=0)


def test_without_a_slope_the_table_is_the_pairs_disagreement_curve(constant_pair):
    table = pair_curve_table(constant_pair, 0.2, OFFSETS, torch.tensor([0.0, 1000.0]))
    assert table.shape == (2, len(OFFSETS)) and table.dtype == torch.float64
    torch.testing.assert_close(table[0], pair_disagreement_curve(constant_pair, 0.2, OFFSETS).double(),
                               rtol=1e-5, atol=0.0)


def test_a_slope_reads_each_pixel_at_its_own_latency(constant_pair):
    # the map a + b f(L): each pixel's disagreement read at its latency on a fine grid, by hand, then averaged
    a, b = 2000.0, 3000.0
    f = PolynomialLatency(order=1).transform(PolynomialLatency.intensity(constant_pair.blurry)).flatten().double()
    fine = torch.arange(0.0, 5001.0, 10.0, dtype=torch.float64)
    maps = pair_disagreement_maps(constant_pair, 0.2, fine).flatten(1).double()
    nearest = ((a + b * f) / 10.0).round().long()
    by_hand = float(maps.gather(0, nearest[None]).mean())
    table = pair_curve_table(constant_pair, 0.2, fine, torch.tensor([0.0, b]))
    assert float(table[1, 200]) == pytest.approx(by_hand, rel=2e-3)  # offset 200 x 10 = a; read between grid points
    assert float(table[1, 200]) != pytest.approx(float(table[0, 200]), rel=1e-2)  # the slope moved the pixels
    # the map's latencies run up to a + b at black pixels: past the pair's last event the entry is not read
    short = simulate("camera", num_frames=2, height=24, width=32, latency_us=3000.0, seed=0)
    cut = short.pairs(after_us=4000.0).split()[0]
    reach = float(cut.events.t.max() - cut.exposure_end_next[0])
    table = pair_curve_table(cut, 0.2, OFFSETS, torch.tensor([0.0, b]))
    assert bool(torch.isinf(table[0, OFFSETS > reach]).all()) and bool(torch.isfinite(table[0, OFFSETS <= reach]).all())
    assert bool(torch.isinf(table[1, OFFSETS + b * float(f.max()) > reach]).all())


def test_one_latency_for_all_pixels_gets_no_slope(constant_pair):
    fit = fit_pair_curve(constant_pair, 0.2)
    assert fit.slope_us == 0.0 and fit.offset_us == fit.single_latency_us and fit.pairs_used == 1
    assert abs(fit.offset_us - 3000.0) <= 250.0
    assert fit.curve.order == 1
    torch.testing.assert_close(fit.curve(constant_pair.blurry), torch.full((1, 1, 48, 64), fit.offset_us))
    # a slope that earns less than min_gain is not taken: with no bar the best grid point stands
    free = fit_pair_curve(constant_pair, 0.2, min_gain=0.0)
    assert free.gain >= 0.0 and (free.slope_us > 0) == (free.gain > 0)


def test_a_threshold_too_high_is_not_taken_for_a_slope():
    # θ 1.45x the true one makes the disagreement grow with intensity: a slope takes it up unless it must also hold
    # at the θ the pair agrees on best without one
    pair = simulate("coffee", num_frames=2, height=96, width=128, latency_us=3000.0, seed=0).pairs()
    unchecked = fit_pair_curve(pair, 0.29, threshold_scales=())
    assert unchecked.slope_us > 0 and unchecked.gain > 0.01
    checked = fit_pair_curve(pair, 0.29)
    assert checked.slope_us == 0.0 and checked.gain <= 0.01 and checked.offset_us == checked.single_latency_us


@pytest.mark.slow
def test_dim_pixels_later_give_a_slope_and_a_closer_map(dim_later, tmp_path):
    pairs = dim_later.pairs()
    fit = fit_pair_curve(pairs, 0.2)
    truth = dim_later.frames().meta["true_latency"][:2].double()
    curve_error = float((fit.curve(pairs.blurry).detach().double() - truth).abs().mean())
    one_error = float((fit.single_latency_us - truth).abs().mean())
    assert fit.pairs_used == 2 and fit.slope_us >= 4000.0 and fit.gain > 0.05
    assert curve_error < 0.6 * one_error  # about 950 against 2070 µs
    # a real slope holds at a threshold 1.45x too high, where the pairs' agreement prefers the true one
    assert fit_pair_curve(pairs, 0.29).slope_us >= 4000.0
    # saved, the spatial corrector applies it to every frame
    save_curve(fit.curve, tmp_path / "curve.pt", source="fit_pair_curve")
    frames = dim_later.frames()
    out = EventLatencyCorrector(mode="spatial", curve=tmp_path / "curve.pt")(frames)
    torch.testing.assert_close(out.latency, fit.curve(frames.blurry).detach())
    assert out.meta["latency_source"] == ["curve"] * 3


@pytest.mark.slow
def test_spatial_mode_given_pairs_slopes_each_frames_constant_latency(dim_later):
    # without a trained curve, spatial mode reads pairs as: the constant corrector's latency (its reader with the
    # pair's agreement) plus the departure of the curve fitted to the pair from that curve's single latency
    pairs = dim_later.pairs()
    constant = EventLatencyCorrector()(pairs)
    spatial = EventLatencyCorrector(mode="spatial")(pairs)
    fits = spatial.meta["pair_curves"]
    departure = torch.cat([fit.departure(pair.blurry) for fit, pair in zip(fits, pairs.split())])
    torch.testing.assert_close(spatial.latency, (constant.latency + departure).clamp(0.0, 20000.0))
    assert spatial.meta["latency_slope_us"].tolist() == [fit.slope_us for fit in fits] and min(
        fit.slope_us for fit in fits) > 0
    truth = dim_later.frames().meta["true_latency"][:2]
    assert float((spatial.latency - truth).abs().mean()) < 0.7 * float((constant.latency - truth).abs().mean())
    # the events and the latent follow the map
    torch.testing.assert_close(spatial.corrected.t, pairs.events.shift(spatial.latency.double()).t)
    assert psnr(spatial.latent, pairs.sharp) > psnr(constant.latent, pairs.sharp) + 1.0
    # a pair that tells nothing keeps its frame's constant latency
    blank = pairs.replace(blurry_next=torch.zeros_like(pairs.blurry_next))
    kept = EventLatencyCorrector(mode="spatial")(blank)
    assert kept.meta["pair_curves"] == [None, None] and kept.meta["latency_slope_us"].tolist() == [0.0, 0.0]


@pytest.mark.slow
def test_a_recordings_curve_slopes_every_frames_constant_latency(dim_later):
    # what the command line runs in spatial mode: one curve for the recording, added to each frame's constant latency
    constant = EventLatencyCorrector()
    fit = fit_pair_curve(dim_later.pairs(), 0.2)
    frames = dim_later.frames()
    flat = constant(frames)
    sloped = SlopedLatencyCorrector(constant, fit, constant.config)(frames)
    torch.testing.assert_close(sloped.latency, (flat.latency + fit.departure(frames.blurry)).clamp(0.0, 20000.0))
    assert sloped.meta["latency_slope_us"].tolist() == [fit.slope_us] * 3 and fit.slope_us >= 4000.0
    truth = frames.meta["true_latency"]
    assert float((sloped.latency - truth).abs().mean()) < 0.7 * float((flat.latency - truth).abs().mean())
    assert psnr(sloped.latent, frames.sharp) > psnr(flat.latent, frames.sharp) + 1.0


def test_the_sloped_corrector_refuses_what_it_cannot_use(constant_pair):
    constant = EventLatencyCorrector()
    fit = fit_pair_curve(constant_pair, 0.2)
    for args, message in (((None, fit, constant.config), "corrector must be a constant corrector module"),
                          ((constant, fit.curve, constant.config), "curve must be a PairCurve"),
                          ((constant, fit, {}), "config must be a SearchConfig")):
        with pytest.raises(ValueError, match=message):
            SlopedLatencyCorrector(*args)


def test_pairs_that_tell_nothing_are_left_out_and_none_is_an_error(constant_pair):
    blank = constant_pair.replace(blurry_next=torch.zeros_like(constant_pair.blurry))
    with pytest.raises(ValueError, match="no pair tells a latency"):
        fit_pair_curve(blank, 0.2)
    events = constant_pair.events
    no_events = constant_pair.replace(events=events.select(torch.zeros(len(events), dtype=torch.bool)))
    with pytest.raises(ValueError, match="no pair tells a latency"):
        fit_pair_curve(no_events, 0.2)


def test_bad_inputs_are_refused(constant_pair):
    frames = simulate("camera", num_frames=2, height=24, width=32, seed=0).frames()
    with pytest.raises(ValueError, match="reads pairs of frames"):
        fit_pair_curve(frames, 0.2)
    with pytest.raises(ValueError, match="threshold must be positive"):
        fit_pair_curve(constant_pair, 0.0)
    for kwargs, message in (({"max_latency_us": 0.0}, "max_latency_us must be a positive"),
                            ({"max_slope_us": -1.0}, "max_slope_us must be a non-negative"),
                            ({"min_gain": float("nan")}, "min_gain must be a non-negative"),
                            ({"threshold_scales": (1.2, 0.0)}, "threshold_scales must be positive")):
        with pytest.raises(ValueError, match=message):
            fit_pair_curve(constant_pair, 0.2, **kwargs)
    with pytest.raises(ValueError, match="one pair of frames"):
        pair_curve_table(frames, 0.2, OFFSETS, torch.tensor([0.0]))
    for offsets in (OFFSETS + 100.0, torch.tensor([0.0, 500.0, 1500.0]), OFFSETS[None], torch.tensor([])):
        with pytest.raises(ValueError, match="offsets must"):
            pair_curve_table(constant_pair, 0.2, offsets, torch.tensor([0.0]))
    with pytest.raises(ValueError, match="slopes must"):
        pair_curve_table(constant_pair, 0.2, OFFSETS, torch.tensor([500.0]))
