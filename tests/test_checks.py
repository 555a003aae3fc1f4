from __future__ import annotations

import math
import re
import warnings

import pytest
import torch
from hypothesis import given
from hypothesis import strategies as st

from evlatcorr import EventFrames, Events, checks
from evlatcorr.checks import (
    check_batch_vector,
    check_exposure,
    check_finite,
    check_has_events,
    check_image,
    check_int,
    check_memory,
    check_search_range,
    check_search_size,
    check_shape,
    check_threshold,
    resolve_memory_budget,
)


class TestCheckShape:
    def test_matching_shapes_pass(self):
        check_shape(torch.zeros(2, 3, 4, 5), ["B", "C", "H", "W"], "image")
        check_shape(torch.zeros(2, 1, 4, 4), ["B", 1, "H", "H"], "latency")  # ints exact, a repeated name equal

    @pytest.mark.parametrize("x, shape, message", [
        ([1.0, 2.0], ["N"], "x must be a torch.Tensor of shape ('N',), got list"),
        (torch.zeros(2, 3), ["B", "C", "H"], "x must have shape ('B', 'C', 'H') (3 dims), got (2, 3)"),
        (torch.zeros(2, 3, 4, 4), ["B", 1, "H", "W"], "x must have shape ('B', 1, 'H', 'W'), got (2, 3, 4, 4) (dim 1)"),
        (torch.zeros(1, 4, 5), ["B", "H", "H"], "x must have shape ('B', 'H', 'H'), got (1, 4, 5) (H differs)"),
    ])
    def test_bad_input_message(self, x, shape, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            check_shape(x, shape, "x")


class TestCheckImage:
    def test_valid_images_pass(self):
        check_image(torch.rand(2, 3, 4, 5), "blurry")
        check_image(torch.zeros(1, 1, 2, 2, dtype=torch.float64), "blurry")
        check_image(torch.full((1, 1, 2, 2), 2.0), "latent", unit_range=False)
        check_image(torch.zeros(1, 2, 2, 2), "flow", channels=(2,))
        check_image(torch.zeros(0, 3, 2, 2), "empty")  # no values: no range to check

    @pytest.mark.parametrize("x, message", [
        (torch.rand(3, 4, 5), "blurry must have shape ('B', 'C', 'H', 'W') (4 dims), got (3, 4, 5)"),
        (torch.zeros(1, 1, 2, 2, dtype=torch.uint8), "blurry must be a floating point tensor, got torch.uint8"),
        (torch.zeros(1, 2, 2, 2), "blurry must have C in (1, 3) channels, got 2"),
        (torch.tensor([[[[0.5, math.nan], [math.inf, 0.5]]]]), "blurry has 2 NaN or infinite values"),
        (torch.tensor([[[[-0.5, 1.0]]]]), "blurry must hold linear intensities in [0, 1], got values in [-0.5, 1]"),
        (torch.tensor([[[[0.0, 255.0]]]]), "got values in [0, 255]"),
    ])
    def test_bad_input_message(self, x, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            check_image(x, "blurry")


def test_check_finite():
    check_finite(torch.tensor([0.0, -1e30]), "t")
    check_finite(torch.tensor([1, 2]), "x")  # integers are always finite
    with pytest.raises(ValueError, match=r"^t has 3 NaN or infinite values$"):
        check_finite(torch.tensor([math.nan, 1.0, math.inf, -math.inf]), "t")


class TestCheckBatchVector:
    def test_scalars_broadcast_to_float64(self):
        out = check_batch_vector(2.5, 3, "exposure_start")
        assert out.dtype == torch.float64 and out.tolist() == [2.5, 2.5, 2.5]
        assert check_batch_vector(torch.tensor(4.0), 2, "t").tolist() == [4.0, 4.0]

    def test_vectors_and_lists_pass_through(self):
        assert check_batch_vector([1.0, 2.0], 2, "t").tolist() == [1.0, 2.0]
        v = torch.tensor([3.0, 4.0], dtype=torch.float64)
        assert torch.equal(check_batch_vector(v, 2, "t"), v)

    @pytest.mark.parametrize("x, message", [
        (torch.zeros(3), "exposure_end must have shape (2,) (one value per sample), got (3,)"),
        (torch.zeros(2, 1), "exposure_end must have shape (2,) (one value per sample), got (2, 1)"),
        (torch.tensor([0.0, math.nan]), "exposure_end has 1 NaN or infinite values"),
    ])
    def test_bad_input_message(self, x, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            check_batch_vector(x, 2, "exposure_end")


def test_check_exposure_names_the_first_bad_sample():
    check_exposure(torch.tensor([0.0, 10.0]), torch.tensor([5.0, 20.0]))
    with pytest.raises(ValueError, match=re.escape("sample 1 has start 10.0 us and end 10.0 us")):
        check_exposure(torch.tensor([0.0, 10.0, 30.0]), torch.tensor([5.0, 10.0, 20.0]))


def test_check_exposure_warns_when_times_look_like_seconds():
    # a 20 ms exposure given in seconds is 0.02 "us": no camera exposes so briefly, so the units are wrong
    with pytest.warns(UserWarning, match=r"shorter than 1 us \(the longest 0.02 us\).*microseconds"):
        check_exposure(torch.tensor([0.0, 0.04], dtype=torch.float64), torch.tensor([0.02, 0.06], dtype=torch.float64))
    events = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([0.01]), torch.tensor([1]), sensor_size=(2, 2))
    with pytest.warns(UserWarning, match="microseconds"):
        EventFrames(torch.full((1, 1, 2, 2), 0.5), events, torch.tensor([0.0]), torch.tensor([0.02]))


def test_check_exposure_is_quiet_for_microsecond_exposures():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_exposure(torch.tensor([0.0, 0.5]), torch.tensor([1.0, 20_000.0]))  # one exposure of 1 us is enough
        check_exposure(torch.empty(0), torch.empty(0))


class TestCheckSearchRange:
    def test_values(self):
        assert check_search_range(None) is None
        assert check_search_range((0, 20000)) == (0.0, 20000.0)
        assert check_search_range(torch.tensor([-5.0, 5.0])) == (-5.0, 5.0)

    @given(st.floats(-1e9, 1e9), st.floats(1e-3, 1e9))
    def test_any_finite_increasing_pair_is_returned_as_floats(self, low, width):
        high = low + width
        assert check_search_range([low, high]) == (low, high)

    @pytest.mark.parametrize("value, message", [
        (5.0, "search_range must be a pair (low, high) of numbers in us, got 5.0"),
        ((1, 2, 3), "search_range must be a pair (low, high) of numbers in us, got (1, 2, 3)"),
        (("a", 1), "search_range must be a pair (low, high) of numbers in us, got ('a', 1)"),
        ((math.nan, 1.0), "search_range must be two finite numbers (low, high) in us, got (nan, 1.0)"),
        ((0, math.inf), "search_range must be two finite numbers (low, high) in us, got (0, inf)"),
        ((5, 5), "search_range must be (low, high) with high > low, got (5, 5)"),
        ((10, 0), "search_range must be (low, high) with high > low, got (10, 0)"),
    ])
    def test_bad_input_message(self, value, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            check_search_range(value)

    def test_name_appears_in_the_message(self):
        with pytest.raises(ValueError, match=r"^--search-us must be"):
            check_search_range((1, 0), "--search-us")


class TestMemoryBudget:
    def test_default_is_read_at_call_time(self, monkeypatch):
        assert resolve_memory_budget() == 2 * 1024**3
        monkeypatch.setattr(checks, "MEMORY_BUDGET_BYTES", 12345)
        assert resolve_memory_budget() == 12345
        assert resolve_memory_budget(1.5e3) == 1500

    @pytest.mark.parametrize("budget", [0, -1, math.nan, math.inf, True, "1 GiB"])
    def test_bad_budget_message(self, budget):
        with pytest.raises(ValueError, match=re.escape(f"memory_budget must be a positive number of bytes, got "
                                                       f"{budget!r}")):
            resolve_memory_budget(budget)

    def test_check_memory_passes_at_the_budget(self):
        check_memory(2**30, "a grid", "use fewer bins", budget=2**30)

    @pytest.mark.parametrize("num_bytes, budget, needs, limit", [
        (3 * 2**30, 2**30, "3.0 GiB", "1.0 GiB"),
        (1536, 1000, "1.5 KiB", "1000 bytes"),
        (5 * 2**40, 12.5 * 2**20, "5.0 TiB", "12.5 MiB"),
    ])
    def test_over_the_budget_message(self, num_bytes, budget, needs, limit):
        message = (f"the event grid (1, 500, 8, 9) needs about {needs}, over the memory budget of {limit}: narrow "
                   "search_range (or raise the budget: memory_budget= or evlatcorr.checks.MEMORY_BUDGET_BYTES)")
        with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
            check_memory(num_bytes, "the event grid (1, 500, 8, 9)", "narrow search_range", budget=budget)

    def test_module_budget_applies_without_an_argument(self, monkeypatch):
        monkeypatch.setattr(checks, "MEMORY_BUDGET_BYTES", 100)
        check_memory(100, "x", "y")
        with pytest.raises(ValueError, match="over the memory budget of 100 bytes"):
            check_memory(101, "x", "y")


@pytest.mark.parametrize("size, ok", [((4, 4), True), ((2, 3, 4, 5), True), ((3, 100), False), ((100, 0), False)])
def test_check_search_size(size, ok):
    if ok:
        check_search_size(size)  # (H, W) or a tensor's whole shape
    else:
        with pytest.raises(ValueError, match=rf"blurry of {size[-2]}x{size[-1]} pixels .* at least 4x4"):
            check_search_size(size, "blurry")


def test_check_has_events_names_the_empty_sample_and_its_window():
    # exposures [0, 100) and [1000, 1100) us: the windows searched are [0, 200) and [1000, 1200)
    t = torch.tensor([50.0, 150.0, 1250.0], dtype=torch.float64)
    ev = Events(torch.zeros(3), torch.zeros(3), t, torch.ones(3), torch.tensor([0, 0, 1]), sensor_size=(2, 2))
    frames = EventFrames(torch.rand(2, 1, 2, 2), ev, torch.tensor([0.0, 1000.0]), torch.tensor([100.0, 1100.0]))
    with pytest.raises(ValueError, match=re.escape("sample 1 has no events in its exposure and search window "
                                                   "[1000, 1200) us: latency cannot be estimated without events; "
                                                   "its 1 event lies in [1250, 1250] us (events and frames must "
                                                   "share one clock, in microseconds)")):
        check_has_events(frames)
    empty = frames.replace(events=Events(ev.x[:2], ev.y[:2], t[:2], ev.p[:2], ev.batch[:2], sensor_size=(2, 2),
                                         batch_size=2))
    with pytest.raises(ValueError, match=r"without events$"):  # none at all: nothing more to say
        check_has_events(empty)
    check_has_events(frames.replace(events=Events(ev.x, ev.y, torch.tensor([50.0, 150.0, 1199.0]), ev.p, ev.batch,
                                                  sensor_size=(2, 2))))


def test_check_has_events_says_when_the_times_look_like_other_units():
    # the same exposures given in seconds: the window is shown as it is, not as [0, 0), and the units named
    ev = Events(torch.zeros(3), torch.zeros(3), torch.tensor([50.0, 150.0, 1250.0], dtype=torch.float64),
                torch.ones(3), torch.tensor([0, 0, 1]), sensor_size=(2, 2))
    with pytest.warns(UserWarning, match="shorter than 1 us"):
        frames = EventFrames(torch.rand(2, 1, 2, 2), ev, torch.tensor([0.0, 1e-3]), torch.tensor([1e-4, 1.1e-3]))
    with pytest.raises(ValueError, match=re.escape("sample 0 has no events in its exposure and search window [0, "
                                                   "0.0002) us (the exposure is 0.0001 us long: evlatcorr takes "
                                                   "times in microseconds)")):
        check_has_events(frames)


def test_check_threshold_broadcasts_and_refuses_non_positive():
    assert check_threshold(0.2, 3).tolist() == pytest.approx([0.2, 0.2, 0.2])
    theta = torch.tensor([0.1, 0.3])
    assert check_threshold(theta, 2) is theta
    with pytest.raises(ValueError, match="threshold must be positive, got -0.1"):
        check_threshold(torch.tensor([0.2, -0.1], dtype=torch.float64), 2)
    with pytest.raises(ValueError, match="threshold has 1 NaN"):
        check_threshold(float("nan"), 1)
    with pytest.raises(ValueError, match="one value per sample"):
        check_threshold(torch.ones(3), 2)


@pytest.mark.parametrize(("value", "minimum", "match"), [
    (0, 1, "n must be a positive integer, got 0"),
    (2.0, 1, "n must be a positive integer, got 2.0"),
    (False, 0, "n must be an integer >= 0, got False"),
    (1, 2, "n must be an integer >= 2, got 1"),
])
def test_check_int_refuses(value, minimum, match):
    with pytest.raises(ValueError, match=re.escape(match)):
        check_int(value, "n", minimum)


def test_check_int_accepts():
    assert check_int(0, "n", minimum=0) == 0
    assert check_int(7, "n") == 7
