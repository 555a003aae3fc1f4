from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.simulate import (
    LATENCY_MODELS,
    PHOTOGRAPHS_TEST,
    PHOTOGRAPHS_TRAIN,
    SimulatedSequence,
    load_photograph,
    luminance,
    simulate,
    simulate_dataset,
)

SMALL = dict(height=32, width=40, exposure_us=5000.0, frame_interval_us=6000.0)


@pytest.fixture(scope="module")
def seq3() -> SimulatedSequence:
    return simulate("astronaut", num_frames=3, seed=0, **SMALL)


def log_lum(rgb: torch.Tensor) -> torch.Tensor:
    return torch.log(luminance(rgb)[..., 0, :, :] + 1e-3)


def per_pixel_sum(ev: Events, values: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    h, w = size
    return torch.zeros(h * w, dtype=values.dtype).index_add_(0, ev.y * w + ev.x, values).view(h, w)


# --- a hand-computable scene: an exponential ramp (log-linear edge) moving at a known speed -----------------------
RAMP_L, RAMP_LO, RAMP_HI, RAMP_V, RAMP_THR = 20.0, 0.05, 0.2, 2.0, 0.1  # px, intensities, px/ms, log units
RAMP_PHOTO = (64, 160)  # large enough that the photo is not resampled


def ramp_image() -> torch.Tensor:
    """Dark (0.05) left, bright (0.2) right, log-intensity linear over RAMP_L px around the centre column."""
    ph, pw = RAMP_PHOTO
    x = torch.arange(pw, dtype=torch.float64)
    x0 = (pw - 1) / 2 - RAMP_L / 2
    a = math.log(RAMP_HI / RAMP_LO) / RAMP_L
    row = RAMP_LO * torch.exp(a * (x - x0).clamp(0, RAMP_L))
    return row.float()[None, None].expand(3, ph, pw).contiguous()


def ramp_sequence(latency: str) -> SimulatedSequence:
    return simulate(ramp_image(), num_frames=1, height=16, width=24, exposure_us=8000.0, frame_interval_us=8000.0,
                    latency=latency, latency_range_us=(500.0, 2000.0), threshold=RAMP_THR, motion=(RAMP_V, 0.0))


def ramp_expected_times(seq: SimulatedSequence, column: int) -> list[float]:
    """Crossing times at a pixel of ``column``: it sees photo column s(t) = pc + (u - uc) - v (t - tc)."""
    ph, pw = RAMP_PHOTO
    pc, uc, tc = (pw - 1) / 2, (24 - 1) / 2, seq.config["t_end_us"] / 2
    x0, a = pc - RAMP_L / 2, math.log(RAMP_HI / RAMP_LO) / RAMP_L
    ref, times = math.log(RAMP_HI + 1e-3), []
    for k in range(1, 100):
        intensity = math.exp(ref - k * RAMP_THR) - 1e-3  # OFF crossings: the pixel goes from bright to dark
        if intensity < RAMP_LO:
            break
        s = x0 + math.log(intensity / RAMP_LO) / a
        times.append(tc - (s - pc - (column - uc)) / RAMP_V * 1000.0)
    return times


# --- smoke and shapes --------------------------------------------------------------------------------------------
def test_photograph_splits_are_disjoint_and_load():
    assert not set(PHOTOGRAPHS_TRAIN) & set(PHOTOGRAPHS_TEST)
    assert len(PHOTOGRAPHS_TEST) >= 8 and len(PHOTOGRAPHS_TRAIN) >= 8
    for name in PHOTOGRAPHS_TRAIN + PHOTOGRAPHS_TEST:
        img = load_photograph(name)
        assert img.dtype == torch.float32 and img.dim() == 3 and img.shape[0] == 3 and min(img.shape[1:]) >= 150
        assert 0.0 <= float(img.min()) and float(img.max()) <= 1.0 and float(img.std()) > 0.04, name
    grey = load_photograph("coins")  # a grey photograph comes back as RGB
    torch.testing.assert_close(grey[0], grey[1])
    torch.testing.assert_close(load_photograph("coins", gain=0.25), grey * 0.25)
    assert torch.equal(load_photograph("ihc"), load_photograph("immunohistochemistry"))


def test_shapes_and_timeline(seq3):
    assert seq3.num_frames == 3 and seq3.sensor_size == (32, 40)
    assert seq3.blurry.shape == seq3.sharp.shape == (3, 3, 32, 40)
    assert seq3.true_latency.shape == (3, 1, 32, 40) and seq3.threshold_map.shape == (1, 1, 32, 40)
    # default margin = exposure (5000) before the first exposure, exposure + constant latency (4000) after the last
    assert seq3.exposure_start.dtype == torch.float64
    assert seq3.exposure_start.tolist() == [5000.0, 11000.0, 17000.0]
    assert seq3.exposure_end.tolist() == [10000.0, 16000.0, 22000.0]
    assert seq3.config["t_end_us"] == 31000.0
    assert seq3.target_frames.shape == (2, 3, 32, 40)  # the two gaps' midpoints
    torch.testing.assert_close(seq3.target_times, torch.tensor([10500.0, 16500.0], dtype=torch.float64))
    for name in ("blurry", "sharp", "target_frames"):
        v = getattr(seq3, name)
        assert 0.0 <= float(v.min()) and float(v.max()) <= 1.0, name


def test_events_in_sensor_sorted_and_spanning_the_sequence(seq3):
    for ev in (seq3.ideal_events, seq3.delayed_events):
        assert isinstance(ev, Events) and ev.batch_size == 1 and ev.sensor_size == (32, 40)
        assert len(ev) > 1000 and ev.t.dtype == torch.float64 and ev.p.dtype == torch.int8
        assert bool((ev.t[1:] >= ev.t[:-1]).all())
        assert 0 <= int(ev.x.min()) and int(ev.x.max()) < 40 and 0 <= int(ev.y.min()) and int(ev.y.max()) < 32
        assert set(ev.p.unique().tolist()) == {-1, 1}
    ev = seq3.ideal_events
    assert float(ev.t.min()) >= 0.0 and float(ev.t.max()) <= 31000.0
    assert float(ev.t.min()) < 1000.0 and float(ev.t.max()) > 30000.0  # events all along the timeline
    # validated by the public constructor (sorted, in range)
    Events(ev.x, ev.y, ev.t, ev.p, sensor_size=ev.sensor_size)


def test_motion_is_strong_enough_and_steps_are_small():
    seq = simulate("camera", num_frames=1, seed=0, height=64, width=80)  # default 20 ms exposure
    assert seq.config["dt_us"] == 200.0  # 0.3 px / (1.5 px/ms)
    # a 20 ms exposure is clearly blurred: blurry differs from the sharp mid-exposure frame
    assert float((seq.blurry - seq.sharp).abs().mean()) > 0.02
    assert simulate("camera", num_frames=1, dt_us=123.0, **SMALL).config["dt_us"] == 123.0


# --- exceptions --------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(latency="quadratic"), "latency must be"),
        (dict(exposure_us=-1.0), "exposure_us"),
        (dict(exposure_us=float("nan")), "exposure_us"),
        (dict(threshold=0.0), "threshold must be positive"),
        (dict(threshold=-0.2), "threshold must be positive"),
        (dict(frame_interval_us=1.0), "frame_interval_us"),
        (dict(latency="intensity", latency_range_us=(0.0, 10.0)), "latency_range_us"),
        (dict(latency_range_us=(5000.0, 100.0)), "latency_range_us"),
        (dict(latency_us=-5.0), "latency_us"),
        (dict(noise_rate_hz=-1.0), "noise_rate_hz"),
        (dict(threshold_sigma=-0.1), "threshold_sigma"),
        (dict(max_speed_px_per_ms=-1.0), "max_speed_px_per_ms"),
        (dict(brightness=0.0), "brightness"),
        (dict(num_frames=0), "num_frames"),
        (dict(height=1), "height and width"),
        (dict(motion="spiral"), "motion"),
        (dict(motion=(1.0,)), "motion"),
        (dict(margin_us=-1.0), "margin_us"),
        (dict(dt_us=0.0), "dt_us"),
        (dict(target_times=[float("inf")]), "target_times"),
        # a zoom compounding over half a second would need the photograph at 10^18 times its size: refused, not
        # allocated
        (dict(num_frames=12, exposure_us=40000.0, frame_interval_us=40000.0, motion="zoom", max_speed_px_per_ms=4.0),
         r"the motion over 564 ms sees .* past the photograph's edges .* over 64 M\): simulate fewer or shorter"),
    ],
)
def test_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        simulate("camera", **{**SMALL, **kwargs})


