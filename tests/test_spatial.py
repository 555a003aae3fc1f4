from __future__ import annotations

import math
import warnings

import pytest
import torch

import evlatcorr.checks
from evlatcorr import EventLatencyCorrector, Events
from evlatcorr.simulate import simulate
from evlatcorr.spatial import (
    LossWeights,
    PolynomialLatency,
    SpatialLatencyCorrector,
    fit_spatial_latency,
    load_curve,
    save_curve,
    spatial_objective,
)


@pytest.fixture(scope="module")
def frames():
    seq = simulate("camera", num_frames=1, latency="intensity", seed=0, height=24, width=32, exposure_us=5000.0,
                   frame_interval_us=5000.0, latency_range_us=(200.0, 3000.0))
    return seq.frames("delayed")


class TestPolynomialLatency:
    def test_zero_init_and_shape(self):
        psi = PolynomialLatency(order=3)
        out = psi(torch.rand(2, 3, 5, 6))
        assert out.shape == (2, 1, 5, 6) and out.abs().max() == 0
        assert psi.coefficients.shape == (4,)

    def test_transform_is_decreasing_and_bounded(self):
        psi = PolynomialLatency()
        f = psi.transform(torch.linspace(0, 1, 101))
        assert bool((f[1:] < f[:-1]).all()) and f[0] == pytest.approx(1.0) and abs(float(f[-1])) < 1e-6
        assert f[50] == pytest.approx(0.14806, abs=1e-4)  # log(0.51 / 1.01) / log(0.01 / 1.01)

    def test_values_by_hand(self):
        psi = PolynomialLatency(order=2, scale_us=1000.0)
        with torch.no_grad():
            psi.coefficients.copy_(torch.tensor([0.5, 2.0, 3.0]))
        img = torch.tensor([0.0, 1.0, 0.5]).view(1, 1, 1, 3)
        f = math.log(0.51 / 1.01) / math.log(0.01 / 1.01)
        expected = torch.tensor([5500.0, 500.0, 1000.0 * (0.5 + 2 * f + 3 * f * f)]).view(1, 1, 1, 3)
        torch.testing.assert_close(psi(img), expected)
        rgb = img.expand(1, 3, 1, 3)  # grey RGB gives the same luminance
        torch.testing.assert_close(psi(rgb), expected)

    def test_non_contiguous(self):
        psi = PolynomialLatency(order=2)
        with torch.no_grad():
            psi.coefficients.copy_(torch.tensor([0.5, 2.0, 3.0]))
        x = torch.rand(2, 1, 6, 5).transpose(-1, -2)
        assert not x.is_contiguous()
        torch.testing.assert_close(psi(x), psi(x.contiguous()))

    def test_device(self, device):
        psi = PolynomialLatency(order=2).to(device)
        with torch.no_grad():
            psi.coefficients.fill_(1.0)
        out = psi(torch.rand(1, 1, 4, 4, device=device))
        assert out.device.type == device.type and bool((out >= 1000.0).all())

    def test_slope_matches_autograd(self):
        psi = PolynomialLatency(order=4)
        with torch.no_grad():
            psi.coefficients.copy_(torch.tensor([0.3, -1.0, 2.0, 0.5, -0.2]))
        x = torch.linspace(0.05, 0.95, 7, dtype=torch.float64, requires_grad=True)
        (grad,) = torch.autograd.grad(psi.curve(x).sum(), x)
        torch.testing.assert_close(psi.slope(x.detach()), grad)

    def test_bad_order(self):
        with pytest.raises(ValueError, match="order"):
            PolynomialLatency(order=-1)
        with pytest.raises(ValueError, match="eps"):
            PolynomialLatency(eps=2.0)
        with pytest.raises(ValueError, match="steps"):
            SpatialLatencyCorrector(steps=0)
        with pytest.raises(ValueError, match="order"):
            EventLatencyCorrector(mode="spatial", order=-2)
        with pytest.raises(ValueError, match="numeric threshold"):
            SpatialLatencyCorrector(threshold="auto")
        with pytest.raises(ValueError, match="threshold must be a positive number or 'auto'"):
            EventLatencyCorrector(mode="spatial", threshold="guess")
        assert SpatialLatencyCorrector(steps=150).progress and not SpatialLatencyCorrector(steps=60).progress

    def test_search_settings_reach_the_spatial_mode(self):
        # the constant starting point of the fit is searched as the corrector was told, not with defaults
        corrector = EventLatencyCorrector(mode="spatial", score="etf", ghost_confidence=None, search_range=(0, 9000),
                                          num_candidates=40)
        config = corrector.spatial.config
        assert (config.score, config.ghost_confidence, config.search_range, config.num_candidates) == (
            "etf", None, (0.0, 9000.0), 40)
        with pytest.raises(ValueError, match="config must be a SearchConfig"):
            SpatialLatencyCorrector(config={"score": "etf"})


