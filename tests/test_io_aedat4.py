"""AEDAT4 reader, on the two shared DAVIS346 recordings (see shared/data/davis346/README.md)."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

from evlatcorr.io import AedatRecording, RecordingError, open_recording
from tests.conftest import shared_data_dir

DAVIS = shared_data_dir() / "davis346"
CRADLE = DAVIS / "cradle_lowlight.aedat4"
STREET = DAVIS / "street_static.aedat4"
needs_files = pytest.mark.skipif(not (CRADLE.is_file() and STREET.is_file()), reason="shared DAVIS recordings absent")

# the README's "events in exposure" column, measured independently with the aedat package
CRADLE_IN_EXPOSURE = [8077, 11230, 20711, 20882, 13897, 7422, 2636, 3238, 8181, 11820, 19058, 22067, 8355]


def stream(rec):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        batches = list(rec)
    return batches, [str(w.message) for w in caught]


@pytest.fixture(scope="module")
def cradle_events():
    if not CRADLE.is_file():
        pytest.skip("shared DAVIS recordings absent")
    return np.concatenate(list(AedatRecording(CRADLE).iter_event_chunks()))


@needs_files
def test_cradle_frames_exposures_and_events(cradle_events):
    rec = open_recording(CRADLE)
    assert isinstance(rec, AedatRecording) and rec.sensor_size == (260, 346) and rec.num_frames == 13
    batches, msgs = stream(rec)
    assert len(batches) == 13
    for i, b in enumerate(batches):
        assert b.blurry.shape == (1, 1, 260, 346) and 0 <= float(b.blurry.min()) and float(b.blurry.max()) <= 1
        assert float(b.exposure_time) == 20000.0
        assert float(b.exposure_start) == 1643243628757800.0 + 40000.0 * i
        inside = b.events.window(b.exposure_start, b.exposure_end)
        assert len(inside) == CRADLE_IN_EXPOSURE[i], i
        assert b.meta["file"] == str(CRADLE) and b.meta["frame"] == i
    # dark frames: the README's median grey level 26-27 / 255
    assert 24 / 255 < float(batches[0].blurry.median()) < 29 / 255
    # frame 12's window (exposure end + 20 ms) runs past the last event: warned, naming file and frame
    assert any("cradle_lowlight.aedat4: frame 12: events end at 1643243629248083 us" in m for m in msgs)
    assert not any("frame 11" in m for m in msgs)
    assert len(cradle_events) == 319512 and np.all(np.diff(cradle_events["t"]) >= 0)
    assert abs(float((cradle_events["p"] > 0).mean()) - 0.522) < 0.001 and set(np.unique(cradle_events["p"])) == {-1, 1}


@needs_files
@pytest.mark.parametrize("before, after", [(0.0, None), (5000.0, 0.0), (0.0, 60000.0)])
def test_cradle_streaming_matches_whole_file(cradle_events, before, after):
    rec = AedatRecording(CRADLE, before_us=before, after_us=after)
    batches, _ = stream(rec)
    for b in batches:
        lo = float(b.exposure_start) - before
        hi = float(b.exposure_end) + (20000.0 if after is None else after)
        want = cradle_events[(cradle_events["t"] >= lo) & (cradle_events["t"] < hi)]
        np.testing.assert_array_equal(b.events.t.numpy(), want["t"])
        np.testing.assert_array_equal(b.events.x.numpy(), want["x"])
        np.testing.assert_array_equal(b.events.p.numpy(), want["p"])
    assert rec.peak_buffered_events < len(cradle_events) // 3  # bounded by the windows, not the file


@needs_files
def test_frame_packets_arriving_late_are_an_error_not_a_loss():
    """Frame packets come ~10.3 ms after their exposure start in this file."""
    batches, _ = stream(AedatRecording(CRADLE, max_frame_delay_us=15000.0))
    assert len(batches) == 13
    late = "cradle_lowlight.aedat4: frame 0 came 10283 us after its window start .* raise max_frame_delay_us"
    with pytest.raises(RecordingError, match=late):
        stream(AedatRecording(CRADLE, max_frame_delay_us=5000.0))


@needs_files
def test_street_static_uses_exposure_fields_and_warns_for_frame_0():
    rec = AedatRecording(STREET, after_us=500.0)
    batches, msgs = stream(rec)
    assert len(batches) == 4 and all(float(b.exposure_time) == 500.0 for b in batches)
    # the frames' t is mid-exposure in this file; we use exposure_begin_t
    assert float(batches[0].exposure_start) == 1589163147364965.0
    counts = [len(b.events.window(b.exposure_start, b.exposure_end)) for b in batches]
    assert counts == [0, 12, 11, 19]
    assert any("street_static.aedat4: frame 0: its window starts at" in m and "before the first event" in m
               for m in msgs)
    assert any("street_static.aedat4: frame 0 has no events inside its exposure" in m for m in msgs)


@needs_files
def test_frame_and_info():
    rec = AedatRecording(CRADLE)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        streamed = list(rec)
    b = rec.frame(4)
    assert torch.equal(b.events.t, streamed[4].events.t) and torch.equal(b.blurry, streamed[4].blurry)
    info = rec.info()
    assert info["format"] == "aedat4" and info["frames"] == 13 and info["events"] == 319512
    assert info["event_time_us (first, last)"] == (1643243628737093.0, 1643243629248083.0)
    assert info["exposure_us (min, max)"] == (20000.0, 20000.0)
    got = rec.events_between(1643243628757800.0, 1643243628777800.0)
    assert len(got) == CRADLE_IN_EXPOSURE[0]


# bad input -----------------------------------------------------------------------------------
def test_wrong_format(tmp_path):
    old = tmp_path / "old.aedat"
    old.write_bytes(b"#!AER-DAT2.0\r\n# some header\r\n")
    with pytest.raises(RecordingError, match="old.aedat: not an AEDAT4 file"):
        AedatRecording(old)


@needs_files
def test_a_truncated_file_keeps_what_it_holds_and_says_so(tmp_path):
    # a recording cut off inside a packet (a crash, a full disk): the packets before it are read, with a warning
    truncated = tmp_path / "t.aedat4"
    truncated.write_bytes(CRADLE.read_bytes()[:2_000_000])
    batches, messages = stream(AedatRecording(truncated))
    assert any(m.startswith(f"{truncated}: the file ends inside the packet after packet ") for m in messages)
    whole, _ = stream(AedatRecording(CRADLE))
    assert 0 < len(batches) < len(whole)
    for cut, full in zip(batches[:-1], whole):  # the frames before the cut are the whole file's
        assert torch.equal(cut.blurry, full.blurry) and torch.equal(cut.events.t, full.events.t)


@needs_files
def test_a_corrupt_packet_is_refused(tmp_path):
    data = bytearray(CRADLE.read_bytes())
    data[300_000:300_064] = b"\xab" * 64  # inside a compressed packet
    bad = tmp_path / "c.aedat4"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="c.aedat4: corrupt file after packet"):
        stream(AedatRecording(bad))


@needs_files
def test_corrupt_header(tmp_path):
    data = bytearray(STREET.read_bytes())
    data[14:200] = b"\xff" * 186
    bad = tmp_path / "bad.aedat4"
    bad.write_bytes(bytes(data))
    with pytest.raises(RecordingError, match="bad.aedat4: cannot decode the AEDAT4 header"):
        AedatRecording(bad)


@needs_files
def test_frame_conversion_colour_16bit_and_refusals():
    rec = AedatRecording(STREET)
    base = dict(width=346, height=260, offset_x=0, offset_y=0, exposure_begin_t=10, exposure_end_t=20)
    rgb = np.zeros((260, 346, 3), np.uint8)
    rgb[..., 0] = 255
    img = rec._image({**base, "format": "RGB", "pixels": rgb}, 3)
    assert img.shape == (3, 260, 346) and img[0].min() == 1.0 and img[1:].max() == 0.0
    rgba = np.zeros((260, 346, 4), np.uint8)
    assert rec._image({**base, "format": "RGBA", "pixels": rgba}, 3).shape == (3, 260, 346)
    grey16 = np.full((260, 346), 65535, np.uint16)
    assert float(rec._image({**base, "format": "I;16", "pixels": grey16}, 3).max()) == 1.0
    with pytest.raises(RecordingError, match="street_static.aedat4: frame 3 .*unsupported frame format"):
        rec._image({**base, "format": "YUV", "pixels": rgb}, 3)
    with pytest.raises(RecordingError, match="frame 3 .*region of interest"):
        rec._image({**base, "width": 100, "offset_x": 10, "format": "L", "pixels": rgb[:, :100, 0]}, 3)
    with pytest.raises(RecordingError, match="street_static.aedat4: frame 7 has no valid exposure timestamps"):
        rec._exposure({**base, "exposure_begin_t": 0, "exposure_end_t": 0}, 7)


@pytest.mark.parametrize("tail", [b"\x00" * 100, b"\x10\x00", (64).to_bytes(4, "little") + b"\x00" * 64],
                         ids=["empty header", "ends inside the size", "no IOHeader"])
def test_a_garbled_header_is_refused_before_the_decoder(tmp_path, tail):
    # the decoder's Rust code panics on these (printing a trace) rather than raising: they are refused before it
    bad = tmp_path / "g.aedat4"
    bad.write_bytes(b"#!AER-DAT4.0\r\n" + tail)
    with pytest.raises(RecordingError, match="g.aedat4: cannot decode the AEDAT4 header"):
        AedatRecording(bad)


def test_a_panic_of_the_decoder_is_a_recording_error(tmp_path, monkeypatch):
    import aedat

    class PanicException(BaseException):  # pyo3's, as the Rust decoder raises it: not an Exception
        pass

    def panics(path):
        raise PanicException("range end index 4 out of range for slice of length 0")

    monkeypatch.setattr(aedat, "Decoder", panics)
    header = tmp_path / "h.aedat4"
    header.write_bytes(b"#!AER-DAT4.0\r\n" + (8).to_bytes(4, "little") + b"\x00\x00\x00\x00IOHE")
    with pytest.raises(RecordingError, match="h.aedat4: cannot decode the AEDAT4 header \\(range end index"):
        AedatRecording(header)

    def interrupted(path):
        raise KeyboardInterrupt

    monkeypatch.setattr(aedat, "Decoder", interrupted)
    with pytest.raises(KeyboardInterrupt):  # what is not the decoder's failure passes through
        AedatRecording(header)
