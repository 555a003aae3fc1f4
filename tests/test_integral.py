from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evlatcorr import Events
from evlatcorr.integral import (
    _row_strips,
    cumsum_,
    cumulative_event_grid,
    event_histogram,
    grid_bytes_per_point,
    sample_grid,
)
from tests.conftest import random_events


def one_pixel(times, pols):
    n = len(times)
    return Events(torch.zeros(n, dtype=torch.long), torch.zeros(n, dtype=torch.long),
                  torch.tensor(times, dtype=torch.float64), torch.tensor(pols), sensor_size=(1, 1))


class TestHistogram:
    def test_smoke_shape(self):
        ev = random_events(100, (4, 5), (0.0, 100.0), batch_size=2)
        assert event_histogram(ev, 0.0, 100.0, num_bins=7).shape == (2, 7, 4, 5)

    def test_values(self):
        ev = one_pixel([0.0, 9.99, 10.0, 25.0, 39.9, 40.0], [1, 1, 0, 1, 0, 1])
        h = event_histogram(ev, 0.0, 40.0, num_bins=4)[0, :, 0, 0]
        assert h.tolist() == [2.0, -1.0, 1.0, -1.0]  # the event at t=40 (= end) is outside

    def test_exceptions(self):
        ev = random_events(10, (2, 2), (0.0, 1.0))
        with pytest.raises(ValueError, match="num_bins"):
            event_histogram(ev, 0.0, 1.0, num_bins=0)
        with pytest.raises(ValueError, match="after its start"):
            event_histogram(ev, 1.0, 1.0)
        with pytest.raises(ValueError, match="one value per sample"):
            event_histogram(ev, torch.zeros(3), 1.0)

    def test_device(self, device):
        ev = random_events(50, (3, 3), (0.0, 10.0)).to(device)
        assert event_histogram(ev, 0.0, 10.0, 4).device.type == device.type


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 10_000), num=st.integers(0, 300), bins=st.integers(1, 600), batch=st.integers(1, 3))
def test_histogram_conserves_polarity_sum(seed, num, bins, batch):
    ev = random_events(num, (3, 4), (0.0, 1000.0), batch_size=batch, seed=seed)
    hist = event_histogram(ev, 0.0, 1000.0, bins)
    expected = torch.zeros(batch).index_add_(0, ev.batch, ev.p.float())
    torch.testing.assert_close(hist.sum(dim=(1, 2, 3)), expected)


