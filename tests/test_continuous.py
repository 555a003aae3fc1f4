from __future__ import annotations

import math

import pytest
import torch

from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.edi import edi_deblur
from evlatcorr.events import Events
from evlatcorr.simulate import simulate


@pytest.fixture(params=["compiled", "tables"])
def reads(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """Both ways a CPU reads windows: the compiled pass over each pixel's events (at every pixel: where few have events
    the tables are the faster), and the tables (a GPU's way)."""
    monkeypatch.setattr("evlatcorr.compiled.ENABLED", request.param == "compiled")
    if request.param == "compiled":
        monkeypatch.setattr("evlatcorr.continuous.SPARSE_SHARE", 0.0)
    return request.param


@pytest.fixture
def tables(monkeypatch: pytest.MonkeyPatch) -> None:
    """The tables on a CPU too: what the tests of the tables' own machinery (strips, blocks, slots) read."""
    monkeypatch.setattr("evlatcorr.compiled.ENABLED", False)


def one_pixel_events(times: list[float] | torch.Tensor, polarity: list[int] | torch.Tensor, sensor=(1, 2)) -> Events:
    """Events at pixel (0, 0) of a sensor whose other pixels have none."""
    t = torch.as_tensor(times, dtype=torch.float64)
    return Events(torch.zeros(len(t), dtype=torch.long), torch.zeros(len(t), dtype=torch.long), t,
                  torch.as_tensor(polarity), sensor_size=sensor)


def test_single_event_known_answer(reads):
    # window [0, 10] us read at 5 us; one +1 event at 2.5 us: level 1 over 7.5 us, 0 over 2.5 us, 1 at the reference
    theta = 0.3
    ci = ContinuousIntegral(one_pixel_events([2.5], [1]), theta)
    log_r = ci.log_ratio(0.0, 10.0, torch.tensor([0.0]))
    expected = math.log((2.5 * math.exp(-theta) + 7.5) / 10.0)
    assert log_r.shape == (1, 1, 1, 2)
    assert log_r[0, 0, 0, 0].item() == pytest.approx(expected, rel=1e-12)
    assert log_r[0, 0, 0, 1].item() == 0.0  # a pixel with no events: R = 1


def test_latency_reads_the_window_later(reads):
    # the same event seen with a latency of 4 us: window [4, 14] read at 9: level 0 over [4, 6.5), 1 over the rest
    ci = ContinuousIntegral(one_pixel_events([6.5], [1]), 0.3)
    log_r = ci.log_ratio(0.0, 10.0, torch.tensor([4.0, 20.0]))
    assert log_r[0, 0, 0, 0].item() == pytest.approx(math.log((2.5 * math.exp(-0.3) + 7.5) / 10.0), rel=1e-12)
    assert log_r[1, 0, 0, 0].item() == pytest.approx(0.0, abs=1e-15)  # [20, 30]: after the event, level constant


def test_inverse_ratio_is_exp_of_minus_log_ratio(reads):
    g = torch.Generator().manual_seed(2)
    n, (h, w) = 3000, (4, 6)
    t, _ = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 1000.0)
    ev = Events(torch.randint(0, w, (n,), generator=g), torch.randint(0, h, (n,), generator=g), t,
                torch.randint(0, 2, (n,), generator=g), sensor_size=(h, w))
    ci, lat = ContinuousIntegral(ev, 0.25), torch.tensor([0.0, 120.0, 333.0])
    inverse = ci.inverse_ratio(100.0, 500.0, lat)
    assert inverse.dtype == torch.float32 and inverse.shape == (3, 1, h, w)
    torch.testing.assert_close(inverse, torch.exp(-ci.log_ratio(100.0, 500.0, lat)).float(), rtol=1e-6, atol=0)


def test_float32_ratio_keeps_its_precision_below_a_much_brighter_past(reads):
    # level 1 over [0, 100), then 60 OFF events (θ = 0.2: e^-12) and flat: a window after them has R = 1 exactly.
    # Read with an earlier window, a running sum from the first time would hold ~90 (us at level 1) before the
    # window's ~0.0006 and lose it in float32; the blocks of interval integrals keep float32's relative precision
    ci = ContinuousIntegral(one_pixel_events(torch.full((60,), 100.0), [-1] * 60), 0.2)
    lat = torch.tensor([-190.0, 0.0], dtype=torch.float64)
    inverse = ci.inverse_ratio(200.0, 300.0, lat)
    torch.testing.assert_close(inverse, torch.exp(-ci.log_ratio(200.0, 300.0, lat)).float(), rtol=1e-6, atol=0)
    assert inverse[1, 0, 0, 0].item() == pytest.approx(1.0, rel=1e-6)


