from __future__ import annotations

import math

import pytest
import torch

import evlatcorr.search_batched
from evlatcorr import Events
from evlatcorr.config import SearchConfig
from evlatcorr.search import search_constant_latency
from evlatcorr.search_batched import frames_can_share_a_pass
from evlatcorr.search_candidates import _Window
from evlatcorr.simulate import simulate

EXPOSURE = 10_000.0


@pytest.fixture
def together_on_cpu(monkeypatch):
    monkeypatch.setattr(evlatcorr.search_batched, "ON_CPU", True)


def recording(num_frames: int = 4, seed: int = 0):
    """Frames of one simulated recording (32x40, 10 ms exposures, 2 ms latency)."""
    return simulate("camera", num_frames=num_frames, height=32, width=40, exposure_us=EXPOSURE,
                    frame_interval_us=12_500.0, latency="constant", latency_us=2000.0, seed=seed).frames("delayed")


def with_events(frames, events: Events):
    return frames.replace(events=events)


def events_changed(events: Events, keep: torch.Tensor | None = None, extra: tuple | None = None) -> Events:
    """``events`` with only ``keep`` (a mask) and ``extra`` events ``(x, y, t, p, batch)`` added, sorted."""
    keep = torch.ones(len(events), dtype=torch.bool) if keep is None else keep
    x, y, t, p, b = events.x[keep], events.y[keep], events.t[keep], events.p[keep], events.batch[keep]
    if extra is not None:
        x, y, t, p, b = (torch.cat([a, torch.as_tensor(e).to(a)]) for a, e in zip((x, y, t, p, b), extra))
    return Events(x, y, t, p, b, sensor_size=events.sensor_size, batch_size=events.batch_size, sort=True)


def assert_as_frame_by_frame(frames, previous=None, **settings):
    together = search_constant_latency(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                                       previous_latency=previous, **settings)
    for i in range(frames.batch_size):
        one = search_constant_latency(frames.blurry[i:i + 1], frames.events.sample(i), frames.exposure_start[i:i + 1],
                                      frames.exposure_end[i:i + 1],
                                      previous_latency=None if previous is None else previous[i:i + 1], **settings)
        # float32 tables summed in another order: the curves agree to float32 rounding, the estimates to a few ns
        assert together.latency[i].item() == pytest.approx(one.latency.item(), abs=0.05)
        assert together.source[i] == one.source[0]
        assert together.fallback[i] == one.fallback[0]
        assert together.ignored_pixels[i] == one.ignored_pixels[0]
        torch.testing.assert_close(together.candidates[i], one.candidates[0])
        torch.testing.assert_close(together.etf[i], one.etf[0], rtol=1e-5, atol=1e-6, equal_nan=True)
        torch.testing.assert_close(together.confidence[i], one.confidence[0], rtol=1e-4, atol=1e-6)
        torch.testing.assert_close(together.latency_spread[i], one.latency_spread[0], rtol=1e-3, atol=0.5,
                                   equal_nan=True)
        if one.log_probability is None:
            assert together.log_probability is None or torch.isnan(together.log_probability[i]).all()
        else:
            torch.testing.assert_close(together.log_probability[i], one.log_probability[0], rtol=1e-3, atol=1e-3)
        if one.log_ratio is None:
            assert together.log_ratio is None
        elif together.log_ratio is not None:  # None where another frame had no window to score, as frame by frame
            torch.testing.assert_close(together.log_ratio[i:i + 1], one.log_ratio, rtol=1e-4, atol=1e-4)
    return together


def test_frames_searched_together_give_each_frame_its_own_result(together_on_cpu):
    frames = recording()
    assert_as_frame_by_frame(frames)
    assert_as_frame_by_frame(frames, previous=torch.tensor([1500.0, 2500.0, 0.0, 9000.0]))
    # a range that bounds the answers: read over 0 to the exposure time all the same
    bounded = assert_as_frame_by_frame(frames, search_range=(500.0, 1500.0))
    assert float(bounded.candidates[0, -1]) == EXPOSURE and bool(((bounded.latency >= 500.0)
                                                                  & (bounded.latency <= 1500.0)).all())


def test_frames_together_with_a_hot_pixel_and_events_that_stop_early(together_on_cpu):
    frames = recording()
    ev, end = frames.events, frames.exposure_end
    # frame 3's events stop 3 ms after its exposure: fewer of its candidates can be scored than the others'
    keep = (ev.batch != 3) | (ev.t <= end[3].item() + 3000.0)
    # frame 1 gets a hot pixel: 300 ON events at (5, 7) over its exposure
    start1 = frames.exposure_start[1].item()
    hot = (torch.full((300,), 7), torch.full((300,), 5), torch.linspace(start1, start1 + EXPOSURE, 300),
           torch.ones(300), torch.ones(300, dtype=torch.long))
    together = assert_as_frame_by_frame(with_events(frames, events_changed(ev, keep, hot)))
    assert together.ignored_pixels == [0, 1, 0, 0]
    assert torch.isinf(together.etf[3]).sum() > torch.isinf(together.etf[0]).sum()


