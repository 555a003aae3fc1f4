from __future__ import annotations

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

import evlatcorr.checks
import evlatcorr.search_candidates
import evlatcorr.search_learned
import evlatcorr.sharpness
from evlatcorr.continuous import ContinuousIntegral
from evlatcorr.edi import edi_deblur
from evlatcorr.search import search_constant_latency, sharpness_score
from tests.conftest import random_events, textured_frames

START, END = torch.tensor([0.0]), torch.tensor([100.0])


def grey_frame(seed: int, size: tuple[int, int] = (8, 9)) -> torch.Tensor:
    """A seeded grey frame in [0.1, 0.9] with structure (unseeded ones made these tests depend on the process)."""
    return textured_frames(1, 1, *size, seed=seed)


@pytest.mark.parametrize("score", ["etf", "sparsity"])
@pytest.mark.parametrize("method, naive_bins, tolerance", [("binned", 50, 1e-5), ("continuous", 20_000, 1e-3)])
def test_one_pass_equals_naive_edi_per_candidate(score, method, naive_bins, tolerance):
    # the binned table must give exactly the score of re-running the 50-bin EDI at each candidate; the
    # continuous integral, the score of an EDI with so many bins that it is continuous in all but name
    ev = random_events(3000, (8, 9), (0.0, 220.0), seed=5)
    blurry = grey_frame(5)
    res = search_constant_latency(blurry, ev, START, END, 0.2, num_bins=50, num_candidates=11, refine=False,
                                  score=score, method=method)
    assert res.candidates.shape == (1, 11) and res.etf.shape == (1, 11)
    naive = torch.cat([
        sharpness_score(edi_deblur(blurry, ev.shift(float(l)), START, END, 0.2, num_bins=naive_bins),
                        l.view(1).float(), None, score, 20.0, 7, 1000.0)
        for l in res.candidates[0]
    ])
    torch.testing.assert_close(res.etf[0].float(), naive, rtol=tolerance, atol=tolerance)
    assert torch.argmin(res.etf[0]) == torch.argmin(naive)
    assert res.candidates[0, 0].item() == 0.0 and res.candidates[0, -1].item() == pytest.approx(100.0)


def test_refined_latency_is_argmin_neighbourhood():
    ev = random_events(3000, (8, 9), (0.0, 220.0), seed=6)
    blurry = grey_frame(6)
    res = search_constant_latency(blurry, ev, START, END, 0.2, num_bins=50, num_candidates=11, score="sparsity")
    coarse_best = float(res.candidates[0, torch.argmin(res.etf[0])])
    assert abs(res.latency.item() - coarse_best) <= 10.0 + 1.0  # within one candidate spacing (+1 sub-interval)
    fine_best = float(res.fine_candidates[0][torch.argmin(res.fine_etf[0])])
    assert res.latency.item() == fine_best  # the best fine candidate itself


def test_search_range_and_batch():
    ev = random_events(4000, (6, 6), (0.0, 400.0), batch_size=2, seed=9)
    res = search_constant_latency(textured_frames(2, 3, 6, 6), ev, torch.zeros(2), torch.full((2,), 100.0),
                                  num_bins=20, search_range=(-50.0, 150.0), num_candidates=5)
    assert res.latency.shape == (2,)
    assert res.candidates[0, 0].item() == pytest.approx(-50.0)
    assert ((res.latency >= -55.0) & (res.latency <= 155.0)).all()


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(num_candidates=1), "num_candidates"),
        (dict(num_bins=1), "num_bins"),
        (dict(search_range=(10.0, 5.0)), "search_range"),
        (dict(search_range=(0.0, math.inf)), "search_range must be two finite numbers"),
        (dict(search_range=(-math.inf, 0.0)), "search_range must be two finite numbers"),
        (dict(search_range=(math.nan, 10.0)), "search_range must be two finite numbers"),
        (dict(search_range=(5.0,)), "search_range must be a pair"),
        (dict(search_range=(0.0, 1e300)), "narrow search_range"),
        (dict(threshold=0.0), "threshold"),
        (dict(memory_budget=0), "memory_budget"),
    ],
)
def test_exceptions(kwargs, match):
    ev = random_events(100, (4, 4), (0.0, 200.0))
    with pytest.raises(ValueError, match=match):
        search_constant_latency(textured_frames(1, 1, 4, 4), ev, START, END, **kwargs)


