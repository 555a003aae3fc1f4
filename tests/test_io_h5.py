"""Our HDF5 format: writers, readers, streaming and bad input."""

from __future__ import annotations

import json
import re
import warnings

import h5py
import numpy as np
import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.io import (
    H5Recording,
    RecordingError,
    num_sequences,
    open_recording,
    read_sequence,
    read_sequences,
    write_dataset,
    write_events,
    write_h5_events,
    write_sequence,
)
from evlatcorr.io import h5 as h5mod
from evlatcorr.simulate import SimulatedSequence
from tests.conftest import random_events

H, W, F = 6, 7, 3
EXPOSURE = 4000.0


def fake_sequence(seed: int = 0, num_events: int = 600) -> SimulatedSequence:
    """A SimulatedSequence with random content (the simulator itself is tested elsewhere)."""
    g = torch.Generator().manual_seed(seed)
    starts = torch.arange(F, dtype=torch.float64) * 5000.0 + 1000.0
    delayed = random_events(num_events, (H, W), (0.0, 16000.0), seed=seed)
    ideal = random_events(num_events // 2, (H, W), (0.0, 16000.0), seed=seed + 1)
    return SimulatedSequence(
        blurry=torch.rand(F, 3, H, W, generator=g), sharp=torch.rand(F, 3, H, W, generator=g),
        exposure_start=starts, exposure_end=starts + EXPOSURE, ideal_events=ideal, delayed_events=delayed,
        true_latency=torch.rand(F, 1, H, W, generator=g) * 3000, target_times=torch.tensor([5500.0, 10500.0]),
        target_frames=torch.rand(2, 3, H, W, generator=g), threshold=0.25, seed=seed,
        config={"exposure_us": EXPOSURE, "latency": "constant", "size": [H, W]},
    )


@pytest.fixture(scope="module")
def seq() -> SimulatedSequence:
    return fake_sequence()


@pytest.fixture()
def h5_file(tmp_path, seq):
    path = tmp_path / "seq.h5"
    write_sequence(path, seq)
    return path


def assert_events_equal(a: Events, b: Events) -> None:
    for name in ("x", "y", "t", "p"):
        assert torch.equal(getattr(a, name).cpu(), getattr(b, name).cpu()), name


# round trips -------------------------------------------------------------------------------------
def test_sequence_round_trip_is_exact(h5_file, seq):
    back = read_sequence(h5_file)
    for name in ("blurry", "sharp", "exposure_start", "exposure_end", "true_latency", "target_times",
                 "target_frames"):
        a, b = getattr(back, name), getattr(seq, name)
        assert a.shape == b.shape and torch.equal(a, b.to(a.dtype)), name
    assert_events_equal(back.delayed_events, seq.delayed_events)
    assert_events_equal(back.ideal_events, seq.ideal_events)
    assert back.threshold == 0.25 and back.seed == 0 and back.config == seq.config
    assert back.delayed_events.sensor_size == (H, W)


def test_layout_and_attributes(h5_file):
    with h5py.File(h5_file) as f:
        assert f.attrs["format"] == "evlatcorr" and f.attrs["version"] == 1 and f.attrs["time_unit"] == "us"
        assert list(f.attrs["sensor_size"]) == [H, W] and str(f.attrs["creator"]).startswith("evlatcorr")
        assert json.loads(f.attrs["config"])["latency"] == "constant"
        assert f["events/x"].dtype == np.uint16 and f["events/t"].dtype == np.float64 and f["events/p"].dtype == np.int8
        assert set(np.unique(f["events/p"][:])) == {-1, 1}
        assert f["events/t"].compression == "lzf" and f["events/t"].chunks == (65536,)
        assert f["frames/blurry"].dtype == np.float32 and f["frames/blurry"].chunks == (1, 3, H, W)
        assert f["frames/latency"].shape == (F, 1, H, W)


def test_dataset_of_several_sequences(tmp_path):
    seqs = [fake_sequence(1), fake_sequence(2, num_events=300)]
    path = tmp_path / "set.h5"
    assert write_dataset(path, seqs, compression="gzip", name="test set") == 2
    assert num_sequences(path) == 2
    with h5py.File(path) as f:
        assert sorted(f["sequences"]) == ["0000", "0001"] and f.attrs["num_sequences"] == 2
        assert f["sequences/0001/events/t"].compression == "gzip" and f.attrs["name"] == "test set"
    back = list(read_sequences(path))
    assert [len(s.delayed_events) for s in back] == [600, 300]
    assert torch.equal(back[1].blurry, seqs[1].blurry)
    assert_events_equal(read_sequence(path, 1).ideal_events, seqs[1].ideal_events)
    with pytest.raises(IndexError, match="sequence 2 out of range"):
        read_sequence(path, 2)
    # as a recording: one segment per sequence, frame numbers run on
    rec = H5Recording(path, after_us=500.0)
    assert rec.num_segments == 2 and rec.num_frames == 2 * F
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        batches = list(rec)
    assert [b.meta["segment"] for b in batches] == [0, 0, 0, 1, 1, 1]
    want = seqs[1].delayed_events.window(float(seqs[1].exposure_start[2]), float(seqs[1].exposure_end[2]) + 500)
    assert_events_equal(batches[5].events, want)
    one = H5Recording(path, sequence=1)
    assert one.num_segments == 1 and one.num_frames == F


@pytest.mark.parametrize("dtype, atol", [("float32", 0.0), ("float16", 1e-3), ("uint16", 1e-5), ("uint8", 2e-3)])
def test_frames_dtype(tmp_path, seq, dtype, atol):
    path = tmp_path / "q.h5"
    write_sequence(path, seq, frames_dtype=dtype, compression=None)
    back = read_sequence(path)
    assert back.blurry.dtype == torch.float32
    torch.testing.assert_close(back.blurry, seq.blurry, rtol=0, atol=atol)
    err = float((back.blurry - seq.blurry).abs().max())
    assert (err == 0.0) if dtype == "float32" else (0 < err <= atol)


def test_write_options_are_checked(tmp_path, seq):
    with pytest.raises(ValueError, match="frames_dtype"):
        write_sequence(tmp_path / "a.h5", seq, frames_dtype="int7")
    with pytest.raises(ValueError, match="compression"):
        write_sequence(tmp_path / "b.h5", seq, compression="zip")
    try:
        import hdf5plugin  # noqa: F401
    except ImportError:
        with pytest.raises(ValueError, match="hdf5plugin"):
            write_sequence(tmp_path / "c.h5", seq, compression="zstd")
    assert list(tmp_path.iterdir()) == []


def test_write_sequence_duck_typing_and_group(tmp_path, seq):
    class Minimal:
        blurry = seq.blurry[:1]
        exposure_start = seq.exposure_start[:1]
        exposure_end = seq.exposure_end[:1]
        events = seq.delayed_events

    with h5py.File(tmp_path / "g.h5", "w") as f:
        write_sequence(f.create_group("mine"), Minimal())
        assert "mine/events/t" in f and "mine/ideal_events" not in f
    with pytest.raises(ValueError, match="lacks \\['events'\\]"):
        write_sequence(tmp_path / "x.h5", type("NoEvents", (), {"blurry": seq.blurry, "exposure_start": 0,
                                                                "exposure_end": 1})())


def test_atomic_write_leaves_nothing(tmp_path, seq):
    class Broken:
        blurry, exposure_start, exposure_end = seq.blurry, seq.exposure_start, seq.exposure_end
        delayed_events = seq.delayed_events

        @property
        def sharp(self):
            raise RuntimeError("boom")

    with pytest.raises(RuntimeError, match="boom"):
        write_sequence(tmp_path / "bad.h5", Broken())
    assert list(tmp_path.iterdir()) == []


def test_write_dataset_of_event_frames(tmp_path, seq):
    frames = seq.frames("delayed", after_us=1000.0)
    frames = frames.replace(latency=torch.full((F, 1, H, W), 123.0))
    path = tmp_path / "frames.h5"
    assert write_dataset(path, frames) == F
    rec = H5Recording(path, sequence=2, after_us=1000.0)
    with pytest.warns(UserWarning, match="frames.h5: frame 0: events end"):  # a sample holds only its window
        batch = rec.frame(0)
    assert_events_equal(batch.events, frames.events.sample(2))
    torch.testing.assert_close(batch.blurry[0], seq.blurry[2])
    torch.testing.assert_close(batch.sharp[0], seq.sharp[2])
    with h5py.File(path) as f:
        assert float(f["sequences/0002/frames/estimated_latency_map"][0, 0, 0, 0]) == 123.0


# reading: streaming vs random access -------------------------------------------------------------
def test_streaming_many_tiny_chunks_matches_in_memory(h5_file, seq):
    """Windows straddling many chunk boundaries: identical events per frame, each event read once."""
    rec = H5Recording(h5_file, after_us=3000.0, chunk_events=7)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        batches = list(rec)
    reference = seq.frames("delayed", after_us=3000.0)
    assert len(batches) == F
    for i, b in enumerate(batches):
        assert_events_equal(b.events, reference.events.sample(i))
        assert torch.equal(b.blurry[0], seq.blurry[i]) and torch.equal(b.sharp[0], seq.sharp[i])
        assert torch.equal(b.meta["true_latency"], seq.true_latency[i:i + 1])
    chunks = list(rec.iter_event_chunks())
    assert len(chunks) == -(-600 // 7) and sum(len(c) for c in chunks) == 600
    np.testing.assert_array_equal(np.concatenate(chunks)["t"], seq.delayed_events.t.numpy())
    assert rec.peak_buffered_events < 400  # the windows (7 ms of 16 ms), not the file


def test_random_access_frame_equals_streamed(h5_file, seq, monkeypatch):
    monkeypatch.setattr(h5mod, "_CHUNK", 16)  # make the binary search loop over many small blocks
    rec = H5Recording(h5_file, before_us=200.0, after_us=2500.0, chunk_events=50)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        streamed = list(rec)
    for i in range(F):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            b = rec.frame(i)
        assert_events_equal(b.events, streamed[i].events)
        assert b.meta["window_us"] == (float(seq.exposure_start[i]) - 200, float(seq.exposure_end[i]) + 2500)
    got = rec.events_between(3333.3, 9876.5)
    assert_events_equal(got, seq.delayed_events.window(3333.3, 9876.5))
    assert len(rec.events_between(-10.0, -5.0)) == 0 and len(rec.events_between(1e9, 2e9)) == 0
    ideal = H5Recording(h5_file, group="ideal_events").events_between(0.0, 1e9)
    assert_events_equal(ideal, seq.ideal_events)


def test_open_recording_and_info(h5_file):
    rec = open_recording(h5_file, after_us=100.0)
    assert isinstance(rec, H5Recording) and rec.sensor_size == (H, W) and len(rec) == F
    info = rec.info()
    assert info["format"] == "evlatcorr-h5" and info["events"] == 600 and info["frames"] == F
    assert info["exposure_us (min, max)"] == (EXPOSURE, EXPOSURE)


def test_write_h5_events_with_frames_of_another_recording(tmp_path, h5_file, seq):
    src = H5Recording(h5_file)
    shifted = Events(seq.delayed_events.x, seq.delayed_events.y, seq.delayed_events.t - 100.0,
                     seq.delayed_events.p, sensor_size=(H, W))
    out = tmp_path / "corrected.h5"
    assert write_events(out, shifted, like=src, source="test") == "evlatcorr"
    back = H5Recording(out)
    assert_events_equal(back.events_between(-1e9, 1e9), shifted)
    assert [f.exposure_start for f in back.frames()] == seq.exposure_start.tolist()
    assert torch.equal(torch.from_numpy(next(iter(back.frames())).image), seq.blurry[0])
    # chunks larger than memory: an iterable of pieces gives the same file content
    out2 = tmp_path / "chunked.h5"
    pieces = (shifted.select((shifted.t >= a) & (shifted.t < a + 4000)) for a in range(-1000, 17000, 4000))
    write_h5_events(out2, pieces, sensor_size=(H, W))
    assert_events_equal(_all_events(out2, (H, W)), shifted)
    with pytest.raises(ValueError, match="sorted"):
        write_h5_events(tmp_path / "bad.h5", [shifted, shifted], sensor_size=(H, W))
    assert not (tmp_path / "bad.h5").exists()


def _all_events(path, size) -> Events:
    with h5py.File(path) as f:
        g = f["events"]
        return Events(g["x"][:].astype(np.int64), g["y"][:].astype(np.int64), g["t"][:], g["p"][:], sensor_size=size)


# bad input ---------------------------------------------------------------------------------------
def test_truncated_file_error_names_file(tmp_path, h5_file):
    data = h5_file.read_bytes()
    cut = tmp_path / "cut.h5"
    cut.write_bytes(data[: len(data) // 3])
    with pytest.raises(RecordingError, match="cut.h5"):
        rec = open_recording(cut)
        list(rec)


def test_missing_exposure_dataset(tmp_path, h5_file):
    with h5py.File(h5_file, "r+") as f:
        del f["frames/exposure_end"]
    with pytest.raises(RecordingError, match="seq.h5: missing dataset /frames/exposure_end"):
        H5Recording(h5_file)


def test_not_a_simulated_sequence(tmp_path, h5_file):
    with h5py.File(h5_file, "r+") as f:
        del f["ideal_events"]
    with pytest.raises(RecordingError, match="is not a simulated sequence .*ideal_events"):
        read_sequence(h5_file)
    assert H5Recording(h5_file).num_frames == F  # still a readable recording


def test_newer_version_and_wrong_format(tmp_path, h5_file):
    with h5py.File(h5_file, "r+") as f:
        f.attrs["version"] = 99
    with pytest.raises(RecordingError, match="version 99 is newer"):
        H5Recording(h5_file)
    other = tmp_path / "other.h5"
    with h5py.File(other, "w") as f:
        f["something"] = [1, 2]
    with pytest.raises(RecordingError, match="other.h5: not an evlatcorr HDF5 file"):
        H5Recording(other)


def test_frame_out_of_range_and_bad_exposure(tmp_path, h5_file):
    rec = H5Recording(h5_file)
    with pytest.raises(IndexError, match="frame 5 out of range"):
        rec.frame(5)
    with h5py.File(h5_file, "r+") as f:
        f["frames/exposure_end"][1] = f["frames/exposure_start"][1]
    with pytest.raises(RecordingError, match="seq.h5: frame 1 has exposure end"):
        list(H5Recording(h5_file))


def test_frame_without_events_warns_with_file_and_frame(tmp_path, h5_file):
    with h5py.File(h5_file, "r+") as f:
        f["frames/exposure_start"][0] = -9000.0
        f["frames/exposure_end"][0] = -8000.0
    rec = H5Recording(h5_file, after_us=100.0)
    with pytest.warns(UserWarning) as caught:
        rec.frame(0)
    msgs = [str(w.message) for w in caught]
    assert any("seq.h5: frame 0 has no events inside its exposure" in m for m in msgs)
    assert any("seq.h5: frame 0: its window starts at -9000 us" in m for m in msgs)


def test_event_frames_field_types(h5_file):
    b = H5Recording(h5_file).frame(0)
    assert isinstance(b, EventFrames) and b.events.t.dtype == torch.float64 and b.events.p.dtype == torch.int8
    assert b.exposure_start.dtype == torch.float64 and b.blurry.dtype == torch.float32


def test_reads_cache_files_of_the_first_writer(h5_file):
    """The first writer stored config as a Python repr: it still reads, with exposure_us recovered."""
    with h5py.File(h5_file, "r+") as f:
        f.attrs["config"] = "{'latency': 'constant', 'v': 1}"
        del f.attrs["creator"]
    back = read_sequence(h5_file)
    assert back.config["exposure_us"] == EXPOSURE and "latency" in back.config["source"]
    assert back.frames("delayed").events.batch_size == F


# polarity, column lengths and per-frame arrays are validated like the Events API ------------------------------
def _set_dataset(f: h5py.File, name: str, data: np.ndarray) -> None:
    del f[name]
    f[name] = data


def test_polarity_outside_the_conventions_is_refused(h5_file):
    # one event with p = 5 used to be read as +1
    with h5py.File(h5_file, "r+") as f:
        f["events/p"][7] = 5
    match = r"seq.h5: /events: polarity must be 0/1, -1/\+1 or bool, got values \[5\]"
    with pytest.raises(RecordingError, match=match):
        list(H5Recording(h5_file))  # streamed, chunk by chunk
    with pytest.raises(RecordingError, match=match):
        H5Recording(h5_file).events_between(-1e9, 1e9)  # random access
    with pytest.raises(RecordingError, match=match):
        read_sequence(h5_file)
    with h5py.File(h5_file, "r+") as f:
        f["events/p"][7] = 0  # -1, 0 and 1: two conventions mixed
    with pytest.raises(RecordingError, match="seq.h5: /events: polarity mixes the 0/1 and -1/\\+1 conventions"):
        list(H5Recording(h5_file))


@pytest.mark.parametrize(("dataset", "message", "short"), [
    # columns of different lengths
    ("events/x", "seq.h5: /events/x, y, t, p differ in length: x 598, y 600, t 600, p 600",
     "seq.h5: /events/x, y, t, p differ in length"),
    # a short per-frame array used to give an IndexError traceback when the last frame was read
    ("frames/exposure_end", "seq.h5: /frames/exposure_end has 2 entries but /frames/blurry has 3 frames",
     "seq.h5: /frames/exposure_end has 2 entries"),
])
def test_inconsistent_lengths_are_refused_at_open(h5_file, dataset, message, short):
    with h5py.File(h5_file, "r+") as f:
        cut = 2 if dataset.startswith("events") else 1
        _set_dataset(f, dataset, f[dataset][:-cut])
    with pytest.raises(RecordingError, match=re.escape(message)):
        H5Recording(h5_file)
    with pytest.raises(RecordingError, match=re.escape(short)):
        read_sequence(h5_file)


def test_per_frame_array_of_a_dataset_sequence_names_its_group(tmp_path, seq):
    path = tmp_path / "set.h5"
    write_dataset(path, [seq, fake_sequence(seed=1)])
    with h5py.File(path, "r+") as f:
        _set_dataset(f, "sequences/0001/frames/latency", f["sequences/0001/frames/latency"][:1])
    with pytest.raises(RecordingError, match="set.h5: /sequences/0001/frames/latency has 1 entries but "
                                             "/sequences/0001/frames/blurry has 3 frames"):
        H5Recording(path)


def test_random_access_checks_the_events_it_reads(h5_file):
    # frame() reads a slice without streaming: its events are checked as streamed chunks are
    with h5py.File(h5_file, "r+") as f:
        x = f["events/x"][:]
        x[:] = W + 3
        f["events/x"][:] = x
    with pytest.raises(RecordingError, match="seq.h5: event coordinates x in \\[10, 10\\].*outside the sensor"):
        H5Recording(h5_file).frame(1)


def test_writer_validates_lengths_and_polarity(tmp_path):
    with h5py.File(tmp_path / "w.h5", "w") as f:
        writer = h5mod.EventWriter(f)
        with pytest.raises(ValueError, match="polarity must be 0/1, -1/\\+1 or bool, got values \\[2\\]"):
            writer.append(np.array([0, 1]), np.array([0, 1]), np.array([1.0, 2.0]), np.array([1, 2]))
        with pytest.raises(ValueError, match="event columns differ in length: x 2, y 1, t 2, p 2"):
            writer.append(np.array([0, 1]), np.array([0]), np.array([1.0, 2.0]), np.array([1, 0]))
        writer.append(np.array([0, 1]), np.array([0, 1]), np.array([1.0, 2.0]), np.array([True, False]))
        assert f["events/p"][:].tolist() == [1, -1] and writer.count == 2
