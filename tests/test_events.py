from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evlatcorr import Events, polarity_to_signed
from tests.conftest import random_events


class TestPolarity:
    @pytest.mark.parametrize(
        "given_p, expected",
        [([0, 1, 1], [-1, 1, 1]), ([-1, 1], [-1, 1]), ([True, False], [1, -1]), ([1.0, 0.0], [1, -1])],
    )
    def test_conventions(self, given_p, expected):
        assert polarity_to_signed(torch.tensor(given_p)).tolist() == expected

    def test_bad_values(self):
        with pytest.raises(ValueError, match="polarity"):
            polarity_to_signed(torch.tensor([0, 2]))
        with pytest.raises(ValueError, match="polarity"):
            polarity_to_signed(torch.tensor([-1, 0]))


class TestEvents:
    def test_smoke(self):
        ev = random_events(100, (10, 12), (0.0, 1000.0), batch_size=3)
        assert len(ev) == 100 and ev.batch_size == 3 and ev.sensor_size == (10, 12)
        assert ev.t.dtype == torch.float64 and ev.p.dtype == torch.int8
        assert int(ev.counts().sum()) == 100
        assert "num_events=100" in repr(ev)

    def test_batch_defaults_to_zero(self):
        ev = Events(torch.tensor([1]), torch.tensor([1]), torch.tensor([3.0]), torch.tensor([1]), sensor_size=(2, 2))
        assert ev.batch.tolist() == [0] and ev.batch_size == 1

    @pytest.mark.parametrize(
        "kwargs, match",
        [
            (dict(x=[5], y=[0], t=[0.0], p=[1]), "x must be in"),
            (dict(x=[0], y=[-1], t=[0.0], p=[1]), "y must be in"),
            (dict(x=[0], y=[0], t=[float("nan")], p=[1]), "NaN"),
            (dict(x=[0, 1], y=[0], t=[0.0], p=[1]), "same length"),
            (dict(x=[0, 0], y=[0, 0], t=[5.0, 1.0], p=[1, 1]), "sorted"),
        ],
    )
    def test_exceptions(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            Events(*(torch.tensor(kwargs[k]) for k in "xytp"), sensor_size=(2, 2))

    def test_float32_absolute_times_warn_that_they_are_already_rounded(self):
        # a DAVIS camera's absolute timestamps (about 1.6e15 us) in float32 are rounded to 2**27 us, over 2 minutes
        xy, p = torch.tensor([0, 1]), torch.tensor([1, 0])
        with pytest.warns(UserWarning, match=r"float32 with times up to 1\.6e\+15 us, where it resolves only about "
                                             r"1\.9\de\+08 us.*pass int64 or float64"):
            ev = Events(xy, torch.zeros(2), torch.tensor([1.6e15, 1.6e15 + 500.0], dtype=torch.float32), p,
                        sensor_size=(1, 2))
        assert ev.t.dtype == torch.float64 and float(ev.t[1] - ev.t[0]) == 0.0  # the 500 us were lost before

    @pytest.mark.parametrize("t", [torch.tensor([0.5, 8.0e6], dtype=torch.float32),  # 8 s: 0.95 us apart at most
                                   torch.tensor([1.6e15, 1.6e15 + 1], dtype=torch.float64),
                                   torch.tensor([1_600_000_000_000_000, 1_600_000_000_000_001])])
    def test_times_fine_enough_pass_quietly(self, t):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            Events(torch.tensor([0, 1]), torch.zeros(2), t, torch.tensor([1, 0]), sensor_size=(1, 2))

    def test_sort_option(self):
        ev = Events(torch.tensor([0, 1]), torch.tensor([0, 0]), torch.tensor([5.0, 1.0]), torch.tensor([1, 0]),
                    sensor_size=(1, 2), sort=True)
        assert ev.t.tolist() == [1.0, 5.0] and ev.x.tolist() == [1, 0]

    def test_batch_size_too_small(self):
        with pytest.raises(ValueError, match="batch_size"):
            Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([0.0]), torch.tensor([1]),
                   batch=torch.tensor([2]), sensor_size=(1, 1), batch_size=2)

    def test_window_per_sample(self):
        ev = Events(torch.zeros(4), torch.zeros(4), torch.tensor([0.0, 10.0, 5.0, 20.0]), torch.ones(4),
                    batch=torch.tensor([0, 0, 1, 1]), sensor_size=(1, 1))
        out = ev.window(torch.tensor([0.0, 10.0]), torch.tensor([10.0, 30.0]))
        assert out.t.tolist() == [0.0, 20.0] and out.batch.tolist() == [0, 1]

    def test_windows_equal_one_mask_per_window(self):
        ev = random_events(500, (3, 4), (0.0, 100.0), seed=1)
        start = torch.tensor([0.0, 20.0, 35.0, 50.0, 99.0, 150.0])
        end = torch.tensor([40.0, 60.0, 35.0, 90.0, 120.0, 160.0])  # overlapping, empty and past the last event
        out = ev.windows(start, end)
        assert out.batch_size == 6 and out.sensor_size == (3, 4)
        for i in range(6):
            inside = (ev.t >= start[i]) & (ev.t < end[i])
            mine = out.batch == i
            for name in ("x", "y", "t", "p"):
                assert torch.equal(getattr(out, name)[mine], getattr(ev, name)[inside])
        assert out.counts().tolist()[2] == 0 and out.counts().tolist()[5] == 0

    def test_windows_refuse_a_batch_and_reversed_bounds(self):
        two = random_events(10, (2, 2), (0.0, 10.0), batch_size=2)
        with pytest.raises(ValueError, match="one stream"):
            two.windows(torch.tensor([0.0]), torch.tensor([5.0]))
        one = random_events(10, (2, 2), (0.0, 10.0))
        with pytest.raises(ValueError, match="end must not be before its start"):
            one.windows(torch.tensor([5.0]), torch.tensor([0.0]))
        with pytest.raises(ValueError, match="same length"):
            one.windows(torch.tensor([0.0, 1.0]), torch.tensor([5.0]))

    def test_since_per_sample(self):
        ev = Events(torch.zeros(4), torch.zeros(4), torch.tensor([0.0, 10.0, 5.0, 20.0]), torch.ones(4),
                    batch=torch.tensor([0, 0, 1, 1]), sensor_size=(1, 1))
        out = ev.since(torch.tensor([10.0, 0.0]))
        assert out.t.tolist() == [10.0, 5.0, 20.0] and out.batch.tolist() == [0, 1, 1]
        with pytest.raises(ValueError, match="start"):
            ev.since(torch.zeros(3))
        with pytest.raises(ValueError, match="start"):
            ev.since(float("nan"))

    def test_shift_scalar_and_map(self):
        ev = Events(torch.tensor([0, 1, 0]), torch.tensor([0, 0, 0]), torch.tensor([10.0, 20.0, 30.0]),
                    torch.ones(3), batch=torch.tensor([0, 0, 1]), sensor_size=(1, 2))
        assert ev.shift(torch.tensor([5.0, 1.0])).t.tolist() == [5.0, 15.0, 29.0]
        lat = torch.tensor([[[[25.0, 0.0]]], [[[2.0, 0.0]]]])
        shifted = ev.shift(lat)
        assert shifted.t.tolist() == [-15.0, 20.0, 28.0]  # re-sorted within the sample
        assert shifted.x.tolist() == [0, 1, 0]

    def test_shift_per_sample_equals_uniform_map(self):
        # the per-sample path skips the sort; it must give what the sorting map path gives
        ev = random_events(300, (4, 5), (0.0, 1000.0), batch_size=3, seed=3)
        lat = torch.tensor([100.0, -50.0, 2000.0])
        fast = ev.shift(lat)
        sorted_ = ev.shift(lat.view(3, 1, 1, 1).expand(3, 1, 4, 5))
        for name in ("x", "y", "t", "p", "batch"):
            assert torch.equal(getattr(fast, name), getattr(sorted_, name)), name

    def test_shift_bad_map(self):
        ev = random_events(10, (4, 4), (0.0, 10.0))
        with pytest.raises(ValueError, match="latency"):
            ev.shift(torch.zeros(1, 1, 3, 4))
        with pytest.raises(ValueError, match="latency"):
            ev.shift(torch.zeros(2))

    def test_numpy_round_trip(self):
        ev = random_events(50, (6, 7), (0.0, 1e6))
        ev = Events(ev.x, ev.y, ev.t.round(), ev.p, sensor_size=(6, 7))
        arr = ev.to_numpy()
        assert set(arr.dtype.names) == {"x", "y", "t", "p"}
        back = Events.from_numpy(arr, sensor_size=(6, 7))
        for name in "xytp":
            assert torch.equal(getattr(back, name), getattr(ev, name))

    def test_from_numpy_bad(self):
        with pytest.raises(ValueError, match="structured"):
            Events.from_numpy(np.zeros(3), sensor_size=(2, 2))

    def test_cat_and_sample(self):
        a = random_events(5, (3, 3), (0.0, 10.0), seed=1)
        b = random_events(7, (3, 3), (0.0, 10.0), seed=2)
        both = Events.cat([a, b])
        assert both.batch_size == 2 and both.counts().tolist() == [5, 7]
        assert torch.equal(both.sample(1).t, b.t)

    def test_non_contiguous(self):
        x = torch.zeros(10, 2, dtype=torch.long)[:, 0]
        t = torch.arange(20.0).view(10, 2)[:, 1]
        ev = Events(x, x, t, torch.ones(10), sensor_size=(1, 1))
        assert ev.window(0.0, 10.0).t.tolist() == [1.0, 3.0, 5.0, 7.0, 9.0]

    def test_device(self, device):
        ev = random_events(20, (3, 3), (0.0, 10.0)).to(device)
        assert ev.t.device.type == device.type
        assert len(ev.shift(1.0)) == 20

    @pytest.mark.parametrize("num", [0, 1, 500])
    def test_last_times_are_each_samples_latest_event(self, device, num):
        ev = random_events(num, (4, 5), (0.0, 100.0), batch_size=4, seed=num).to(device)
        last = ev.last_times()
        assert last.device.type == device.type and last.dtype == torch.float64
        for b in range(4):
            times = ev.t[ev.batch == b]
            assert last[b].item() == (times.max().item() if len(times) else -float("inf"))


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), num=st.integers(0, 200), batch_size=st.integers(1, 3))
def test_shift_unshift_identity(seed, num, batch_size):
    ev = random_events(num, (5, 6), (0.0, 1000.0), batch_size=batch_size, seed=seed)
    g = torch.Generator().manual_seed(seed)
    lat = torch.rand(batch_size, 1, 5, 6, generator=g, dtype=torch.float64) * 500
    back = ev.shift(lat).shift(-lat)
    key = lambda e: sorted(zip(e.batch.tolist(), e.t.round(decimals=6).tolist(), e.x.tolist(), e.y.tolist(),  # noqa: E731
                               e.p.tolist()))
    assert key(back) == key(ev)