def test_device(device):
    ev = random_events(500, (4, 4), (0.0, 200.0)).to(device)
    res = search_constant_latency(textured_frames(1, 1, 4, 4).to(device), ev, START, END, num_bins=20,
                                  num_candidates=5)
    assert res.latency.device.type == device.type


@pytest.mark.parametrize("score", ["etf", "sparsity"])
def test_never_scores_a_window_past_the_last_event(score):
    # events stop 30 us after the exposure end: no candidate above 30 us may be scored or returned
    ev = random_events(3000, (8, 9), (0.0, END.item() + 30.0), seed=11)
    blurry = grey_frame(11)
    res = search_constant_latency(blurry, ev, START, END, 0.2, num_bins=50, num_candidates=11, score=score)
    last = ev.t.max().item() - END.item()
    scored = res.candidates[0][torch.isfinite(res.etf[0])]
    assert scored.max().item() <= last + 2.0  # the last event's sub-interval (2 us) is read whole
    assert torch.isinf(res.etf[0][res.candidates[0] > last + 2.0]).all()
    assert res.latency.item() <= last + 2.0


def test_no_events_past_the_exposure_falls_back_to_previous_or_zero():
    ev = random_events(500, (4, 4), (0.0, 90.0), seed=12)  # nothing after the exposure end
    blurry = textured_frames(1, 1, 4, 4)
    res = search_constant_latency(blurry, ev, START, END, num_bins=20, num_candidates=5)
    assert res.fallback.tolist() == [True] and res.confidence.tolist() == [0.0]
    assert res.latency.item() == 0.0
    res = search_constant_latency(blurry, ev, START, END, num_bins=20, num_candidates=5,
                                  previous_latency=torch.tensor([40.0]))
    assert res.latency.item() == 40.0


def test_sparsity_score_ignores_brightness_scale():
    image = torch.rand(3, 1, 16, 16) * 0.5 + 0.1
    lat = torch.zeros(3)
    a = sharpness_score(image, lat, None, "sparsity", 20.0, 7, 1000.0)
    b = sharpness_score(image * 1.7, lat, None, "sparsity", 20.0, 7, 1000.0)
    torch.testing.assert_close(a, b, rtol=1e-5, atol=0.0)  # log(I / mean(I) + c): a scale cancels
    with pytest.raises(ValueError, match="score"):
        sharpness_score(image, lat, None, "psnr", 20.0, 7, 1000.0)


def test_consensus_is_the_median_of_the_three_sparsity_estimates():
    ev = random_events(3000, (8, 9), (0.0, 220.0), seed=13)
    blurry = grey_frame(13)
    run = lambda score: search_constant_latency(blurry, ev, START, END, 0.2, num_bins=50, num_candidates=11,  # noqa: E731
                                                refine=False, score=score)
    members = sorted(run(s).latency.item() for s in ("sparsity", "sparsity_bright", "sparsity_multiscale"))
    assert run("consensus").latency.item() == members[1]
    with pytest.raises(ValueError, match="score"):
        run("psnr")


# --- the search range is respected, whatever its width -----------------------------------------------------
# exposure 20 ms in 50 sub-intervals of 400 us: candidates are multiples of 400 us
LONG_END = torch.tensor([20000.0])


@pytest.fixture(scope="module")
def long_exposure():
    return random_events(4000, (8, 9), (0.0, 60000.0), seed=21), grey_frame(21)


def test_latency_is_clamped_into_a_range_that_does_not_start_on_a_candidate(long_exposure):
    # binned: candidates 4000, 4400, ...: the best one, 4000 us, lies below the range (returned before clamping)
    ev, blurry = long_exposure
    res = search_constant_latency(blurry, ev, START, LONG_END, num_bins=50, search_range=(4300.0, 5800.0),
                                  num_candidates=11, method="binned", score="consensus")
    assert res.candidates[0, 0].item() == 4000.0
    assert res.fallback.tolist() == [False]
    assert res.latency.item() == 4300.0


def test_continuous_candidates_span_the_range_exactly(long_exposure):
    # continuous: the first and last candidates are the range's ends, spaced by a whole fraction of
    # half the exposure (10 ms / 67 = 149.25 us <= 1500 us / 10)
    ev, blurry = long_exposure
    res = search_constant_latency(blurry, ev, START, LONG_END, num_bins=50, search_range=(4300.0, 5800.0),
                                  num_candidates=11, score="sparsity")  # the learned reader reads 0 to the exposure
    candidates = res.candidates[0]
    assert candidates[0].item() == 4300.0 and candidates[-1].item() == 5800.0
    torch.testing.assert_close(torch.diff(candidates)[:-1], torch.full((len(candidates) - 2,), 10000.0 / 67),
                               rtol=0, atol=1e-4, check_dtype=False)
    assert 4300.0 <= res.latency.item() <= 5800.0