def test_gradients_reach_every_coefficient(frames):
    # finite differences of L_total (float64) against autograd, for every a_i
    f64 = frames.replace(blurry=frames.blurry.double())
    psi = PolynomialLatency(order=2).double()
    with torch.no_grad():
        psi.coefficients.copy_(torch.tensor([0.8, 0.5, 0.3], dtype=torch.float64))
    l_const = torch.tensor([600.0], dtype=torch.float64)
    args = (f64, l_const, torch.tensor([5000.0], dtype=torch.float64), torch.tensor([3.0], dtype=torch.float64))

    def total(coeffs):
        with torch.no_grad():
            psi.coefficients.copy_(coeffs)
        return spatial_objective(psi, *args, num_bins=40)["total"]

    base = psi.coefficients.detach().clone()
    loss = spatial_objective(psi, *args, num_bins=40)["total"]
    (grad,) = torch.autograd.grad(loss, psi.coefficients)
    for i in range(3):
        step = torch.zeros(3, dtype=torch.float64)
        step[i] = 1e-4
        numeric = (total(base + step) - total(base - step)) / 2e-4
        assert float(grad[i]) != 0.0
        assert float(grad[i]) == pytest.approx(float(numeric.detach()), rel=0.05, abs=1e-6)


def test_fit_decreases_loss_and_is_monotone(frames):
    model, history = fit_spatial_latency(frames, PolynomialLatency(order=3), steps=15, lr=0.05, num_bins=40,
                                         weights=LossWeights(dev=1.0))
    assert history[-1] < history[0]
    ramp = torch.linspace(0.02, 1.0, 50)
    slope = model.slope(ramp).detach()
    assert float(slope.max()) <= 1e-3 * float(slope.abs().max()) + 50.0  # non-increasing up to a tolerance (us)


def test_checkpoint_round_trip(tmp_path):
    psi = PolynomialLatency(order=2, eps=0.02, scale_us=500.0)
    with torch.no_grad():
        psi.coefficients.copy_(torch.tensor([1.0, 2.0, 3.0]))
    save_curve(psi, tmp_path / "curve.pt")
    back = load_curve(tmp_path / "curve.pt")
    assert (back.order, back.eps, back.scale_us) == (2, 0.02, 500.0)
    x = torch.rand(1, 1, 4, 4)
    torch.testing.assert_close(back(x), psi(x))
    with pytest.raises(FileNotFoundError):
        load_curve(tmp_path / "missing.pt")


def test_corrector_spatial_mode(frames, tmp_path):
    psi = PolynomialLatency(order=1)
    with torch.no_grad():
        psi.coefficients.copy_(torch.tensor([0.5, 1.0]))  # 0.5 ms bright .. 1.5 ms dark
    save_curve(psi, tmp_path / "c.pt")
    out = EventLatencyCorrector(mode="spatial", curve=str(tmp_path / "c.pt"), num_bins=50)(frames)
    expected = psi(frames.blurry).clamp(0, 5000)
    torch.testing.assert_close(out.latency, expected)
    assert out.latency.std() > 0 and out.latent.shape == frames.blurry.shape
    assert out.meta["latency_source"] == ["curve"] and not out.meta["latency_fallback"].any()
    fitted = EventLatencyCorrector(mode="spatial", num_bins=50, steps=3, train_bins=30)(frames)
    assert fitted.latency.shape == (1, 1, 24, 32)
    # a search range bounds the map at both ends
    bounded = EventLatencyCorrector(mode="spatial", curve=str(tmp_path / "c.pt"), num_bins=50,
                                    search_range=(800.0, 1200.0))(frames)
    torch.testing.assert_close(bounded.latency, psi(frames.blurry).clamp(800.0, 1200.0))


