import math

import pytest
import torch

from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.events import Events
from evlatcorr.overshoot import OVERSHOOT_RANGE, _upper_quantile, overshoot, overshoot_stride
from tests.conftest import random_events

THETA = 0.25


def _one_pixel(times, polarities):
    n = len(times)
    return Events(torch.zeros(n, dtype=torch.long), torch.zeros(n, dtype=torch.long),
                  torch.tensor(times, dtype=torch.float64), torch.tensor(polarities), sensor_size=(1, 1))


@pytest.mark.parametrize(("latency", "expected"), [(0.0, 2 * THETA), (3.0, 0.0)])
def test_peak_rise_of_a_brightening_pixel(latency, expected):
    # two ON events at 6 and 7 us, window [0, 10] read `latency` late (reference: its middle). At 0 the counts at
    # the start, quarters, middle and end are 0, 0, 0, 2, 2: the log latent rises 2θ above the middle's. At 3 us
    # the middle (8 us) already has both: nothing rises above it
    ci = ContinuousIntegral(_one_pixel([6.0, 7.0], [1, 1]), THETA)
    inverse, peak = torch.empty(1, 1, 1, 1), torch.empty(1, 1, 1, 1)
    ci.inverse_ratio(0.0, 10.0, torch.tensor([latency]), out=inverse, peak_out=peak)
    assert float(peak) == pytest.approx(expected, abs=1e-6)


@pytest.mark.parametrize(("latency", "expected"), [(0.0, 0.0), (3.0, THETA)])
def test_peak_rise_of_a_darkening_pixel(latency, expected):
    # one OFF event at 6 us: read at 0 the middle (5 us) is before it and is the highest; read at 3 us the middle
    # (8 us) is after it, one step below the window's start
    ci = ContinuousIntegral(_one_pixel([6.0], [0]), THETA)
    inverse, peak = torch.empty(1, 1, 1, 1), torch.empty(1, 1, 1, 1)
    ci.inverse_ratio(0.0, 10.0, torch.tensor([latency]), out=inverse, peak_out=peak)
    assert float(peak) == pytest.approx(expected, abs=1e-6)


def test_peak_read_leaves_the_ratios_and_changes_as_they_are():
    events = random_events(4000, (12, 16), (0.0, 30000.0), seed=3)
    ci = ContinuousIntegral(events, 0.2)
    lat = torch.arange(0.0, 10001.0, 200.0)  # spaced by exposure / 100: the quarters are times already read
    shape = (len(lat), 1, 12, 16)
    alone, change_alone = torch.empty(shape), torch.empty(shape)
    ci.inverse_ratio(0.0, 20000.0, lat, out=alone, change_out=change_alone)
    with_peak, change, peak = torch.empty(shape), torch.empty(shape), torch.empty(shape)
    ci.inverse_ratio(0.0, 20000.0, lat, out=with_peak, change_out=change, peak_out=peak)
    assert torch.equal(with_peak, alone) and torch.equal(change, change_alone)
    assert bool((peak >= 0).all())
    # the rise is a whole number of steps, at least the window's net change past the middle
    steps = peak / 0.2
    torch.testing.assert_close(steps, steps.round(), rtol=0, atol=1e-4)
    later_half = ci.log_change(10000.0, 20000.0, lat)
    assert bool((peak >= later_half - 1e-5).all())


def test_peak_out_of_the_wrong_shape_is_refused():
    ci = ContinuousIntegral(random_events(100, (4, 4), (0.0, 2000.0), seed=0), 0.2)
    with pytest.raises(ValueError, match="peak_out must be float32"):
        ci.inverse_ratio(0.0, 1000.0, torch.tensor([0.0, 10.0]), peak_out=torch.empty(1, 1, 4, 4))
    with pytest.raises(ValueError, match="peak_out must be float32"):  # every 2nd row and column: 2 x 2
        ci.inverse_ratio(0.0, 1000.0, torch.tensor([0.0, 10.0]), peak_out=torch.empty(2, 1, 4, 4), peak_stride=2)
    with pytest.raises(ValueError, match="peak_stride must be"):
        ci.inverse_ratio(0.0, 1000.0, torch.tensor([0.0]), peak_out=torch.empty(1, 1, 4, 4), peak_stride=0)


def test_overshoot_is_the_upper_percentile_over_the_brightest_pixel():
    g = torch.Generator().manual_seed(0)
    grey = 0.1 + 0.8 * torch.rand(1, 1, 20, 30, generator=g)
    inverse = 0.5 + torch.rand(3, 1, 20, 30, generator=g)
    log_peak = torch.rand(3, 1, 20, 30, generator=g)
    top = (torch.log(grey) + torch.log(inverse) + log_peak).flatten(1)
    expected = (torch.quantile(top, 0.99, dim=1) - math.log(float(grey.max()))).double()
    torch.testing.assert_close(overshoot(grey, inverse, log_peak), expected, rtol=0, atol=1e-5)


