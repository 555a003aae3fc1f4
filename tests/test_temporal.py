import math
import warnings

import pytest
import torch

from evlatcorr.curve_reader import probability_centre
from evlatcorr.edi import edi_deblur
from evlatcorr.search import search_constant_latency
from evlatcorr.temporal import (
    DEFAULT_NO_LATENCY_MASS,
    DEFAULT_PAIR_REFINE,
    PAIR_REFINE_HALF_WIDTH,
    frame_evidence,
    fuse_latencies,
    no_latency_share,
)
from tests.conftest import random_events, textured_frames

CANDIDATES = torch.arange(0.0, 2000.0, 100.0, dtype=torch.float64)


def belief(mean: float, sigma: float, candidates: torch.Tensor = CANDIDATES) -> torch.Tensor:
    """A frame's log-probability over the candidates: a Gaussian around ``mean``."""
    return torch.log_softmax(-((candidates - mean) / sigma) ** 2, 0)


def test_no_window_gives_each_frames_own_centre():
    log_p = torch.stack([belief(430.0, 150.0), belief(1210.0, 300.0)])
    fused = fuse_latencies(torch.tensor([0.0, 0.0]), CANDIDATES, log_p, before=0, after=0)
    expected = [probability_centre(row, CANDIDATES, len(CANDIDATES))[1] for row in log_p]
    torch.testing.assert_close(fused, torch.tensor(expected, dtype=torch.float64), rtol=0, atol=1e-9)


def test_no_latency_share_is_the_probability_of_the_candidates_whose_centre_reaches_zero():
    log_p = torch.log(torch.tensor([0.2, 0.1, 0.1, 0.5, 0.1]))
    assert no_latency_share(log_p, torch.arange(5.0)) == pytest.approx(0.4)  # 0 and the two candidates above it
    assert no_latency_share(log_p, torch.arange(1.0, 6.0)) == 0.0  # candidates that do not start at no latency
    unscored = torch.tensor([0.0, -math.inf, math.nan, 0.0, 0.0])
    assert no_latency_share(unscored, torch.arange(5.0)) == pytest.approx(1 / 3)
    with pytest.raises(ValueError, match="1-D of one length"):
        no_latency_share(log_p, torch.arange(4.0))
    for bad in (torch.full((5,), -math.inf), torch.tensor([0.0, math.inf, 0.0, 0.0, 0.0])):
        with pytest.raises(ValueError, match="needs finite log-probabilities"):
            no_latency_share(bad, torch.arange(5.0))


def test_fused_frames_that_keep_no_latency_likely_get_none():
    # three frames unsure between no latency and a little: their fused probability keeps a share near 0
    log_p = torch.stack([belief(150.0, 300.0), belief(300.0, 400.0), belief(200.0, 300.0)])
    own = torch.tensor([150.0, 300.0, 200.0])
    share = no_latency_share(log_p.sum(0), CANDIDATES)
    assert DEFAULT_NO_LATENCY_MASS < share < 0.99
    without = fuse_latencies(own, CANDIDATES, log_p, before=1, after=1, no_latency_mass=None)
    assert bool((without > 0).all())
    torch.testing.assert_close(fuse_latencies(own, CANDIDATES, log_p, 1, 1), torch.zeros(3, dtype=torch.float64))
    assert bool((fuse_latencies(own, CANDIDATES, log_p, 1, 1, no_latency_mass=share + 0.01) > 0).all())
    # one frame's evidence alone (no window, or a stream's first frame) never decides it
    torch.testing.assert_close(fuse_latencies(own, CANDIDATES, log_p, 0, 0),
                               fuse_latencies(own, CANDIDATES, log_p, 0, 0, no_latency_mass=None))
    stream = fuse_latencies(own, CANDIDATES, log_p, 1, 0)
    assert float(stream[0]) > 0.0 and float(stream[1]) == float(stream[2]) == 0.0
    # frames sure of a latency well above 0 keep their fused centre
    sure = torch.stack([belief(1200.0, 150.0)] * 3)
    torch.testing.assert_close(fuse_latencies(own, CANDIDATES, sure, 1, 1),
                               fuse_latencies(own, CANDIDATES, sure, 1, 1, no_latency_mass=None))
    for bad in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="no_latency_mass"):
            fuse_latencies(own, CANDIDATES, log_p, 1, 1, no_latency_mass=bad)


