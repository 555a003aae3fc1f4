"""HighREV reader: split-folder (NTIRE 2025) and video-folder (REFID) layouts, swapped x/y."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from evlatcorr.io import HighREVRecording, RecordingError, open_recording

H, W = 6, 9
PIECES = 4  # per frame in the split layout: 3 inside the exposure, the last one after it


def random_events(rng, n, t0, t1):
    t = np.sort(rng.uniform(t0, t1, n)).round()
    return rng.integers(0, W, n), rng.integers(0, H, n), t, rng.integers(0, 2, n)


def save_npz(path, x, y, t, p, column=True):
    """As HighREV stores them: x and y swapped, (N, 1) columns, polarity 0/1."""
    shape = (-1, 1) if column else (-1,)
    np.savez(path, x=y.reshape(shape), y=x.reshape(shape), timestamp=t.reshape(shape), polarity=p.reshape(shape))


def save_png(path, rng):
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    Image.fromarray(img).save(path)
    return img


def make_split(root, sequences=("seqA", "seqB"), frames=3):
    """<split>/blur/<seq>_<k>.png, sharp/..., event/<seq>_<k>_<j>.npz; frame k spans [1000k, 1000k + 600)."""
    rng = np.random.default_rng(0)
    for d in ("blur", "sharp", "event"):
        (root / d).mkdir(parents=True)
    truth = {}
    for s, seq in enumerate(sequences):
        for k in range(frames):
            stem = f"{seq}_{k:05d}"
            blur = save_png(root / "blur" / f"{stem}.png", rng)
            save_png(root / "sharp" / f"{stem}.png", rng)
            pieces = []
            for j in range(PIECES):
                lo = 1000.0 * k + 200.0 * j + 7 * s
                hi = lo + (200.0 if j < PIECES - 1 else 400.0)
                pieces.append(random_events(rng, 15, lo, hi - 1))
                save_npz(root / "event" / f"{stem}_{j:02d}.npz", *pieces[-1])
            truth[(seq, k)] = (blur, pieces)
    return truth


def cat(pieces):
    return [np.concatenate(c) for c in zip(*pieces)]


def stream(rec):
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return list(rec)


def test_split_layout(tmp_path):
    truth = make_split(tmp_path / "val")
    rec = open_recording(tmp_path / "val", after_us=400.0)
    assert isinstance(rec, HighREVRecording) and rec.layout == "split" and rec.sensor_size == (H, W)
    assert rec.segment_names == ["seqA", "seqB"] and rec.num_frames == 6
    batches = stream(rec)
    assert [b.meta["sequence"] for b in batches] == ["seqA"] * 3 + ["seqB"] * 3
    for b, key in zip(batches, [(s, k) for s in ("seqA", "seqB") for k in range(3)]):
        blur, pieces = truth[key]
        x, y, t, p = cat(pieces[: PIECES - 1])  # the exposure: all pieces but the last
        assert float(b.exposure_start) == t.min() and float(b.exposure_end) == t.max()
        torch.testing.assert_close(b.blurry[0], torch.from_numpy(blur.transpose(2, 0, 1) / 255.0).float())
        assert b.sharp is not None and b.sharp.shape == (1, 3, H, W)
        inside = b.events.window(b.exposure_start, b.exposure_end + 1e-9)
        order = np.argsort(t, kind="stable")
        np.testing.assert_array_equal(inside.x.numpy(), x[order])  # swapped back: x is the column
        np.testing.assert_array_equal(inside.y.numpy(), y[order])
        np.testing.assert_array_equal(inside.p.numpy(), np.where(p[order] > 0, 1, -1))
    # the window after exposure end reaches into the last piece (and only this frame's sequence)
    _, pieces = truth[("seqA", 0)]
    end = float(batches[0].exposure_end)
    after = batches[0].events.window(end + 1e-9, end + 400.0)
    assert len(after) == int(((pieces[3][2] > end) & (pieces[3][2] < end + 400)).sum()) > 0


def test_split_layout_one_sequence_and_units(tmp_path):
    make_split(tmp_path / "val")
    rec = HighREVRecording(tmp_path / "val", sequence="seqB", time_unit="ms")
    assert rec.num_segments == 1 and rec.num_frames == 3
    assert rec.frame_times()[0][0] >= 7 * 1000.0  # ms -> µs
    with pytest.raises(RecordingError, match="no sequence 'seqC'; there are \\['seqA', 'seqB'\\]"):
        HighREVRecording(tmp_path / "val", sequence="seqC")
    keep_all = HighREVRecording(tmp_path / "val", sequence="seqA", drop_last=False)
    default = HighREVRecording(tmp_path / "val", sequence="seqA")
    assert default.frame_times()[0][1] < 600.0 <= keep_all.frame_times()[0][1]  # the last piece starts at 600
    assert HighREVRecording(tmp_path / "val").events_between(0.0, 1e6, segment=1).t.min() >= 7.0


def test_swap_xy_wrong_is_a_clear_error(tmp_path):
    make_split(tmp_path / "val")
    rec = HighREVRecording(tmp_path / "val", swap_xy=False)
    with pytest.raises(RecordingError, match="outside the sensor .*swapped in HighREV files: check swap_xy=False"):
        stream(rec)


def make_video(root, frames=3, m=3, n=1, inside=True, with_gt=True):
    """REFID layout: <split>/<video>/blur, gt, event (or <split>_event/<video>), one piece per sub-frame gap."""
    rng = np.random.default_rng(1)
    video = root / "test" / "vid"
    (video / "blur").mkdir(parents=True)
    events = video / "event" if inside else root / "test_event" / "vid"
    events.mkdir(parents=True)
    if with_gt:
        (video / "gt").mkdir()
    pieces = []
    for i in range(frames * (m + n)):
        pieces.append(random_events(rng, 10, 100.0 * i, 100.0 * i + 99))
        save_npz(events / f"{i:06d}.npz", *pieces[-1], column=False)
        if with_gt:
            save_png(video / "gt" / f"{i:06d}.png", rng)
    for k in range(frames):
        save_png(video / "blur" / f"{k:06d}.png", rng)
    return video, pieces


@pytest.mark.parametrize("inside", [True, False])
def test_video_layout(tmp_path, inside):
    video, pieces = make_video(tmp_path, inside=inside)
    rec = open_recording(video, m=3, n=1)
    assert rec.layout == "video" and rec.num_frames == 3 and rec.num_segments == 1
    batches = stream(rec)
    for k, b in enumerate(batches):
        t = np.concatenate([pieces[k * 4][2], pieces[k * 4 + 1][2]])  # the m - 1 = 2 gaps of its sub-frames
        assert float(b.exposure_start) == t.min() and float(b.exposure_end) == t.max()
        gt = np.asarray(Image.open(video / "gt" / f"{k * 4 + 1:06d}.png"))  # the middle sub-frame
        torch.testing.assert_close(b.sharp[0], torch.from_numpy(gt.transpose(2, 0, 1) / 255.0).float())
    assert sum(len(c) for c in rec.iter_event_chunks()) == 10 * len(pieces)


def test_missing_event_files_and_frame_without_events(tmp_path):
    video, _ = make_video(tmp_path)
    files = sorted((video / "event").glob("*.npz"))
    for f in files[8:]:
        f.unlink()
    with pytest.raises(RecordingError, match="frame 2 \\(000002.png\\) needs event files 8...9"):
        HighREVRecording(video, m=3, n=1)
    root = tmp_path / "split"
    make_split(root, sequences=("s",), frames=2)
    for j in range(PIECES - 1):
        np.savez(root / "event" / f"s_00001_{j:02d}.npz", x=np.zeros(0), y=np.zeros(0), timestamp=np.zeros(0),
                 polarity=np.zeros(0))
    with pytest.raises(RecordingError, match="frame 1 \\(s_00001.png\\) has no events in its exposure pieces"):
        list(HighREVRecording(root))


def test_corrupt_and_wrong_files(tmp_path):
    make_split(tmp_path / "val", sequences=("a",), frames=1)
    (tmp_path / "val" / "event" / "a_00000_01.npz").write_bytes(b"PK\x03\x04 broken")
    with pytest.raises(RecordingError, match="a_00000_01.npz: cannot read npz"):
        list(HighREVRecording(tmp_path / "val"))
    np.savez(tmp_path / "val" / "event" / "a_00000_01.npz", xs=np.zeros(3))
    with pytest.raises(RecordingError, match="a_00000_01.npz: not a HighREV event file, missing keys"):
        list(HighREVRecording(tmp_path / "val"))
    (tmp_path / "empty" / "blur").mkdir(parents=True)
    with pytest.raises(RecordingError, match="no blur/\\*.png"):
        HighREVRecording(tmp_path / "empty")
    with pytest.raises(RecordingError, match="unknown format: a folder .*subfolders \\['val'\\] are HighREV"):
        open_recording(tmp_path)


def test_polarity_and_column_lengths_are_validated(tmp_path):
    make_split(tmp_path / "val", sequences=("a",), frames=1)
    piece = tmp_path / "val" / "event" / "a_00000_01.npz"
    rng = np.random.default_rng(1)
    x, y, t, p = random_events(rng, 10, 200.0, 399.0)
    p[3] = 3  # used to be read as ON
    save_npz(piece, x, y, t, p)
    with pytest.raises(RecordingError, match=r"a_00000_01.npz: polarity must be 0/1, -1/\+1 or bool, got "
                                             r"values \[3\]"):
        list(HighREVRecording(tmp_path / "val"))
    save_npz(piece, x, y[:-2], t, np.ones(10))
    with pytest.raises(RecordingError, match="a_00000_01.npz: event columns differ in length: x 10, y 8, t 10, "
                                             "p 10"):
        list(HighREVRecording(tmp_path / "val"))