class TestCumulativeGrid:
    def test_step_matches_histogram(self):
        ev = random_events(500, (4, 4), (0.0, 100.0), batch_size=2)
        cum = cumulative_event_grid(ev, 0.0, 10.0, 10, "step")
        hist = event_histogram(ev, 0.0, 100.0, 10)
        torch.testing.assert_close(cum[:, 1:], hist.cumsum(1))
        assert cum[:, 0].abs().max() == 0

    def test_linear_known_answer(self):
        # events at 10 (+1) and 30 (-1): +1 spread over (0, 10], -1 over (10, 30]
        ev = one_pixel([10.0, 30.0], [1, 0])
        cum = cumulative_event_grid(ev, 0.0, 5.0, 8, "linear", dtype=torch.float64)[0, :, 0, 0]
        expected = [0.0, 0.5, 1.0, 0.75, 0.5, 0.25, 0.0, 0.0, 0.0]
        torch.testing.assert_close(cum, torch.tensor(expected, dtype=torch.float64))

    def test_linear_previous_event_before_grid(self):
        # the previous event at the pixel (t=-10) starts the ramp of the next one (t=10)
        ev = one_pixel([-10.0, 10.0], [1, 1])
        cum = cumulative_event_grid(ev, 0.0, 5.0, 4, "linear", dtype=torch.float64)[0, :, 0, 0]
        torch.testing.assert_close(cum, torch.tensor([0.0, 0.25, 0.5, 0.5, 0.5], dtype=torch.float64))

    def test_linear_spreads_capped_at_max_spread(self):
        # events at 10 (+1) and 30 (-1) with spreads of at most 5: +1 over (5, 10], -1 over (25, 30]; a cap longer
        # than every interval changes nothing
        ev = one_pixel([10.0, 30.0], [1, 0])
        cum = cumulative_event_grid(ev, 0.0, 5.0, 8, "linear", dtype=torch.float64, max_spread_us=5.0)[0, :, 0, 0]
        expected = [0.0, 0.0, 1.0, 1.0, 1.0, 1.0, 0.0, 0.0, 0.0]
        torch.testing.assert_close(cum, torch.tensor(expected, dtype=torch.float64))
        wide = cumulative_event_grid(ev, 0.0, 5.0, 8, "linear", dtype=torch.float64, max_spread_us=50.0)
        torch.testing.assert_close(wide, cumulative_event_grid(ev, 0.0, 5.0, 8, "linear", dtype=torch.float64))
        for integral, cap in (("step", 5.0), ("linear", 0.0), ("linear", -1.0)):
            with pytest.raises(ValueError, match="max_spread_us is a positive interval of the 'linear' integral"):
                cumulative_event_grid(ev, 0.0, 5.0, 8, integral, max_spread_us=cap)

    def test_linear_spreads_capped_by_the_interval_to_the_next_event(self):
        # a burst at 20, 25, 30: the first event, after a quiet since the grid's start, is spread over twice the
        # burst's interval, (10, 20], not back to 0; the others over their interval since the previous event
        ev = one_pixel([20.0, 25.0, 30.0], [1, 1, 1])
        cum = cumulative_event_grid(ev, 0.0, 5.0, 8, "linear", dtype=torch.float64, next_spread_factor=2.0)
        expected = [0.0, 0.0, 0.0, 0.5, 1.0, 2.0, 3.0, 3.0, 3.0]
        torch.testing.assert_close(cum[0, :, 0, 0], torch.tensor(expected, dtype=torch.float64))
        plain = cumulative_event_grid(ev, 0.0, 5.0, 8, "linear", dtype=torch.float64)[0, :, 0, 0]
        torch.testing.assert_close(plain, torch.tensor([0.0, 0.25, 0.5, 0.75, 1.0, 2.0, 3.0, 3.0, 3.0],
                                                       dtype=torch.float64))
        # the pixel's last event has no next one: a lone event keeps the cap
        lone = cumulative_event_grid(one_pixel([20.0], [1]), 0.0, 5.0, 8, "linear", dtype=torch.float64,
                                     max_spread_us=10.0, next_spread_factor=2.0)[0, :, 0, 0]
        torch.testing.assert_close(lone, torch.tensor([0.0, 0.0, 0.0, 0.5, 1.0, 1.0, 1.0, 1.0, 1.0],
                                                      dtype=torch.float64))
        for integral, factor in (("step", 2.0), ("linear", 0.0), ("linear", -1.0)):
            with pytest.raises(ValueError, match="next_spread_factor is a positive factor of the 'linear' integral"):
                cumulative_event_grid(ev, 0.0, 5.0, 8, integral, next_spread_factor=factor)

    def test_linear_equals_step_at_event_times(self):
        # at every grid point after all events both integrals hold the full polarity sum
        ev = random_events(300, (3, 3), (0.0, 90.0), seed=3)
        step = cumulative_event_grid(ev, 0.0, 10.0, 10, "step", dtype=torch.float64)
        lin = cumulative_event_grid(ev, 0.0, 10.0, 10, "linear", dtype=torch.float64)
        torch.testing.assert_close(step[:, -1], lin[:, -1])

    def test_exceptions(self):
        ev = random_events(10, (2, 2), (0.0, 1.0))
        with pytest.raises(ValueError, match="integral"):
            cumulative_event_grid(ev, 0.0, 1.0, 4, "cubic")
        with pytest.raises(ValueError, match="bin_width"):
            cumulative_event_grid(ev, 0.0, 0.0, 4)

    def test_over_the_memory_budget_is_refused_before_allocating(self):
        ev = random_events(10, (2, 2), (0.0, 1.0))
        # 10**9 bins x 4 pixels x 12 bytes = 48 GB: refused from the sizes alone (allocating it would fail)
        with pytest.raises(ValueError, match=r"cumulative event grid \(1, 1000000001, 2, 2\) needs about 44.7 GiB, "
                                             "over the memory budget of 2.0 GiB: use fewer num_bins"):
            cumulative_event_grid(ev, 0.0, 1.0, 10**9)
        with pytest.raises(ValueError, match=r"event histogram \(1, 1000, 2, 2\) needs about 15.6 KiB"):
            event_histogram(ev, 0.0, 1.0, 1000, memory_budget=1000)
        assert cumulative_event_grid(ev, 0.0, 1.0, 10, memory_budget=11 * 4 * 12).shape == (1, 11, 2, 2)  # just fits
        with pytest.raises(ValueError, match="memory budget"):
            cumulative_event_grid(ev, 0.0, 1.0, 10, memory_budget=11 * 4 * 12 - 1)

    def test_bytes_per_point(self):
        assert grid_bytes_per_point("step", torch.float32) == 12
        assert grid_bytes_per_point("step", torch.float64) == 24
        assert grid_bytes_per_point("linear", torch.float32) == 36