def test_an_unsure_frame_off_on_its_own_follows_its_confident_neighbours():
    log_p = torch.stack([belief(400.0, 150.0), belief(1500.0, 1000.0), belief(400.0, 150.0)])
    own = torch.tensor([400.0, 1500.0, 400.0])
    fused = fuse_latencies(own, CANDIDATES, log_p, before=1, after=1)
    assert float((fused - 400.0).abs().max()) < 50.0
    # a stream (no later frames): the first frame has only itself, the middle one its confident predecessor
    stream = fuse_latencies(own, CANDIDATES, log_p, before=1, after=0)
    assert float(stream[0]) == pytest.approx(probability_centre(log_p[0], CANDIDATES, 20)[1])
    assert abs(float(stream[1]) - 400.0) < 100.0


def test_a_later_frame_never_changes_a_streamed_estimate():
    log_p = torch.stack([belief(400.0, 300.0), belief(600.0, 300.0), belief(800.0, 300.0)])
    first = fuse_latencies(torch.zeros(3), CANDIDATES, log_p, before=2, after=0)
    log_p[2] = belief(1900.0, 100.0)
    second = fuse_latencies(torch.zeros(3), CANDIDATES, log_p, before=2, after=0)
    torch.testing.assert_close(first[:2], second[:2], rtol=0, atol=0)
    assert float(second[2]) > float(first[2])


def test_the_fused_latency_never_needs_events_past_the_frames_last_one():
    # frame 1's events stop early: only its first 6 candidates could be scored; its neighbours are sure of 1500 us
    log_p = torch.stack([belief(1500.0, 100.0), belief(300.0, 2000.0), belief(1500.0, 100.0)])
    log_p[1, 6:] = -math.inf
    log_p[1, :6] = torch.log_softmax(log_p[1, :6], 0)
    fused = fuse_latencies(torch.tensor([1500.0, 300.0, 1500.0]), CANDIDATES, log_p, before=1, after=1)
    assert float(fused[1]) <= float(CANDIDATES[5])
    # and candidates another frame could not score say nothing against them: its neighbours still get 1500 us
    assert abs(float(fused[0]) - 1500.0) < 60.0 and abs(float(fused[2]) - 1500.0) < 60.0


def test_a_frame_without_evidence_takes_its_neighbours_latency():
    # the middle frame could score nothing (e.g. its events stop at its exposure's end): it fell back to no shift
    log_p = torch.stack([belief(400.0, 150.0), torch.full((20,), math.nan), belief(400.0, 150.0)])
    fused = fuse_latencies(torch.tensor([400.0, 0.0, 400.0]), CANDIDATES, log_p, before=1, after=1)
    assert abs(float(fused[1]) - 400.0) < 30.0
    rows = [belief(400.0, 150.0), None, belief(400.0, 150.0)]  # a list, as the command line gathers them
    torch.testing.assert_close(fuse_latencies(torch.tensor([400.0, 0.0, 400.0]), [CANDIDATES] * 3, rows, 1, 1), fused)
    # no frame of its window has evidence, or none is given at all: its own latency stays
    alone = fuse_latencies(torch.tensor([400.0, 0.0, 400.0]), CANDIDATES, log_p, before=0, after=0)
    assert float(alone[1]) == 0.0
    assert torch.equal(fuse_latencies(torch.tensor([1.0, 2.0]), CANDIDATES, None), torch.tensor([1.0, 2.0]).double())


def test_frames_with_other_candidates_are_interpolated():
    fine = torch.arange(0.0, 2000.0, 50.0, dtype=torch.float64)
    rows = [belief(700.0, 200.0), belief(700.0, 200.0, fine), belief(700.0, 200.0)]
    fused = fuse_latencies(torch.zeros(3), [CANDIDATES, fine, CANDIDATES], rows, before=1, after=1)
    assert float((fused - 700.0).abs().max()) < 30.0


