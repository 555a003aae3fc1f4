from __future__ import annotations

import pytest
import torch

import evlatcorr.compiled
import evlatcorr.continuous
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.events import Events
from evlatcorr.simulate import simulate


def _frame_events(hot_pixel: bool = True) -> tuple[Events, float, float]:
    """A simulated 24x32 frame's events, with a hot pixel (300 ON events), events exactly on the windows' ends and a
    still corner with none."""
    frames = simulate("camera", num_frames=1, latency="constant", latency_us=1500.0, seed=2, height=24, width=32,
                      exposure_us=5000.0).frames("delayed")
    ev, start, end = frames.events, float(frames.exposure_start), float(frames.exposure_end)
    keep = ~((ev.x >= 28) & (ev.y >= 20))  # a corner with no events
    x, y, t, p = ev.x[keep], ev.y[keep], ev.t[keep], ev.p[keep]
    on_ends = torch.tensor([start, end, start + 500.0, end + 500.0], dtype=torch.float64)
    x, y = torch.cat([x, torch.full((4,), 3)]), torch.cat([y, torch.full((4,), 5)])
    t, p = torch.cat([t, on_ends]), torch.cat([p, torch.tensor([1, -1, 1, -1], dtype=p.dtype)])
    if hot_pixel:
        x, y = torch.cat([x, torch.full((300,), 7)]), torch.cat([y, torch.full((300,), 9)])
        t = torch.cat([t, torch.linspace(start - 1000.0, end + 3000.0, 300, dtype=torch.float64)])
        p = torch.cat([p, torch.ones(300, dtype=p.dtype)])
    return Events(x, y, t, p, sensor_size=(24, 32), sort=True), start, end