@pytest.mark.parametrize(
    "image, match",
    [("lena", "unknown photograph"), (torch.rand(2, 50, 50), r"\(3, H, W\)"), (torch.rand(3, 50, 50) * 2, r"\[0, 1\]"),
     (torch.zeros(3, 50, 50, dtype=torch.uint8), "floating point"), ([1, 2], "photograph name or a tensor")],
)
def test_bad_image(image, match):
    with pytest.raises(ValueError, match=match):
        simulate(image, **SMALL)


def test_bad_photograph_and_method_arguments(seq3):
    with pytest.raises(ValueError, match="unknown photograph"):
        load_photograph("lena")
    with pytest.raises(ValueError, match="gain"):
        load_photograph("camera", gain=0.0)
    with pytest.raises(ValueError, match="which"):
        seq3.frames("late")
    with pytest.raises(ValueError, match="before_us"):
        seq3.frames(before_us=-1.0)
    with pytest.raises(ValueError, match="times_per_pair"):
        seq3.pairs(times_per_pair=0)
    with pytest.raises(ValueError, match="at least 2 frames"):
        simulate("camera", num_frames=1, **SMALL).pairs()
    with pytest.raises(ValueError, match="non-empty"):
        simulate_dataset([])


# --- values: hand-computed references ----------------------------------------------------------------------------
def test_deterministic_given_seed():
    a = simulate("coffee", num_frames=1, seed=3, noise_rate_hz=20.0, threshold_sigma=0.1, **SMALL)
    b = simulate("coffee", num_frames=1, seed=3, noise_rate_hz=20.0, threshold_sigma=0.1, **SMALL)
    c = simulate("coffee", num_frames=1, seed=4, noise_rate_hz=20.0, threshold_sigma=0.1, **SMALL)
    for name in ("x", "y", "t", "p"):
        assert torch.equal(getattr(a.ideal_events, name), getattr(b.ideal_events, name))
        assert torch.equal(getattr(a.delayed_events, name), getattr(b.delayed_events, name))
    assert torch.equal(a.blurry, b.blurry) and torch.equal(a.threshold_map, b.threshold_map)
    assert not torch.equal(a.blurry, c.blurry)
    assert len(a.ideal_events) != len(c.ideal_events) or not torch.equal(a.ideal_events.t, c.ideal_events.t)