def test_block_sums_equal_the_direct_sums_of_any_windows(device):
    from evlatcorr.continuous import _Windows

    g = torch.Generator().manual_seed(7)
    intervals, p = 40, 3
    values = torch.rand(intervals, p, generator=g, dtype=torch.float64)
    # windows of 4 to 30 intervals (exactly one block, two blocks, several whole blocks in between), and evenly
    # spaced ones of 20 (the first and the last exactly one block: one read backwards, one forwards)
    for a, b in ((torch.tensor([0, 4, 3, 0, 10, 9]), torch.tensor([4, 8, 9, 30, 40, 13])),
                 (torch.arange(21), torch.arange(21) + 20)):
        windows = _Windows(a, b, intervals + 1, device)
        # past the intervals: never read
        table = torch.full((windows.rows, p), math.nan, dtype=torch.float64, device=device)
        table[:intervals] = values.to(device)
        sums = windows.sums(table, torch.full_like(table, math.nan)).cpu()
        expected = torch.stack([values[lo:hi].sum(0) for lo, hi in zip(a.tolist(), b.tolist())])
        torch.testing.assert_close(sums, expected, rtol=1e-12, atol=0)


def test_log_change_counts_each_windows_net_events():
    # +1 at 5 us, -1 at 15, +1 at 25; windows [l, l + 10): the sign of the one event inside, 0 past the last
    theta = 0.5
    ci = ContinuousIntegral(one_pixel_events([5.0, 15.0, 25.0], [1, -1, 1]), theta)
    change = ci.log_change(0.0, 10.0, torch.tensor([0.0, 10.0, 20.0, 30.0, 7.0]))
    assert change.shape == (5, 1, 1, 2) and change.dtype == torch.float32
    torch.testing.assert_close(change[:, 0, 0, 0], torch.tensor([0.5, -0.5, 0.5, 0.0, -0.5]))
    assert not bool(change[:, 0, 0, 1].any())  # no events at the other pixel


def test_log_change_equals_a_count_of_random_events():
    g = torch.Generator().manual_seed(3)
    n, (h, w) = 4000, (5, 7)
    t, _ = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 1000.0)
    x, y = torch.randint(0, w, (n,), generator=g), torch.randint(0, h, (n,), generator=g)
    p = torch.randint(0, 2, (n,), generator=g) * 2 - 1
    ci = ContinuousIntegral(Events(x, y, t, p, sensor_size=(h, w)), 0.2)
    lat = torch.tensor([0.0, 37.5, 301.25, 600.0])
    change = ci.log_change(100.0, 350.0, lat)
    for k, l in enumerate(lat.tolist()):
        inside = (t >= 100.0 + l) & (t < 350.0 + l)
        count = torch.zeros(h * w).index_add_(0, (y * w + x)[inside], p[inside].float()).view(h, w)
        torch.testing.assert_close(change[k, 0], 0.2 * count)


def test_inverse_ratio_reads_the_event_change_from_its_own_tables(monkeypatch, tables):
    # the same windows' change as log_change, strip by strip (two rows a strip), with a pixel of no events
    g = torch.Generator().manual_seed(5)
    n, (h, w) = 3000, (5, 7)
    t, _ = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 1000.0)
    x, y = torch.randint(0, w - 1, (n,), generator=g), torch.randint(0, h, (n,), generator=g)  # last column: none
    p = torch.randint(0, 2, (n,), generator=g) * 2 - 1
    ci = ContinuousIntegral(Events(x, y, t, p, sensor_size=(h, w)), 0.2)
    lat = torch.tensor([0.0, 37.5, 301.25, 600.0], dtype=torch.float64)
    monkeypatch.setattr("evlatcorr.continuous.STRIP_BYTES", 2 * w * 12 * 40)
    change = torch.full((4, 1, h, w), math.nan)
    inverse = ci.inverse_ratio(100.0, 350.0, lat, change_out=change)
    torch.testing.assert_close(change, ci.log_change(100.0, 350.0, lat), atol=1e-5, rtol=0)
    assert not bool(change[..., -1].any())
    torch.testing.assert_close(inverse, ci.inverse_ratio(100.0, 350.0, lat))
    with pytest.raises(ValueError, match="change_out must be float32"):
        ci.inverse_ratio(100.0, 350.0, lat, change_out=torch.empty(4, 1, h, w, dtype=torch.float64))