@pytest.mark.parametrize(
    "latency, candidates, log_p, before, after, match",
    [
        (torch.zeros(2), CANDIDATES, torch.zeros(2, 20), -1, 0, "whole numbers"),
        (torch.zeros(2), CANDIDATES, torch.zeros(2, 20), 1, True, "whole numbers"),
        (torch.tensor([0.0, math.nan]), CANDIDATES, torch.zeros(2, 20), 1, 1, "finite"),
        (torch.zeros(2), CANDIDATES, torch.zeros(3, 20), 1, 1, "one row per frame"),
        (torch.zeros(2), CANDIDATES, torch.zeros(2, 19), 1, 1, "one length"),
        (torch.zeros(2), CANDIDATES, torch.zeros(20), 1, 1, r"\(N, K\)"),
    ],
)
def test_bad_arguments_are_refused(latency, candidates, log_p, before, after, match):
    with pytest.raises(ValueError, match=match):
        fuse_latencies(latency, candidates, log_p, before, after)


def test_the_search_gives_the_readers_log_probability_of_each_scored_candidate():
    ev = random_events(3000, (8, 9), (0.0, 200.0), seed=6)
    blurry = textured_frames(1, 1, 8, 9, seed=6)
    args = (blurry, ev, torch.zeros(1), torch.full((1,), 100.0), 0.2)
    res = search_constant_latency(*args, num_bins=50, num_candidates=11, score="learned")
    log_p = res.log_probability
    assert log_p.shape == res.candidates.shape and log_p.dtype == torch.float64
    scored = torch.isfinite(res.etf[0])
    assert torch.equal(torch.isfinite(log_p[0]), scored)  # −inf where a window runs past the last event
    assert float(torch.logsumexp(log_p[0, scored], 0)) == pytest.approx(0.0, abs=1e-9)
    # the frame's own evidence does not carry the temporal prior
    prior = search_constant_latency(*args, num_bins=50, num_candidates=11, score="learned",
                                    previous_latency=torch.tensor([0.0]))
    torch.testing.assert_close(prior.log_probability, log_p)
    assert search_constant_latency(*args, num_bins=50, num_candidates=11, score="consensus").log_probability is None


def test_the_streaming_corrector_fuses_each_frame_with_the_frames_before_it():
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.simulate import simulate
    from evlatcorr.temporal import StreamingLatencyCorrector

    seq = simulate("camera", num_frames=3, height=32, width=48, latency_us=3000.0, seed=0)
    frames = seq.frames("delayed")
    corrector = EventLatencyCorrector(threshold=0.2)
    alone = corrector(frames)
    stream = StreamingLatencyCorrector(corrector, before=2)
    outs = [stream(frame) for frame in frames.split()]
    own = torch.stack([o.meta["frame_latency_us"][0] for o in outs])
    # each frame's own estimate (float64), as the frame alone gives it (its latency map is float32)
    torch.testing.assert_close(own, alone.latency.flatten(1).mean(1).double(), rtol=0, atol=1e-3)
    # the first frame has nothing before it; the others take their predecessors' evidence
    fused = fuse_latencies(own, alone.meta["etf_curve"][0], alone.meta["latency_log_probability"], before=2, after=0)
    for k, out in enumerate(outs):
        assert float(out.latency.mean()) == pytest.approx(float(fused[k]), abs=1e-3)
        # the events and the latent image follow the fused latency
        assert torch.allclose(out.corrected.t.sort().values,
                              frames.split()[k].events.shift(fused[k:k + 1]).t.sort().values)
        assert out.latent.shape == frames.blurry[:1].shape and bool(torch.isfinite(out.latent).all())
        # read at the fused latency from the search's own integral: the continuous EDI there
        frame = frames.split()[k]
        want = edi_deblur(frame.blurry, frame.events, frame.exposure_start, frame.exposure_end, 0.2,
                          latency=fused[k:k + 1], integral="continuous")
        torch.testing.assert_close(out.latent, want, rtol=1e-5, atol=1e-6)
    # a batch of the three frames in one call gives the same, and reset() forgets the earlier frames
    stream.reset()
    batched = stream(frames)
    torch.testing.assert_close(batched.latency.flatten(1).mean(1).double(), fused, rtol=0, atol=1e-3)
    stream.reset()
    torch.testing.assert_close(stream(frames.split()[2]).latency, alone.latency[2:3], rtol=0, atol=1e-3)


