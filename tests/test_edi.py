from __future__ import annotations

import math

import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.edi import edi_deblur, edi_interpolate, edi_log_ratio, estimate_threshold
from evlatcorr.event_grid import _event_grid_bytes, _grid_times, event_grid
from tests.conftest import random_events


def one_pixel(times, pols, sensor_size=(1, 1)):
    n = len(times)
    return Events(torch.zeros(n, dtype=torch.long), torch.zeros(n, dtype=torch.long),
                  torch.tensor(times, dtype=torch.float64), torch.tensor(pols), sensor_size=sensor_size)


START, END = torch.tensor([0.0]), torch.tensor([100.0])


class TestEDIDeblur:
    def test_smoke_shapes(self):
        ev = random_events(400, (6, 7), (0.0, 200.0), batch_size=2)
        out = edi_deblur(torch.rand(2, 3, 6, 7), ev, torch.zeros(2), torch.full((2,), 100.0), num_bins=20)
        assert out.shape == (2, 3, 6, 7) and torch.isfinite(out).all()

    def test_no_events_is_identity(self):
        ev = one_pixel([], [])
        blurry = torch.full((1, 1, 1, 1), 0.3)
        torch.testing.assert_close(edi_deblur(blurry, ev, START, END, num_bins=10), blurry)

    def test_single_event_known_answer(self):
        # latent at t=0, one +1 event at t=50: B = I0 (0.5 + 0.5 e^θ) (trapezoid exact: the event is between samples)
        theta = 0.3
        ev = one_pixel([50.5], [1])
        blurry = torch.full((1, 1, 1, 1), 0.5, dtype=torch.float64)
        out = edi_deblur(blurry, ev, START, END, theta, num_bins=100, time=torch.tensor([0.0]))
        expected = 0.5 / (0.505 + 0.495 * math.exp(theta))  # 50.5 of 100 samples before the event (trapezoid)
        assert out.item() == pytest.approx(expected, rel=1e-6)

    def test_latency_reads_later_events(self):
        # an event stamped 30 us late with latency 30 equals the on-time event without latency
        theta = 0.2
        blurry = torch.full((1, 1, 1, 1), 0.5)
        late = edi_deblur(blurry, one_pixel([70.5], [1]), START, END, theta, latency=30.0, num_bins=100)
        on_time = edi_deblur(blurry, one_pixel([40.5], [1]), START, END, theta, num_bins=100)
        torch.testing.assert_close(late, on_time)

    def test_latency_equals_shifted_events(self):
        ev = random_events(2000, (5, 5), (0.0, 300.0), seed=4)
        blurry = torch.rand(1, 1, 5, 5)
        lat = (torch.rand(1, 1, 5, 5) * 50).round() * 2.0  # whole sub-intervals (2 us): no interpolation
        a = edi_deblur(blurry, ev, START, END, 0.2, latency=lat, num_bins=50, integral="step")
        b = edi_deblur(blurry, ev.shift(lat), START, END, 0.2, num_bins=50, integral="step")
        torch.testing.assert_close(a, b)

    def test_many_events_no_overflow(self):
        ev = one_pixel(torch.linspace(1.0, 99.0, 5000).tolist(), [1] * 5000)
        blurry = torch.tensor([[[[0.7]]]])
        out = edi_deblur(blurry, ev, START, END, 0.2, num_bins=500)
        assert torch.isfinite(out).all()
        # C(u) - C(mid) = rate (u - 50) on [1, 99] (rate = 5000/98 per us) and 2500 on [99, 100], so
        # log R = log((1/100) [∫ exp(θ rate (u - 50)) du + 1 us · e^{500}]) = 500 + log((1 + 1/(θ rate)) / 100)
        log_r = edi_log_ratio(ev, START, END, 0.2, num_bins=500)
        expected = 500 + math.log((1 + 1 / (0.2 * 5000 / 98)) / 100)
        assert torch.isfinite(log_r).all() and log_r.item() == pytest.approx(expected, abs=0.1)

    def test_black_pixel_stays_black(self):
        ev = one_pixel([10.0, 20.0], [0, 0])
        out = edi_deblur(torch.zeros(1, 1, 1, 1), ev, START, END, 0.2, num_bins=10)
        assert out.item() == 0.0

    @pytest.mark.parametrize(
        "blurry, match",
        [
            (torch.full((1, 1, 2, 2), float("nan")), "NaN"),
            (torch.full((1, 1, 2, 2), -0.5), r"\[0, 1\]"),
            (torch.rand(2, 1, 2, 2), "batch_size"),
            (torch.rand(1, 1, 3, 2), "sensor_size"),
            (torch.rand(1, 2, 2, 2), "channels"),
        ],
    )
    def test_bad_blurry(self, blurry, match):
        ev = random_events(10, (2, 2), (0.0, 100.0))
        with pytest.raises(ValueError, match=match):
            edi_deblur(blurry, ev, START, END)

    def test_bad_exposure_and_threshold(self):
        ev = random_events(10, (2, 2), (0.0, 100.0))
        blurry = torch.rand(1, 1, 2, 2)
        with pytest.raises(ValueError, match="exposure_end must be after"):
            edi_deblur(blurry, ev, END, START)
        with pytest.raises(ValueError, match="threshold"):
            edi_deblur(blurry, ev, START, END, threshold=-0.1)
        with pytest.raises(ValueError, match="threshold"):
            edi_deblur(blurry, ev, START, END, threshold="magic")

    def test_non_contiguous(self):
        ev = random_events(300, (4, 6), (0.0, 200.0))
        blurry = torch.rand(1, 1, 6, 4).transpose(-1, -2)
        assert not blurry.is_contiguous()
        torch.testing.assert_close(edi_deblur(blurry, ev, START, END, num_bins=20),
                                   edi_deblur(blurry.contiguous(), ev, START, END, num_bins=20))

    @pytest.mark.parametrize("integral", ["step", "linear"])
    def test_gradcheck_latency_map(self, integral):
        ev = random_events(400, (3, 4), (0.0, 250.0), seed=7)
        blurry = torch.rand(1, 1, 3, 4, dtype=torch.float64) * 0.8 + 0.1
        lat = (torch.rand(1, 1, 3, 4, dtype=torch.float64) * 60 + 20.3).requires_grad_()
        fn = lambda l: edi_deblur(blurry, ev, START, END, 0.2, latency=l, num_bins=40, integral=integral)  # noqa: E731
        assert torch.autograd.gradcheck(fn, (lat,), eps=1e-4, atol=1e-6, rtol=1e-3)

    @pytest.mark.parametrize("integral", ["step", "linear"])
    def test_gradcheck_scalar_per_sample(self, integral):
        ev = random_events(600, (3, 3), (0.0, 250.0), batch_size=2, seed=8)
        blurry = torch.rand(2, 1, 3, 3, dtype=torch.float64) * 0.8 + 0.1
        lat = torch.tensor([13.37, 51.1], dtype=torch.float64, requires_grad=True)
        fn = lambda l: edi_deblur(blurry, ev, torch.zeros(2), torch.full((2,), 100.0), 0.2, latency=l,  # noqa: E731
                                  num_bins=40, integral=integral)
        assert torch.autograd.gradcheck(fn, (lat,), eps=1e-4, atol=1e-6, rtol=1e-3)

    def test_device(self, device):
        ev = random_events(300, (4, 4), (0.0, 200.0)).to(device)
        out = edi_deblur(torch.rand(1, 1, 4, 4, device=device), ev, START, END, num_bins=20)
        assert out.device.type == device.type