def test_event_slots_equal_a_binary_search_of_each_event():
    # events before, on and after the times, several pixels (pixel order differs from time order)
    t = torch.tensor([1.0, 2.0, 2.0, 3.0, 5.0, 7.5, 9.0, 12.0], dtype=torch.float64)
    x = torch.tensor([1, 0, 1, 0, 1, 0, 0, 1])
    ev = Events(x, torch.zeros(8, dtype=torch.long), t, torch.tensor([1, -1, 1, 1, -1, 1, -1, 1]), sensor_size=(1, 2))
    ci = ContinuousIntegral(ev, 0.3)
    times = torch.tensor([2.0, 3.0, 4.0, 9.0, 10.0], dtype=torch.float64)
    expected = torch.searchsorted(times, ci.t, right=True)
    assert torch.equal(ci._slots(times).long(), expected)


@pytest.mark.parametrize("reference", [0.0, 0.3, 0.5, 1.0])
@pytest.mark.parametrize("latency", [-20.0, 0.0, 37.3, 150.0, 400.0])
def test_one_window_from_per_pixel_sums_equals_the_tables(reference, latency, device, tables):
    # one latency is read from per-pixel sums, several from tables: the same log R, a hot pixel, events on window
    # ends and windows past the last event included
    t = torch.cat([torch.rand(3000, generator=torch.Generator().manual_seed(3), dtype=torch.float64) * 300.0,
                   torch.tensor([10.0, 110.0, 60.0], dtype=torch.float64),  # on the ends and the reference
                   torch.linspace(0.0, 299.0, 100, dtype=torch.float64)])  # a hot pixel at (0, 0)
    g = torch.Generator().manual_seed(4)
    x = torch.cat([torch.randint(0, 6, (3003,), generator=g), torch.zeros(100, dtype=torch.long)])
    y = torch.cat([torch.randint(0, 5, (3003,), generator=g), torch.zeros(100, dtype=torch.long)])
    p = torch.cat([torch.randint(0, 2, (3003,), generator=g), torch.ones(100, dtype=torch.long)])
    ci = ContinuousIntegral(Events(x, y, t, p, sensor_size=(5, 6), sort=True).to(device), 0.3, max_log_range=15.0)
    assert bool(ci.ignored[0])
    lat = torch.tensor([latency, 5.0], dtype=torch.float64)
    tables = ci.log_ratio(10.0, 110.0, lat, reference)[:1]
    torch.testing.assert_close(ci.log_ratio(10.0, 110.0, lat[:1], reference), tables, rtol=0, atol=1e-12)


def test_a_sample_with_no_events_reads_r_equal_to_one(reads):
    empty = torch.zeros(0, dtype=torch.long)
    ci = ContinuousIntegral(Events(empty, empty, torch.zeros(0, dtype=torch.float64), empty, sensor_size=(2, 3)), 0.2,
                            max_log_range=15.0)
    lat = torch.tensor([0.0, 3.0, 3.0])
    change = torch.empty(3, 1, 2, 3)
    assert torch.equal(ci.inverse_ratio(0.0, 10.0, lat, change_out=change), torch.ones(3, 1, 2, 3))
    assert torch.equal(ci.log_ratio(0.0, 10.0, lat), torch.zeros(3, 1, 2, 3, dtype=torch.float64))
    assert not bool(change.any()) and not bool(ci.log_change(0.0, 10.0, lat).any())