def test_a_frame_with_nothing_to_score_among_others(together_on_cpu):
    frames = recording(3)
    ev = frames.events
    keep = (ev.batch != 1) | (ev.t <= frames.exposure_end[1].item())  # frame 1: no events past its exposure
    together = assert_as_frame_by_frame(with_events(frames, events_changed(ev, keep)))
    assert together.source[1] == "fallback" and together.log_ratio is None


def test_passes_sized_to_the_memory_budget_give_the_same_results(together_on_cpu, monkeypatch):
    frames = recording(5)
    whole = search_constant_latency(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end)
    passes = []
    original = evlatcorr.search_batched._search_pass
    monkeypatch.setattr(evlatcorr.search_batched, "_search_pass",
                        lambda *a: passes.append(a[8] - a[7]) or original(*a))  # frames last − first
    split = search_constant_latency(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                                    memory_budget=2 * 40 * 32 * 24 * 101 + 2 * 120 * 10**3)
    assert len(passes) > 1 and sum(passes) == 5
    torch.testing.assert_close(split.latency, whole.latency, rtol=0, atol=0.05)
    torch.testing.assert_close(split.log_ratio, whole.log_ratio, rtol=1e-4, atol=1e-4)


def test_which_frames_share_a_pass(together_on_cpu):
    grey = torch.rand(3, 1, 4, 4)
    spans = [_Window(s, s + 100.0, 0.0, 100.0, 50.0) for s in (0.0, 200.0, 400.0)]
    learned = SearchConfig()
    assert frames_can_share_a_pass(grey, spans, [0.2] * 3, learned, "continuous")
    assert not frames_can_share_a_pass(grey[:1], spans[:1], [0.2], learned, "continuous")
    assert not frames_can_share_a_pass(grey, spans, [0.2, 0.2, 0.3], learned, "continuous")
    assert not frames_can_share_a_pass(grey, spans, [0.2] * 3, learned, "binned")
    assert not frames_can_share_a_pass(grey, spans, [0.2] * 3, SearchConfig(score="consensus"), "continuous")
    other_exposure = spans[:2] + [_Window(400.0, 450.0, 0.0, 50.0, 50.0)]
    assert not frames_can_share_a_pass(grey, other_exposure, [0.2] * 3, learned, "continuous")


def test_a_cpu_searches_frame_by_frame_unless_asked(monkeypatch):
    monkeypatch.setattr(evlatcorr.search_batched, "ON_CPU", False)
    spans = [_Window(s, s + 100.0, 0.0, 100.0, 50.0) for s in (0.0, 200.0)]
    assert not frames_can_share_a_pass(torch.rand(2, 1, 4, 4), spans, [0.2] * 2, SearchConfig(), "continuous")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU: the frames share a pass there by default")
def test_frames_together_on_cuda():
    frames = recording().to(torch.device("cuda"))
    assert frames_can_share_a_pass(frames.blurry, [_Window(0.0, EXPOSURE, 0.0, EXPOSURE, math.inf)] * 2, [0.2] * 2,
                                   SearchConfig(), "continuous")
    together = assert_as_frame_by_frame(frames)
    assert together.latency.device.type == "cuda"
    from evlatcorr.temporal import StreamingLatencyCorrector

    streamed = StreamingLatencyCorrector()(frames)
    one_by_one = StreamingLatencyCorrector()
    for k, frame in enumerate(frames.split()):
        assert float(streamed.latency[k].mean()) == pytest.approx(float(one_by_one(frame).latency.mean()), abs=0.05)


def test_a_stream_of_frames_searched_together_fuses_them_as_frame_by_frame(together_on_cpu):
    from evlatcorr import EventLatencyCorrector
    from evlatcorr.temporal import StreamingLatencyCorrector

    frames = recording()
    one_by_one = StreamingLatencyCorrector(EventLatencyCorrector())
    outs = [one_by_one(frame) for frame in frames.split()]
    together = StreamingLatencyCorrector(EventLatencyCorrector())(frames)
    for k, out in enumerate(outs):
        assert float(together.latency[k].mean()) == pytest.approx(float(out.latency.mean()), abs=0.05)
        assert float(together.meta["frame_latency_us"][k]) == pytest.approx(float(out.meta["frame_latency_us"][0]),
                                                                           abs=0.05)
        torch.testing.assert_close(together.latent[k:k + 1], out.latent, rtol=1e-4, atol=1e-4)
    assert "latency_history" not in together.meta