def test_log_ratio_brightening_pixel():
    # +1 events brighten the pixel after them: the latent at the exposure start is darker than the blur
    ev = one_pixel([25.5, 50.5, 75.5], [1, 1, 1])
    log_r = edi_log_ratio(ev, START, END, 0.2, time=torch.tensor([0.0]), num_bins=100)
    assert log_r.item() > 0


class TestEventGrid:
    def test_span_known_answer(self):
        # 10 us spacing; reads from 0 to 100 + 30, with one spare bin before and two after
        grid = event_grid(one_pixel([50.0], [1]), START, END, num_bins=10, latency_range=(0.0, 30.0))
        assert (grid.start.item(), grid.end.item()) == (-10.0, 150.0)
        assert grid.cum.shape == (1, 17, 1, 1) and grid.cum[0, -1].item() == 1.0

    @pytest.mark.parametrize("integral", ["step", "linear"])
    def test_prebuilt_grid_gives_the_same_latent(self, integral):
        ev = random_events(3000, (5, 6), (0.0, 300.0), seed=2, batch_size=2)
        blurry = torch.rand(2, 1, 5, 6, dtype=torch.float64)
        start, end = torch.zeros(2), torch.full((2,), 100.0)
        grid = event_grid(ev, start, end, 40, (0.0, 150.0), integral="linear" if integral == "linear" else "step",
                          dtype=torch.float64)
        for latency in (torch.tensor([10.0, 40.0]), torch.rand(2, 1, 5, 6, dtype=torch.float64) * 150):
            ref = edi_deblur(blurry, ev, start, end, 0.2, latency, 40, integral=integral)
            mine = edi_deblur(blurry, ev, start, end, 0.2, latency, 40, integral=integral, grid=grid)
            if integral == "step":
                torch.testing.assert_close(mine, ref)
            else:  # the linear ramp of a pixel's first event starts at the (earlier) grid start
                assert (mine - ref).abs().mean() < 0.05 * ref.abs().mean()

    def test_gradient_through_a_prebuilt_grid(self):
        ev = random_events(500, (4, 4), (0.0, 250.0), seed=5)
        grid = event_grid(ev, START, END, 20, (0.0, 100.0), integral="linear", dtype=torch.float64)
        lat = (torch.rand(1, 1, 4, 4, dtype=torch.float64) * 80 + 10).requires_grad_()
        blurry = torch.rand(1, 1, 4, 4, dtype=torch.float64)
        assert torch.autograd.gradcheck(
            lambda l: edi_deblur(blurry, ev, START, END, 0.2, l, 20, integral="linear", grid=grid), (lat,))

    def test_grid_too_narrow_or_other_bins(self):
        ev = random_events(100, (2, 2), (0.0, 200.0))
        grid = event_grid(ev, START, END, 10, (0.0, 20.0))
        with pytest.raises(ValueError, match="wider latency_range"):
            edi_deblur(torch.rand(1, 1, 2, 2), ev, START, END, 0.2, 60.0, 10, grid=grid)
        with pytest.raises(ValueError, match="num_bins=20"):
            edi_deblur(torch.rand(1, 1, 2, 2), ev, START, END, 0.2, 10.0, 20, grid=grid)
        with pytest.raises(ValueError, match="low <= high"):
            event_grid(ev, START, END, 10, (30.0, 20.0))

    @pytest.mark.parametrize("integral, dtype", [("step", torch.float32), ("linear", torch.float64)])
    def test_bytes_estimate_matches_the_grid(self, integral, dtype):
        ev = random_events(300, (3, 5), (0.0, 300.0), seed=4, batch_size=2)
        start, end = torch.zeros(2), torch.full((2,), 100.0)
        grid = event_grid(ev, start, end, 10, (0.0, 30.0), integral=integral, dtype=dtype)
        per_point = 12 if integral == "step" else 40  # the step grid's 3 float32 arrays; linear's 4 float64 + out
        times = _grid_times(ev, start, end, 10, (0.0, 30.0), None)
        assert _event_grid_bytes(ev, *times, 10, integral, dtype) == grid.cum.numel() * per_point

    def test_grid_over_the_memory_budget_is_refused(self):
        # latencies up to 1e9 us in 10 us steps: 10**8 grid points x 4 pixels x 12 bytes
        ev = random_events(100, (2, 2), (0.0, 200.0))
        with pytest.raises(ValueError, match=r"event grid \(1, 100000014, 2, 2\) needs about 4.5 GiB.*spans "
                                             r"\[0, 1000000100\] us.*narrow latency_range"):
            event_grid(ev, START, END, 10, (0.0, 1e9))