def test_hot_pixel_is_read_as_having_no_events(reads):
    # pixel (0, 0): 100 ON events (θC spans 20 > 15: a hot pixel); pixel (0, 1): an ordinary +1, -1
    hot_t = torch.linspace(1.0, 99.0, 100, dtype=torch.float64)
    t = torch.cat([hot_t, torch.tensor([30.0, 60.0], dtype=torch.float64)])
    x = torch.cat([torch.zeros(100, dtype=torch.long), torch.ones(2, dtype=torch.long)])
    p = torch.cat([torch.ones(100, dtype=torch.long), torch.tensor([1, -1])])
    events = Events(x, torch.zeros(102, dtype=torch.long), t, p, sensor_size=(1, 2), sort=True)
    lat = torch.tensor([0.0, 10.0])
    plain = ContinuousIntegral(events, 0.2)
    guarded = ContinuousIntegral(events, 0.2, max_log_range=15.0)
    assert guarded.ignored.tolist() == [True, False] and not bool(plain.ignored.any())
    log_r = guarded.log_ratio(0.0, 80.0, lat)
    assert torch.equal(log_r[..., 0], torch.zeros(2, 1, 1))  # no events: R = 1
    torch.testing.assert_close(log_r[..., 1], plain.log_ratio(0.0, 80.0, lat)[..., 1])
    change = torch.empty(2, 1, 1, 2)
    guarded.inverse_ratio(0.0, 80.0, lat, change_out=change)
    assert torch.equal(change[..., 0], torch.zeros(2, 1, 1))
    torch.testing.assert_close(change[..., 1], plain.log_change(0.0, 80.0, lat)[..., 1], atol=1e-6, rtol=0)


def test_thousands_of_events_geometric_series(reads):
    # 3000 +1 events every 2 us from t = 1 us: over [0, 6000] the level is k·θ on [2k - 1, 2k + 1) (k >= 1) and 0 on
    # [0, 1); read at the end (6000 us, after all 3000 events): R = Σ_k exp(θ(C_k − 3000)) dt_k / 6000
    n, theta = 3000, 0.01
    times = 1.0 + 2.0 * torch.arange(n, dtype=torch.float64)
    ci = ContinuousIntegral(one_pixel_events(times, torch.ones(n, dtype=torch.long)), theta)
    log_r = ci.log_ratio(0.0, 6000.0, torch.tensor([0.0]), reference=1.0)[0, 0, 0, 0].item()
    q = math.exp(theta)
    # level 0 for 1 us, levels 1..n-1 for 2 us each, level n for the last 1 us
    total = 1.0 + 2.0 * (q**n - q) / (q - 1) + q**n
    assert log_r == pytest.approx(math.log(total / 6000.0) - n * theta, rel=1e-10)


def test_equals_binned_edi_in_the_limit_of_many_bins(reads):
    frames = simulate("camera", num_frames=1, latency="constant", latency_us=2000.0, seed=0, height=24, width=32,
                      exposure_us=10_000.0).frames("delayed")
    start, end = float(frames.exposure_start), float(frames.exposure_end)
    latencies = torch.tensor([0.0, 1234.5, 2000.0])
    log_r = ContinuousIntegral(frames.events, 0.2).log_ratio(start, end, latencies)
    pixel = frames.events.pixel_index()
    for k, latency in enumerate(latencies.tolist()):
        exact = frames.blurry.double() * torch.exp(-log_r[k:k + 1])
        errors = []
        for bins in (500, 5000, 50_000):
            # a pixel with an event within two bins of a window end or the reference is read differently by the
            # binned EDI (it interpolates C between grid points): compare the others
            near = torch.zeros(24 * 32, dtype=torch.bool)
            for time in (start + latency, end + latency, (start + end) / 2 + latency):
                near[pixel[(frames.events.t - time).abs() < 2 * (end - start) / bins]] = True
            binned = edi_deblur(frames.blurry.double(), frames.events, frames.exposure_start, frames.exposure_end,
                                threshold=0.2, latency=latency, num_bins=bins)
            errors.append(float((exact - binned).abs().amax(1).flatten()[~near].max()))
        assert errors[0] > errors[1] > errors[2]
        assert errors[2] < 2e-5


