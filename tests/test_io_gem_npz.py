"""GEM NPZ pairs (XiangZ-0/GEM codes/datasets/README.md layout)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from evlatcorr.io import GemNpzRecording, RecordingError, open_recording

H, W = 8, 12


def write_pair(path, seed=0, scale_factor=1, drop=None, t0=0, p_signed=True, sharp=True, float_blur=False):
    """blur1/2 (C, H, W) 0..255, integer exposures, events dict in µs, sharp_imgs with timestamps."""
    rng = np.random.default_rng(seed)
    eh, ew = H // scale_factor, W // scale_factor
    n = 300
    t = np.sort(rng.integers(t0, t0 + 20000, n))
    p = rng.integers(0, 2, n)
    data = dict(
        blur1=rng.integers(0, 256, (3, H, W)).astype(np.float64 if float_blur else np.uint8),
        blur2=rng.integers(0, 256, (3, H, W)).astype(np.uint8),
        exp_start1=t0 + 1000, exp_end1=t0 + 9000, exp_start2=t0 + 11000, exp_end2=t0 + 19000,
        events=np.array({"x": rng.integers(0, ew, n), "y": rng.integers(0, eh, n), "t": t,
                         "p": 2 * p - 1 if p_signed else p}, dtype=object),
        scale_factor=scale_factor,
    )
    if sharp:
        data["sharp_imgs"] = rng.integers(0, 256, (4, 3, H, W)).astype(np.uint8)
        data["sharp_timestamps"] = np.array([t0 + 3000, t0 + 7000, t0 + 13000, t0 + 17000])
    if drop:
        data.pop(drop)
    np.savez(path, **data)
    return data


def stream(rec):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batches = list(rec)
    return batches, [str(w.message) for w in caught]


def test_reads_a_pair(tmp_path):
    data = write_pair(tmp_path / "pair.npz")
    rec = open_recording(tmp_path / "pair.npz", after_us=1000.0)
    assert isinstance(rec, GemNpzRecording) and rec.sensor_size == (H, W) and rec.num_frames == 2
    batches, msgs = stream(rec)
    ev = data["events"].item()
    for k, b in enumerate(batches, start=1):
        start, end = data[f"exp_start{k}"], data[f"exp_end{k}"]
        assert float(b.exposure_start) == start and float(b.exposure_end) == end
        torch.testing.assert_close(b.blurry[0], torch.from_numpy(data[f"blur{k}"] / 255.0).float())
        sel = (ev["t"] >= start) & (ev["t"] < end + 1000)
        np.testing.assert_array_equal(b.events.t.numpy(), ev["t"][sel])
        np.testing.assert_array_equal(b.events.x.numpy(), ev["x"][sel])
        np.testing.assert_array_equal(b.events.p.numpy(), ev["p"][sel])
        # ground truth: nearest sharp image to mid-exposure, and those inside the exposure as targets
        torch.testing.assert_close(b.sharp[0], torch.from_numpy(data["sharp_imgs"][2 * k - 2] / 255.0).float())
        assert b.target_times.tolist() == [[start + 2000.0, start + 6000.0]]
        assert b.target_frames.shape == (1, 2, 3, H, W)
    assert b.meta["source"] == "pair.npz" and b.meta["pair"] == 2
    assert any("pair.npz: frame 1: events end" in m for m in msgs)  # GEM stores no events after exp_end2


def test_no_events_after_the_second_exposure_warns(tmp_path):
    write_pair(tmp_path / "pair.npz")
    batches, msgs = stream(GemNpzRecording(tmp_path / "pair.npz"))  # after_us = exposure time = 8000
    assert any("pair.npz: frame 1: events end at" in m for m in msgs)
    assert len(batches) == 2


def test_polarity_units_and_float_images(tmp_path):
    data = write_pair(tmp_path / "p01.npz", p_signed=False, float_blur=True, t0=5)
    rec = GemNpzRecording(tmp_path / "p01.npz", time_unit="ms")
    b = rec.frame(0)
    assert float(b.exposure_start) == (5 + 1000) * 1000.0 and set(b.events.p.tolist()) <= {-1, 1}
    assert float(b.blurry.max()) <= 1.0 and float(b.blurry.max()) > 0.9  # float 0..255 is divided by 255 too
    ev = data["events"].item()
    assert int((b.events.p > 0).sum()) == int(ev["p"][(ev["t"] >= 1005) & (ev["t"] < 9005 + 8000)].sum())


def test_folder_of_pairs_is_one_segment_per_file(tmp_path):
    write_pair(tmp_path / "a.npz", seed=1)
    write_pair(tmp_path / "b.npz", seed=2, t0=0)  # its own time base, overlapping a's
    rec = open_recording(tmp_path, after_us=500.0)
    assert isinstance(rec, GemNpzRecording) and rec.segment_names == ["a.npz", "b.npz"] and rec.num_frames == 4
    batches, _ = stream(rec)
    assert [b.meta["frame"] for b in batches] == [0, 1, 2, 3] and [b.meta["segment"] for b in batches] == [0, 0, 1, 1]
    ev_b = np.load(tmp_path / "b.npz", allow_pickle=True)["events"].item()
    sel = (ev_b["t"] >= 1000) & (ev_b["t"] < 9500)
    np.testing.assert_array_equal(batches[2].events.t.numpy(), ev_b["t"][sel])


def test_lower_resolution_events(tmp_path):
    write_pair(tmp_path / "sf.npz", scale_factor=4)
    with pytest.raises(RecordingError, match="sf.npz: events are 4x lower resolution .*downsample_frames=True"):
        GemNpzRecording(tmp_path / "sf.npz")
    rec = GemNpzRecording(tmp_path / "sf.npz", downsample_frames=True)
    assert rec.sensor_size == (H // 4, W // 4)
    b = rec.frame(0)
    full = np.load(tmp_path / "sf.npz")["blur1"] / 255.0
    want = full.reshape(3, H // 4, 4, W // 4, 4).mean((2, 4))
    torch.testing.assert_close(b.blurry[0], torch.from_numpy(want).float())
    assert b.sharp.shape == (1, 3, H // 4, W // 4)


def test_bad_files(tmp_path):
    write_pair(tmp_path / "noexp.npz", drop="exp_end2")
    with pytest.raises(RecordingError, match="noexp.npz: not a GEM npz pair, missing keys \\['exp_end2'\\]"):
        GemNpzRecording(tmp_path / "noexp.npz")
    with pytest.raises(RecordingError, match="unknown format: an npz with keys"):
        open_recording(tmp_path / "noexp.npz")
    data = write_pair(tmp_path / "bad_exp.npz")
    data["exp_end1"] = data["exp_start1"]
    np.savez(tmp_path / "bad_exp.npz", **data)
    with pytest.raises(RecordingError, match="bad_exp.npz: frame 0 \\(blur1\\) has exposure end"):
        list(GemNpzRecording(tmp_path / "bad_exp.npz"))
    full = (tmp_path / "bad_exp.npz").read_bytes()
    (tmp_path / "cut.npz").write_bytes(full[: len(full) // 2])
    with pytest.raises(RecordingError, match="cut.npz: cannot read as npz \\(truncated or corrupt\\?\\)"):
        open_recording(tmp_path / "cut.npz")
    with pytest.raises(RecordingError, match="cut.npz: cannot read npz \\(truncated or corrupt\\?\\)"):
        GemNpzRecording(tmp_path / "cut.npz")


def test_polarity_and_column_lengths_are_validated(tmp_path):
    data = write_pair(tmp_path / "p2.npz")
    data["events"].item()["p"][5] = 2  # ±1 file with one 2: used to be read as ON
    np.savez(tmp_path / "p2.npz", **data)
    with pytest.raises(RecordingError, match=r"p2.npz: events: polarity must be 0/1, -1/\+1 or bool, got "
                                             r"values \[2\]"):
        list(GemNpzRecording(tmp_path / "p2.npz"))
    data = write_pair(tmp_path / "short.npz")
    data["events"].item()["y"] = data["events"].item()["y"][:-1]
    np.savez(tmp_path / "short.npz", **data)
    with pytest.raises(RecordingError, match="short.npz: events x, y, t, p differ in length: x 300, y 299, t 300, "
                                             "p 300"):
        GemNpzRecording(tmp_path / "short.npz")


def test_sharp_images_and_their_timestamps_must_pair_up(tmp_path):
    data = write_pair(tmp_path / "sharp.npz")
    data["sharp_timestamps"] = data["sharp_timestamps"][:3]
    np.savez(tmp_path / "sharp.npz", **data)
    with pytest.raises(RecordingError, match="sharp.npz: sharp_imgs holds 4 images but sharp_timestamps 3 times"):
        GemNpzRecording(tmp_path / "sharp.npz")