def test_row_strips_partition_the_events():
    ev = random_events(500, (7, 3), (0.0, 100.0), batch_size=2, seed=4)
    strips = _row_strips(ev, 3)
    assert [(r0, r1) for r0, r1, _ in strips] == [(0, 3), (3, 6), (6, 7)]
    assert sum(len(sub) for _, _, sub in strips) == len(ev)
    for r0, r1, sub in strips:
        assert sub.sensor_size == (r1 - r0, 3) and sub.batch_size == 2
        inside = (ev.y >= r0) & (ev.y < r1)
        assert torch.equal(sub.t.sort().values, ev.t[inside].sort().values)
        assert bool((sub.y >= 0).all() and (sub.y < r1 - r0).all())
    # the strips' grids, stacked, are the whole grid
    whole = cumulative_event_grid(ev, 0.0, 10.0, 10)
    torch.testing.assert_close(torch.cat([cumulative_event_grid(sub, 0.0, 10.0, 10) for _, _, sub in strips], 2),
                               whole, rtol=0, atol=0)


def test_sample_grid_interpolates_and_differentiates():
    cum = torch.tensor([0.0, 1.0, 3.0], dtype=torch.float64).view(1, 3, 1, 1)
    pos = torch.tensor([0.5, 1.25, 2.0], dtype=torch.float64).view(1, 3, 1, 1).requires_grad_()
    out = sample_grid(cum, pos)
    torch.testing.assert_close(out.flatten(), torch.tensor([0.5, 1.5, 3.0], dtype=torch.float64))
    assert torch.autograd.gradcheck(lambda p: sample_grid(cum, p), (pos.detach()[:, :2].clone().requires_grad_(),))


@pytest.mark.parametrize("dim", [0, 1, 3])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_cumsum_in_place_is_torch_cumsum_bit_for_bit(dim, dtype):
    g = torch.Generator().manual_seed(0)
    if dtype == torch.float64:
        table = torch.randn(3, 40, 5, 7, generator=g, dtype=dtype) * 1e3
    else:  # event counts: integer values, exact in float32 either way
        table = torch.randint(-3, 4, (3, 40, 5, 7), generator=g).to(dtype)
    want = torch.cumsum(table, dim)
    out = cumsum_(table, dim)
    assert out is table and torch.equal(out, want)


@pytest.mark.parametrize("reverse", [False, True])
def test_cumsum_into_out_leaves_the_table(device, reverse):
    g = torch.Generator().manual_seed(1)
    table = torch.randint(-3, 4, (4, 30, 6), generator=g).float().to(device)
    kept, out = table.clone(), torch.full_like(table, math.nan)
    want = torch.cumsum(table.flip(1), 1).flip(1) if reverse else torch.cumsum(table, 1)
    assert cumsum_(table, 1, reverse=reverse, out=out) is out
    assert torch.equal(out, want) and torch.equal(table, kept)
    assert torch.equal(cumsum_(table.clone(), 1, reverse=reverse), want)  # in place, the same sums


@pytest.mark.parametrize("table, dim, match", [
    (torch.tensor(1.0), 0, "at least one dimension"),
    ([1.0, 2.0], 0, "got list"),
    (torch.zeros(2, 3), 2, r"dim must be an int in \[-2, 1\]"),
    (torch.zeros(2, 3), 0.5, "got 0.5"),
])
def test_cumsum_in_place_bad_arguments(table, dim, match):
    with pytest.raises(ValueError, match=match):
        cumsum_(table, dim)


def test_cumsum_out_of_another_shape():
    with pytest.raises(ValueError, match=r"out must be a tensor of table's shape \(2, 3\), got \(3, 2\)"):
        cumsum_(torch.zeros(2, 3), 0, out=torch.zeros(3, 2))


def test_cumsum_in_place_negative_dim_and_a_known_answer():
    table = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    assert cumsum_(table, -1).tolist() == [[1.0, 3.0, 6.0], [4.0, 9.0, 15.0]]