def test_times_evaluated_together_or_apart_agree(reads):
    frames = simulate("camera", num_frames=1, latency="constant", latency_us=1000.0, seed=1, height=12, width=16,
                      exposure_us=5000.0).frames("delayed")
    ci = ContinuousIntegral(frames.events, 0.2)
    start, end = float(frames.exposure_start), float(frames.exposure_end)
    # evenly spaced candidates read their table rows as views, uneven ones gather them: the same values
    for latencies in (torch.linspace(0.0, 3000.0, 7), torch.tensor([0.0, 130.0, 1000.0, 2999.0])):
        together = ci.log_ratio(start, end, latencies)
        apart = torch.cat([ci.log_ratio(start, end, torch.tensor([v])) for v in latencies.tolist()])
        torch.testing.assert_close(together, apart, rtol=1e-10, atol=1e-12)


@pytest.mark.parametrize("kwargs, match", [
    (dict(threshold=0.0), "threshold must be positive"),
    (dict(batch_size=2), "one sample"),
    (dict(max_log_range=0.0), "max_log_range must be positive"),
])
def test_bad_arguments(kwargs, match):
    ev = Events(torch.zeros(2, dtype=torch.long), torch.zeros(2, dtype=torch.long), torch.tensor([1.0, 2.0]),
                torch.ones(2), batch=torch.tensor([0, kwargs.get("batch_size", 1) - 1]), sensor_size=(1, 1))
    with pytest.raises(ValueError, match=match):
        ContinuousIntegral(ev, kwargs.get("threshold", 0.2), kwargs.get("max_log_range"))


def test_edi_deblur_continuous_integral_matches_many_bins_and_takes_one_latency_per_sample():
    frames = simulate("camera", num_frames=2, latency="constant", latency_us=2000.0, seed=2, height=12, width=16,
                      exposure_us=5000.0).frames("delayed")
    latency = torch.tensor([2000.0, 1500.0])
    exact = edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, 0.2, latency,
                       integral="continuous")
    binned = edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, 0.2, latency,
                        num_bins=50_000)
    assert exact.shape == frames.blurry.shape and exact.dtype == frames.blurry.dtype
    assert float((exact - binned).abs().median()) < 1e-5
    with pytest.raises(ValueError, match="one latency per sample"):
        edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, 0.2,
                   torch.zeros(2, 1, 12, 16), integral="continuous")


def test_strips_of_rows_give_the_same_ratios(monkeypatch, tables):
    import evlatcorr.continuous

    frames = simulate("camera", num_frames=1, latency="constant", latency_us=1000.0, seed=4, height=12, width=16,
                      exposure_us=5000.0).frames("delayed")
    start, end = float(frames.exposure_start), float(frames.exposure_end)
    latencies = torch.linspace(0.0, 3000.0, 7)
    whole = ContinuousIntegral(frames.events, 0.2).log_ratio(start, end, latencies)
    # 1 kB per strip: one row (of 16 pixels) at a time
    monkeypatch.setattr(evlatcorr.continuous, "STRIP_BYTES", 1000)
    rows = ContinuousIntegral(frames.events, 0.2).log_ratio(start, end, latencies)
    torch.testing.assert_close(rows, whole, rtol=1e-12, atol=1e-12)


