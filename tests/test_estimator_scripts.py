from __future__ import annotations

import pytest
import torch

from evlatcorr.benchmark.accuracy import load_estimator, make_cases, simulate_case
from evlatcorr.correction import EventLatencyCorrector
from evlatcorr.frames import EventFrames
from tests.test_accuracy import tiny_case

TILES = "benchmarks/estimators/tiles.py"


def test_tiles_whole_frame_read_is_the_corrector_s_reader_estimate():
    delayed = simulate_case(tiny_case())[0]
    delayed.meta["threshold"] = 0.2
    corrected = EventLatencyCorrector(threshold=0.2, tiles=False)(delayed)  # the whole frame's reader alone
    assert corrected.meta["latency_source"][0] in ("sharpness", "reader")
    whole = load_estimator(f"{TILES}:estimate_whole")(delayed)
    assert whole.shape == (1, 1, *delayed.blurry.shape[-2:])
    torch.testing.assert_close(whole, corrected.latency.to(whole), atol=0.05, rtol=0)


@pytest.fixture(scope="module")
def text_case():
    # a dev case the reader gets right (text translating at 1.2 px/ms, a constant 10.86 ms): tiles of a 96x128
    # frame are large enough to read
    case = next(c for c in make_cases("dev") if c.name.startswith("dev-17-"))
    delayed = simulate_case(case)[0]
    delayed.meta["threshold"] = case.threshold
    return case, delayed


def test_tiles_fused_estimate_lies_where_the_events_are_and_near_the_truth(text_case):
    case, delayed = text_case
    fused = float(load_estimator(f"{TILES}:estimate")(delayed).unique())
    last = float(delayed.events.t.max() - delayed.exposure_end[0])
    assert 0.0 <= fused <= last
    assert abs(fused - case.latency_us) < 500.0


def test_tile_features_of_the_whole_frame_are_what_the_search_reads(text_case):
    from evlatcorr.search import candidate_curves

    case, delayed = text_case
    candidates, valid, whole, tiled = load_estimator(f"{TILES}:tile_features")(delayed, ((3, 3),))
    expected = candidate_curves(delayed.blurry, delayed.events, float(delayed.exposure_start[0]),
                                float(delayed.exposure_end[0]), case.threshold)
    torch.testing.assert_close(candidates, expected[0].double())
    assert torch.equal(whole, expected[1]) and torch.equal(valid, expected[2])
    tiles, share = tiled[0]
    assert tiles.shape == (9, *whole.shape) and float(share.sum()) == pytest.approx(1.0)
    assert torch.equal(tiles[:, -1], whole[-1].expand(9, -1))  # every tile is read over the same candidates


def test_tile_latency_map_covers_the_frame_with_the_tiles_estimates(text_case):
    case, delayed = text_case
    latency = load_estimator(f"{TILES}:estimate_map_3x3")(delayed)
    assert latency.shape == (1, 1, 96, 128) and torch.isfinite(latency).all()
    # one latency for every pixel here: each tile's estimate is near it
    assert float((latency - case.latency_us).abs().max()) < 1500.0


def test_tiles_refuse_a_batch_and_tiles_too_small_to_read(text_case):
    tile_log_probabilities = load_estimator(f"{TILES}:tile_log_probabilities")
    tile_latency_map = load_estimator(f"{TILES}:tile_latency_map")
    _, delayed = text_case
    with pytest.raises(ValueError, match="one frame"):
        tile_log_probabilities(EventFrames.cat([delayed, delayed]))
    for grid in ((0, 2), (40, 2), (2, 2.5)):
        with pytest.raises(ValueError, match="at least 3x3 pixels"):
            tile_latency_map(delayed, grid)


def test_reader_script_reads_the_shipped_reader_or_one_trained_without_the_overshoot(text_case, tmp_path,
                                                                                      monkeypatch):
    from evlatcorr.curve_reader import (
        NUM_FEATURES,
        curve_features,
        load_curve_reader,
        save_curve_reader,
        train_curve_reader,
    )

    case, delayed = text_case
    estimate = load_estimator("benchmarks/estimators/reader.py:estimate")
    monkeypatch.delenv("EVLATCORR_READER", raising=False)
    shipped = float(estimate(delayed).unique())
    # the shipped reader's centre: the whole-frame corrector's estimate here (no fallback decides this frame)
    corrected = EventLatencyCorrector(threshold=case.threshold, tiles=False)(delayed)
    assert abs(shipped - float(corrected.latency.mean())) < 1.0 and abs(shipped - case.latency_us) < 500.0
    # a reader trained (briefly) without the overshoot reads the curves without its row
    k = 101
    curves = curve_features(torch.rand(4, 3, k), torch.zeros(4, k), torch.ones(4, k, dtype=torch.bool),
                            torch.zeros(4, k))
    five = train_curve_reader(curves[:, [0, 1, 2, 3, 5]], torch.ones(4, k, dtype=torch.bool),
                              torch.arange(k) * 200.0, torch.full((4,), 5000.0), members=1, epochs=1)
    path = tmp_path / "five.safetensors"
    save_curve_reader(five, path)
    monkeypatch.setenv("EVLATCORR_READER", str(path))
    assert load_curve_reader(str(path)).members[0].net[0].in_channels == NUM_FEATURES - 1
    assert 0.0 <= float(estimate(delayed).unique()) <= float(delayed.events.t.max() - delayed.exposure_end[0])
    with pytest.raises(ValueError, match="one frame"):
        estimate(EventFrames.cat([delayed, delayed]))