def test_the_fit_leaves_the_callers_frames_out_of_its_graph(frames):
    # a blurry input that requires grad (an upstream module in training) gets no gradient from the fit's steps
    blurry = frames.blurry.clone().requires_grad_()
    with warnings.catch_warnings():
        warnings.simplefilter("error", UserWarning)  # nor torch's warning of a scalar read of a graph
        out = EventLatencyCorrector(mode="spatial", num_bins=50, steps=3, train_bins=30)(frames.replace(blurry=blurry))
    assert blurry.grad is None
    plain = EventLatencyCorrector(mode="spatial", num_bins=50, steps=3, train_bins=30)(frames)
    torch.testing.assert_close(out.latency, plain.latency)


def test_fit_without_events_is_refused(frames):
    # as the constant search: the fit used to run on a frame without events and return l_const = 0
    none = frames.replace(events=Events(torch.zeros(0), torch.zeros(0), torch.zeros(0), torch.zeros(0),
                                        sensor_size=frames.sensor_size))
    with pytest.raises(ValueError, match="sample 0 has no events"):
        fit_spatial_latency(none, steps=1, num_bins=20)
    with pytest.raises(ValueError, match="search_range must be two finite numbers"):
        fit_spatial_latency(frames, steps=1, num_bins=20, search_range=(0.0, math.inf))


def test_fit_over_the_memory_budget_reads_strips(frames, monkeypatch):
    # a 1 MB budget: no grid kept across steps (2.4 MB), and the search table (1.3 MB) and each step's EDI
    # (2 to 3 MB) run in strips. Only the linear integral's first ramps differ (they start at each grid's start).
    kw = dict(steps=4, lr=0.05, num_bins=40, start_from_constant=True)
    model, history = fit_spatial_latency(frames, PolynomialLatency(order=3), **kw)
    monkeypatch.setattr(evlatcorr.checks, "MEMORY_BUDGET_BYTES", 1_000_000)
    small, small_history = fit_spatial_latency(frames, PolynomialLatency(order=3), **kw)
    torch.testing.assert_close(small.coefficients, model.coefficients, rtol=0.02, atol=2e-3)
    torch.testing.assert_close(torch.tensor(small_history), torch.tensor(history), rtol=1e-3, atol=0.0)


def _two_frames_the_first_set_to(value: float):
    """Two delayed frames, and their blurry images with the first one uniform at ``value``."""
    frames = simulate("camera", num_frames=2, height=32, width=40, latency_us=3000.0, seed=0).frames("delayed")
    blurry = frames.blurry.clone()
    blurry[0] = value
    return frames, blurry


def test_a_black_frame_is_left_out_of_the_fit_and_keeps_the_fallback():
    # as in constant mode: a black frame used to get a map from the fit (984 us here) with no warning
    from evlatcorr.sample_warnings import SampleWarning

    frames, blurry = _two_frames_the_first_set_to(0.0)
    corrector = EventLatencyCorrector(mode="spatial", threshold=0.2, steps=10)
    with pytest.warns(SampleWarning, match="sample 0: black or saturated in nearly every pixel"):
        out = corrector(frames.replace(blurry=blurry))
    alone = corrector(frames.split()[1])  # the fit sees the other frame alone
    assert float(out.latency[0].abs().max()) == 0.0
    torch.testing.assert_close(out.latency[1], alone.latency[0])
    with pytest.warns(SampleWarning, match=r"samples \[0, 1\]"):
        none = corrector(frames.replace(blurry=torch.ones_like(blurry)))  # saturated: nothing to fit
    assert float(none.latency.abs().max()) == 0.0