def test_pairs_add_their_agreement_to_their_first_frame_alone_and_in_a_stream():
    # interpolation and REFID pass each frame with the next one: the corrector fuses the frame's evidence with their
    # agreement, and a stream with the earlier frames' too, as fuse_latencies(pair_log_odds=) does for a recording,
    # one call at a time or in one batch
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.pair_evidence import pair_log_odds
    from evlatcorr.simulate import simulate
    from evlatcorr.temporal import StreamingLatencyCorrector

    seq = simulate("camera", num_frames=4, height=32, width=48, latency_us=3000.0, seed=0)
    pairs = seq.pairs("delayed", after_us=20000.0)  # 3 pairs, events past the next exposure and the search
    each_alone = EventLatencyCorrector(threshold=0.2, pair_weight=0.0)
    own, candidates, log_p = _evidence(each_alone(pairs))
    agreement = [pair_log_odds(pair, 0.2, candidates[k]) for k, pair in enumerate(pairs.split())]
    assert all(a is not None for a in agreement)
    with_pair = EventLatencyCorrector(threshold=0.2)(pairs)
    torch.testing.assert_close(with_pair.latency.flatten(1).mean(1).double(),
                               fuse_latencies(own, candidates, log_p, 0, 0, pair_log_odds=agreement), rtol=0,
                               atol=1e-3)
    torch.testing.assert_close(with_pair.meta["frame_latency_us"], own, rtol=0, atol=1e-3)
    agreed = torch.stack([candidates[k][a.argmax()] for k, a in enumerate(agreement)])  # where each pair agreed best
    torch.testing.assert_close(with_pair.meta["pair_latency_us"], agreed, rtol=0, atol=0)
    assert with_pair.blurry_next is not None  # the pair goes on to the model behind
    want = fuse_latencies(own, candidates, log_p, before=2, after=0, pair_log_odds=agreement)
    without = fuse_latencies(own, candidates, log_p, before=2, after=0)
    assert not torch.allclose(want, without, rtol=0, atol=1.0)
    stream = StreamingLatencyCorrector(threshold=0.2)
    streamed = torch.stack([stream(pair).latency.mean().double() for pair in pairs.split()])
    torch.testing.assert_close(streamed, want, rtol=0, atol=1e-3)
    stream.reset()
    together = stream(pairs)
    torch.testing.assert_close(together.latency.flatten(1).mean(1).double(), want, rtol=0, atol=1e-3)
    torch.testing.assert_close(together.meta["pair_latency_us"], agreed, rtol=0, atol=0)
    assert bool(StreamingLatencyCorrector(threshold=0.2)(seq.frames("delayed").split()[0]).meta["pair_latency_us"]
                .isnan().all())  # a single frame has no pair
    plain = StreamingLatencyCorrector(each_alone)
    torch.testing.assert_close(torch.stack([plain(pair).latency.mean().double() for pair in pairs.split()]),
                               without, rtol=0, atol=1e-3)