def test_crossing_count_and_times_of_a_moving_ramp():
    # the pixel goes from 0.2 to 0.05: floor(log(0.201 / 0.051) / 0.1) = 13 OFF events at known times
    seq = ramp_sequence("none")
    assert seq.config["photo_scale"] == 1.0 and seq.config["dt_us"] == 150.0  # 0.3 px / (2 px/ms)
    expected_count = math.floor(math.log((RAMP_HI + 1e-3) / (RAMP_LO + 1e-3)) / RAMP_THR)
    assert expected_count == 13
    ev = seq.ideal_events
    for column in (9, 11, 12, 14):
        for row in (0, 8, 15):
            mine = (ev.x == column) & (ev.y == row)
            assert int(mine.sum()) == expected_count
            assert ev.p[mine].tolist() == [-1] * expected_count
            want = torch.tensor(ramp_expected_times(seq, column), dtype=torch.float64)
            torch.testing.assert_close(ev.t[mine], want, rtol=0, atol=10.0)  # µs; the ramp crosses 1 px in 500 µs


def test_events_integrate_to_the_log_intensity_change():
    # the known answer EDI relies on: from the start (reference = log level), sum(p * threshold) up to any time
    # equals the change of log-luminance at every pixel to within one threshold (of that pixel)
    for sigma in (0.0, 0.1):
        seq = simulate("coffee", num_frames=2, latency="none", seed=1, threshold=0.15, threshold_sigma=sigma, **SMALL)
        thr = seq.threshold_map[0, 0]
        for t1 in (float(seq.exposure_start[0]), float(seq.exposure_end[1]), seq.config["t_end_us"]):
            change = log_lum(seq.render([t1]))[0] - log_lum(seq.render([0.0]))[0]
            ev = seq.ideal_events.window(0.0, t1 + 1e-6)
            counted = per_pixel_sum(ev, ev.p.float() * thr[ev.y, ev.x], (32, 40))
            err = (counted - change).abs()
            assert bool((err < thr + 1e-4).all()), float((err / thr).max())
        assert float(change.abs().max()) > 1.0  # the scene really changed
    # between two arbitrary times the two reference lags add up: |error| < 2 thresholds
    t0, t1 = float(seq.exposure_start[0] + 2500), float(seq.exposure_start[1] + 2500)
    change = log_lum(seq.sharp[1]) - log_lum(seq.sharp[0])  # the sharp frames are at those mid-exposure times
    ev = seq.ideal_events.window(t0, t1)
    counted = per_pixel_sum(ev, ev.p.float() * thr[ev.y, ev.x], (32, 40))
    assert bool(((counted - change).abs() < 2 * thr + 1e-4).all())