@pytest.mark.parametrize("search_range", [(100.0, 101.0), (0.0, 1.0), (399.5, 400.5)])
def test_range_narrower_than_a_candidate_step(long_exposure, search_range):
    ev, blurry = long_exposure
    res = search_constant_latency(blurry, ev, START, LONG_END, num_bins=50, search_range=search_range)
    assert search_range[0] <= res.latency.item() <= search_range[1]


@settings(max_examples=25, deadline=None)
@given(low=st.floats(0.0, 20000.0), width=st.floats(0.5, 20000.0),
       score=st.sampled_from(["sparsity", "etf", "learned"]))
def test_property_latency_lies_in_the_search_range(long_exposure, low, width, score):
    ev, blurry = long_exposure
    high = low + width
    res = search_constant_latency(blurry, ev, START, LONG_END, num_bins=50, search_range=(low, high),
                                  num_candidates=11, score=score)
    assert low <= res.latency.item() <= high


# --- memory: estimated before allocating; streamed in strips or refused --------------------------------------
@pytest.mark.parametrize("integral, score", [("step", "consensus"), ("linear", "etf")])
def test_table_over_the_budget_is_streamed_with_the_same_result(long_exposure, integral, score):
    # the table (50 + 50 sub-intervals: 102 grid points x 72 pixels x 20 bytes = 147 kB) is over a 100 kB
    # budget: it is rebuilt a row (59 kB while built) at a time for every batch of candidates, with the same numbers
    ev, blurry = long_exposure
    kw = dict(num_bins=50, search_range=(0.0, 20000.0), num_candidates=11, integral=integral, score=score,
              method="binned")
    whole = search_constant_latency(blurry, ev, START, LONG_END, **kw)
    strips = search_constant_latency(blurry, ev, START, LONG_END, memory_budget=100_000, **kw)
    assert torch.equal(whole.latency, strips.latency)
    assert torch.equal(whole.etf, strips.etf)
    assert all(torch.equal(a, b) for a, b in zip(whole.fine_etf, strips.fine_etf))


def test_continuous_integral_reads_fewer_candidates_at_once_when_they_do_not_fit(long_exposure, monkeypatch):
    # 4000 events keep 160 kB; a 163 456-byte cap per read leaves room for 3 candidates (72 px x 16 bytes each:
    # the ratio, the latent and, for the default learned score, the event change and the peak rise)
    ev, blurry = long_exposure
    kw = dict(num_bins=50, search_range=(0.0, 20000.0), num_candidates=11)
    whole = search_constant_latency(blurry, ev, START, LONG_END, **kw)
    monkeypatch.setattr(evlatcorr.search_candidates, "_CONTINUOUS_READ_BYTES", 163_456)
    calls = []
    original = ContinuousIntegral.inverse_ratio
    monkeypatch.setattr(ContinuousIntegral, "inverse_ratio",
                        lambda self, *a, **k: calls.append(len(a[2])) or original(self, *a, **k))
    chunked = search_constant_latency(blurry, ev, START, LONG_END, **kw)
    assert max(calls) == 3
    # the reads sum their float32 tables over other times: the same scores to float32 rounding
    torch.testing.assert_close(whole.etf, chunked.etf, rtol=1e-6, atol=0)
    # the learned reader's estimate is a probability-weighted mean of candidates: that rounding moves it by ns
    assert chunked.latency.item() == pytest.approx(whole.latency.item(), abs=0.01)


