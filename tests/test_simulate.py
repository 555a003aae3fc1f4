from __future__ import annotations

import math

import pytest
import torch

from evlatcorr import Events
from evlatcorr.simulate import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN, load_photograph, simulate, simulate_dataset

SMALL = dict(height=32, width=40, exposure_us=5000.0, frame_interval_us=6000.0)


def test_photograph_splits_are_disjoint_and_load():
    assert not set(PHOTOGRAPHS_TRAIN) & set(PHOTOGRAPHS_TEST)
    assert len(PHOTOGRAPHS_TEST) >= 8
    img = load_photograph("coins")  # a grey photograph comes back as RGB
    assert img.shape[0] == 3 and 0.0 <= float(img.min()) and float(img.max()) <= 1.0
    torch.testing.assert_close(img[0], img[1])


def test_shapes_and_ground_truth():
    seq = simulate("astronaut", num_frames=3, seed=0, **SMALL)
    assert seq.blurry.shape == seq.sharp.shape == (3, 3, 32, 40)
    assert seq.true_latency.shape == (3, 1, 32, 40)
    assert seq.exposure_start.tolist() == [5000.0, 11000.0, 17000.0]
    assert (seq.exposure_end - seq.exposure_start).tolist() == [5000.0] * 3
    assert seq.target_frames.shape == (2, 3, 32, 40)  # the two gaps' midpoints
    torch.testing.assert_close(seq.target_times, torch.tensor([10500.0, 16500.0], dtype=torch.float64))
    ev = seq.ideal_events
    assert len(ev) > 100 and ev.sensor_size == (32, 40)
    assert bool((ev.t[1:] >= ev.t[:-1]).all())
    assert float(ev.t.min()) >= 0.0


def test_deterministic_given_seed():
    a = simulate("coffee", num_frames=1, seed=3, **SMALL)
    b = simulate("coffee", num_frames=1, seed=3, **SMALL)
    c = simulate("coffee", num_frames=1, seed=4, **SMALL)
    assert torch.equal(a.ideal_events.t, b.ideal_events.t) and torch.equal(a.blurry, b.blurry)
    assert len(a.ideal_events) != len(c.ideal_events) or not torch.equal(a.ideal_events.t, c.ideal_events.t)


def test_constant_latency_is_an_exact_shift():
    seq = simulate("camera", num_frames=1, latency="constant", latency_us=1234.0, seed=0, **SMALL)
    torch.testing.assert_close(seq.delayed_events.t, seq.ideal_events.t + 1234.0)
    assert torch.equal(seq.delayed_events.x, seq.ideal_events.x)
    assert seq.true_latency.unique().tolist() == [1234.0]


def test_blurry_is_mean_over_exposure():
    # a static camera (speed 0): blurry == sharp, and no events at all
    seq = simulate("camera", num_frames=1, speed_px_per_ms=0.0, seed=0, **SMALL)
    torch.testing.assert_close(seq.blurry, seq.sharp, atol=1e-5, rtol=0)
    assert len(seq.ideal_events) == 0


def test_events_integrate_to_log_change():
    # summed polarity x threshold between two times equals the log-intensity change up to the two reference
    # levels' lag (each < threshold): |error| < 2 threshold, and about threshold/2 on average
    seq = simulate("brick", num_frames=2, latency="none", seed=1, threshold=0.15, **SMALL)
    t0, t1 = float(seq.exposure_start[0] + 2500), float(seq.exposure_start[1] + 2500)
    frame0, frame1 = seq.sharp[0], seq.sharp[1]  # rendered at those mid-exposure times
    lum = lambda f: 0.299 * f[0] + 0.587 * f[1] + 0.114 * f[2]  # noqa: E731
    change = torch.log(lum(frame1) + 1e-3) - torch.log(lum(frame0) + 1e-3)
    ev = seq.ideal_events.window(t0, t1)
    counted = torch.zeros(32 * 40).index_add_(0, ev.y * 40 + ev.x, ev.p.float()).view(32, 40) * 0.15
    err = (counted - change).abs()
    assert float(err.max()) < 2 * 0.15 + 1e-3
    assert float(err.mean()) < 0.15 / 2


def test_intensity_latency_makes_dim_pixels_late():
    seq = simulate("camera", num_frames=1, latency="intensity", latency_range_us=(500.0, 10000.0), seed=0,
                   height=32, width=40, exposure_us=20000.0, frame_interval_us=20000.0)
    lum = 0.299 * seq.blurry[0, 0] + 0.587 * seq.blurry[0, 1] + 0.114 * seq.blurry[0, 2]
    lat = seq.true_latency[0, 0]
    assert 500.0 <= float(lat.min()) and float(lat.max()) <= 10000.0
    bright, dim = lum > lum.quantile(0.8), lum < lum.quantile(0.2)
    assert float(lat[dim].mean()) > float(lat[bright].mean()) + 2000.0
    torch.testing.assert_close(lat, (500.0 / lum.clamp_min(1e-6)).clamp(500.0, 10000.0))
    # the delayed stream lags: its median event time is later than the ideal one's
    assert float(seq.delayed_events.t.median()) > float(seq.ideal_events.t.median())


def test_noise_rate():
    quiet = simulate("camera", num_frames=1, speed_px_per_ms=0.0, noise_rate_hz=50.0, seed=2, **SMALL)
    duration = quiet.config["margin_us"] + 5000.0 + 5000.0 + 4000.0 + 1000.0  # simulated span, us
    expected = 50.0 * duration * 1e-6 * 32 * 40
    assert abs(len(quiet.ideal_events) - expected) < 5 * math.sqrt(expected)


def test_frames_and_pairs_batches():
    seq = simulate("chelsea", num_frames=2, seed=0, **SMALL)
    frames = seq.frames("delayed")
    assert frames.batch_size == 2 and frames.sharp is not None
    assert float(frames.events.t[frames.events.batch == 0].max()) < float(seq.exposure_end[0]) + 5000.0
    pairs = seq.pairs("ideal")
    assert pairs.batch_size == 1 and pairs.blurry_next is not None
    assert pairs.target_frames.shape == (1, 1, 3, 32, 40)
    assert isinstance(pairs.events, Events)


def test_dataset_varies_motion():
    seqs = simulate_dataset(["camera", "camera"], num_frames=1, **SMALL)
    assert not torch.equal(seqs[0].blurry, seqs[1].blurry)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(latency="quadratic"), "latency must be"),
        (dict(exposure_us=-1.0), "exposure_us"),
        (dict(threshold=0.0), "threshold"),
        (dict(frame_interval_us=1.0), "frame_interval_us"),
        (dict(latency="intensity", latency_range_us=(0.0, 10.0)), "latency_range_us"),
    ],
)
def test_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        simulate("camera", **{**SMALL, **kwargs})


def test_unknown_photograph():
    with pytest.raises(ValueError, match="unknown photograph"):
        simulate("lena", **SMALL)
