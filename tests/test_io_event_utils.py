"""event_utils-style HDF5 (TimoStoff/event_utils hdf5_packager layout; EFNet's raw-event files)."""

from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest
import torch

from evlatcorr import Events
from evlatcorr.io import (
    EventUtilsRecording,
    H5Recording,
    RecordingError,
    open_recording,
    write_event_utils,
    write_events,
    write_sequence,
)
from tests.conftest import random_events

H, W = 5, 8
STARTS_US = [1000.0, 6000.0, 11000.0]
EXPOSURE = 3000.0


@pytest.fixture(scope="module")
def events() -> Events:
    ev = random_events(500, (H, W), (0.0, 16000.0), seed=4)
    return Events(ev.x, ev.y, ev.t.round(), ev.p, sensor_size=(H, W))  # whole µs: exact in seconds and back


def images(colour: bool = False) -> list[np.ndarray]:
    rng = np.random.default_rng(0)
    return [rng.integers(0, 256, (H, W, 3) if colour else (H, W), dtype=np.uint8) for _ in STARTS_US]


def make(path, events: Events, exposure_attrs: bool = True, colour: bool = False, sharp: bool = False,
         channels_first: bool = False, unit: float = 1e6, resolution=(H, W)):
    """A file laid out as event_utils' hdf5_packager writes it (times in seconds by default)."""
    with h5py.File(path, "w") as f:
        f.create_dataset("events/xs", data=events.x.numpy().astype(np.int16), maxshape=(None,), chunks=True)
        f.create_dataset("events/ys", data=events.y.numpy().astype(np.int16), maxshape=(None,), chunks=True)
        f.create_dataset("events/ts", data=events.t.numpy() / unit, maxshape=(None,), chunks=True)
        f.create_dataset("events/ps", data=events.p.numpy() > 0, maxshape=(None,), chunks=True)  # bool
        for i, (img, start) in enumerate(zip(images(colour), STARTS_US)):
            data = img.transpose(2, 0, 1) if channels_first else img
            ds = f.create_dataset(f"images/image{i:09d}", data=data)
            ds.attrs["size"] = data.shape
            ds.attrs["timestamp"] = (start + EXPOSURE / 2) / unit
            ds.attrs["type"] = "color_bgr" if colour else "greyscale"
            if exposure_attrs:
                ds.attrs["exposure_start"] = start / unit
                ds.attrs["exposure_end"] = (start + EXPOSURE) / unit
            if sharp:
                f.create_dataset(f"sharp_images/image{i:09d}", data=data // 2)
        f.attrs.update({"num_events": len(events), "num_imgs": len(STARTS_US), "t0": 0.0,
                        "sensor_resolution": list(resolution)})
    return path


def window(events: Events, start: float, after: float) -> Events:
    return events.window(start, start + EXPOSURE + after)


def test_reads_and_converts_units(tmp_path, events):
    rec = open_recording(make(tmp_path / "eu.h5", events), after_us=1500.0)
    assert isinstance(rec, EventUtilsRecording) and rec.time_unit == "s" and rec.sensor_size == (H, W)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        batches = list(rec)
    assert len(batches) == 3
    for b, start, img in zip(batches, STARTS_US, images()):
        assert float(b.exposure_start) == pytest.approx(start, abs=1e-6)  # seconds -> µs
        assert float(b.exposure_time) == pytest.approx(EXPOSURE, abs=1e-6)
        want = window(events, start, 1500.0)
        torch.testing.assert_close(b.events.t, want.t, rtol=0, atol=1e-6)
        assert torch.equal(b.events.x, want.x) and torch.equal(b.events.p, want.p)  # bool -> ±1
        torch.testing.assert_close(b.blurry[0, 0], torch.from_numpy(img / 255.0).float())


def test_random_access_matches_streaming(tmp_path, events):
    rec = EventUtilsRecording(make(tmp_path / "eu.h5", events), chunk_events=9, before_us=700.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        streamed = list(rec)
        for i in range(3):
            assert torch.equal(rec.frame(i).events.t, streamed[i].events.t)
    got = rec.events_between(2000.0, 7000.0)
    assert torch.equal(got.t, events.window(2000.0, 7000.0).t.round())


def test_explicit_and_microsecond_units(tmp_path, events):
    path = make(tmp_path / "us.h5", events, unit=1.0)  # integer-valued µs stored as float
    rec = EventUtilsRecording(path)
    assert rec.time_unit == "us" and float(rec.frame(1).exposure_start) == 6000.0
    forced = EventUtilsRecording(make(tmp_path / "ms.h5", events, unit=1e3), time_unit="ms")
    assert float(forced.frame(1).exposure_start) == pytest.approx(6000.0)
    with pytest.raises(ValueError, match="time_unit"):
        EventUtilsRecording(path, time_unit="minutes")


def test_missing_exposure_timestamps(tmp_path, events):
    path = make(tmp_path / "noexp.h5", events, exposure_attrs=False)
    with pytest.raises(RecordingError, match="noexp.h5: frame 0 \\(image000000000\\) has no exposure_start"):
        list(open_recording(path))
    mid = EventUtilsRecording(path, exposure_us=EXPOSURE)
    assert float(mid.frame(1).exposure_start) == pytest.approx(6000.0)
    start = EventUtilsRecording(path, exposure_us=1000.0, timestamp_is="start")
    assert float(start.frame(1).exposure_start) == pytest.approx(6000.0 + EXPOSURE / 2)
    end = EventUtilsRecording(path, exposure_us=1000.0, timestamp_is="end")
    assert float(end.frame(1).exposure_end) == pytest.approx(6000.0 + EXPOSURE / 2)


def test_an_exposure_given_for_images_that_carry_their_own_is_not_used_and_says_so(tmp_path, events):
    rec = EventUtilsRecording(make(tmp_path / "exp.h5", events), exposure_us=1000.0)
    with pytest.warns(UserWarning, match="exp.h5: images with their own exposure_start/exposure_end keep them; "
                                         "exposure_us=1000 is used only"):
        batch = rec.frame(1)
    assert float(batch.exposure_start) == pytest.approx(6000.0)
    assert float(batch.exposure_time) == pytest.approx(EXPOSURE)


def test_colour_bgr_channels_first_and_sharp(tmp_path, events):
    rec = EventUtilsRecording(make(tmp_path / "c.h5", events, colour=True, sharp=True))
    b = rec.frame(0)
    bgr = images(colour=True)[0]
    assert b.blurry.shape == (1, 3, H, W)
    torch.testing.assert_close(b.blurry[0, 0], torch.from_numpy(bgr[..., 2] / 255.0).float())  # R first
    assert b.sharp is not None and b.sharp.shape == (1, 3, H, W)
    efnet = EventUtilsRecording(make(tmp_path / "chw.h5", events, colour=True, channels_first=True))
    assert efnet.sensor_size == (H, W) and efnet.frame(0).blurry.shape == (1, 3, H, W)


def test_sensor_resolution_disagreeing_with_images(tmp_path, events):
    path = make(tmp_path / "wh.h5", events, resolution=(W, H))  # someone stored (W, H)
    with pytest.warns(UserWarning, match="wh.h5: sensor_resolution \\(8, 5\\) disagrees with the images"):
        rec = EventUtilsRecording(path)
    assert rec.sensor_size == (H, W)


def test_write_round_trip_copies_images(tmp_path, events):
    src = EventUtilsRecording(make(tmp_path / "src.h5", events, sharp=True))
    shifted = Events(events.x, events.y, events.t - 250.0, events.p, sensor_size=(H, W))
    out = tmp_path / "out.h5"
    assert write_events(out, shifted, like=src) == "event_utils"
    with h5py.File(out) as f:
        assert f["events/ps"].dtype == np.bool_ and f["events/xs"].dtype == np.int16
        assert f.attrs["num_events"] == len(events) and f.attrs["time_unit"] == "s"
        assert list(f.attrs["sensor_resolution"]) == [H, W] and len(f["sharp_images"]) == 3
        assert f["images/image000000001"].attrs["event_idx"] > 0
    back = EventUtilsRecording(out)
    torch.testing.assert_close(back.events_between(-1e9, 1e9).t, shifted.t, rtol=0, atol=1e-6)
    assert [s for s, _, _ in back.frame_times()] == pytest.approx(STARTS_US)


def test_write_from_our_format_and_chunks(tmp_path, events):
    from tests.test_io_h5 import fake_sequence

    seq = fake_sequence()
    src_path = tmp_path / "ours.h5"
    write_sequence(src_path, seq)
    src = H5Recording(src_path)
    out = tmp_path / "eu_out.h5"
    ev = seq.delayed_events
    write_event_utils(out, [ev.select(ev.t < 8000), ev.select(ev.t >= 8000)], like=src, time_unit="us")
    back = EventUtilsRecording(out)
    assert back.time_unit == "us" and back.num_frames == 3
    assert torch.equal(back.events_between(-1e9, 1e9).t, ev.t)
    b = back.frame(1)
    assert float(b.exposure_start) == float(seq.exposure_start[1])
    torch.testing.assert_close(b.blurry, seq.blurry[1:2], rtol=0, atol=0.5 / 255 + 1e-6)  # uint8 images


def test_bad_files(tmp_path, events):
    junk = tmp_path / "junk.h5"
    junk.write_bytes(b"\x89HDF\r\n\x1a\n" + b"\x00" * 100)
    with pytest.raises(RecordingError, match="junk.h5"):
        EventUtilsRecording(junk)
    with h5py.File(tmp_path / "noev.h5", "w") as f:
        f["events/xs"] = [1]
    with pytest.raises(RecordingError, match="noev.h5: no /events/xs, ys, ts, ps"):
        EventUtilsRecording(tmp_path / "noev.h5")
    path = make(tmp_path / "noimg.h5", events)
    with h5py.File(path, "r+") as f:
        del f["images"]
    with pytest.raises(RecordingError, match="noimg.h5: no /images"):
        len(EventUtilsRecording(path))


def test_polarity_outside_the_conventions_is_refused(tmp_path, events):
    path = make(tmp_path / "p5.h5", events)
    with h5py.File(path, "r+") as f:
        ps = f["events/ps"][:].astype(np.uint8)
        ps[10] = 5  # used to be read as ON
        del f["events/ps"]
        f["events/ps"] = ps
    match = r"p5.h5: /events \(events 0..499\): polarity must be 0/1, -1/\+1 or bool, got values \[5\]"
    with pytest.raises(RecordingError, match=match):
        list(EventUtilsRecording(path))
    with pytest.raises(RecordingError, match=r"p5.h5: /events .*polarity must be"):
        EventUtilsRecording(path).events_between(-1e12, 1e12)


def test_event_columns_of_different_lengths_are_refused_at_open(tmp_path, events):
    path = make(tmp_path / "short.h5", events)
    with h5py.File(path, "r+") as f:
        ts = f["events/ts"][:-3]
        del f["events/ts"]
        f["events/ts"] = ts
    with pytest.raises(RecordingError, match="short.h5: /events/xs, ys, ts, ps differ in length: xs 500, ys 500, "
                                             "ts 497, ps 500"):
        EventUtilsRecording(path)