def test_saturated_script_clips_the_brightest_share_and_keeps_the_text_case_near_the_truth(text_case, monkeypatch):
    saturate = load_estimator("benchmarks/estimators/saturated.py:saturate")
    ramp = torch.linspace(0.0, 0.5, 100).view(1, 1, 10, 10)
    clipped = saturate(ramp, 0.05)
    # the 95th percentile reaches 1: the 5 brightest of 100 pixels (and the one it interpolates into) are clipped
    assert float(clipped.max()) == 1.0 and 5 <= int((clipped == 1.0).sum()) <= 6
    torch.testing.assert_close(clipped[clipped < 1], (ramp / torch.quantile(ramp, 0.95))[clipped < 1])
    for share in (0.0, 1.0, -0.1):
        with pytest.raises(ValueError, match="saturated share"):
            saturate(ramp, share)
    case, delayed = text_case
    monkeypatch.setenv("EVLATCORR_SATURATED", "0.03")
    latency = load_estimator("benchmarks/estimators/saturated.py:estimate")(delayed)
    assert latency.shape == (1, 1, 96, 128)
    assert abs(float(latency.mean()) - case.latency_us) < 500.0


def test_reader_point_script_centre_is_the_reader_script_s_and_the_others_lie_in_the_range(text_case, monkeypatch):
    monkeypatch.delenv("EVLATCORR_READER", raising=False)
    case, delayed = text_case
    points = {name: float(load_estimator(f"benchmarks/estimators/reader_point.py:{name}")(delayed).unique())
              for name in ("centre", "mean", "median", "tempered", "centre_1", "centre_3", "centre_5")}
    assert points["centre"] == pytest.approx(float(load_estimator("benchmarks/estimators/reader.py:estimate")(
        delayed).unique()), abs=1e-3)
    last = float(delayed.events.t.max() - delayed.exposure_end[0])
    assert all(0.0 <= v <= last for v in points.values())
    # a clear single mode on this frame: all the points lie near the truth
    assert all(abs(v - case.latency_us) < 1000.0 for v in points.values())
    with pytest.raises(ValueError, match="one frame"):
        load_estimator("benchmarks/estimators/reader_point.py:median")(EventFrames.cat([delayed, delayed]))


def test_threshold_error_script_gives_the_corrector_a_scaled_threshold(text_case, monkeypatch):
    import evlatcorr.correction

    case, delayed = text_case
    given = []
    original = evlatcorr.correction.EventLatencyCorrector.__init__

    def spy(self, *args, **kwargs):
        given.append(kwargs.get("threshold"))
        original(self, *args, **kwargs)

    monkeypatch.setattr(evlatcorr.correction.EventLatencyCorrector, "__init__", spy)
    for name, scale in (("low", 0.7), ("high", 1.4), ("far_low", 0.4), ("far_high", 2.5)):
        latency = load_estimator(f"benchmarks/estimators/threshold_error.py:{name}")(delayed)
        assert latency.shape == (1, 1, 96, 128)
        if name in ("low", "high"):  # a third off: the text case's latency barely moves
            assert abs(float(latency.mean()) - case.latency_us) < 1500.0
        assert given[-1] == pytest.approx(scale * case.threshold)


def test_training_script_reads_ideal_frames_of_evenly_spread_constant_cases(tmp_path, monkeypatch):
    monkeypatch.syspath_prepend("benchmarks")  # the script imports its _setup
    extract_ideal = load_estimator("benchmarks/train_curve_reader.py:extract_ideal")
    cache = tmp_path / "ideal.pt"
    data = extract_ideal(2, cache)
    # the first and the middle constant-latency training case, their ideal events against a target of 0
    from evlatcorr.benchmark.accuracy import TRAIN_SPLITS
    constant = [c.name for s in TRAIN_SPLITS for c in make_cases(s) if c.latency_model == "constant"]
    assert data["names"] == [f"{constant[0]}-ideal", f"{constant[len(constant) // 2]}-ideal"]
    assert data["targets"].tolist() == [0.0, 0.0]
    assert data["curves"].shape[:1] == (2,) and data["valid"].shape == (2, data["curves"].shape[-1])
    assert data["valid"].any(1).all()
    # read back from the cache as written
    again = extract_ideal(2, cache)
    assert torch.equal(again["curves"], data["curves"]) and again["names"] == data["names"]
    with pytest.raises(SystemExit, match="--ideal-frames"):
        extract_ideal(0, None)


