from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from evlatcorr import EventFrames, Events


def _events(batch_size: int = 1, sensor_size=(2, 3)) -> Events:
    n = 2 * batch_size
    return Events(torch.tensor([0, 2] * batch_size), torch.tensor([1, 0] * batch_size),
                  torch.tensor([5.0, 15.0] * batch_size), torch.tensor([1, 0] * batch_size),
                  torch.arange(n) // 2, sensor_size=sensor_size, batch_size=batch_size)


def _frames(**kwargs) -> EventFrames:
    fields = dict(blurry=torch.full((2, 1, 2, 3), 0.5), events=_events(2), exposure_start=torch.tensor([0.0, 100.0]),
                  exposure_end=torch.tensor([10.0, 130.0]))
    fields.update(kwargs)
    return EventFrames(**fields)


class TestConstruction:
    def test_properties(self):
        fr = _frames()
        assert fr.batch_size == 2 and fr.sensor_size == (2, 3) and fr.device == torch.device("cpu")
        assert fr.exposure_time.tolist() == [10.0, 30.0]
        assert fr.latency is fr.corrected is fr.output is None and fr.meta == {}

    def test_exposures_become_float64_vectors(self):
        fr = _frames(exposure_start=torch.tensor([0, 100]), exposure_end=[10.0, 130.0])
        assert fr.exposure_start.dtype == fr.exposure_end.dtype == torch.float64
        assert fr.exposure_start.tolist() == [0.0, 100.0] and fr.exposure_end.tolist() == [10.0, 130.0]
        scalar = _frames(exposure_start=0.0, exposure_end=torch.tensor(25.0))  # one exposure for every sample
        assert scalar.exposure_start.tolist() == [0.0, 0.0] and scalar.exposure_time.tolist() == [25.0, 25.0]

    def test_float32_absolute_exposures_warn_at_the_caller_that_they_are_already_rounded(self):
        # a camera's absolute times in float32 lose minutes: start and end become one time, refused as empty
        start, end = torch.tensor([1.6e15], dtype=torch.float32), torch.tensor([1.6e15 + 2e4], dtype=torch.float32)
        with pytest.warns(UserWarning, match=r"exposure_(start|end) is float32 with times up to 1\.6e\+15 us, where "
                                             r"it resolves only about 1\.9\de\+08 us.*pass int64 or float64") as caught:
            with pytest.raises(ValueError, match="exposure_end must be after exposure_start"):
                _frames(blurry=torch.full((1, 1, 2, 3), 0.5), events=_events(1), exposure_start=start,
                        exposure_end=end)
        names = [str(w.message).split()[0] for w in caught]
        assert names == ["exposure_start", "exposure_end"] and {w.filename for w in caught} == {__file__}
        with pytest.warns(UserWarning, match=r"exposure_start is float32 .* about 1\.9\de\+08 us"):  # numpy too
            _frames(exposure_start=np.array([1.6e15, 1.6e15], dtype=np.float32),
                    exposure_end=torch.tensor([1.6e15 + 1e8, 1.6e15 + 2e8], dtype=torch.float64))
        fine = _frames(exposure_start=torch.tensor([0.0, 100.0], dtype=torch.float32))  # 8 s of float32 is fine
        assert fine.exposure_start.dtype == torch.float64

    def test_target_times_become_float64_columns(self):
        fr = _frames(target_times=torch.tensor([3.0, 103.0]))
        assert fr.target_times.dtype == torch.float64 and fr.target_times.tolist() == [[3.0], [103.0]]
        fr = _frames(target_times=[[1.0, 2.0], [3.0, 4.0]], target_frames=torch.zeros(2, 2, 3, 2, 3))
        assert fr.target_times.shape == (2, 2)

    def test_optional_fields_of_the_right_shape_are_kept(self):
        latency = torch.full((2, 1, 2, 3), 7.0)
        sharp = torch.rand(2, 3, 2, 3)  # the ground truth may be RGB for a grey blurry frame
        fr = _frames(latency=latency, sharp=sharp, blurry_next=torch.rand(2, 1, 2, 3), exposure_start_next=[20, 140],
                     exposure_end_next=[30.0, 170.0], meta={"frame": [0, 1]})
        assert fr.latency is latency and fr.sharp is sharp and fr.meta == {"frame": [0, 1]}
        assert fr.exposure_start_next.dtype == torch.float64 and fr.exposure_start_next.tolist() == [20.0, 140.0]

    def test_non_contiguous_blurry(self):
        blurry = torch.rand(2, 1, 3, 2).transpose(-1, -2)
        assert not blurry.is_contiguous()
        fr = _frames(blurry=blurry)
        assert fr.sensor_size == (2, 3) and torch.equal(fr.blurry, blurry)


class TestBadInput:
    @pytest.mark.parametrize("kwargs, message", [
        (dict(blurry=torch.rand(2, 2, 3)), "blurry must have shape ('B', 'C', 'H', 'W') (4 dims), got (2, 2, 3)"),
        (dict(blurry=torch.full((2, 1, 2, 3), 1.5)),
         "blurry must hold linear intensities in [0, 1], got values in [1.5, 1.5]"),
        (dict(events=torch.zeros(4, 4)), "events must be evlatcorr.Events, got Tensor"),
        (dict(events=_events(1)), "events have batch_size 1 but blurry has 2 frames; to cut one recording's events "
                                  "into each frame's window, use EventFrames.from_stream"),
        (dict(events=_events(3)), "events have batch_size 3 but blurry has 2 frames"),
        (dict(events=_events(2, sensor_size=(3, 3))),
         "events sensor_size (3, 3) does not match blurry (H, W)=(2, 3)"),
        (dict(exposure_start=torch.zeros(3)),
         "exposure_start must have shape (2,) (one value per sample), got (3,)"),
        (dict(exposure_end=torch.tensor([10.0, 90.0])),
         "exposure_end must be after exposure_start; sample 1 has start 100.0 us and end 90.0 us"),
        (dict(latency=torch.zeros(2, 2, 3)), "latency must have shape (2, 1, 2, 3) (4 dims), got (2, 2, 3)"),
        (dict(latency=torch.zeros(2, 3, 2, 3)), "latency must have shape (2, 1, 2, 3), got (2, 3, 2, 3) (dim 1)"),
        (dict(sharp=torch.zeros(2, 3, 3, 2)), "sharp must have shape (2, 'C', 2, 3), got (2, 3, 3, 2) (dim 2)"),
        (dict(blurry_next=torch.rand(2, 1, 2, 3)), "blurry_next needs exposure_start_next and exposure_end_next"),
        (dict(blurry_next=torch.rand(2, 3, 2, 3), exposure_start_next=20.0, exposure_end_next=30.0),
         "blurry_next must have shape (2, 1, 2, 3), got (2, 3, 2, 3) (dim 1)"),
        (dict(blurry_next=torch.rand(2, 1, 2, 3), exposure_start_next=[20.0, 140.0], exposure_end_next=[30.0, 140.0]),
         "sample 1 has start 140.0 us and end 140.0 us"),
        (dict(target_times=torch.zeros(3, 1)), "target_times must have shape (2, 'T'), got (3, 1) (dim 0)"),
        (dict(target_times=torch.zeros(2, 2), target_frames=torch.zeros(2, 3, 1, 2, 3)),
         "target_frames must have shape (2, 2, 'C', 2, 3), got (2, 3, 1, 2, 3) (dim 1)"),
    ])
    def test_message(self, kwargs, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            _frames(**kwargs)


class TestFromStream:
    def test_each_frame_gets_its_window_as_a_recording_reader_cuts_it(self, tmp_path):
        from evlatcorr.io import open_recording, write_sequence
        from evlatcorr.simulate import simulate

        seq = simulate("camera", num_frames=3, height=12, width=16, exposure_us=20000.0, frame_interval_us=25000.0,
                       latency="constant", latency_us=3000.0)
        path = tmp_path / "rec.h5"
        write_sequence(path, seq)
        stream = seq.delayed_events
        batch = EventFrames.from_stream(seq.blurry, stream, seq.exposure_start, seq.exposure_end)
        read = EventFrames.cat(list(open_recording(path)))
        for name in ("x", "y", "t", "p", "batch"):
            assert torch.equal(getattr(batch.events, name), getattr(read.events, name))

    def test_window_bounds_and_fields(self):
        ev = Events(torch.zeros(5), torch.zeros(5), torch.tensor([0.0, 8.0, 15.0, 25.0, 45.0]), torch.ones(5),
                    sensor_size=(1, 1))
        blurry = torch.rand(2, 1, 1, 1)
        default = EventFrames.from_stream(blurry, ev, [10.0, 20.0], [20.0, 30.0], meta={"frame": [0, 1]})
        assert default.events.t.tolist() == [15.0, 25.0, 25.0] and default.events.batch.tolist() == [0, 0, 1]
        assert default.meta == {"frame": [0, 1]}
        wider = EventFrames.from_stream(blurry, ev, [10.0, 20.0], [20.0, 30.0], before_us=5.0, after_us=20.0)
        assert wider.events.t.tolist() == [8.0, 15.0, 25.0, 15.0, 25.0, 45.0]

    def test_float32_absolute_exposures_warn_at_the_caller(self):
        ev = Events(torch.zeros(1), torch.zeros(1), torch.tensor([1.6e15], dtype=torch.float64), torch.ones(1),
                    sensor_size=(1, 1))
        start = torch.tensor([1.6e15], dtype=torch.float32)
        with pytest.warns(UserWarning, match=r"exposure_start is float32 with times up to 1\.6e\+15 us") as caught:
            EventFrames.from_stream(torch.rand(1, 1, 1, 1), ev, start, torch.tensor([1.6e15 + 1e9],
                                                                                    dtype=torch.float64))
        assert {w.filename for w in caught} == {__file__}

    @pytest.mark.parametrize("kwargs, message", [
        (dict(before_us=-1.0), "before_us must be a finite number >= 0, got -1.0"),
        (dict(after_us=float("nan")), "after_us must be None or a finite number >= 0, got nan"),
        (dict(exposure_end=[20.0, 15.0]), "sample 1 has start 20.0 us and end 15.0 us"),
        (dict(exposure_start=[0.0]), "exposure_start must have shape (2,) (one value per sample), got (1,)"),
        (dict(blurry=torch.rand(1, 1, 1)), "blurry must have shape ('B', 'C', 'H', 'W') (4 dims), got (1, 1, 1)"),
        (dict(events=torch.zeros(3)), "events must be evlatcorr.Events, got Tensor"),
    ])
    def test_bad_input(self, kwargs, message):
        fields = dict(blurry=torch.rand(2, 1, 1, 1), exposure_start=[0.0, 20.0], exposure_end=[10.0, 30.0],
                      events=Events(torch.zeros(1), torch.zeros(1), torch.tensor([1.0]), torch.ones(1),
                                    sensor_size=(1, 1)))
        fields.update(kwargs)
        with pytest.raises(ValueError, match=re.escape(message)):
            EventFrames.from_stream(**fields)


class TestReplace:
    def test_copy_with_changes_and_the_original_untouched(self):
        fr = _frames()
        latency = torch.ones(2, 1, 2, 3)
        out = fr.replace(latency=latency, exposure_end=[20.0, 140.0])
        assert out is not fr and out.latency is latency and out.exposure_end.tolist() == [20.0, 140.0]
        assert fr.latency is None and fr.exposure_end.tolist() == [10.0, 130.0]
        assert out.blurry is fr.blurry and out.events is fr.events  # unchanged fields are shared, not copied

    def test_changes_are_validated(self):
        with pytest.raises(ValueError, match=re.escape("latency must have shape (2, 1, 2, 3)")):
            _frames().replace(latency=torch.zeros(1, 1, 2, 3))
        with pytest.raises(TypeError):
            _frames().replace(no_such_field=1)


class TestTo:
    def test_every_tensor_and_the_events_move(self, device):
        fr = _frames(latency=torch.ones(2, 1, 2, 3), corrected=_events(2), target_times=torch.tensor([1.0, 2.0]),
                     meta={"name": "x"})
        out = fr.to(device)
        for name in ("blurry", "exposure_start", "exposure_end", "latency", "target_times"):
            assert getattr(out, name).device.type == device.type, name
            torch.testing.assert_close(getattr(out, name).cpu(), getattr(fr, name))
        for events in (out.events, out.corrected):
            assert events.t.device.type == events.x.device.type == events.batch.device.type == device.type
        assert out.events.t.cpu().tolist() == fr.events.t.tolist() and out.meta == {"name": "x"}
        assert out.sharp is None and out.device.type == device.type



# --- batch operations ------------------------------------------------------------------------------
def _numbered(batch_size: int = 2, h: int = 3, w: int = 4, **kwargs) -> EventFrames:
    """Images whose values are their flat pixel index (sample b adds 100 b), so slices are easy to check."""
    image = (torch.arange(batch_size * h * w, dtype=torch.float32).view(batch_size, 1, h, w) % (h * w)
             + 100 * torch.arange(batch_size).view(-1, 1, 1, 1)) / 1000
    ev = Events(torch.tensor([0, 3, 1, 2]), torch.tensor([0, 2, 1, 2]), torch.tensor([1.0, 2.0, 3.0, 4.0]),
                torch.tensor([1, -1, 1, 1]), torch.tensor([0, 0, 1, 1]), sensor_size=(h, w), batch_size=batch_size)
    fields = dict(blurry=image, events=ev, exposure_start=torch.tensor([0.0, 100.0]),
                  exposure_end=torch.tensor([10.0, 130.0]))
    fields.update(kwargs)
    return EventFrames(**fields)


class TestCrop:
    def test_known_pixels_and_events(self):
        fr = _numbered(sharp=torch.zeros(2, 3, 3, 4), latency=torch.ones(2, 1, 3, 4),
                       meta={"true_latency": torch.arange(24.0).view(2, 1, 3, 4), "which": "delayed"})
        out = fr.crop(1, 1, 2, 3)  # rows 1-2, columns 1-3
        assert (out.blurry[0, 0] * 1000).tolist() == [[5.0, 6.0, 7.0], [9.0, 10.0, 11.0]]
        assert (out.blurry[1, 0] * 1000).tolist() == [[105.0, 106.0, 107.0], [109.0, 110.0, 111.0]]
        # events (x, y): (0, 0) and (3, 2) of sample 0, (1, 1) and (2, 2) of sample 1: (0, 0) falls outside
        assert out.events.x.tolist() == [2, 0, 1] and out.events.y.tolist() == [1, 0, 1]
        assert out.events.t.tolist() == [2.0, 3.0, 4.0] and out.events.batch.tolist() == [0, 1, 1]
        assert out.events.p.tolist() == [-1, 1, 1] and out.events.sensor_size == (2, 3)
        assert out.sharp.shape == (2, 3, 2, 3) and out.latency.shape == (2, 1, 2, 3)
        assert out.meta["true_latency"][0, 0].tolist() == [[5.0, 6.0, 7.0], [9.0, 10.0, 11.0]]
        assert out.meta["which"] == "delayed" and out.blurry.is_contiguous()

    def test_hflip_mirrors_images_and_events_together(self):
        out = _numbered().crop(0, 0, 3, 4, hflip=True)
        assert (out.blurry[0, 0, 0] * 1000).tolist() == [3.0, 2.0, 1.0, 0.0]
        assert out.events.x.tolist() == [3, 0, 2, 1] and out.events.y.tolist() == [0, 2, 1, 2]

    def test_corrected_events_and_the_pair_fields_are_cropped(self):
        fr = _numbered(corrected=_numbered().events, blurry_next=torch.rand(2, 1, 3, 4), exposure_start_next=20.0,
                       exposure_end_next=30.0, target_times=[[5.0], [6.0]], target_frames=torch.rand(2, 1, 1, 3, 4))
        out = fr.crop(0, 2, 3, 2)
        assert out.corrected.x.tolist() == [1, 0] and out.blurry_next.shape == (2, 1, 3, 2)
        assert out.target_frames.shape == (2, 1, 1, 3, 2) and out.target_times.tolist() == [[5.0], [6.0]]

    @pytest.mark.parametrize("box", [(1, 0, 3, 4), (0, 0, 0, 4), (-1, 0, 2, 2), (0, 2, 3, 3)])
    def test_outside_raises(self, box):
        with pytest.raises(ValueError, match=re.escape(f"crop {box} does not fit in (H, W)=(3, 4)")):
            _numbered().crop(*box)


class TestCatAndSplit:
    def test_split_known_parts(self):
        fr = _numbered(sharp=torch.rand(2, 3, 3, 4), target_times=[1.0, 2.0],
                       meta={"frame_index": [4, 5], "true_latency": torch.tensor([7.0, 8.0]), "file": "x.h5"})
        first, second = fr.split()
        assert first.batch_size == second.batch_size == 1
        assert second.exposure_start.tolist() == [100.0] and second.target_times.tolist() == [[2.0]]
        assert torch.equal(second.sharp, fr.sharp[1:]) and torch.equal(second.blurry, fr.blurry[1:])
        assert second.events.x.tolist() == [1, 2] and second.events.batch.tolist() == [0, 0]
        assert second.meta["frame_index"] == [5] and second.meta["true_latency"].tolist() == [8.0]
        assert second.meta["file"] == "x.h5"

    def test_cat_inverts_split_keeping_every_field(self):
        fr = _numbered(latency=torch.rand(2, 1, 3, 4), latent=torch.rand(2, 1, 3, 4), corrected=_numbered().events,
                       sharp=torch.rand(2, 3, 3, 4), blurry_next=torch.rand(2, 1, 3, 4),
                       exposure_start_next=[20.0, 140.0], exposure_end_next=[30.0, 170.0],
                       target_times=[[25.0, 26.0], [150.0, 151.0]], target_frames=torch.rand(2, 2, 1, 3, 4),
                       output=torch.rand(2, 1, 3, 4), meta={"frame_index": [4, 5], "which": "ideal",
                                                            "true_latency": torch.rand(2, 1, 3, 4)})
        back = EventFrames.cat(fr.split())
        for f in ("blurry", "exposure_start", "exposure_end", "latency", "latent", "sharp", "blurry_next",
                  "exposure_start_next", "exposure_end_next", "target_times", "target_frames", "output"):
            assert torch.equal(getattr(back, f), getattr(fr, f)), f
        for a, b in ((back.events, fr.events), (back.corrected, fr.corrected)):
            assert a.batch.tolist() == b.batch.tolist() and a.x.tolist() == b.x.tolist() and a.batch_size == 2
        assert back.meta["frame_index"] == [4, 5] and back.meta["which"] == "ideal"
        assert torch.equal(back.meta["true_latency"], fr.meta["true_latency"])

    def test_cat_offsets_the_events_of_multi_sample_items(self):
        out = EventFrames.cat([_numbered(), _numbered()])
        assert out.batch_size == 4 and out.events.batch.tolist() == [0, 0, 1, 1, 2, 2, 3, 3]
        assert out.exposure_end.tolist() == [10.0, 130.0, 10.0, 130.0]

    def test_cat_meta_keeps_shared_values_and_drops_differing_ones(self):
        a, b = _numbered(meta={"file": "x", "frame": 1, "only_a": 0}), _numbered(meta={"file": "x", "frame": 2})
        assert EventFrames.cat([a, b]).meta == {"file": "x"}

    @pytest.mark.parametrize("items, message", [
        ([], "cannot collate an empty list of EventFrames"),
        ([_numbered(), _numbered(h=4)], "samples must share one (H, W) to be batched, got [(3, 4), (4, 4)]"),
        ([_numbered(sharp=torch.rand(2, 1, 3, 4)), _numbered()],
         "cannot batch samples where sharp is set on some and missing on others"),
        ([_numbered(corrected=_numbered().events), _numbered()],
         "cannot batch samples where corrected is set on some and missing on others"),
    ])
    def test_cat_bad_input(self, items, message):
        with pytest.raises(ValueError, match=re.escape(message)):
            EventFrames.cat(items)


def test_a_tuple_of_per_sample_tensors_in_meta_is_split_and_concatenated_per_sample():
    # the corrector's etf_curve: (candidates (B, K), scores (B, K))
    curve = (torch.tensor([[0.0, 1.0], [0.0, 2.0]]), torch.tensor([[5.0, 6.0], [7.0, 8.0]]))
    fr = _frames(meta={"etf_curve": curve, "pair": (torch.zeros(3), torch.zeros(3)), "name": "x"})
    first, second = fr.split()
    assert torch.equal(second.meta["etf_curve"][0], curve[0][1:]) and torch.equal(second.meta["etf_curve"][1],
                                                                                   curve[1][1:])
    assert first.meta["pair"] is fr.meta["pair"] and first.meta["name"] == "x"  # not one entry per sample: kept
    joined = EventFrames.cat([first, second])
    assert all(torch.equal(a, b) for a, b in zip(joined.meta["etf_curve"], curve))
    # curves of other lengths have no batched form: dropped, as other entries that differ
    other = first.replace(meta={"etf_curve": (torch.zeros(1, 3), torch.zeros(1, 3))})
    assert "etf_curve" not in EventFrames.cat([first, other]).meta