def test_the_pairs_place_the_latency_near_where_the_readers_put_it():
    # the readers (two frames sure of about 800 µs) choose the neighbourhood; a pair whose agreement is best at
    # 1100 µs draws the latency towards it once refined, the further the more it counts, where fused once it barely
    # moves the readers' centre
    log_p = torch.stack([belief(800.0, 150.0), belief(800.0, 150.0)])
    pair = -4.0 * torch.log1p(((CANDIDATES - 1100.0) / 300.0) ** 2)  # log-odds, their maximum 0 at 1100 µs

    def fused_with(refine):
        return fuse_latencies(torch.zeros(2), CANDIDATES, log_p, 1, 1, pair_log_odds=[pair, None], pair_refine=refine)

    fused, refined, sharper = fused_with(None), fused_with(DEFAULT_PAIR_REFINE), fused_with(3 * DEFAULT_PAIR_REFINE)
    assert float((fused - 870.0).abs().max()) < 20.0
    assert float((refined - 1045.0).abs().max()) < 20.0  # 10x by default
    assert float((sharper - 1100.0).abs().max()) < 20.0
    torch.testing.assert_close(fuse_latencies(torch.zeros(2), CANDIDATES, log_p, 1, 1, pair_log_odds=[pair, None]),
                               refined, rtol=0, atol=0)
    # refining by 1 is no refinement; without pairs there is nothing to refine with
    torch.testing.assert_close(fused_with(1.0), fused, rtol=0, atol=0)
    alone = fuse_latencies(torch.zeros(2), CANDIDATES, log_p, 1, 1)
    torch.testing.assert_close(alone, fuse_latencies(torch.zeros(2), CANDIDATES, log_p, 1, 1, pair_refine=None),
                               rtol=0, atol=0)


def test_a_pair_that_agrees_far_from_the_readers_cannot_carry_the_latency_there():
    # a pair agreeing best at 1800 µs, far from where three sure frames put it (300 µs), moves the latency no further
    # than the refinement's reach
    log_p = torch.stack([belief(300.0, 100.0)] * 3)
    pair = -3.0 * torch.log1p(((CANDIDATES - 1800.0) / 200.0) ** 2)
    refined = fuse_latencies(torch.zeros(3), CANDIDATES, log_p, 1, 1, pair_log_odds=[pair, pair, None])
    step = float(CANDIDATES[1] - CANDIDATES[0])
    assert float(refined.max()) <= 300.0 + PAIR_REFINE_HALF_WIDTH * step + 1e-6
    assert float(refined.min()) > 300.0  # pulled towards the pair, inside the reach


@pytest.mark.parametrize("refine", [0.5, 0.0, math.nan, math.inf, True])
def test_a_refinement_under_one_or_not_a_number_is_refused(refine):
    with pytest.raises(ValueError, match="pair_refine"):
        fuse_latencies(torch.zeros(2), CANDIDATES, torch.zeros(2, 20), 1, 1, pair_refine=refine)


def _evidence(out):
    return out.latency.flatten(1).mean(1).double(), out.meta["etf_curve"][0], out.meta["latency_log_probability"]