def test_blurry_is_the_mean_of_the_frames_over_the_exposure(seq3):
    for i in range(3):
        times = torch.linspace(float(seq3.exposure_start[i]), float(seq3.exposure_end[i]), 401)
        frames = seq3.render(times)
        reference = (frames[1:] + frames[:-1]).mean(0) / 2  # trapezoid rule
        torch.testing.assert_close(seq3.blurry[i], reference, rtol=0, atol=2e-3)
        assert float((seq3.blurry[i] - seq3.sharp[i]).abs().max()) > 0.05  # and it is blurred
    torch.testing.assert_close(seq3.sharp, seq3.render((seq3.exposure_start + seq3.exposure_end) / 2))
    torch.testing.assert_close(seq3.target_frames, seq3.render(seq3.target_times))


def test_static_camera_gives_sharp_frames_and_no_events():
    seq = simulate("camera", num_frames=1, motion=(0.0, 0.0), **SMALL)
    torch.testing.assert_close(seq.blurry, seq.sharp, atol=1e-5, rtol=0)
    assert len(seq.ideal_events) == 0 and len(seq.delayed_events) == 0


def test_brightness_scales_the_scene():
    bright = simulate("coffee", num_frames=1, seed=2, **SMALL)
    dim = simulate("coffee", num_frames=1, seed=2, brightness=0.25, **SMALL)
    torch.testing.assert_close(dim.blurry, bright.blurry * 0.25, atol=1e-5, rtol=1e-4)
    torch.testing.assert_close(dim.sharp, bright.sharp * 0.25, atol=1e-5, rtol=1e-4)


def test_constant_latency_is_an_exact_shift():
    seq = simulate("camera", num_frames=1, latency="constant", latency_us=1234.0, seed=0, **SMALL)
    torch.testing.assert_close(seq.delayed_events.t, seq.ideal_events.t + 1234.0, rtol=0, atol=0)
    assert torch.equal(seq.delayed_events.x, seq.ideal_events.x) and torch.equal(seq.delayed_events.p,
                                                                                   seq.ideal_events.p)
    assert seq.true_latency.unique().tolist() == [1234.0]
    none = simulate("camera", num_frames=1, latency="none", seed=0, **SMALL)
    assert torch.equal(none.delayed_events.t, none.ideal_events.t) and none.true_latency.unique().tolist() == [0.0]