class TestMemory:
    def test_time_far_from_the_exposure_is_refused_before_allocating(self):
        # time 1e9 us with 40 us sub-intervals: 25 million grid points per pixel, 2.5 GiB for one row of 9 pixels
        ev = random_events(2000, (8, 9), (0.0, 60000.0), seed=5)
        blurry = torch.rand(1, 1, 8, 9, generator=torch.Generator().manual_seed(5))
        with pytest.raises(ValueError, match=r"one row of the EDI .* needs about 2.5 GiB, over the memory budget "
                                             r"of 2.0 GiB: it spans \[0, 1000000000\] us .*bring `time` closer"):
            edi_deblur(blurry, ev, START, torch.tensor([20000.0]), time=torch.tensor([1e9]))
        with pytest.raises(ValueError, match="time has 1 NaN or infinite"):
            edi_deblur(blurry, ev, START, torch.tensor([20000.0]), time=torch.tensor([math.inf]))

    @pytest.mark.parametrize("integral", ["step", "linear"])
    def test_over_the_budget_runs_in_strips_of_rows(self, integral):
        # the whole EDI (2 frames x 42 pixels x (grid 105 x 24 or 40 + reads 41 x 56) bytes) is 0.4 to 0.55 MB, a
        # row 58 to 78 kB: a 100 kB budget makes strips of one row, with the same latent (up to float rounding)
        # and the same gradient
        ev = random_events(3000, (7, 6), (0.0, 300.0), seed=8, batch_size=2)
        g = torch.Generator().manual_seed(8)
        blurry = torch.rand(2, 3, 7, 6, dtype=torch.float64, generator=g) * 0.8 + 0.1
        start, end = torch.zeros(2), torch.full((2,), 100.0)
        lat = (torch.rand(2, 1, 7, 6, dtype=torch.float64, generator=g) * 150).requires_grad_()
        whole = edi_deblur(blurry, ev, start, end, 0.2, lat, 40, torch.tensor([30.0, 70.0]), integral)
        strips = edi_deblur(blurry, ev, start, end, 0.2, lat, 40, torch.tensor([30.0, 70.0]), integral,
                            memory_budget=100_000)
        torch.testing.assert_close(strips, whole, rtol=1e-12, atol=1e-12)
        (grad_whole,) = torch.autograd.grad(whole.sum(), lat)
        (grad_strips,) = torch.autograd.grad(strips.sum(), lat)
        torch.testing.assert_close(grad_strips, grad_whole, rtol=1e-10, atol=1e-12)
        assert grad_whole.abs().sum() > 0
        with pytest.raises(ValueError, match="one row of the EDI"):
            edi_deblur(blurry, ev, start, end, 0.2, lat, 40, integral=integral, memory_budget=1000)