def _read(events: Events, start: float, end: float, latencies: torch.Tensor, compiled: bool, stride: int = 3,
          monkeypatch: pytest.MonkeyPatch | None = None) -> tuple[torch.Tensor, ...]:
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", compiled)
    ci = ContinuousIntegral(events, 0.2, max_log_range=15.0)
    assert ci.active is None  # most pixels have events: a CPU reads them all, by the compiled pass if it may
    k = len(latencies)
    ratio, change = torch.full((k, 1, 24, 32), float("nan")), torch.full((k, 1, 24, 32), float("nan"))
    peak = torch.full((k, 1, -(-24 // stride), -(-32 // stride)), float("nan"))
    ci.inverse_ratio(start, end, latencies, out=ratio, change_out=change, peak_out=peak, peak_stride=stride)
    return ratio, change, peak, ci.log_ratio(start, end, latencies), ci.ignored


@pytest.mark.parametrize("latencies", [torch.linspace(0.0, 5000.0, 21),  # evenly spaced, as the search reads them
                                       torch.tensor([-300.0, 0.0, 130.0, 1499.5, 4999.0])])  # uneven, below 0 too
@pytest.mark.parametrize("stride", [1, 3])
def test_compiled_reads_equal_the_tables(monkeypatch, latencies, stride):
    events, start, end = _frame_events()
    compiled = _read(events, start, end, latencies, True, stride, monkeypatch)
    tables = _read(events, start, end, latencies, False, stride, monkeypatch)
    assert bool(compiled[-1][9 * 32 + 7]) and int(compiled[-1].sum()) == 1  # the hot pixel, read as having none
    ratio, change, peak, log_ratio = compiled[:4]
    torch.testing.assert_close(ratio, tables[0], rtol=2e-6, atol=0)  # float32 tables against float64 sums
    torch.testing.assert_close(change, tables[1], rtol=0, atol=1e-6)
    torch.testing.assert_close(peak, tables[2], rtol=0, atol=1e-6)
    torch.testing.assert_close(log_ratio, tables[3], rtol=0, atol=1e-12)
    # the still corner: R = 1, no change, no rise
    assert bool((ratio[..., 20:, 28:] == 1).all()) and bool((log_ratio[..., 20:, 28:] == 0).all())
    assert not bool(change[..., 20:, 28:].any())
    assert bool((change != 0).any()) and bool((peak > 0).any())


def test_one_window_equals_the_per_pixel_sums(monkeypatch):
    # on a CPU one latency is read by the compiled pass too; the GPU's per-pixel sums give the same log R
    events, start, end = _frame_events()
    for latency in (0.0, 500.0, 1234.5):
        lat = torch.tensor([latency], dtype=torch.float64)
        compiled = _read(events, start, end, lat, True, monkeypatch=monkeypatch)[3]
        monkeypatch.setattr(evlatcorr.compiled, "ENABLED", False)
        sums = ContinuousIntegral(events, 0.2, max_log_range=15.0).log_ratio(start, end, lat)
        torch.testing.assert_close(compiled, sums, rtol=0, atol=1e-12)


def test_few_pixels_with_events_are_read_from_their_tables(monkeypatch):
    # a still scene with a small moving corner: the tables at those pixels alone, faster there than the compiled pass
    # over every pixel; both give the same
    frames = simulate("camera", num_frames=1, latency="constant", latency_us=1000.0, seed=4, height=24, width=32,
                      exposure_us=5000.0).frames("delayed")
    ev, start, end = frames.events, float(frames.exposure_start), float(frames.exposure_end)
    corner = (ev.x < 12) & (ev.y < 10)
    events = Events(ev.x[corner], ev.y[corner], ev.t[corner], ev.p[corner], sensor_size=(24, 32))
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", True)
    sparse = ContinuousIntegral(events, 0.2)
    assert sparse.active is not None
    monkeypatch.setattr(evlatcorr.continuous, "SPARSE_SHARE", 0.0)
    every = ContinuousIntegral(events, 0.2)
    assert every.active is None
    latencies = torch.linspace(0.0, 3000.0, 7)
    torch.testing.assert_close(sparse.inverse_ratio(start, end, latencies), every.inverse_ratio(start, end, latencies),
                               rtol=2e-6, atol=0)


def test_the_threads_split_the_pixels_and_not_the_result(monkeypatch):
    events, start, end = _frame_events(hot_pixel=False)
    latencies = torch.linspace(0.0, 5000.0, 11)
    threads = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        one = _read(events, start, end, latencies, True, monkeypatch=monkeypatch)
        torch.set_num_threads(3)
        three = _read(events, start, end, latencies, True, monkeypatch=monkeypatch)
    finally:
        torch.set_num_threads(threads)
    for a, b in zip(one, three):
        assert torch.equal(a, b)


def test_a_window_far_below_a_brighter_past_is_summed_from_its_events(monkeypatch):
    # level 1 over [0, 100), then 150 OFF events at 100 us (θ = 0.2: e^-30, beyond what a difference of running sums
    # keeps), then one ON event at 250: the window [200, 300] read at 250 holds e^-30 for 50 us and e^-29.8 for 50
    t = torch.cat([torch.full((150,), 100.0, dtype=torch.float64), torch.tensor([250.0], dtype=torch.float64)])
    p = torch.cat([torch.zeros(150, dtype=torch.long), torch.ones(1, dtype=torch.long)])
    events = Events(torch.zeros(151, dtype=torch.long), torch.zeros(151, dtype=torch.long), t, p, sensor_size=(1, 1))
    monkeypatch.setattr(evlatcorr.compiled, "ENABLED", True)
    ci = ContinuousIntegral(events, 0.2)
    assert ci.active is None
    lat = torch.tensor([-200.0, 0.0], dtype=torch.float64)  # the first window [0, 100]: the bright past itself
    log_ratio = ci.log_ratio(200.0, 300.0, lat)
    # at the reference (250: the ON event not yet counted) the level is e^-30 relative to the window's
    expected = torch.log(torch.tensor(0.5 + 0.5 * torch.exp(torch.tensor(0.2, dtype=torch.float64)).item(),
                                      dtype=torch.float64))
    torch.testing.assert_close(log_ratio[1, 0, 0, 0], expected, rtol=1e-9, atol=0)
    assert log_ratio[0, 0, 0, 0].item() == pytest.approx(0.0, abs=1e-12)  # [0, 100]: level 1 throughout
    inverse = ci.inverse_ratio(200.0, 300.0, lat)
    torch.testing.assert_close(inverse, torch.exp(-log_ratio).float(), rtol=1e-6, atol=0)


def test_read_windows_refuses_what_it_cannot_read():
    from evlatcorr.compiled.window_reads import read_windows

    t, step = torch.zeros(2, dtype=torch.float64), torch.ones(2, dtype=torch.int8)
    bounds, peak = torch.tensor([0, 2, 2]), torch.zeros(2, dtype=torch.int32)
    times, index = torch.tensor([0.0, 1.0], dtype=torch.float64), torch.tensor([0])
    ok = dict(t=t, step=step, run_bounds=bounds, peak_count=peak, theta=0.2, times=times, a=index, b=index + 1,
              r=index, quarters=[], duration=1.0, width=2)
    read_windows(**ok, out=torch.empty(1, 2))  # accepted
    with pytest.raises(ValueError, match=r"out shape \(1, 2\)"):
        read_windows(**ok, out=torch.empty(1, 3))
    with pytest.raises(ValueError, match="out must be one of"):
        read_windows(**ok, out=torch.empty(1, 2, dtype=torch.float16))
    with pytest.raises(ValueError, match="one index per window"):
        read_windows(**{**ok, "b": torch.tensor([1, 1])}, out=torch.empty(1, 2))
    with pytest.raises(ValueError, match="change must have 1 rows of 2"):
        read_windows(**ok, out=torch.empty(1, 2), change=torch.empty(1, 3))