def test_a_still_frame_in_a_stream_keeps_the_latency_before_it():
    # a recording that starts still (the shared street recording's first frame has no events) and stills again:
    # the stream carries the latency over them, as `evlatcorr correct` does, instead of refusing them
    from evlatcorr.checks import NoEventsError
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.frames import EventFrames
    from evlatcorr.sample_warnings import SampleWarning
    from evlatcorr.simulate import simulate
    from evlatcorr.temporal import StreamingLatencyCorrector

    seq = simulate("camera", num_frames=4, height=32, width=48, latency_us=3000.0, seed=0)
    parts = seq.frames("delayed").split()

    def still(frame):  # its events moved before its exposure: none to estimate from, some to shift
        ev = frame.events
        events = type(ev)(ev.x, ev.y, ev.t - 3 * float(frame.exposure_time[0]), ev.p, sensor_size=ev.sensor_size)
        return frame.replace(events=events)

    frames = [still(parts[0]), parts[1], still(parts[2]), parts[3]]
    assert len(frames[0].events) > 0
    with pytest.raises(NoEventsError, match="sample 0 has no events") as refused:
        EventLatencyCorrector(threshold=0.2)(frames[0])  # one frame alone has nothing to take a latency from
    assert isinstance(refused.value, ValueError) and refused.value.sample == 0
    stream = StreamingLatencyCorrector(threshold=0.2)
    with pytest.warns(SampleWarning, match="no events in its exposure and search window: its events keep the "
                                            "previous frame's latency") as caught:
        outs = [stream(frame) for frame in frames]
    assert [o.meta["latency_source"] for o in outs] == [["no events"], ["reader"], ["no events"], ["reader"]]
    assert sum("no events" in str(w.message) for w in caught) == 2
    latencies = [float(o.latency.mean()) for o in outs]
    assert latencies[0] == 0.0 and latencies[2] == latencies[1] and abs(latencies[1] - 3000.0) < 1000.0
    for frame, out, latency in zip(frames, outs, latencies):
        assert out.latency.shape == (1, 1, 32, 48)
        torch.testing.assert_close(out.corrected.t, frame.events.t - latency, rtol=0, atol=1e-3)  # float32 maps
    torch.testing.assert_close(outs[2].latent, frames[2].blurry)  # no events in it: nothing to undo
    assert bool(outs[2].meta["latency_fallback"][0]) and math.isnan(float(outs[2].meta["frame_latency_us"][0]))
    # the still frame adds no evidence: frame 3 fuses with frame 1 as if frame 2 were not there
    stream.reset()
    stream(frames[1])
    assert float(stream(frames[3]).latency.mean()) == pytest.approx(latencies[3], abs=1e-3)
    # the same frames in one call: the same latencies, the still frames named by their place in the batch
    stream.reset()
    with pytest.warns(SampleWarning) as caught:
        batched = stream(EventFrames.cat(frames))
    torch.testing.assert_close(batched.latency.flatten(1).mean(1), torch.tensor(latencies), rtol=0, atol=1e-3)
    assert batched.meta["latency_source"] == ["no events", "reader", "no events", "reader"]
    assert {str(w.message).split(":")[0] for w in caught if "no events" in str(w.message)} == {"frame 0", "frame 2"}