class TestInterpolate:
    def make(self):
        ev = random_events(3000, (5, 5), (0.0, 400.0), seed=11)
        return EventFrames(torch.rand(1, 1, 5, 5), ev, START, END, blurry_next=torch.rand(1, 1, 5, 5),
                           exposure_start_next=torch.tensor([200.0]), exposure_end_next=torch.tensor([300.0]))

    def test_shapes_and_endpoints(self):
        frames = self.make()
        out = edi_interpolate(frames, torch.tensor([[50.0, 150.0, 250.0]]), num_bins=20)
        assert out.shape == (1, 3, 1, 5, 5)
        first = edi_deblur(frames.blurry, frames.events, START, END, num_bins=20)
        second = edi_deblur(frames.blurry_next, frames.events, frames.exposure_start_next,
                            frames.exposure_end_next, num_bins=20)
        torch.testing.assert_close(out[:, 0], first)
        torch.testing.assert_close(out[:, 2], second)

    def test_midpoint_blends_both(self):
        frames = self.make()
        t = torch.tensor([150.0])
        mid = edi_interpolate(frames, t, num_bins=20)[:, 0]
        a = edi_deblur(frames.blurry, frames.events, START, END, num_bins=20, time=t)
        b = edi_deblur(frames.blurry_next, frames.events, frames.exposure_start_next, frames.exposure_end_next,
                       num_bins=20, time=t)
        torch.testing.assert_close(mid, (a + b) / 2)

    def test_needs_next(self):
        ev = random_events(10, (2, 2), (0.0, 100.0))
        with pytest.raises(ValueError, match="blurry_next"):
            edi_interpolate(EventFrames(torch.rand(1, 1, 2, 2), ev, START, END), torch.tensor([50.0]))


