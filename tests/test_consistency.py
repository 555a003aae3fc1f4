from __future__ import annotations

import pytest
import torch

from evlatcorr import EventLatencyCorrector
from evlatcorr.consistency import estimate_recording_threshold, pair_disagreement
from evlatcorr.simulate import simulate


@pytest.fixture(scope="module")
def pairs_theta_05():
    """Three pairs of a recording made with θ = 0.5 and a 3 ms latency."""
    seq = simulate("astronaut", num_frames=4, height=64, width=80, threshold=0.5, latency_us=3000.0, seed=1)
    return seq.pairs("delayed", after_us=20000.0)


def test_disagreement_shapes_and_errors(pairs_theta_05):
    d = pair_disagreement(pairs_theta_05, 0.5, 3000.0)
    assert d.shape == (3,) and bool((d > 0).all())
    per_pair = pair_disagreement(pairs_theta_05, 0.5, torch.full((3,), 3000.0))
    torch.testing.assert_close(d, per_pair)
    single = pairs_theta_05.replace(blurry_next=None)
    with pytest.raises(ValueError, match="blurry_next"):
        pair_disagreement(single)
    with pytest.raises(ValueError, match="latency"):
        pair_disagreement(pairs_theta_05, 0.5, torch.zeros(2))
    with pytest.raises(ValueError, match="bounds"):
        estimate_recording_threshold(pairs_theta_05, bounds=(0.5, 0.1))


def test_disagreement_is_lowest_near_the_true_threshold_and_latency(pairs_theta_05):
    at = lambda theta, latency: float(pair_disagreement(pairs_theta_05, theta, latency).mean())  # noqa: E731
    assert at(0.5, 3000.0) < at(0.5, 0.0)  # the stamped events disagree more than the corrected ones
    assert at(0.5, 3000.0) < at(0.2, 3000.0) and at(0.5, 3000.0) < at(1.0, 3000.0)


def test_recording_threshold_recovers_theta_and_keeps_the_latency(pairs_theta_05):
    theta = estimate_recording_threshold(pairs_theta_05, latency=3000.0)
    assert theta == pytest.approx(0.5, rel=0.15)
    # estimated jointly with the latency (the search at θ = 0.2 first), as the command line does
    first = EventLatencyCorrector(threshold=0.2)(pairs_theta_05).latency.mean(dim=(1, 2, 3))
    joint = estimate_recording_threshold(pairs_theta_05, latency=first)
    assert joint == pytest.approx(0.5, rel=0.15)
    known = EventLatencyCorrector(threshold=0.5)(pairs_theta_05).latency.mean(dim=(1, 2, 3))
    auto = EventLatencyCorrector(threshold=joint)(pairs_theta_05).latency.mean(dim=(1, 2, 3))
    error_known, error_auto = (known - 3000.0).abs(), (auto - 3000.0).abs()
    assert float(error_auto.median()) <= float(error_known.median()) + 100.0


def test_short_exposures_far_apart_fit_the_memory_budget(monkeypatch):
    # a 2 ms exposure read 9 ms away: the grids reach the gap's middle in steps of exposure / num_bins. Under a
    # 40 MB budget the former grids asked for about 130 MB each and stopped (as a 5 ms DAVIS346
    # exposure 20 ms away did under the default 2 GiB); the points now fit half the budget each
    import evlatcorr.checks

    seq = simulate("astronaut", num_frames=3, height=64, width=80, exposure_us=2000.0, frame_interval_us=20000.0,
                   threshold=0.5, latency_us=1000.0, seed=1)
    pairs = seq.pairs("delayed", after_us=5000.0)
    monkeypatch.setattr(evlatcorr.checks, "MEMORY_BUDGET_BYTES", 40 * 2**20)
    theta = estimate_recording_threshold(pairs, latency=1000.0)
    assert 0.3 < theta < 0.8


@pytest.mark.parametrize("found, edge", [(0.0501, "low"), (1.49, "high"), (0.3, None)])
def test_a_recordings_threshold_at_the_end_of_its_range_is_said(monkeypatch, tmp_path, found, edge):
    # a threshold at the search's low end (5 of the 48 test recordings of benchmarks/threshold.py) leaves the blur
    # in: the user should hear of it, not find it in the output
    import warnings

    import evlatcorr.consistency
    from evlatcorr.io import H5Recording, write_sequence
    from evlatcorr.restore import recording_threshold
    from evlatcorr.simulate import simulate

    write_sequence(tmp_path / "r.h5", simulate("camera", num_frames=3, height=32, width=40, exposure_us=10_000.0,
                                               frame_interval_us=12_000.0, latency_us=2000.0, seed=0))
    monkeypatch.setattr(evlatcorr.consistency, "estimate_recording_threshold", lambda *a, **k: found)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert recording_threshold(H5Recording(tmp_path / "r.h5")) == found
    said = [str(w.message) for w in caught if "contrast threshold estimate" in str(w.message)]
    if edge is None:
        assert not said
    else:
        assert len(said) == 1 and f"lies at the {edge} end of its search range 0.05-1.5" in said[0]
        assert "give the camera's threshold if you know it" in said[0]


def test_the_disagreement_at_the_pixels_events_change_equals_the_whole_images():
    # the search over θ works only where either frame's events change its EDI: elsewhere each latent is its blurry
    # frame at every θ. The whole images' EDI (edi.latent_from_grid_reads) must give the same disagreement
    import torch

    from evlatcorr.consistency import _FLOOR, _gap_middle, _gap_reads, _latency_vector, pair_disagreement
    from evlatcorr.edi import edi_deblur
    from evlatcorr.events import Events
    from evlatcorr.simulate import simulate

    seq = simulate("astronaut", num_frames=3, height=32, width=40, latency_us=2000.0, brightness=0.1, seed=1)
    pairs = seq.pairs("delayed", after_us=8000.0)
    ev = pairs.events
    left = ev.x < 25  # the right of the image still: its pixels keep their blurry frames at every θ
    pairs = pairs.replace(events=Events.from_canonical(ev.x[left], ev.y[left], ev.t[left], ev.p[left], ev.batch[left],
                                                       ev.sensor_size, ev.batch_size))
    reads = _gap_reads(pairs, _latency_vector(2000.0, pairs), 100)
    assert 0 < len(reads.batch) <= 2 * 32 * 25  # the pixels with events, no others
    t = _gap_middle(pairs)
    for theta in (0.05, 0.2, torch.tensor([0.3, 0.7])):
        whole = [edi_deblur(blurry, pairs.events, start, end, theta, 2000.0, num_bins=100, time=t)
                 for blurry, start, end in ((pairs.blurry, pairs.exposure_start, pairs.exposure_end),
                                            (pairs.blurry_next, pairs.exposure_start_next, pairs.exposure_end_next))]
        expected = (torch.log(whole[0].clamp_min(0) + _FLOOR) - torch.log(whole[1].clamp_min(0) + _FLOOR)).abs()
        got = pair_disagreement(pairs, theta, 2000.0, num_bins=100)
        torch.testing.assert_close(got, expected.mean(dim=(1, 2, 3)).to(got.dtype), rtol=1e-4, atol=1e-6)