def test_table_whose_row_is_over_the_budget_is_refused_before_allocating(monkeypatch):
    # events over 1e9 us and a range to 1e9 us: 25 million sub-intervals of 40 us, 2 GB per row of 4 pixels
    ev = random_events(2000, (4, 4), (0.0, 1e9), seed=3)
    with pytest.raises(ValueError, match="latency search table .* over the memory budget of 2.0 GiB: .*narrow "
                                         "search_range"):
        search_constant_latency(grey_frame(3, (4, 4)), ev, START, torch.tensor([20000.0]), search_range=(0.0, 1e9),
                                method="binned")
    # the continuous integral reads only the candidates' windows: the same range is searched in a few MB
    res = search_constant_latency(grey_frame(3, (4, 4)), ev, START, torch.tensor([20000.0]), search_range=(0.0, 1e9))
    assert 0.0 <= res.latency.item() <= 1e9
    # the budget is the module constant, read at call time
    monkeypatch.setattr(evlatcorr.checks, "MEMORY_BUDGET_BYTES", 1000)
    for method in ("binned", "continuous"):
        with pytest.raises(ValueError, match="over the memory budget of 1000 bytes"):
            search_constant_latency(grey_frame(3, (4, 4)), ev, START, END, num_bins=20, num_candidates=5,
                                    method=method)


@pytest.mark.parametrize("score", ["learned", "consensus"])
def test_scores_are_the_same_whatever_the_candidates_scored_at_once(score, monkeypatch):
    # a CPU scores 16 candidates at a time (cache), a GPU all of them (kernel launches): the same scores
    ev = random_events(6000, (12, 14), (0.0, 260.0), seed=5)
    blurry = grey_frame(5, (12, 14))
    kw = dict(num_bins=50, num_candidates=40, score=score)
    chunked = search_constant_latency(blurry, ev, START, END, **kw)
    for module in (evlatcorr.search_candidates, evlatcorr.search_learned):  # the scores and the ghost moments
        monkeypatch.setattr(module, "_score_chunk", lambda image: 1000)
    at_once = search_constant_latency(blurry, ev, START, END, **kw)
    torch.testing.assert_close(at_once.etf, chunked.etf, rtol=1e-6, atol=0)
    # the learned reader's estimate weighs candidates by float32 scores' probabilities: equal to rounding
    assert at_once.latency.item() == pytest.approx(chunked.latency.item(), abs=0.01)


@pytest.mark.parametrize("shape", [(5, 1, 20, 24), (3, 1, 1, 7), (3, 1, 6, 1), (2, 1, 1, 1), (2, 1, 2, 2)])
def test_padded_gradient_sparsity_equals_the_piecewise_one(shape, device):
    # a GPU takes the padded form (fewer kernel launches), a CPU the piecewise one (no image-sized copies)
    image = torch.rand(*shape, generator=torch.Generator().manual_seed(9)).log()
    want = evlatcorr.sharpness._gradient_sparsity(image)
    torch.testing.assert_close(evlatcorr.sharpness._padded_gradient_sparsity(image), want, rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(evlatcorr.sharpness._gradient_sparsity(image.to(device)).cpu(), want, rtol=1e-5,
                               atol=1e-7)


@pytest.mark.parametrize("shape", [(3, 1, 7, 9), (2, 1, 8, 8), (2, 1, 2, 3), (16, 1, 26, 34)])
def test_mean_pool_equals_avg_pool2d(shape):
    image = torch.randn(*shape, generator=torch.Generator().manual_seed(7))
    torch.testing.assert_close(evlatcorr.sharpness._mean_pool(image, 2), torch.nn.functional.avg_pool2d(image, 2),
                               rtol=1e-6, atol=1e-6)


def test_mean_pool_of_one_row_fails_as_avg_pool2d_does():
    with pytest.raises(RuntimeError, match="too small"):
        evlatcorr.sharpness._mean_pool(torch.randn(1, 1, 1, 5), 2)


def test_the_fallback_warning_of_both_modes_names_its_kind_and_refuses_another():
    from evlatcorr.search import fallback_warning

    warning = fallback_warning("clipped", [3], "{its} latency is the fallback 0 us")
    assert warning.kind == "clipped" and warning.samples == (3,)
    assert str(warning) == ("sample 3: black or saturated in nearly every pixel (fewer than 0.5% inside the sensor's "
                            "range): nothing for EDI to sharpen; its latency is the fallback 0 us")
    flat = fallback_warning("flat", [0, 2], "{its} latency is the fallback 0 us")
    assert flat.kind == "flat" and str(flat).startswith("samples [0, 2]: flat: no structure above its pixel noise")
    assert str(flat).endswith("nothing for EDI to sharpen; their latency is the fallback 0 us")
    with pytest.raises(ValueError, match="kind must be 'clipped', 'flat' or 'fallback', got 'hot_pixels'"):
        fallback_warning("hot_pixels", [0], "")