def test_overshoot_of_several_frames_is_each_frames_and_is_clamped():
    g = torch.Generator().manual_seed(1)
    grey = 0.2 + 0.5 * torch.rand(1, 3, 10, 12, generator=g)
    inverse = 0.5 + torch.rand(4, 3, 10, 12, generator=g)
    log_peak = torch.rand(4, 3, 10, 12, generator=g)
    log_peak[:, 2] += 10.0  # a frame whose latents blow up: read at the top of the range
    together = overshoot(grey, inverse, log_peak)
    assert together.shape == (4, 3)
    for f in range(3):
        part = slice(f, f + 1)
        torch.testing.assert_close(together[:, f], overshoot(grey[:, part], inverse[:, part], log_peak[:, part]),
                                   rtol=0, atol=0)
    assert bool((together[:, 2] == OVERSHOOT_RANGE[1]).all())


def test_overshoot_of_a_large_frame_reads_every_third_row_and_column():
    # a DAVIS346 frame: every 3rd row and column, 87 x 116 pixels (the reader's training frames: 96 x 128, whole)
    assert overshoot_stride(260, 346) == 3 and overshoot_stride(96, 128) == 1 and overshoot_stride(4, 4) == 1
    with pytest.raises(ValueError, match="at least one pixel"):
        overshoot_stride(0, 346)
    g = torch.Generator().manual_seed(2)
    grey = 0.1 + 0.8 * torch.rand(1, 1, 260, 346, generator=g)
    inverse = 0.5 + torch.rand(2, 1, 260, 346, generator=g)
    log_peak = torch.rand(2, 1, 87, 116, generator=g)
    sampled = [x[..., ::3, ::3] for x in (grey, inverse)]
    assert sampled[0].shape[-2:] == (87, 116)
    torch.testing.assert_close(overshoot(grey, inverse, log_peak), overshoot(*sampled, log_peak), rtol=0, atol=0)
    # the continuous integral reads the peak rise at those pixels only: the same values as at every pixel
    events = random_events(20000, (260, 346), (0.0, 30000.0), seed=5)
    ci, lat = ContinuousIntegral(events, 0.2), torch.arange(0.0, 4001.0, 200.0)
    every, strided = torch.empty(len(lat), 1, 260, 346), torch.empty(len(lat), 1, 87, 116)
    ci.inverse_ratio(0.0, 20000.0, lat, out=torch.empty(len(lat), 1, 260, 346), peak_out=every)
    ci.inverse_ratio(0.0, 20000.0, lat, out=torch.empty(len(lat), 1, 260, 346), peak_out=strided, peak_stride=3)
    assert torch.equal(strided, every[..., ::3, ::3])


def test_upper_quantile_equals_torch_quantile():
    g = torch.Generator().manual_seed(3)
    for n in (1, 2, 7, 100, 1001):
        values = torch.randn(5, n, generator=g, dtype=torch.float64)
        for q in (0.9, 0.99, 1.0):
            torch.testing.assert_close(_upper_quantile(values, q), torch.quantile(values, q, dim=1))


def test_overshoot_refuses_mismatched_shapes():
    with pytest.raises(ValueError, match="grey must be"):
        overshoot(torch.rand(1, 1, 4, 4), torch.rand(2, 1, 4, 4), torch.rand(3, 1, 4, 4))
    with pytest.raises(ValueError, match="grey must be"):
        overshoot(torch.rand(2, 1, 4, 4), torch.rand(2, 1, 4, 4), torch.rand(2, 1, 4, 4))


def test_binned_table_reads_the_same_peak_rise_as_the_continuous_integral():
    from evlatcorr.search_binned import _ShiftTable

    events = random_events(3000, (6, 8), (0.0, 15000.0), seed=4)
    n, width_us, shifts = 100, 100.0, torch.arange(0, 40, 4)
    table = _ShiftTable(events, 0.0, width_us, n, int(shifts.max()), 0.2)
    binned = table.log_peak(shifts)
    peak = torch.empty(len(shifts), 1, 6, 8)
    ContinuousIntegral(events, 0.2).inverse_ratio(0.0, n * width_us, shifts.double() * width_us,
                                                  out=torch.empty_like(peak), peak_out=peak)
    torch.testing.assert_close(binned, peak, rtol=0, atol=1e-5)