def test_a_flat_frame_is_left_out_of_the_fit_and_a_trained_curve_still_reads_it(tmp_path):
    from evlatcorr.sample_warnings import SampleWarning

    frames, blurry = _two_frames_the_first_set_to(0.3)
    corrector = EventLatencyCorrector(mode="spatial", threshold=0.2, steps=10)
    with pytest.warns(SampleWarning, match="sample 0: flat: no structure above its pixel noise"):
        out = corrector(frames.replace(blurry=blurry))
    assert out.meta["latency_source"] == ["flat", "fit"]
    assert float(out.latency[0].abs().max()) == 0.0
    torch.testing.assert_close(out.latency[1], corrector(frames.split()[1]).latency[0])
    # a curve maps intensity to latency: a flat frame has intensities to read
    curve = PolynomialLatency(order=1)
    with torch.no_grad():
        curve.coefficients.copy_(torch.tensor([2.0, 0.0]))  # 2 ms whatever the intensity
    save_curve(curve, tmp_path / "curve.pt")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read = EventLatencyCorrector(mode="spatial", threshold=0.2, curve=tmp_path / "curve.pt")(
            frames.replace(blurry=blurry))
    assert read.meta["latency_source"] == ["curve", "curve"]
    assert float(read.latency[0].mean()) == pytest.approx(float(read.latency[1].mean()), rel=1e-4)
    assert float(read.latency[0].mean()) == pytest.approx(2000.0, rel=1e-4)


def test_a_fit_to_too_few_events_is_named_and_a_trained_curve_is_not(tmp_path):
    frame = simulate("camera", num_frames=1, height=32, width=40, latency_us=3000.0, seed=0).frames("delayed")
    ev = frame.events
    keep = torch.zeros(len(ev), dtype=torch.bool)
    keep[torch.randperm(len(ev), generator=torch.Generator().manual_seed(0))[:60]] = True
    thin = frame.replace(events=ev.select(keep))
    corrector = EventLatencyCorrector(mode="spatial", threshold=0.2, steps=5)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out = corrector(thin)
    (few,) = [w.message for w in caught if getattr(w.message, "kind", "") == "few_events"]
    n = int(out.meta["events_in_window"][0])
    assert 0 < n <= 60 and str(few).startswith(f"sample 0: only {n} event(s) in its exposure and search window, "
                                              "too few (under 100) to tell a latency from: the map fitted")
    # with all its events the frame is not named, and a trained curve reads intensities, not events
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        corrector(frame)
    assert not [w for w in caught if getattr(w.message, "kind", "") == "few_events"]
    save_curve(PolynomialLatency(order=1), tmp_path / "curve.pt")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        read = EventLatencyCorrector(mode="spatial", threshold=0.2, curve=tmp_path / "curve.pt")(thin)
    assert read.meta["latency_source"] == ["curve"]
    assert not [w for w in caught if getattr(w.message, "kind", "") == "few_events"]


def test_a_frame_without_a_latency_minimum_is_left_out_of_the_fit_with_a_warning():
    # events that stop at the exposure's end (a recording's last frame) leave the constant search nothing to score:
    # the fit used to anchor that frame's map at the search's fallback, silently (the CSV said nothing)
    from evlatcorr.frames import EventFrames
    from evlatcorr.sample_warnings import SampleWarning

    first, second = simulate("camera", num_frames=2, height=32, width=40, latency_us=3000.0,
                             seed=0).frames("delayed").split()
    ev = first.events
    kept = ev.t < float(first.exposure_end[0])
    cut = first.replace(events=Events(ev.x[kept], ev.y[kept], ev.t[kept], ev.p[kept], sensor_size=ev.sensor_size))
    corrector = EventLatencyCorrector(mode="spatial", threshold=0.2, steps=10)
    with pytest.warns(SampleWarning, match="sample 0: the sharpness score has no clear minimum"):
        out = corrector(EventFrames.cat([cut, second]))
    assert out.meta["latency_source"] == ["fallback", "fit"]
    assert out.meta["latency_fallback"].tolist() == [True, False]
    assert float(out.latency[0].abs().max()) == 0.0
    alone = corrector(second)  # the fit sees the other frame alone
    torch.testing.assert_close(out.latency[1], alone.latency[0])
    assert alone.meta["latency_source"] == ["fit"] and 1000.0 < float(alone.latency.mean()) < 5000.0
    with pytest.warns(SampleWarning, match="sample 0: the sharpness score"):
        none = corrector(cut)  # nothing left to fit
    assert float(none.latency.abs().max()) == 0.0 and none.meta["latency_source"] == ["fallback"]