def set_lag(ideal: Events, delayed: Events, mask: torch.Tensor, t_end: float, bin_us: float = 250.0) -> float:
    """The shift (µs) that best aligns the integrated delayed events of the pixels in ``mask`` :math:`(H, W)`
    with their integrated ideal events (L1 over time and pixels)."""
    h, w = mask.shape
    nb = int(t_end // bin_us) + 1

    def integrated(ev: Events) -> torch.Tensor:
        b = (ev.t / bin_us).long().clamp(max=nb - 1)
        flat = torch.zeros(h * w * nb).index_add_(0, (ev.y * w + ev.x) * nb + b, ev.p.float())
        return flat.view(h * w, nb).cumsum(1)[mask.flatten()]

    si, sd = integrated(ideal), integrated(delayed)
    costs = [float((sd - torch.cat([torch.zeros(len(si), k), si[:, :nb - k]], 1)).abs().sum()) for k in range(60)]
    return min(range(60), key=costs.__getitem__) * bin_us


def test_intensity_latency_makes_dim_pixels_late():
    seq = simulate("astronaut", num_frames=1, latency="intensity", latency_range_us=(500.0, 10000.0), seed=0,
                   height=32, width=40, exposure_us=20000.0, frame_interval_us=20000.0)
    lum = luminance(seq.blurry)[0, 0]
    lat = seq.true_latency[0, 0]
    assert 500.0 <= float(lat.min()) and float(lat.max()) <= 10000.0
    torch.testing.assert_close(lat, (500.0 / lum).clamp(500.0, 10000.0))  # τ at the blurry frame's luminance
    bright, dim = lum > lum.quantile(0.75), lum < lum.quantile(0.25)
    assert float(lat[dim].mean()) > float(lat[bright].mean()) + 2000.0
    # the delayed events of dim pixels lag the ideal ones more than those of bright pixels
    t_end = seq.config["t_end_us"]
    lag_bright = set_lag(seq.ideal_events, seq.delayed_events, bright, t_end)
    lag_dim = set_lag(seq.ideal_events, seq.delayed_events, dim, t_end)
    assert 500.0 <= lag_bright and lag_dim > lag_bright + 500.0 and lag_dim <= 10000.0
    assert set_lag(seq.ideal_events, seq.ideal_events, dim, t_end) == 0.0  # the estimator's own zero
    assert seq.config["warmup_us"] >= 4 * 10000.0  # the filter starts in its steady state


def test_intensity_latency_lags_a_moving_ramp_by_tau():
    # intensities 0.05..0.2 with latency_range (500, 2000): τ = 500 / I >= 2500 is clipped to 2000 everywhere.
    # A first-order filter lags level crossings by τ on average; the filtered signal crosses the same levels.
    ideal, seq = ramp_sequence("none"), ramp_sequence("intensity")
    torch.testing.assert_close(seq.true_latency, torch.full_like(seq.true_latency, 2000.0))
    assert seq.config["t_end_us"] == ideal.config["t_end_us"] + 2000.0  # events run on by the largest latency
    for column in (10, 12, 13):
        a = (seq.ideal_events.x == column) & (seq.ideal_events.y == 5)
        d = (seq.delayed_events.x == column) & (seq.delayed_events.y == 5)
        assert int(a.sum()) == int(d.sum()) == 13
        want = torch.tensor(ramp_expected_times(seq, column), dtype=torch.float64)
        torch.testing.assert_close(seq.ideal_events.t[a], want, rtol=0, atol=10.0)
        lags = seq.delayed_events.t[d] - seq.ideal_events.t[a]
        assert bool((lags > 0).all()) and bool((lags < 2000.0 * 1.7).all())
        assert abs(float(lags.mean()) - 2000.0) < 100.0
        assert abs(float(lags[6:10].mean()) - 2000.0) < 150.0  # mid-ramp, the steady state: lag ≈ τ


def test_intensity_delay_shifts_each_event_by_the_true_map():
    seq = simulate("coffee", num_frames=2, latency="intensity_delay", latency_range_us=(300.0, 4000.0), seed=0,
                   **SMALL)
    ideal, delayed = seq.ideal_events, seq.delayed_events
    assert len(ideal) == len(delayed)
    mids = (seq.exposure_start + seq.exposure_end) / 2
    nearest = (ideal.t[:, None] - mids[None]).abs().argmin(1)
    want = ideal.t + seq.true_latency[nearest, 0, ideal.y, ideal.x].double()
    torch.testing.assert_close(delayed.t, want.sort().values)


def test_noise_rate_and_polarity():
    seq = simulate("camera", num_frames=1, motion=(0.0, 0.0), noise_rate_hz=50.0, seed=2, **SMALL)
    duration = seq.config["t_end_us"]
    expected = 50.0 * duration * 1e-6 * 32 * 40
    ev = seq.ideal_events
    assert abs(len(ev) - expected) < 5 * math.sqrt(expected)
    assert abs(float(ev.p.float().mean())) < 5 / math.sqrt(len(ev))
    assert abs(float(ev.t.mean()) - duration / 2) < 5 * duration / math.sqrt(12 * len(ev))
    assert torch.equal(seq.delayed_events.t, ev.t)  # noise is not delayed


def test_threshold_mismatch():
    seq = simulate("camera", num_frames=1, threshold=0.2, threshold_sigma=0.1, height=64, width=80,
                   exposure_us=2000.0, frame_interval_us=2000.0)
    thr = seq.threshold_map
    assert float(thr.min()) >= 0.2 * 0.2
    assert abs(float(thr.mean()) - 0.2) < 0.005 and abs(float(thr.std()) - 0.02) < 0.003
    uniform = simulate("camera", num_frames=1, threshold=0.2, height=16, width=20, exposure_us=2000.0)
    assert uniform.threshold_map.unique().tolist() == [pytest.approx(0.2)]


# --- batches for the corrector ----------------------------------------------------------------------------------
def test_frames_batch(seq3):
    frames = seq3.frames("delayed")
    assert isinstance(frames, EventFrames) and frames.batch_size == 3 and frames.sharp is not None
    assert torch.equal(frames.blurry, seq3.blurry) and torch.equal(frames.meta["true_latency"], seq3.true_latency)
    for i in range(3):
        t = frames.events.sample(i).t
        want = seq3.delayed_events.window(float(seq3.exposure_start[i]), float(seq3.exposure_end[i]) + 5000.0)
        assert torch.equal(t, want.t)  # default window: [start, end + exposure)
    wide = seq3.frames("ideal", before_us=1000.0, after_us=2000.0).events.sample(1)
    assert float(wide.t.min()) >= 11000.0 - 1000.0 and float(wide.t.max()) < 16000.0 + 2000.0
    assert float(wide.t.min()) < 10100.0 and float(wide.t.max()) > 17900.0


def test_pairs_batch(seq3):
    pairs = seq3.pairs("ideal")
    assert pairs.batch_size == 2 and pairs.blurry_next is not None
    assert torch.equal(pairs.blurry_next, seq3.blurry[1:])
    assert pairs.target_times.tolist() == [[10500.0], [16500.0]]
    assert torch.equal(pairs.target_frames[:, 0], seq3.target_frames)
    first = pairs.events.sample(0)
    assert float(first.t.min()) >= 5000.0 and float(first.t.max()) < 16000.0 + 5000.0
    three = seq3.pairs("delayed", times_per_pair=3)
    assert three.target_frames.shape == (2, 3, 3, 32, 40)
    torch.testing.assert_close(three.target_times[0], torch.tensor([9000.0, 10500.0, 12000.0], dtype=torch.float64))
    torch.testing.assert_close(three.target_frames[1], seq3.render(three.target_times[1]))
    stored = SimulatedSequence(**{**seq3.__dict__, "renderer": None})  # as read back from a file
    assert torch.equal(stored.pairs("ideal").target_frames, pairs.target_frames)
    with pytest.raises(ValueError, match="cannot render"):
        stored.pairs("ideal", times_per_pair=3)


def test_requested_target_times():
    seq = simulate("chelsea", num_frames=2, target_times=[9500.0, 12000.0], **SMALL)
    assert seq.target_times.tolist() == [10500.0, 9500.0, 12000.0]
    torch.testing.assert_close(seq.target_frames[1:], seq.render([9500.0, 12000.0]))


def test_dataset_varies_motion():
    seqs = simulate_dataset(["camera", "camera"], num_frames=1, **SMALL)
    assert [s.seed for s in seqs] == [0, 1]
    assert not torch.equal(seqs[0].blurry, seqs[1].blurry)


@pytest.mark.parametrize("latency", LATENCY_MODELS)
def test_every_latency_model_runs(latency):
    seq = simulate("rocket", num_frames=2, latency=latency, height=16, width=20, exposure_us=2000.0,
                   frame_interval_us=3000.0, latency_range_us=(200.0, 1000.0))
    assert seq.config["latency"] == latency and seq.frames().batch_size == 2
    assert float(seq.true_latency.min()) >= 0.0


# --- non-contiguous input, device ---------------------------------------------------------------------------------
def test_non_contiguous_and_grey_image():
    img = torch.rand(60, 70, 3, generator=torch.Generator().manual_seed(0))
    chw = img.permute(2, 0, 1)  # non-contiguous
    assert not chw.is_contiguous()
    a = simulate(chw, num_frames=1, **SMALL)
    b = simulate(chw.contiguous(), num_frames=1, **SMALL)
    assert torch.equal(a.blurry, b.blurry) and torch.equal(a.ideal_events.t, b.ideal_events.t)
    grey = simulate(chw[0], num_frames=1, **SMALL)
    torch.testing.assert_close(grey.blurry[:, 0], grey.blurry[:, 2])


def test_device(device):
    seq = simulate("camera", num_frames=2, device=device, noise_rate_hz=10.0, **SMALL)
    assert seq.blurry.device.type == device.type and seq.ideal_events.device.type == device.type
    cpu = simulate("camera", num_frames=2, noise_rate_hz=10.0, **SMALL)
    torch.testing.assert_close(seq.blurry.cpu(), cpu.blurry, atol=1e-4, rtol=0)
    assert abs(len(seq.ideal_events) - len(cpu.ideal_events)) <= 0.01 * len(cpu.ideal_events)


# --- motion kinds, moving objects, leak and refractory noise -----------------------------------------------------
TINY = dict(num_frames=1, height=24, width=32, exposure_us=4000.0, frame_interval_us=4000.0)


def texture() -> torch.Tensor:
    from evlatcorr.scenes import procedural_scene

    return procedural_scene("noise", 64, 80, seed=0)


def events_per_pixel(ev: Events, size: tuple[int, int]) -> torch.Tensor:
    return per_pixel_sum(ev, torch.ones(len(ev)), size)


@pytest.mark.parametrize("motion", ["rotation", "zoom"])
def test_rotation_and_zoom_fire_more_at_the_corners(motion):
    seq = simulate(texture(), motion=motion, max_speed_px_per_ms=2.0, seed=1, **TINY)
    again = simulate(texture(), motion=motion, max_speed_px_per_ms=2.0, seed=1, **TINY)
    assert torch.equal(seq.ideal_events.t, again.ideal_events.t) and torch.equal(seq.blurry, again.blurry)
    assert seq.config["motion"] == motion and seq.config["dt_us"] == pytest.approx(150.0)  # 0.3 px / 2 px/ms
    counts = events_per_pixel(seq.ideal_events, (24, 32))
    yy, xx = torch.meshgrid(torch.arange(24.0) - 11.5, torch.arange(32.0) - 15.5, indexing="ij")
    r = torch.sqrt(xx**2 + yy**2)
    assert len(seq.ideal_events) > 1000
    # image speed grows with the distance to the centre: the centre stays sharp and quiet
    assert float(counts[r < 4].mean()) < 0.4 * float(counts[r > 14].mean())
    assert float((seq.blurry - seq.sharp).abs()[..., r > 14].mean()) > 2 * float(
        (seq.blurry - seq.sharp).abs()[..., r < 4].mean())


def test_rotation_and_zoom_directions_are_seeded():
    spins = {simulate(texture(), motion="rotation", max_speed_px_per_ms=2.0, seed=s, **TINY).render([0.0, 8000.0])
             .sum().item() for s in range(6)}
    assert len(spins) > 1  # the random sign differs across seeds


def moving_disc_background() -> torch.Tensor:
    background = torch.full((3, 40, 50), 0.4)
    background[:, :, 25:] = 0.7  # a static edge: it must not fire
    return background


def moving_disc_sequence(**kwargs):
    from evlatcorr.simulate import ObjectSpec

    background = moving_disc_background()
    disc = ObjectSpec(torch.full((3, 6, 6), 0.05), size=(8, 8), position=(6.0, 6.0), velocity=(1.0, 0.0),
                      shape="disc", time_us=0.0)
    return simulate(background, objects=[disc], **{**TINY, **kwargs}), disc


def test_objects_move_over_a_static_background():
    seq, disc = moving_disc_sequence()
    ev = seq.ideal_events
    assert len(ev) > 50 and seq.config["objects"][0]["velocity"] == [1.0, 0.0]
    assert seq.config["dt_us"] == 200.0  # min(200, 0.3 px / 1 px/ms)
    t_end = seq.config["t_end_us"]
    # every event lies in the band the disc sweeps: rows 6 ± 5, columns from 6 - 5 to 6 + t_end / 1000 + 5
    assert int(ev.y.min()) >= 1 and int(ev.y.max()) <= 11
    assert int(ev.x.min()) >= 1 and int(ev.x.max()) <= 6 + t_end / 1000 + 5
    # and the disc's edge moves by 1 px/ms: the mean event column follows it
    early, late = ev.window(0.0, t_end / 3), ev.window(2 * t_end / 3, t_end + 1)
    shift = float(late.x.float().mean() - early.x.float().mean())
    assert abs(shift - 2 * t_end / 3 / 1000) < 1.5
    # frames: away from the object's band the view is the still background (with its static edge)
    frames = seq.render([0.0, 8000.0])
    still = simulate(moving_disc_background(), motion=(0.0, 0.0), **TINY).render([0.0])
    assert float(still.max() - still.min()) > 0.2
    torch.testing.assert_close(frames[:, :, 13:], still[:, :, 13:].expand(2, -1, -1, -1), rtol=0, atol=1e-6)
    assert float(frames[0, 0, 6, 6]) < 0.1 and float(frames[1, 0, 6, 14]) < 0.1  # the dark disc's centre
    assert float(frames[1, 0, 6, 6]) == pytest.approx(0.4, abs=1e-4)  # it has left


def test_objects_colour_and_luminance_agree():
    seq, _ = moving_disc_sequence()
    t = 3000.0
    rgb = seq.render([t])
    ev = seq.ideal_events
    assert torch.equal(ev.p.unique(), torch.tensor([-1, 1], dtype=torch.int8))
    # the blurry frame is the mean of the composited colour frames, as without objects
    times = torch.linspace(float(seq.exposure_start[0]), float(seq.exposure_end[0]), 201)
    frames = seq.render(times)
    torch.testing.assert_close(seq.blurry[0], (frames[1:] + frames[:-1]).mean(0) / 2, rtol=0, atol=3e-3)
    assert rgb.shape == (1, 3, 24, 32)


@pytest.mark.parametrize(
    "kwargs, match",
    [(dict(shape="star"), "shape"), (dict(size=(1, 8)), "size"), (dict(velocity=(float("nan"), 0.0)), "finite"),
     (dict(sprite=3), "sprite"), (dict(sprite=("plasma", 1)), "procedural"), (dict(sprite=("text", 1.5)), "seed")],
)
def test_bad_objects(kwargs, match):
    from evlatcorr.simulate import ObjectSpec

    spec = ObjectSpec(**{**dict(sprite="coins", size=(8, 8), position=(5.0, 5.0)), **kwargs})
    with pytest.raises(ValueError, match=match):
        simulate("camera", objects=[spec], **TINY)


def test_objects_need_a_static_camera():
    from evlatcorr.simulate import ObjectSpec

    spec = ObjectSpec(("shapes", 3), size=(10, 12), position=(5.0, 5.0), velocity=(1.0, 1.0), shape="rect")
    with pytest.raises(ValueError, match="static background"):
        simulate("camera", objects=[spec], motion="rotation", **TINY)
    with pytest.raises(ValueError, match="sequence of ObjectSpec"):
        simulate("camera", objects=spec, **TINY)
    seq = simulate("camera", objects=[spec], motion=(0.0, 0.0), **TINY)  # procedural sprite, rounded rectangle
    assert len(seq.ideal_events) > 0 and seq.config["objects"][0]["sprite"] == ["shapes", 3]
    photo = simulate("camera", objects=[dataclasses.replace(spec, sprite="text")], **TINY)  # the photograph
    assert not torch.equal(photo.blurry, seq.blurry)


def test_leak_events_rate_and_polarity():
    seq = simulate("camera", motion=(0.0, 0.0), leak_rate_hz=20.0, seed=4, **TINY)
    ev = seq.ideal_events
    t_end = seq.config["t_end_us"]
    expected = 20.0 * t_end * 1e-6 * 24 * 32
    assert abs(len(ev) - expected) < 0.1 * expected
    assert ev.p.unique().tolist() == [1]  # ON events only
    assert torch.equal(seq.delayed_events.t, ev.t)  # like shot noise: not delayed
    assert float(ev.t.min()) >= 0.0 and float(ev.t.max()) < t_end
    # periodic per pixel: a long sequence gives several events per pixel at equal intervals
    long = simulate("camera", motion=(0.0, 0.0), leak_rate_hz=200.0, seed=4, latency="none", **{**TINY,
                    "exposure_us": 20000.0, "frame_interval_us": 20000.0}).ideal_events
    pix = long.y * 32 + long.x
    for p in pix.unique()[:10].tolist():
        gaps = long.t[pix == p].diff()
        if gaps.numel() >= 2:
            torch.testing.assert_close(gaps, gaps[:1].expand_as(gaps), rtol=1e-9, atol=1e-6)
    # rates differ between pixels (lognormal spread)
    counts = events_per_pixel(long, (24, 32))
    assert float(counts.std()) > 0.2 * float(counts.mean())


def test_refractory_period():
    from evlatcorr.simulate import apply_refractory

    base = simulate("coffee", latency="constant", latency_us=500.0, noise_rate_hz=50.0, seed=2, **TINY)
    seq = simulate("coffee", latency="constant", latency_us=500.0, noise_rate_hz=50.0, refractory_us=800.0, seed=2,
                   **TINY)
    for full, kept in ((base.ideal_events, seq.ideal_events), (base.delayed_events, seq.delayed_events)):
        assert 0 < len(kept) < 0.9 * len(full)
        order = torch.argsort(kept.y * 32 + kept.x, stable=True)
        pix, t = (kept.y * 32 + kept.x)[order], kept.t[order]
        same = pix[1:] == pix[:-1]
        assert float((t[1:] - t[:-1])[same].min()) >= 800.0  # kept events of a pixel are a dead time apart
        assert bool((kept.t[1:] >= kept.t[:-1]).all())
    assert seq.config["refractory_us"] == 800.0
    # the vectorised rule: an event is dropped when the previous one of its pixel (kept or not) is too close
    ev = Events(torch.zeros(5), torch.zeros(5), torch.tensor([0.0, 60.0, 120.0, 400.0, 450.0]), torch.ones(5),
                sensor_size=(1, 2))
    assert apply_refractory(ev, 100.0).t.tolist() == [0.0, 400.0]
    assert apply_refractory(ev, 0.0) is ev
    with pytest.raises(ValueError, match="refractory_us"):
        apply_refractory(ev, -1.0)


@pytest.mark.parametrize("kwargs", [dict(leak_rate_hz=-1.0), dict(refractory_us=-5.0), dict(leak_rate_hz=float("nan"))])
def test_bad_noise_parameters(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        simulate("camera", **{**TINY, **kwargs})


def test_new_noise_is_seeded():
    kw = dict(leak_rate_hz=5.0, refractory_us=300.0, noise_rate_hz=10.0, threshold_sigma=0.1, motion="zoom",
              latency="intensity_delay", latency_range_us=(200.0, 2000.0), **TINY)
    a, b = simulate("rocket", seed=9, **kw), simulate("rocket", seed=9, **kw)
    for name in ("x", "y", "t", "p"):
        assert torch.equal(getattr(a.delayed_events, name), getattr(b.delayed_events, name))
        assert torch.equal(getattr(a.ideal_events, name), getattr(b.ideal_events, name))


def test_latency_beyond_a_second_is_refused_before_allocating():
    with pytest.raises(ValueError, match=r"latency_us must be in \[0, 1000000\]"):
        simulate("camera", num_frames=1, height=8, width=8, latency_us=1e9)
    with pytest.raises(ValueError, match="latency_range_us"):
        simulate("camera", num_frames=1, height=8, width=8, latency="intensity", latency_range_us=(500.0, 1e12))