def test_estimate_threshold_bounds():
    ev = random_events(300, (8, 8), (0.0, 200.0))
    theta = estimate_threshold(torch.rand(1, 1, 8, 8), ev, START, END, num_bins=20, iterations=5)
    assert theta.shape == (1,) and 0.02 <= float(theta) <= 1.0
    with pytest.raises(ValueError, match="bounds"):
        estimate_threshold(torch.rand(1, 1, 8, 8), ev, START, END, bounds=(1.0, 0.5))
    # a frame one pixel high or wide: a clear refusal, where the filters failed inside kornia's padding
    line = random_events(50, (1, 8), (0.0, 200.0))
    with pytest.raises(ValueError, match="threshold='auto' needs frames of at least 2x2 pixels .*got 1x8"):
        estimate_threshold(torch.rand(1, 1, 1, 8), line, START, END)
    with pytest.raises(ValueError, match="at least 2x2 pixels"):
        edi_deblur(torch.rand(1, 1, 1, 8), line, START, END, threshold="auto")
    assert edi_deblur(torch.rand(1, 1, 1, 8), line, START, END, threshold=0.2).shape == (1, 1, 1, 8)


def test_grid_reads_finish_at_any_threshold_as_edi_deblur_does():
    # what the EDI reads of a grid does not depend on θ: read once, finished at several θ, it gives edi_deblur's latent
    # to the bit (at a reference outside the exposure, as the two-frame consistency reads it)
    from evlatcorr.edi import event_grid, grid_reads, latent_from_grid_reads
    from evlatcorr.simulate import simulate

    frames = simulate("camera", num_frames=1, height=24, width=32, latency_us=2000.0, seed=3).frames("delayed")
    start, end = frames.exposure_start, frames.exposure_end
    time = end + 3000.0
    grid = event_grid(frames.events, start, end, 150, (2000.0, 2000.0), time=time)
    reads = grid_reads(frames.blurry, frames.events, start, end, grid, 2000.0, 150, time)
    assert len(reads) == 3  # 151 samples in chunks of at most 64
    for theta in (0.1, 0.2, torch.tensor([0.45])):
        expected = edi_deblur(frames.blurry, frames.events, start, end, theta, 2000.0, 150, time, grid=grid)
        assert torch.equal(latent_from_grid_reads(frames.blurry, reads, theta, 150), expected)
    with pytest.raises(ValueError, match="grid was built for num_bins=150"):
        grid_reads(frames.blurry, frames.events, start, end, grid, 2000.0, 100, time)
    with pytest.raises(ValueError, match="threshold"):
        latent_from_grid_reads(frames.blurry, reads, -0.2, 150)
    with pytest.raises(ValueError, match=r"grid_reads of 1 frame\(s\) of 24x32 with num_bins=100 \(101 samples"):
        latent_from_grid_reads(frames.blurry, reads, 0.2, 100)  # made for 150 bins
    with pytest.raises(ValueError, match="grid_reads of 1 frame"):
        latent_from_grid_reads(frames.blurry[:, :, :12], reads, 0.2, 150)  # another size
    with pytest.raises(ValueError, match="grid_reads of 1 frame"):
        latent_from_grid_reads(frames.blurry, [], 0.2, 150)
