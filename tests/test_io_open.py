"""``open_recording`` (format sniffing) and ``write_events`` (writing back in the input's format)."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import torch

from evlatcorr.io import (
    EventUtilsRecording,
    H5Recording,
    RecordingError,
    open_recording,
    write_events,
    write_sequence,
)
from tests.test_io_h5 import fake_sequence


@pytest.fixture()
def ours(tmp_path):
    path = tmp_path / "ours.h5"
    write_sequence(path, fake_sequence())
    return path


def test_sniffs_by_content_not_extension(tmp_path, ours):
    renamed = tmp_path / "recording.dat"
    renamed.write_bytes(ours.read_bytes())
    assert isinstance(open_recording(renamed), H5Recording)
    assert isinstance(open_recording(str(ours)), H5Recording)


# a file's name, its bytes, and the start of the message that names what is wrong with it
BAD_FILES = [
    ("junk.bin", b"\x00\x01 not a recording", "junk.bin: unknown format \\(supported: AEDAT4"),
    ("fake.h5", b"not hdf5 at all", "fake.h5: named like HDF5 but has no HDF5 signature"),
    ("fake.aedat4", b"hello world, not an event file", "fake.aedat4: named like AEDAT but"),
    ("old.aedat", b"#!AER-DAT2.0\r\n# some header\r\n", "old.aedat: AEDAT 2.0 is not supported"),
]


@pytest.mark.parametrize(("name", "content", "message"), BAD_FILES)
def test_bad_file_is_named(tmp_path, name, content, message):
    (tmp_path / name).write_bytes(content)
    with pytest.raises(RecordingError, match=message):
        open_recording(tmp_path / name)


def test_unknown_and_missing(tmp_path):
    with pytest.raises(FileNotFoundError, match="nothing.h5: no such file"):
        open_recording(tmp_path / "nothing.h5")
    with h5py.File(tmp_path / "other.h5", "w") as f:
        f["something"] = [1, 2]
    with pytest.raises(RecordingError, match="other.h5: unknown format: an HDF5 file with top-level \\['something'\\]"):
        open_recording(tmp_path / "other.h5")
    (tmp_path / "emptydir").mkdir()
    with pytest.raises(RecordingError, match="emptydir: unknown format: a folder"):
        open_recording(tmp_path / "emptydir")


def test_reader_options_are_checked(ours):
    with pytest.raises(TypeError, match="read by H5Recording, which does not take \\['exposure_us'\\]"):
        open_recording(ours, exposure_us=100.0)
    assert open_recording(ours, sequence=0, after_us=10.0).after_us == 10.0


def test_frame_gamma_makes_display_encoded_frames_linear_in_every_read(ours):
    plain, encoded = open_recording(ours), open_recording(ours, frame_gamma=2.2)
    assert plain.frame_gamma == 1.0 and encoded.frame_gamma == 2.2
    for index, (streamed, kept) in enumerate(zip(encoded, plain)):
        torch.testing.assert_close(streamed.blurry, kept.blurry.clamp(0, 1) ** 2.2)
        if kept.sharp is not None:
            torch.testing.assert_close(streamed.sharp, kept.sharp.clamp(0, 1) ** 2.2)
        torch.testing.assert_close(streamed.events.t, kept.events.t)  # the events are untouched
        torch.testing.assert_close(encoded.frame(index).blurry, streamed.blurry)  # random access too
    for bad in (0, -1.0, float("nan"), float("inf"), "2.2", True):
        with pytest.raises(ValueError, match="frame_gamma must be a finite number > 0"):
            open_recording(ours, frame_gamma=bad)


def test_write_events_picks_the_input_format(tmp_path, ours):
    seq = fake_sequence()
    rec = H5Recording(ours)
    assert write_events(tmp_path / "a.h5", seq.delayed_events, like=rec) == "evlatcorr"
    assert isinstance(open_recording(tmp_path / "a.h5"), H5Recording)
    assert write_events(tmp_path / "b.h5", seq.delayed_events, like=rec, format="event_utils") == "event_utils"
    eu = open_recording(tmp_path / "b.h5")
    assert isinstance(eu, EventUtilsRecording) and eu.num_frames == 3
    assert write_events(tmp_path / "c.h5", seq.delayed_events, like=eu) == "event_utils"
    back = EventUtilsRecording(tmp_path / "c.h5")
    torch.testing.assert_close(back.events_between(-1e9, 1e9).t, seq.delayed_events.t, rtol=0, atol=1e-3)
    with pytest.raises(ValueError, match="format must be"):
        write_events(tmp_path / "d.h5", seq.delayed_events, format="aedat4")
    assert not (tmp_path / "d.h5").exists()
    np.testing.assert_array_equal([f.index for f in back.frames()], [0, 1, 2])