def test_reader_estimate_from_curves_below_zero_is_never_negative():
    estimate_before = load_estimator("benchmarks/estimators/reader.py:estimate_before")
    case = tiny_case()
    early = simulate_case(case, before_us=2000.0)[0]
    early.meta["threshold"] = case.threshold
    latency = estimate_before(early)
    assert latency.shape == (1, 1, *early.blurry.shape[-2:]) and float(latency.min()) >= 0.0
    # frames without events before the exposure cannot be read so
    plain = simulate_case(case)[0]
    plain.meta["threshold"] = case.threshold
    with pytest.raises(ValueError, match="--before-us"):
        estimate_before(plain)


NO_LATENCY = "benchmarks/estimators/no_latency.py"


def test_no_latency_estimator_answers_zero_above_its_threshold_and_the_corrector_below(monkeypatch):
    delayed = simulate_case(tiny_case())[0]
    delayed.meta["threshold"] = 0.2
    estimate = load_estimator(f"{NO_LATENCY}:estimate")
    corrected = EventLatencyCorrector(threshold=0.2)(delayed).latency
    monkeypatch.setenv("EVLATCORR_NO_LATENCY_MASS", "1e-12")  # any share of the probability near 0 is enough
    assert float(estimate(delayed).abs().max()) == 0.0
    monkeypatch.setenv("EVLATCORR_NO_LATENCY_MASS", "0.999999")
    torch.testing.assert_close(estimate(delayed), corrected)
    monkeypatch.setenv("EVLATCORR_NO_LATENCY_MASS", "1.5")
    with pytest.raises(ValueError, match="must be in"):
        estimate(delayed)


def test_training_script_leaves_out_every_frame_of_the_named_photographs_and_nothing_else(monkeypatch):
    monkeypatch.syspath_prepend("benchmarks")  # the script imports its _setup
    leave_out = load_estimator("benchmarks/train_curve_reader.py:leave_out")
    from evlatcorr.benchmark.accuracy import TRAIN_SPLITS
    cases = [c for s in TRAIN_SPLITS for c in make_cases(s)]
    n = len(cases)
    rows = torch.arange(n, dtype=torch.float64)
    data = {"latencies": torch.arange(3.0), "curves": rows[:, None, None].expand(n, 2, 3),
            "valid": torch.ones(n, 3, dtype=torch.bool), "targets": rows, "names": [c.name for c in cases]}
    kept = leave_out(data, ["coins", "text"])
    # procedural text scenes stay: only the photographs go
    expected = [i for i, c in enumerate(cases) if c.procedural or c.scene not in ("coins", "text")]
    assert any(c.procedural and c.scene == "text" for c in cases)
    assert kept["targets"].tolist() == expected and kept["curves"][:, 0, 0].tolist() == expected
    assert kept["names"] == [cases[i].name for i in expected] and len(expected) < n
    with pytest.raises(SystemExit, match="training photographs"):
        leave_out(data, ["camera"])  # a test photograph: never trained on anyway
    with pytest.raises(SystemExit, match="another --cache"):
        leave_out(data | {"names": data["names"][::-1]}, ["coins"])


SELF_CALIBRATION = "benchmarks/estimators/self_calibration.py"


def test_ramp_world_frame_is_the_blurry_frame_where_no_pixel_has_events(text_case):
    _, delayed = text_case
    ramp_world_frame = load_estimator(f"{SELF_CALIBRATION}:ramp_world_frame")
    ramps = ramp_world_frame(delayed, torch.tensor([1000.0], dtype=torch.float64)).blurry
    assert ramps.shape == delayed.blurry.shape and ramps.min() >= 0 and ramps.max() <= 1
    quiet = torch.ones(96 * 128, dtype=torch.bool)
    quiet[delayed.events.pixel_index()] = False  # pixels with no event at all: both integrals are 0 there
    assert quiet.sum() > 100
    scale = ramps[0, 0].flatten()[quiet] / delayed.blurry[0, 0].flatten()[quiet]
    torch.testing.assert_close(scale, torch.full_like(scale, float(scale[0])))
    assert not torch.allclose(ramps, delayed.blurry * scale[0])  # and a different frame where events are


