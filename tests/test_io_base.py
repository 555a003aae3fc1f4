"""The streaming engine of ``evlatcorr.io.base.Recording``, on in-memory recordings."""

from __future__ import annotations

import warnings
from collections.abc import Iterator

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from evlatcorr import EventFrames, Events
from evlatcorr.io.base import (
    EVENT_DTYPE,
    FrameInfo,
    Recording,
    RecordingError,
    SegmentEnd,
    iter_events_as_chunks,
    structured_events,
    to_unit_image,
)

SIZE = (4, 5)


def make_events(times: np.ndarray, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    n = len(times)
    return structured_events(rng.integers(0, SIZE[1], n), rng.integers(0, SIZE[0], n), np.sort(times),
                             rng.integers(0, 2, n))


class MemoryRecording(Recording):
    """Frames and events held in memory, served in chunks of the given sizes.

    ``interleaved=True`` serves frames and chunks in one stream, each frame placed ``delay`` µs of
    events after its exposure start (like AEDAT4 packets).
    """

    format_name = "memory"

    def __init__(self, segments: list[tuple[list[tuple[float, float]], np.ndarray]], chunk: int | list[int] = 3,
                 before_us: float = 0.0, after_us: float | None = None, interleaved: bool = False,
                 delay: float = 0.0, max_frame_delay_us: float = 1e9) -> None:
        super().__init__(".", before_us, after_us)
        self.path = "mem.rec"  # type: ignore[assignment]
        self.segments, self.chunk, self.interleaved, self.delay = segments, chunk, interleaved, delay
        self._frame_delay_us = max_frame_delay_us if interleaved else 0.0
        self.sensor_size = SIZE
        self.segment_names = [str(i) for i in range(len(segments))] if len(segments) > 1 else []
        self.chunks_served = 0
        self.events_served = 0

    def frames(self) -> Iterator[FrameInfo]:
        index = 0
        for seg, (frames, _) in enumerate(self.segments):
            for start, end in frames:
                yield FrameInfo(index, start, end, np.full((1, *SIZE), index / 100, np.float32), segment=seg)
                index += 1

    def _chunks_of(self, events: np.ndarray) -> Iterator[np.ndarray]:
        sizes = self.chunk if isinstance(self.chunk, list) else [self.chunk]
        i, k = 0, 0
        while i < len(events):
            size = max(1, sizes[k % len(sizes)])
            self.chunks_served += 1
            self.events_served += len(events[i:i + size])
            yield events[i:i + size]
            i, k = i + size, k + 1

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        for seg, (_, events) in enumerate(self.segments):
            if seg:
                yield SegmentEnd()
            yield from self._chunks_of(events)

    def _items(self):
        if not self.interleaved:
            yield from super()._items()
            return
        frames = list(self.frames())
        for seg, (_, events) in enumerate(self.segments):
            if seg:
                yield SegmentEnd()
            todo = [f for f in frames if f.segment == seg]
            for chunk in self._chunks_of(events):
                while todo and chunk["t"][0] >= todo[0].exposure_start + self.delay:
                    yield todo.pop(0)
                yield chunk
            yield from todo


def reference(events: np.ndarray, lo: float, hi: float) -> np.ndarray:
    return events[(events["t"] >= lo) & (events["t"] < hi)]


def stream(rec: Recording) -> list[EventFrames]:
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return list(rec)


# smoke / shapes -------------------------------------------------------------------------------
def test_smoke_one_frame():
    ev = make_events(np.arange(10.0))
    rec = MemoryRecording([([(2.0, 5.0)], ev)], chunk=4)
    (batch,) = stream(rec)
    assert isinstance(batch, EventFrames) and batch.blurry.shape == (1, 1, *SIZE)
    assert batch.events.t.tolist() == [2.0, 3.0, 4.0, 5.0, 6.0, 7.0]  # [2, 5 + 3)
    assert batch.meta == {"file": "mem.rec", "frame": 0, "segment": 0, "window_us": (2.0, 8.0)}
    assert float(batch.exposure_start) == 2.0 and float(batch.exposure_end) == 5.0
    assert rec.num_frames == len(rec) == 1


def test_before_and_after_parameters():
    ev = make_events(np.arange(20.0))
    rec = MemoryRecording([([(5.0, 8.0)], ev)], before_us=2.0, after_us=0.0)
    assert stream(rec)[0].events.t.tolist() == [3.0, 4.0, 5.0, 6.0, 7.0]
    rec = MemoryRecording([([(5.0, 8.0)], ev)], after_us=10.0)
    assert stream(rec)[0].events.t.tolist() == [float(v) for v in range(5, 18)]


@pytest.mark.parametrize("kwargs", [{"before_us": -1.0}, {"after_us": -5.0}, {"before_us": float("nan")}])
def test_bad_window_parameters(kwargs):
    with pytest.raises(ValueError, match="before_us|after_us"):
        MemoryRecording([([(0.0, 1.0)], make_events(np.arange(3.0)))], **kwargs)


# chunk boundaries: the "must not lose events" --------------------------------------
@pytest.mark.parametrize("interleaved", [False, True])
@pytest.mark.parametrize("chunk", [1, 2, 7, [1, 13, 2], 1000])
def test_tiny_chunks_equal_in_memory_read(chunk, interleaved):
    rng = np.random.default_rng(1)
    ev = make_events(np.round(rng.uniform(0, 1000, 400)), seed=1)  # duplicate stamps on boundaries
    frames = [(100.0 * k + 10, 100.0 * k + 60) for k in range(9)]
    rec = MemoryRecording([(frames, ev)], chunk=chunk, after_us=70.0, interleaved=interleaved, delay=30.0)
    batches = stream(rec)
    assert [b.meta["frame"] for b in batches] == list(range(9))
    for (start, end), b in zip(frames, batches):
        want = reference(ev, start, end + 70.0)  # windows overlap: [10, 130) and [110, 230)
        np.testing.assert_array_equal(b.events.t.numpy(), want["t"])
        np.testing.assert_array_equal(b.events.x.numpy(), want["x"])
        np.testing.assert_array_equal(b.events.p.numpy(), want["p"])
    assert rec.events_served == len(ev)  # every event read exactly once, in one pass
    if chunk == 1:
        assert rec.peak_buffered_events <= 130  # bounded by the overlapping windows, not the file (400)


@settings(max_examples=60, deadline=None)
@given(times=st.lists(st.integers(0, 300), min_size=0, max_size=120),
       starts=st.lists(st.integers(-20, 320), min_size=1, max_size=8),
       length=st.integers(1, 40), before=st.integers(0, 30), after=st.integers(0, 60),
       chunks=st.lists(st.integers(1, 9), min_size=1, max_size=5), interleaved=st.booleans(),
       delay=st.integers(0, 50))
def test_streaming_property(times, starts, length, before, after, chunks, interleaved, delay):
    """Any chunking, any frames: each frame gets exactly its window's events, each event is read once."""
    ev = make_events(np.asarray(times, dtype=np.float64))
    frames = [(float(s), float(s + length)) for s in sorted(starts)]
    rec = MemoryRecording([(frames, ev)], chunk=chunks, before_us=before, after_us=after, interleaved=interleaved,
                          delay=delay)
    batches = stream(rec)
    assert len(batches) == len(frames)
    for (s, e), b in zip(frames, batches):
        np.testing.assert_array_equal(b.events.t.numpy(), reference(ev, s - before, e + after)["t"])
    assert rec.events_served == len(ev)


def test_segments_do_not_mix_events():
    a = make_events(np.arange(0.0, 50.0))
    b = make_events(np.arange(0.0, 50.0) + 0.5, seed=3)  # its own time base, overlapping a's
    rec = MemoryRecording([([(10.0, 20.0), (30.0, 40.0)], a), ([(5.0, 15.0)], b)], chunk=6)
    batches = stream(rec)
    assert [x.meta["segment"] for x in batches] == [0, 0, 1] and [x.meta["frame"] for x in batches] == [0, 1, 2]
    np.testing.assert_array_equal(batches[2].events.t.numpy(), reference(b, 5.0, 25.0)["t"])
    np.testing.assert_array_equal(batches[1].events.t.numpy(), reference(a, 30.0, 50.0)["t"])
    assert rec.num_segments == 2
    with pytest.raises(ValueError, match="segment"):
        rec.events_between(0.0, 10.0)
    np.testing.assert_array_equal(rec.events_between(0.0, 3.0, segment=1).t.numpy(), [0.5, 1.5, 2.5])


# random access and summaries ----------------------------------------------------------------
def test_frame_and_events_between():
    ev = make_events(np.arange(100.0))
    rec = MemoryRecording([([(10.0, 20.0), (40.0, 45.0), (60.0, 70.0)], ev)], chunk=7)
    b = rec.frame(1)
    assert b.meta["frame"] == 1 and b.events.t.tolist() == [float(v) for v in range(40, 50)]
    assert rec.frame(-1).meta["frame"] == 2
    with pytest.raises(IndexError, match="frame 3 out of range"):
        rec.frame(3)
    got = rec.events_between(12.5, 30.0)
    assert got.t.tolist() == [float(v) for v in range(13, 30)] and got.sensor_size == SIZE
    assert len(rec.events_between(500.0, 600.0)) == 0
    with pytest.raises(ValueError, match="t1 >= t0"):
        rec.events_between(5.0, 1.0)


def test_info():
    ev = make_events(np.arange(10.0))
    info = MemoryRecording([([(2.0, 5.0), (6.0, 7.0)], ev)]).info()
    assert info["frames"] == 2 and info["events"] == 10 and info["exposure_us (min, max)"] == (1.0, 3.0)
    assert info["event_time_us (first, last)"] == (0.0, 9.0) and info["sensor_size (H, W)"] == SIZE
    assert 0 <= info["on_fraction"] <= 1
    # events inside each exposure [start, end): 2, 3, 4 and 6; chunks of 3 split the windows
    assert info["events in each exposure (min, median, max)"] == (1, 2, 3)
    assert info["frames without events in their exposure"] == "0 of 2"
    # and up to one exposure time after it, where the latency is searched: [2, 8) holds 2-7, [6, 8) holds 6 and 7
    assert info["events in each exposure and search window (min, median, max)"] == (2, 4, 6)
    assert info["frames under 100 events there (too few to tell a latency)"] == "2 of 2"


def test_info_counts_each_segments_events_in_its_own_frames():
    # two segments with their own time bases: a frame of one must not count the other's events at the same times
    a = make_events(np.arange(0.0, 50.0))
    b = make_events(np.arange(0.0, 50.0) + 0.5, seed=3)
    info = MemoryRecording([([(10.0, 20.0), (30.0, 40.0), (60.0, 70.0)], a), ([(5.0, 8.0)], b)], chunk=6).info()
    assert info["events in each exposure (min, median, max)"] == (0, 6, 10)  # 10, 10, 0 and 3: median 6.5
    assert info["frames without events in their exposure"] == "1 of 4"
    # [10, 30), [30, 50), [60, 80) of the first segment (20, 20, 0) and [5, 11) of the second (6)
    assert info["events in each exposure and search window (min, median, max)"] == (0, 13, 20)


# bad input: clear errors and warnings that name the file and the frame ----------------------
def test_warns_frame_without_events_and_late_window():
    ev = make_events(np.array([0.0, 1.0, 2.0, 50.0, 51.0]))
    rec = MemoryRecording([([(10.0, 20.0), (45.0, 55.0)], ev)], chunk=2)
    with pytest.warns(UserWarning) as caught:
        list(rec)
    msgs = [str(w.message) for w in caught]
    assert any("mem.rec: frame 0 has no events inside its exposure" in m for m in msgs)
    assert any("mem.rec: frame 1: events end at 51 us, before the end of its window 65 us" in m for m in msgs)


def test_warns_window_before_first_event_and_events_after_last_frame():
    ev = make_events(np.arange(100.0, 200.0))
    rec = MemoryRecording([([(50.0, 110.0)], ev)], chunk=5, after_us=10.0)
    with pytest.warns(UserWarning) as caught:
        batches = list(rec)
    msgs = [str(w.message) for w in caught]
    assert any("frame 0: its window starts at 50 us, 50 us before the first event (100 us)" in m for m in msgs)
    assert any("mem.rec: 80 events after the window of the last frame (0) lie in no frame's window" in m for m in msgs)
    assert len(batches[0].events) == 20


def test_no_warning_when_covered():
    ev = make_events(np.arange(0.0, 105.0))  # a short tail after the last window is normal
    rec = MemoryRecording([([(10.0, 20.0), (40.0, 50.0)], ev)], chunk=5, after_us=50.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(list(rec)) == 2


def test_unsorted_events_are_refused():
    ev = make_events(np.arange(10.0))
    ev["t"][5] = 1.0
    with pytest.raises(RecordingError, match="mem.rec: events are not sorted by time"):
        list(MemoryRecording([([(0.0, 9.0)], ev)], chunk=3))


def test_frames_out_of_order_are_refused():
    ev = make_events(np.arange(10.0))
    with pytest.raises(RecordingError, match="mem.rec: frame 1 starts its exposure at 2 us, before the previous"):
        list(MemoryRecording([([(5.0, 6.0), (2.0, 3.0)], ev)]))


def test_bad_exposure_is_refused():
    ev = make_events(np.arange(10.0))
    with pytest.raises(RecordingError, match="mem.rec: frame 0 has exposure end 5.0 us <= start 5.0 us"):
        list(MemoryRecording([([(5.0, 5.0)], ev)]))


def test_events_outside_sensor_are_refused():
    ev = make_events(np.arange(10.0))
    ev["x"][3] = SIZE[1]
    with pytest.raises(RecordingError, match="outside the sensor"):
        list(MemoryRecording([([(0.0, 9.0)], ev)]))


def test_late_frame_in_interleaved_stream():
    """A frame packet arriving after its events were released is an error, not a silent loss."""
    ev = make_events(np.arange(0.0, 1000.0))
    frames = [(100.0, 150.0), (400.0, 450.0)]
    ok = MemoryRecording([(frames, ev)], chunk=10, interleaved=True, delay=300.0, max_frame_delay_us=400.0)
    assert len(stream(ok)) == 2
    late = MemoryRecording([(frames, ev)], chunk=10, interleaved=True, delay=300.0, max_frame_delay_us=100.0)
    with pytest.raises(RecordingError, match="mem.rec: frame 0 came .* raise max_frame_delay_us"):
        stream(late)
    assert late.peak_buffered_events <= 120  # holds ~max_frame_delay_us of events while no frame waits


# conversion helpers ----------------------------------------------------------------------------
@pytest.mark.parametrize("p, want", [
    (np.array([0, 1, 1, 0]), [-1, 1, 1, -1]),
    (np.array([-1, 1, 1, -1]), [-1, 1, 1, -1]),
    (np.array([False, True, True, False]), [-1, 1, 1, -1]),
    (np.array([1, 1, 1, 1]), [1, 1, 1, 1]),
    (np.array([0, 0, 0, 0]), [-1, -1, -1, -1]),
    (np.array([[0], [1], [1], [0]], dtype=np.float32), [-1, 1, 1, -1]),
])
def test_structured_events_polarity(p, want):
    ev = structured_events(np.arange(4), np.arange(4), np.arange(4.0), p)
    assert ev.dtype == EVENT_DTYPE and ev["p"].tolist() == want


def test_structured_events_column_vectors_and_lengths():
    ev = structured_events(np.arange(3)[:, None], np.arange(3)[:, None], np.arange(3.0)[:, None], np.ones((3, 1)))
    assert ev["x"].tolist() == [0, 1, 2]
    with pytest.raises(ValueError, match="differ in length"):
        structured_events(np.arange(3), np.arange(2), np.arange(3.0), np.ones(3))


def test_to_unit_image():
    grey = to_unit_image(np.array([[0, 255]], np.uint8), "x")
    assert grey.shape == (1, 1, 2) and grey.dtype == np.float32 and grey[0, 0, 1] == 1.0
    rgba = np.zeros((2, 3, 4), np.uint16)
    rgba[..., 2] = 65535
    img = to_unit_image(rgba, "x")
    assert img.shape == (3, 2, 3) and img[2].min() == 1.0 and img[:2].max() == 0.0
    chw = to_unit_image(np.full((3, 2, 2), 255.0), "x", channels_last=False, scale=1 / 255)
    assert chw.shape == (3, 2, 2) and float(chw.max()) == 1.0
    with pytest.raises(RecordingError, match="f.png: unsupported pixel type int64"):
        to_unit_image(np.zeros((2, 2), np.int64), "f.png")
    with pytest.raises(RecordingError, match="unsupported image shape"):
        to_unit_image(np.zeros((2, 2, 5), np.uint8), "f.png")
    with pytest.raises(RecordingError, match="NaN"):
        to_unit_image(np.full((2, 2), np.nan, np.float32), "f.png")


def test_iter_events_as_chunks():
    ev = Events(torch.tensor([1, 2]), torch.tensor([0, 1]), torch.tensor([1.0, 2.0]), torch.tensor([0, 1]),
                sensor_size=SIZE)
    (chunk,) = list(iter_events_as_chunks(ev))
    assert chunk["p"].tolist() == [-1, 1] and chunk["t"].tolist() == [1.0, 2.0]
    two = list(iter_events_as_chunks([ev, chunk]))
    assert len(two) == 2
    batch = Events.cat([ev, ev])
    with pytest.raises(ValueError, match="one sample"):
        list(iter_events_as_chunks(batch))
    with pytest.raises(ValueError, match="expected Events"):
        list(iter_events_as_chunks([np.zeros(3)]))



@pytest.mark.parametrize("p, match", [
    (np.array([0, 1, 2]), "got values \\[2\\]"),
    (np.array([-1, 1, 5, -3]), "got values \\[-3, 5\\]"),
    (np.array([-1, 0, 1]), "mixes the 0/1 and -1/\\+1 conventions"),
    (np.array([0.0, 0.5, 1.0]), "got values \\[0.5\\]"),
    (np.array([1.0, np.nan]), "got values \\[nan\\]"),
    (np.array([300, 1], dtype=np.uint16), "got values \\[300\\]"),
    (np.array(["1", "0"]), "got dtype <U1"),
])
def test_structured_events_refuses_bad_polarity(p, match):
    n = len(p)
    with pytest.raises(RecordingError, match="f.h5: /events: polarity .*" + match):
        structured_events(np.arange(n), np.arange(n), np.arange(n, dtype=float), p, where="f.h5: /events")
    with pytest.raises(ValueError, match="polarity") as info:  # without a file: a plain ValueError
        structured_events(np.arange(n), np.arange(n), np.arange(n, dtype=float), p)
    assert not isinstance(info.value, RecordingError)


def test_structured_events_refuses_fractional_coordinates():
    with pytest.raises(RecordingError, match="f.npz: x must hold integer pixel coordinates"):
        structured_events(np.array([0.5, 1.0]), np.array([0, 1]), np.array([0.0, 1.0]), np.array([0, 1]),
                          where="f.npz")


@settings(max_examples=25, deadline=None)
@given(st.lists(st.sampled_from([-1, 1]), max_size=50), st.lists(st.sampled_from([0, 1]), max_size=50))
def test_structured_events_polarity_conventions_agree(signed, binary):
    # the same ON/OFF sequence in either convention (or as bool) gives the same ±1
    for values in (signed, binary):
        n = len(values)
        ev = structured_events(np.zeros(n, int), np.zeros(n, int), np.arange(n, dtype=float), np.array(values, int))
        assert ev["p"].tolist() == [1 if v > 0 else -1 for v in values]
        as_bool = structured_events(np.zeros(n, int), np.zeros(n, int), np.arange(n, dtype=float),
                                    np.array(values, int) > 0)
        assert as_bool["p"].tolist() == ev["p"].tolist()