def test_corrector_latent_is_the_continuous_edi_at_its_latency():
    from evlatcorr import EventLatencyCorrector

    frames = simulate("camera", num_frames=2, latency="constant", latency_us=2000.0, seed=5, height=16, width=20,
                      exposure_us=5000.0).frames("delayed")
    out = EventLatencyCorrector(threshold=0.2)(frames)
    latency = out.latency[:, 0, 0, 0].double()
    expected = edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, 0.2, latency,
                          integral="continuous")
    torch.testing.assert_close(out.latent, expected, rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("stride", [1, 3])
def test_reading_the_pixels_with_events_alone_gives_what_every_pixel_gives(monkeypatch, stride, tables):
    # a small object moving over a still background: few pixels have events, and only theirs are read, in strips of
    # a few pixels; every other pixel's ratio is 1, its change and peak rise 0
    import evlatcorr.continuous

    frames = simulate("camera", num_frames=1, latency="constant", latency_us=1000.0, seed=4, height=24, width=32,
                      exposure_us=5000.0).frames("delayed")
    ev = frames.events
    corner = (ev.x < 12) & (ev.y < 10)
    events = Events(ev.x[corner], ev.y[corner], ev.t[corner], ev.p[corner], sensor_size=(24, 32))
    start, end = float(frames.exposure_start), float(frames.exposure_end)
    latencies = torch.linspace(0.0, 3000.0, 7)

    def read(ci):
        ratio, change = torch.empty(7, 1, 24, 32), torch.empty(7, 1, 24, 32)
        peak = torch.empty(7, 1, -(-24 // stride), -(-32 // stride))
        ci.inverse_ratio(start, end, latencies, out=ratio, change_out=change, peak_out=peak, peak_stride=stride)
        return ratio, change, peak, ci.log_ratio(start, end, latencies)

    monkeypatch.setattr(evlatcorr.continuous, "SPARSE_SHARE", 0.0)  # every pixel read
    every = ContinuousIntegral(events, 0.2)
    assert every.active is None
    monkeypatch.setattr(evlatcorr.continuous, "SPARSE_SHARE", 0.5)
    monkeypatch.setattr(evlatcorr.continuous, "STRIP_BYTES", 20_000)  # a few pixels per strip
    active = ContinuousIntegral(events, 0.2)
    assert active.active is not None and len(active.active) <= 12 * 10
    for got, want in zip(read(active), read(every)):
        torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-6)
    outside = torch.ones(24, 32, dtype=torch.bool)
    outside[:10, :12] = False
    ratio, change, peak, log_ratio = read(active)
    assert bool((ratio[:, 0][:, outside] == 1).all()) and bool((log_ratio[:, 0][:, outside] == 0).all())
    assert bool((change[:, 0][:, outside] == 0).all())
    assert bool((change != 0).any()) and bool((peak != 0).any())  # the corner's events are read


@pytest.mark.parametrize("way", ["compiled", "tables in strips", "pixels with events"])
def test_peak_of_stacked_frames_is_each_frames_own(monkeypatch, way):
    # three frames of 13 rows stacked as one tall sensor (as several frames searched in one pass are): the peak is read
    # at every 3rd row and column of each frame, whose sampled rows do not fall every 3rd row of the tall image
    import evlatcorr.continuous

    monkeypatch.setattr("evlatcorr.compiled.ENABLED", way != "tables in strips")
    monkeypatch.setattr(evlatcorr.continuous, "SPARSE_SHARE", 0.5 if way == "pixels with events" else 0.0)
    monkeypatch.setattr(evlatcorr.continuous, "STRIP_BYTES", 60_000)  # strips that cross the frames' edges
    frames = simulate("camera", num_frames=3, latency="constant", latency_us=1000.0, seed=6, height=13, width=17,
                      exposure_us=5000.0, frame_interval_us=5000.0).frames("delayed", after_us=5000.0)
    latencies, stride, per_frame = torch.linspace(0.0, 4000.0, 5), 3, (5, 6)
    singles, parts = [], []
    for j in range(3):
        ev = frames.events.sample(j)
        keep = (ev.x < 8) if way == "pixels with events" else torch.ones(len(ev), dtype=torch.bool)
        ev = Events(ev.x[keep], ev.y[keep], ev.t[keep] - float(frames.exposure_start[j]), ev.p[keep],
                    sensor_size=(13, 17))
        parts.append(ev)
        peak = torch.empty(5, 1, *per_frame)
        ContinuousIntegral(ev, 0.2).inverse_ratio(0.0, 5000.0, latencies, peak_out=peak, peak_stride=stride)
        singles.append(peak)
    rows = torch.cat([e.y + 13 * j for j, e in enumerate(parts)])  # frame j's rows moved down by 13 j
    tall = Events.from_canonical(torch.cat([e.x for e in parts]), rows, torch.cat([e.t for e in parts]),
                                 torch.cat([e.p for e in parts]), torch.zeros_like(rows), (39, 17), 1)
    integral = ContinuousIntegral(tall, 0.2, time_sorted=False)
    assert (integral.active is not None) == (way == "pixels with events")
    peak = torch.empty(5, 1, 3 * per_frame[0], per_frame[1])
    integral.inverse_ratio(0.0, 5000.0, latencies, peak_out=peak, peak_stride=stride, peak_frame_height=13)
    torch.testing.assert_close(peak.view(5, 3, *per_frame), torch.cat(singles, 1))
    assert bool((peak != 0).any())
    with pytest.raises(ValueError, match="peak_frame_height must divide"):
        integral.inverse_ratio(0.0, 5000.0, latencies, peak_out=peak, peak_stride=stride, peak_frame_height=12)