def test_a_stream_names_its_frames_and_a_run_of_still_frames_once():
    # a still stretch warned of at every frame buried the rest (a street recording: a warning per frame); the stream
    # names the first frame of a run, by its number in the stream, and each frame's meta keeps its count
    from evlatcorr.sample_warnings import SampleWarning
    from evlatcorr.simulate import simulate
    from evlatcorr.temporal import StreamingLatencyCorrector

    seq = simulate("camera", num_frames=6, height=32, width=48, latency_us=3000.0, seed=0)
    parts = seq.frames("delayed").split()

    def thinned(frame):  # 20 of its events: under FEW_EVENTS in any window
        ev = frame.events
        keep = torch.arange(0, len(ev), max(1, len(ev) // 20))[:20]
        return frame.replace(events=type(ev)(ev.x[keep], ev.y[keep], ev.t[keep], ev.p[keep],
                                             sensor_size=ev.sensor_size))

    frames = [parts[0], thinned(parts[1]), thinned(parts[2]), thinned(parts[3]), parts[4], thinned(parts[5])]
    stream = StreamingLatencyCorrector(threshold=0.2)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        outs = [stream(frame) for frame in frames]
    few = [w for w in caught if isinstance(w.message, SampleWarning) and w.message.kind == "few_events"]
    assert [w.message.samples for w in few] == [(1,), (5,)]  # frames 2 and 3 continue frame 1's run
    assert str(few[0].message).startswith("frame 1: only ") and "not named" in str(few[0].message)
    assert {w.filename for w in caught} == {__file__}  # the line calling the stream, not the library's
    assert [int(o.meta["events_in_window"][0]) < 100 for o in outs] == [False, True, True, True, False, True]
    # after a reset the numbers start again; name_frames=False passes the corrector's own warnings, every frame's
    stream.reset()
    with pytest.warns(SampleWarning, match="^frame 0: only "):
        stream(frames[1])
    quiet = StreamingLatencyCorrector(threshold=0.2, name_frames=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for frame in frames[1:4]:
            quiet(frame)
    assert [str(w.message)[:17] for w in caught if getattr(w.message, "kind", "") == "few_events"] == [
        "sample 0: only 20"] * 3


def test_the_streaming_corrector_refuses_a_spatial_corrector_or_a_negative_window():
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.temporal import StreamingLatencyCorrector

    with pytest.raises(ValueError, match="constant-mode"):
        StreamingLatencyCorrector(EventLatencyCorrector(mode="spatial"))
    with pytest.raises(ValueError, match="whole number"):
        StreamingLatencyCorrector(before=-1)
    with pytest.raises(ValueError, match=r"give a corrector or its settings \(threshold\), not both"):
        StreamingLatencyCorrector(EventLatencyCorrector(), threshold=0.5)
    with pytest.raises(ValueError, match="constant-mode"):
        StreamingLatencyCorrector(mode="spatial")


def test_the_streaming_corrector_makes_its_corrector_from_settings():
    from evlatcorr.temporal import StreamingLatencyCorrector

    stream = StreamingLatencyCorrector(threshold=0.5, search_range=(0.0, 5000.0), before=1)
    assert stream.corrector.threshold == 0.5 and stream.corrector.search_range == (0.0, 5000.0) and stream.before == 1


def test_frame_evidence_reads_each_frame_of_a_constant_correction():
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.simulate import simulate

    frames = simulate("camera", num_frames=2, height=24, width=32, latency_us=2000.0, seed=0).frames("delayed")
    out = EventLatencyCorrector()(frames)
    evidence = frame_evidence(out)
    assert len(evidence) == 2
    for b, (own, candidates, log_p) in enumerate(evidence):
        assert own == pytest.approx(float(out.latency[b].mean()))
        torch.testing.assert_close(candidates, out.meta["etf_curve"][0][b].double().cpu())
        torch.testing.assert_close(log_p, out.meta["latency_log_probability"][b].cpu())
    # the consensus has no reader: no evidence, the frame's own latency only
    consensus = frame_evidence(EventLatencyCorrector(score="consensus")(frames))
    assert [log_p for _, _, log_p in consensus] == [None, None]
    with pytest.raises(ValueError, match="constant-mode EventLatencyCorrector"):
        frame_evidence(frames)


def test_probability_centre_refuses_shapes_that_do_not_match():
    with pytest.raises(ValueError, match="num_valid"):
        probability_centre(torch.zeros(4), torch.arange(4.0), 0)
    with pytest.raises(ValueError, match=r"\(K,\)"):
        probability_centre(torch.zeros(4), torch.arange(5.0), 4)
    # a pick at the edge of the valid candidates keeps no neighbours: it stays where it is
    assert probability_centre(torch.tensor([0.0, 1.0, 5.0, -1e4]), torch.arange(4.0), 3) == (2.0, 2.0)


def test_latency_history_fuses_each_frame_with_the_ones_before_it():
    from evlatcorr.temporal import LatencyHistory

    cand = torch.arange(0.0, 2000.0, 100.0)
    rows = [torch.log_softmax(-((cand - mean) / sigma) ** 2, 0) for mean, sigma in ((400.0, 150.0), (1500.0, 1000.0),
                                                                                      (700.0, 150.0))]
    own = torch.tensor([400.0, 1500.0, 700.0], dtype=torch.float64)
    history = LatencyHistory(before=1)
    fused = [history.fuse(float(own[k]), cand, rows[k]) for k in range(3)]
    expected = fuse_latencies(own, cand, torch.stack(rows), before=1, after=0)
    assert fused == pytest.approx(expected.tolist(), abs=1e-9)
    assert abs(fused[1] - 400.0) < 100.0  # the unsure frame follows its confident predecessor
    history.reset()
    assert history.fuse(1500.0, cand, rows[1]) == pytest.approx(float(fuse_latencies(own[1:2], cand, rows[1][None])[0]))
    # a frame with no evidence of its own takes its predecessor's
    without = history.fuse(1234.0, cand, None)
    want = fuse_latencies(torch.tensor([1500.0, 1234.0], dtype=torch.float64), [cand, cand], [rows[1], None], 1, 0)
    assert without == pytest.approx(float(want[1])) and abs(without - 1234.0) > 50.0


def test_latency_history_takes_one_threshold_or_one_per_pair_and_reset_forgets_the_pairs():
    from evlatcorr.temporal import LatencyHistory

    history = LatencyHistory(before=1)
    with pytest.raises(ValueError, match="one threshold or one per pair \\(2\\), got 3"):
        history.expect_pairs([None, None], [0.2, 0.3, 0.4])
    history.expect_pairs([None, None], 0.2)
    history.reset()
    cand = torch.arange(0.0, 2000.0, 100.0)
    sure = torch.log_softmax(-((cand - 400.0) / 150.0) ** 2, 0)
    assert round(history.fuse(400.0, cand, sure)) == 400  # no pair left to read
    # before=0 and no pair: nothing to fuse, the frame's own estimate as it is
    assert LatencyHistory(before=0).fuse(1234.5, cand, sure) == 1234.5


@pytest.mark.parametrize("before", [-1, 1.5, True])
def test_latency_history_refuses_a_bad_window(before):
    from evlatcorr.temporal import LatencyHistory

    with pytest.raises(ValueError, match="before must be a whole number"):
        LatencyHistory(before)


def test_the_streamed_latency_stays_inside_the_search_range():
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.simulate import simulate
    from evlatcorr.temporal import StreamingLatencyCorrector

    seq = simulate("camera", num_frames=3, height=32, width=48, latency_us=3000.0, seed=0)
    # a range between two candidates (20 ms exposure: spaced 200 us), away from the true 3 ms
    stream = StreamingLatencyCorrector(EventLatencyCorrector(threshold=0.2, search_range=(1250.0, 1350.0)), before=2)
    for frame in seq.frames("delayed").split():
        out = stream(frame)
        assert 1250.0 <= float(out.latency.mean()) <= 1350.0
        assert 1250.0 <= float(out.meta["frame_latency_us"][0]) <= 1350.0


@pytest.fixture(scope="module")
def astronaut_recordings():
    """The fused latencies of 5 frames of the astronaut scene (48x64) with no latency and 3 ms late: each frame's own
    estimates, fused ±2 and fused as a stream."""
    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.simulate import simulate

    out = {}
    for latency in (0.0, 3000.0):
        seq = simulate("astronaut", num_frames=5, height=48, width=64, latency="constant", latency_us=latency, seed=0)
        evidence = frame_evidence(EventLatencyCorrector(threshold=float(seq.threshold))(seq.frames("delayed")))
        own = torch.tensor([e[0] for e in evidence], dtype=torch.float64)
        rows = ([e[1] for e in evidence], [e[2] for e in evidence])
        out[latency] = own, fuse_latencies(own, *rows), fuse_latencies(own, *rows, before=2, after=0)
    return out


def test_a_recording_without_latency_gets_none_where_its_frames_together_keep_it_likely(astronaut_recordings):
    own, fused, stream = astronaut_recordings[0.0]
    assert float(own.abs().max()) > 150.0  # some frames alone find a few hundred µs (step EDI's lag)
    assert float(fused.abs().max()) <= 150.0
    assert float(stream[1:].abs().max()) <= 150.0  # a stream's first frame has only its own evidence


def test_a_late_recording_keeps_its_fused_latency(astronaut_recordings):
    _, fused, stream = astronaut_recordings[3000.0]
    assert float((fused - 3000.0).abs().max()) < 600.0 and float(stream[1:].min()) > 2000.0


def test_the_streaming_corrector_starts_again_when_time_goes_back():
    # the same recording passed twice without reset(): its second pass is a new recording, with a warning, and its
    # first frame takes no evidence from the first pass's last frames
    import warnings

    from evlatcorr.simulate import simulate
    from evlatcorr.temporal import StreamingLatencyCorrector

    frames = simulate("camera", num_frames=3, height=32, width=48, latency_us=3000.0, seed=0).frames("delayed")
    stream = StreamingLatencyCorrector(threshold=0.2)
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message="StreamingLatencyCorrector")
        first_pass = [stream(frame) for frame in frames.split()]  # in order: no warning
    with pytest.warns(UserWarning, match="before the last frame's .* taken as a new recording"):
        again = stream(frames.split()[0])
    torch.testing.assert_close(again.latency, first_pass[0].latency)