def test_self_calibration_estimates_lie_in_the_range_and_thresholds_keep_the_default_s_reading(text_case):
    case, delayed = text_case
    default = float(load_estimator(f"{SELF_CALIBRATION}:default")(delayed).unique())
    thresholds = float(load_estimator(f"{SELF_CALIBRATION}:thresholds")(delayed).unique())
    boot = load_estimator(f"{SELF_CALIBRATION}:bootstrap")(delayed)
    assert boot.shape == (1, 1, 96, 128) and float(boot.min()) >= 0.0
    assert abs(default - case.latency_us) < 500.0 and abs(thresholds - default) < 500.0


def test_tile_reader_script_reads_a_delay_frame_s_tiles_and_takes_known_targets(tmp_path):
    from evlatcorr.benchmark.accuracy import DELAY_TRAIN_SPLIT

    read_case = load_estimator("benchmarks/train_tile_reader.py:_read_case")
    known_targets = load_estimator("benchmarks/train_tile_reader.py:known_targets")
    case = make_cases(DELAY_TRAIN_SPLIT, num=1)[0]
    assert case.latency_model == "intensity_delay" and len(make_cases(DELAY_TRAIN_SPLIT)) == 300
    torch.save({"names": [case.name], "targets": torch.tensor([1234.0], dtype=torch.float64)}, tmp_path / "t.pt")
    known = known_targets([tmp_path / "t.pt"])
    assert known == {case.name: 1234.0}
    name, latencies, whole, tiles, share, valid, target = read_case((case, known[case.name]))
    assert name == case.name and target == 1234.0  # no best-shift scan where the target is known
    assert tiles.shape == (9, *whole.shape) and whole.shape[-1] == len(latencies) == len(valid)
    assert float(share.sum()) == pytest.approx(1.0) and int(valid.sum()) >= 3


def test_display_gamma_estimators_encode_the_frames_and_frame_gamma_undoes_it(monkeypatch):
    delayed = simulate_case(tiny_case())[0]
    delayed.meta["threshold"] = 0.2
    script = "benchmarks/estimators/display_gamma.py"
    linear = load_estimator(f"{script}:linear")(delayed)
    torch.testing.assert_close(linear, EventLatencyCorrector(threshold=0.2)(delayed).latency)
    torch.testing.assert_close(load_estimator(f"{script}:linearised")(delayed), linear, atol=1.0, rtol=0)
    encode = load_estimator(f"{script}:encode")
    torch.testing.assert_close(encode(delayed, 2.2).blurry, delayed.blurry.clamp(0, 1) ** (1 / 2.2))
    assert load_estimator(f"{script}:encoded")(delayed).shape == linear.shape
    monkeypatch.setenv("EVLATCORR_DISPLAY_GAMMA", "0")
    with pytest.raises(ValueError, match="frame_gamma must be a finite number > 0"):
        load_estimator(f"{script}:encoded")(delayed)


def test_display_gamma_recording_script_moves_the_estimate_and_frame_gamma_takes_it_back(tmp_path):
    import sys
    from pathlib import Path

    from tests.conftest import shared_data_dir

    recording = shared_data_dir() / "davis346" / "cradle_lowlight.aedat4"
    if not recording.is_file():
        pytest.skip("shared DAVIS346 data absent")
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from display_gamma_recording import main

    results = main([str(recording), "--min-events", "40000"])  # its busiest frames
    as_read, encoded, given = (results[k] for k in ("as read", "encoded", "encoded, frame_gamma=2.2"))
    assert len(as_read) > 0
    assert given == pytest.approx(as_read, abs=1.0)  # µs: the encoded frames made linear again
    assert encoded != pytest.approx(as_read, abs=1.0)
    with pytest.raises(SystemExit):
        main([str(recording), "--gamma", "0"])


def test_binned_pixels_script_averages_blocks_keeps_their_events_and_answers_the_frame_s_size(text_case):
    case, delayed = text_case
    binned = load_estimator("benchmarks/estimators/binned_pixels.py:binned_frames")(delayed)
    assert binned.sensor_size == (48, 64) and binned.blurry.shape == (1, 3, 48, 64)
    torch.testing.assert_close(binned.blurry[0, :, 0, 0], delayed.blurry[0, :, :2, :2].mean((1, 2)))
    ev, bev = delayed.events, binned.events
    assert len(bev) == len(ev)  # 96x128 fills whole blocks: every event kept
    first = bev.x.eq(0) & bev.y.eq(0)  # block (0, 0) holds the events of pixels (0-1, 0-1)
    assert int(first.sum()) == int((ev.x.lt(2) & ev.y.lt(2)).sum())
    for name in ("binned", "both", "default"):
        latency = load_estimator(f"benchmarks/estimators/binned_pixels.py:{name}")(delayed)
        assert latency.shape == (1, 1, 96, 128)
        assert abs(float(latency.mean()) - case.latency_us) < 1000.0
