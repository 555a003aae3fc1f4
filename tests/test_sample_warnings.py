"""Warnings about samples of a batch (:mod:`evlatcorr.sample_warnings`)."""

import pickle

import pytest

from evlatcorr.sample_warnings import SampleWarning


def test_sample_warning_names_its_samples_by_index_or_by_the_callers_names():
    one = SampleWarning("events_end", [2], "events of {which} end early", "events end early")
    assert str(one) == "events of sample 2 end early"
    assert one.naming(["frame 10", "frame 11", "frame 12"]) == "events of frame 12 end early"
    several = SampleWarning("fallback", [0, 2], "{which}: fallback", "the fallback")
    assert str(several) == "samples [0, 2]: fallback" and several.summary == "the fallback"
    assert several.naming(["frame 3", "frame 4", "frame 5"]) == "frames 3, 5: fallback"
    assert several.naming(["a.h5", "b.h5", "c.h5"]) == "a.h5, c.h5: fallback"  # names that are not "noun number"


def test_sample_warning_pickles_as_it_was_made():
    w = pickle.loads(pickle.dumps(SampleWarning("hot_pixels", [1], "{which}: 3 hot pixels", "hot pixels")))
    assert (w.kind, w.samples, w.summary, str(w)) == ("hot_pixels", (1,), "hot pixels", "sample 1: 3 hot pixels")


def test_sample_warning_refuses_no_samples_a_text_without_them_and_too_few_names():
    with pytest.raises(ValueError, match="one sample or more"):
        SampleWarning("fallback", [], "{which}: fallback", "the fallback")
    with pytest.raises(ValueError, match="one sample or more"):
        SampleWarning("fallback", [0], "fallback", "the fallback")
    with pytest.raises(ValueError, match=r"a name for each of samples \[0, 3\], got 2"):
        SampleWarning("fallback", [0, 3], "{which}: fallback", "the fallback").naming(["frame 1", "frame 2"])


def test_a_warning_deep_in_a_corrector_points_at_the_line_that_called_it():
    # under nn.Sequential, nn.Module's __call__ and the search the warning used to point at a line of the library
    import warnings

    import torch
    from torch import nn

    from evlatcorr.correction import EventLatencyCorrector
    from evlatcorr.simulate import simulate

    frames = simulate("camera", num_frames=1, height=32, width=48, latency_us=3000.0, seed=0).frames("delayed")
    ev = frames.events
    keep = ev.t < float(frames.exposure_end[0]) + 2000.0  # the events stop 2 ms past the exposure: a warning
    short = frames.replace(events=type(ev)(ev.x[keep], ev.y[keep], ev.t[keep], ev.p[keep],
                                           sensor_size=ev.sensor_size))
    pipeline = nn.Sequential(EventLatencyCorrector(threshold=0.2), nn.Identity())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        with torch.no_grad():
            pipeline(short)
    events_end = [w for w in caught if getattr(w.message, "kind", "") == "events_end"]
    assert len(events_end) == 1 and events_end[0].filename == __file__
