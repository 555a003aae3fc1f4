from __future__ import annotations

import warnings

import h5py
import numpy as np
import pytest
import torch

from evlatcorr import Events
from evlatcorr.io import (
    AedatRecording,
    EventUtilsRecording,
    H5Recording,
    RecordingError,
    open_recording,
    read_sequence,
    write_event_utils,
    write_sequence,
)
from evlatcorr.simulate import simulate
from tests.conftest import shared_data_dir

DAVIS = shared_data_dir() / "davis346"
SMALL = dict(height=24, width=30, exposure_us=4000.0, frame_interval_us=5000.0)


@pytest.fixture(scope="module")
def sequence():
    return simulate("camera", num_frames=3, seed=0, **SMALL)


@pytest.fixture()
def h5_file(tmp_path, sequence):
    path = tmp_path / "seq.h5"
    write_sequence(path, sequence)
    return path


class TestOurHDF5:
    def test_round_trip(self, h5_file, sequence):
        back = read_sequence(h5_file)
        for name in ("blurry", "sharp", "exposure_start", "exposure_end", "true_latency", "target_times",
                     "target_frames"):
            torch.testing.assert_close(getattr(back, name), getattr(sequence, name).to(getattr(back, name).dtype))
        for which in ("ideal_events", "delayed_events"):
            a, b = getattr(back, which), getattr(sequence, which)
            assert torch.equal(a.t, b.t) and torch.equal(a.x, b.x) and torch.equal(a.p, b.p)
        with h5py.File(h5_file) as f:
            assert f.attrs["format"] == "evlatcorr" and list(f.attrs["sensor_size"]) == [24, 30]
            assert f["events/t"].compression == "lzf" and f["events/x"].dtype == np.uint16

    def test_streaming_many_small_chunks_loses_nothing(self, h5_file, sequence):
        reference = sequence.frames("delayed", after_us=4000.0)
        rec = H5Recording(h5_file, after_us=4000.0, chunk_events=7)  # windows straddle many chunk boundaries
        batches = list(rec)
        assert len(batches) == 3
        for i, batch in enumerate(batches):
            want = reference.events.sample(i)
            assert torch.equal(batch.events.t, want.t) and torch.equal(batch.events.x, want.x)
            torch.testing.assert_close(batch.blurry[0], sequence.blurry[i])
        # the whole stream, read in tiny chunks, is read exactly once
        total = sum(len(c) for c in rec.iter_event_chunks())
        assert total == len(sequence.delayed_events)

    def test_events_between_binary_search(self, h5_file, sequence):
        rec = H5Recording(h5_file, chunk_events=5)
        got = rec.events_between(6000.0, 9000.0)
        want = sequence.delayed_events.window(6000.0, 9000.0)
        assert torch.equal(got.t, want.t)

    def test_atomic_write_leaves_nothing(self, tmp_path, sequence):
        class Broken:
            def __getattr__(self, name):
                if name == "ideal_events":
                    return sequence.ideal_events
                raise RuntimeError("boom")

        with pytest.raises(RuntimeError):
            write_sequence(tmp_path / "bad.h5", Broken())
        assert list(tmp_path.iterdir()) == []

    def test_truncated_file(self, tmp_path, h5_file):
        data = h5_file.read_bytes()
        cut = tmp_path / "cut.h5"
        cut.write_bytes(data[: len(data) // 3])
        with pytest.raises((RecordingError, OSError)):
            list(H5Recording(cut))

    def test_warns_when_events_end_early(self, h5_file):
        rec = H5Recording(h5_file, after_us=50_000.0)
        with pytest.warns(UserWarning, match="frame 2: events end"):
            list(rec)


class TestEventUtils:
    def make(self, tmp_path, sequence, with_exposure=True):
        path = tmp_path / "eu.h5"
        ev = sequence.delayed_events
        with h5py.File(path, "w") as f:
            f["events/xs"] = ev.x.numpy().astype(np.int16)
            f["events/ys"] = ev.y.numpy().astype(np.int16)
            f["events/ts"] = ev.t.numpy() / 1e6  # seconds
            f["events/ps"] = (ev.p.numpy() > 0).astype(np.uint8)  # 0/1
            for i in range(sequence.num_frames):
                img = (sequence.blurry[i].mean(0).numpy() * 255).round().astype(np.uint8)
                ds = f.create_dataset(f"images/image{i:09d}", data=img)
                mid = float(sequence.exposure_start[i] + sequence.exposure_end[i]) / 2 / 1e6
                ds.attrs["timestamp"] = mid
                if with_exposure:
                    ds.attrs["exposure_start"] = float(sequence.exposure_start[i]) / 1e6
                    ds.attrs["exposure_end"] = float(sequence.exposure_end[i]) / 1e6
        return path

    def test_units_converted(self, tmp_path, sequence):
        rec = open_recording(self.make(tmp_path, sequence), after_us=4000.0)
        assert isinstance(rec, EventUtilsRecording) and rec.sensor_size == (24, 30)
        batch = rec.frame(1)
        assert float(batch.exposure_start) == pytest.approx(9000.0, abs=1e-3)  # seconds -> us
        want = sequence.frames("delayed", after_us=4000.0).events.sample(1)
        assert len(batch.events) == len(want)
        torch.testing.assert_close(batch.events.t, want.t, rtol=0, atol=1e-3)
        assert set(batch.events.p.tolist()) == {-1, 1}

    def test_missing_exposure(self, tmp_path, sequence):
        path = self.make(tmp_path, sequence, with_exposure=False)
        with pytest.raises(RecordingError, match="frame 0 .* no exposure"):
            list(open_recording(path))
        rec = EventUtilsRecording(path, exposure_us=4000.0)
        assert float(next(iter(rec)).exposure_time) == pytest.approx(4000.0)

    def test_write_round_trip(self, tmp_path, sequence):
        src = EventUtilsRecording(self.make(tmp_path, sequence))
        out = tmp_path / "out.h5"
        ev = Events(sequence.delayed_events.x, sequence.delayed_events.y, sequence.delayed_events.t.round(),
                    sequence.delayed_events.p, sensor_size=(24, 30))
        write_event_utils(out, ev, like=src)
        back = EventUtilsRecording(out, time_unit="s")
        chunks = np.concatenate(list(back.iter_event_chunks()))
        np.testing.assert_allclose(chunks["t"], ev.t.numpy(), atol=1e-3)
        assert len(list(back.frames())) == 3


@pytest.mark.skipif(not (DAVIS / "cradle_lowlight.aedat4").is_file(), reason="shared DAVIS recordings absent")
class TestAedat4:
    def test_cradle_frames_and_events(self):
        rec = AedatRecording(DAVIS / "cradle_lowlight.aedat4")
        assert rec.sensor_size == (260, 346)
        frames = list(rec.frames())
        assert len(frames) == 13
        assert all(f.exposure_end - f.exposure_start == 20000.0 for f in frames)
        assert frames[0].exposure_start == 1643243628757800.0 and frames[0].image.shape == (1, 260, 346)
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            batches = list(rec)
        # frame 12's window (exposure end + 20 ms) runs past the last event: warned, naming file and frame
        assert any("frame 12" in str(w.message) and "cradle_lowlight" in str(w.message) for w in caught)
        # the README's count of events inside frame 0's exposure
        b0 = batches[0]
        inside = b0.events.window(b0.exposure_start, b0.exposure_end)
        assert len(inside) == 8077

    def test_streaming_matches_whole_file(self):
        rec = AedatRecording(DAVIS / "street_static.aedat4", after_us=500.0)
        all_events = np.concatenate(list(rec.iter_event_chunks()))
        assert len(all_events) == 6676
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            batches = list(rec)
        for b in batches:
            lo, hi = float(b.exposure_start), float(b.exposure_end) + 500.0
            want = int(((all_events["t"] >= lo) & (all_events["t"] < hi)).sum())
            assert len(b.events) == want

    def test_wrong_format(self, tmp_path):
        bad = tmp_path / "x.aedat4"
        bad.write_bytes(b"#!AER-DAT2.0\r\n")
        with pytest.raises(RecordingError, match="not an AEDAT4"):
            AedatRecording(bad)
        truncated = tmp_path / "t.aedat4"
        truncated.write_bytes((DAVIS / "street_static.aedat4").read_bytes()[:5000])
        with pytest.raises(RecordingError, match="t.aedat4: the file ends inside its first packet"):
            list(AedatRecording(truncated).iter_event_chunks())


class TestGemNpz:
    def write(self, path, sequence, scale_factor=1, drop=None):
        ev = sequence.delayed_events
        data = dict(blur1=(sequence.blurry[0].numpy() * 255).round().astype(np.uint8),
                    blur2=(sequence.blurry[1].numpy() * 255).round().astype(np.uint8),
                    exp_start1=int(sequence.exposure_start[0]), exp_end1=int(sequence.exposure_end[0]),
                    exp_start2=int(sequence.exposure_start[1]), exp_end2=int(sequence.exposure_end[1]),
                    events=np.array({"x": ev.x.numpy(), "y": ev.y.numpy(), "t": ev.t.numpy().round(),
                                     "p": (ev.p.numpy() > 0).astype(np.uint8)}, dtype=object),
                    scale_factor=scale_factor)
        if drop:
            data.pop(drop)
        np.savez(path, **data)
        return path

    def test_reads_pairs(self, tmp_path, sequence):
        from evlatcorr.io import GemNpzRecording

        rec = open_recording(self.write(tmp_path / "pair.npz", sequence), after_us=4000.0)
        assert isinstance(rec, GemNpzRecording) and rec.sensor_size == (24, 30)
        batches = list(rec)
        assert len(batches) == 2 and batches[0].blurry.shape == (1, 3, 24, 30)
        assert float(batches[1].exposure_start) == float(sequence.exposure_start[1])
        want = sequence.delayed_events.window(float(sequence.exposure_start[1]), float(sequence.exposure_end[1]) + 4000)
        assert len(batches[1].events) == len(want) and set(batches[1].events.p.tolist()) == {-1, 1}

    def test_refuses_lower_resolution_events_and_missing_keys(self, tmp_path, sequence):
        from evlatcorr.io import GemNpzRecording

        with pytest.raises(RecordingError, match="pixel-aligned"):
            GemNpzRecording(self.write(tmp_path / "sf.npz", sequence, scale_factor=4))
        with pytest.raises(RecordingError, match="unknown format"):
            open_recording(self.write(tmp_path / "bad.npz", sequence, drop="exp_end2"))


class TestHighREV:
    def make(self, tmp_path, sequence, m=3, n=1):
        from PIL import Image

        video = tmp_path / "HighREV" / "train" / "seqA"
        (video / "blur").mkdir(parents=True)
        events_dir = tmp_path / "HighREV" / "train_event" / "seqA"
        events_dir.mkdir(parents=True)
        ev = sequence.delayed_events
        edges = torch.linspace(0.0, float(ev.t.max()) + 1, 3 * (m + n) + 1)
        for i in range(3 * (m + n)):
            sel = ev.window(float(edges[i]), float(edges[i + 1]))
            np.savez(events_dir / f"{i:06d}.npz", x=sel.y.numpy(), y=sel.x.numpy(),  # swapped, as in HighREV
                     timestamp=sel.t.numpy(), polarity=(sel.p.numpy() > 0).astype(np.uint8))
        for k in range(3):
            img = (sequence.blurry[k].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
            Image.fromarray(img).save(video / "blur" / f"{k:06d}.png")
        return video, edges

    def test_layout_and_conventions(self, tmp_path, sequence):
        from evlatcorr.io import HighREVRecording

        video, edges = self.make(tmp_path, sequence)
        rec = open_recording(video, m=3, n=1)
        assert isinstance(rec, HighREVRecording) and rec.sensor_size == (24, 30)
        frames = list(rec.frames())
        assert len(frames) == 3
        # frame 1 uses event files 4 and 5: its exposure spans their events
        inside = sequence.delayed_events.window(float(edges[4]), float(edges[6]))
        assert frames[1].exposure_start == pytest.approx(float(inside.t.min()))
        assert frames[1].exposure_end == pytest.approx(float(inside.t.max()))
        chunks = np.concatenate(list(rec.iter_event_chunks()))
        assert len(chunks) == len(sequence.delayed_events)
        np.testing.assert_array_equal(chunks["x"], sequence.delayed_events.x.numpy())  # un-swapped

    def test_missing_event_files(self, tmp_path, sequence):
        from evlatcorr.io import HighREVRecording

        video, _ = self.make(tmp_path, sequence)
        for f in sorted((tmp_path / "HighREV" / "train_event" / "seqA").glob("*.npz"))[8:]:
            f.unlink()
        with pytest.raises(RecordingError, match="frame 2"):
            list(HighREVRecording(video, m=3, n=1).frames())


def test_frame_without_events_and_events_after_last_frame_warn(tmp_path):
    seq = simulate("camera", num_frames=2, seed=0, **SMALL)
    path = tmp_path / "s.h5"
    write_sequence(path, seq)
    with h5py.File(path, "r+") as f:  # move frame 0 to before the first event
        f["frames/exposure_start"][0] = -9000.0
        f["frames/exposure_end"][0] = -8000.0
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        list(H5Recording(path, after_us=100.0))
    messages = [str(w.message) for w in caught]
    assert any("frame 0 has no events" in m and "s.h5" in m for m in messages)
    assert any("after the window of the last frame (1)" in m for m in messages)
