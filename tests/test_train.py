from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter
from evlatcorr.adapters.refid import refid_output_times
from evlatcorr.edi import edi_deblur
from evlatcorr.simulate import PHOTOGRAPHS_TEST
from evlatcorr.train import (
    CorrectedRestorationModule,
    RecordingRestorationData,
    RestorationModule,
    SimulatedRestorationData,
    build_adapter,
    checkpoint_name,
    collate_frames,
    crop_frames,
    main,
    restoration_pair,
)

from .conftest import random_events, shared_data_dir


def _frames(h: int = 6, w: int = 8, seed: int = 0) -> EventFrames:
    g = torch.Generator().manual_seed(seed)
    ev = random_events(200, (h, w), (0.0, 100.0), seed=seed)
    return EventFrames(torch.rand(1, 3, h, w, generator=g), ev, torch.tensor([0.0]), torch.tensor([80.0]),
                       sharp=torch.rand(1, 3, h, w, generator=g), meta={"true_latency": torch.rand(1, 1, h, w)})


# --- crops and batches -------------------------------------------------------------------------------
class TestCropFrames:
    def test_images_are_the_slices(self):
        fr = _frames()
        out = crop_frames(fr, 1, 2, 4, 5)
        assert torch.equal(out.blurry, fr.blurry[..., 1:5, 2:7])
        assert torch.equal(out.sharp, fr.sharp[..., 1:5, 2:7])
        assert torch.equal(out.meta["true_latency"], fr.meta["true_latency"][..., 1:5, 2:7])

    def test_events_inside_kept_and_moved_outside_dropped(self):
        ev = Events(torch.tensor([2, 6, 7]), torch.tensor([1, 4, 5]), torch.tensor([1.0, 2.0, 3.0]),
                    torch.tensor([1, 0, 1]), sensor_size=(6, 8))
        fr = EventFrames(torch.rand(1, 1, 6, 8), ev, torch.tensor([0.0]), torch.tensor([5.0]))
        out = crop_frames(fr, 1, 2, 4, 5)  # rows 1..4, columns 2..6: the event at (7, 5) is outside
        assert out.events.x.tolist() == [0, 4] and out.events.y.tolist() == [0, 3]
        assert out.events.t.tolist() == [1.0, 2.0] and out.events.p.tolist() == [1, -1]

    def test_flip_mirrors_images_and_events_together(self):
        fr = _frames()
        out = crop_frames(fr, 0, 0, 6, 8, hflip=True)
        assert torch.equal(out.blurry, fr.blurry.flip(-1))
        assert out.events.x.tolist() == (7 - fr.events.x).tolist()

    def test_crop_outside_raises(self):
        with pytest.raises(ValueError, match="does not fit"):
            crop_frames(_frames(), 3, 0, 4, 8)


class TestCollate:
    def test_batches_every_field(self):
        out = collate_frames([_frames(seed=0), _frames(seed=1)])
        assert out.batch_size == 2 and out.sharp.shape == (2, 3, 6, 8)
        assert out.events.counts().tolist() == [200, 200]
        assert out.meta["true_latency"].shape == (2, 1, 6, 8)

    def test_different_sizes_raise(self):
        with pytest.raises(ValueError, match="crop them first"):
            collate_frames([_frames(), _frames(6, 10)])

    def test_partly_missing_field_raises(self):
        with pytest.raises(ValueError, match="some and missing"):
            collate_frames([_frames(), _frames().replace(sharp=None)])


# --- data ----------------------------------------------------------------------------------------------
class TestSimulatedRestorationData:
    def test_deblur_samples_are_crops_with_sharp_targets(self):
        data = SimulatedRestorationData(photographs=["coins", "moon"], size=(32, 40), crop=(16, 24), sequences=1,
                                        num_frames=2, batch_size=2, steps_per_epoch=3)
        data.setup()
        batch = next(iter(data.train_dataloader()))
        assert batch.batch_size == 2 and batch.sensor_size == (16, 24)
        assert batch.sharp.shape == (2, 3, 16, 24)
        assert len(data.train_dataloader()) == 3
        val = next(iter(data.val_dataloader()))
        assert val.sensor_size == (32, 40)

    def test_default_photographs_exclude_the_test_split(self):
        assert not set(SimulatedRestorationData().photographs) & set(PHOTOGRAPHS_TEST)

    def test_ideal_and_delayed_events_differ_by_the_latency(self):
        data = SimulatedRestorationData(photographs=["coins"], size=(24, 32), crop=(24, 32), sequences=1,
                                        num_frames=2, latency_us=(3000.0, 3000.0))
        ideal, delayed = data.simulate([0])[0]
        assert ideal.events.t.median() < delayed.events.t.median()
        assert ideal.sharp is not None and torch.equal(ideal.blurry, delayed.blurry)

    def test_interpolation_targets_at_requested_times(self):
        def times(frames):
            return refid_output_times(frames, 4, 1)

        data = SimulatedRestorationData("interpolation", photographs=["coins"], size=(24, 32), crop=(16, 16),
                                        sequences=1, num_frames=2, target_times=times)
        ideal, _ = data.simulate([0])[0]
        assert ideal.target_frames.shape == (1, 9, 3, 24, 32)
        # the middle REFID 4+1 output is the gap midpoint (20 ms exposure, 25 ms interval)
        assert float(ideal.target_times[0, 4] - ideal.exposure_end[0]) == pytest.approx(2500.0)

    @pytest.mark.parametrize("kwargs, match", [(dict(task="x"), "task"), (dict(events="late"), "events"),
                                               (dict(crop=(200, 10)), "larger")])
    def test_bad_arguments(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            SimulatedRestorationData(**kwargs)


# --- modules -------------------------------------------------------------------------------------------
def _sim_batch(task: str = "deblur", size=(32, 32), events: str = "ideal"):
    data = SimulatedRestorationData(task, photographs=["coins"], size=size, crop=size, sequences=1, num_frames=2,
                                    target_times=(lambda f: refid_output_times(f, 4, 1)) if task != "deblur" else None)
    pair = data.simulate([0])[0]
    return pair[0] if events == "ideal" else pair[1]


def test_build_adapter_and_names():
    assert isinstance(build_adapter("efnet"), EFNetAdapter) and not build_adapter("efnet").clamp
    assert isinstance(build_adapter("gem"), GEMAdapter)
    assert isinstance(build_adapter("refid"), REFIDAdapter)
    assert checkpoint_name("refid", (4, 1)) == "refid-4-1" and checkpoint_name("refid", (11, 1)) == "refid"
    with pytest.raises(ValueError, match="unknown model"):
        build_adapter("unet")


def test_restoration_pair_picks_nearest_refid_output():
    batch = _sim_batch("interpolation").replace(target_times=None, target_frames=None)
    times = refid_output_times(batch, 4, 1)
    target_times = times[:, 4:5]
    out = batch.replace(output=torch.arange(9.0).view(1, 9, 1, 1, 1).expand(1, 9, 3, 32, 32),
                        target_times=target_times, target_frames=torch.zeros(1, 1, 3, 32, 32),
                        meta={"output_times": times})
    pred, target = restoration_pair(out, "interpolation")
    assert pred.shape == target.shape == (1, 1, 3, 32, 32) and float(pred.mean()) == 4.0


@pytest.mark.parametrize("model, lr", [("efnet", 1e-4), ("gem", 1e-3)])  # measured: -23 %, -49 %
def test_training_reduces_the_loss_on_a_fixed_batch(model, lr):
    torch.manual_seed(0)
    module = RestorationModule(model)
    batch = _sim_batch()
    optimiser = torch.optim.Adam(module.parameters(), lr=lr)
    losses = []
    for _ in range(12):
        loss = module.training_step(batch, 0)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.85 * losses[0]


def test_refid_training_step_supervises_every_output_frame():
    module = RestorationModule("refid", refid_layout=(4, 1))
    loss = module.training_step(_sim_batch("interpolation"), 0)
    loss.backward()
    assert torch.isfinite(loss) and module.adapter.net.pred.conv2d.weight.grad.abs().sum() > 0


def _tiny_cli(tmp_path, *extra):
    return ["--model", "efnet", "--size", "32", "40", "--crop", "32", "32", "--sequences", "1",
            "--num-frames", "2", "--batch-size", "2", "--val-every", "2", "--warmup-steps", "1",
            "--photographs", "coins", "--out", str(tmp_path / "run"), *extra]


@pytest.mark.slow
def test_cli_trains_exports_and_resumes(tmp_path, capsys):
    card = main(_tiny_cli(tmp_path, "--max-steps", "2", "--export", str(tmp_path / "ckpt")))
    assert card["steps"] == 2 and card["val_psnr"] > 0 and card["data"]["photographs"] == ["coins"]
    written = json.loads((tmp_path / "ckpt" / "efnet.json").read_text())
    assert written["files"] and written["val_psnr"] == card["val_psnr"]
    exported = EFNetAdapter(checkpoint=str(tmp_path / "ckpt" / "efnet.safetensors"))  # strict load
    trained = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    for key, value in exported.net.state_dict().items():  # fp16 export of the trained weights
        assert torch.allclose(value, trained[f"adapter.net.{key}"].half().float())
    card = main(_tiny_cli(tmp_path, "--max-steps", "4", "--resume", "last"))
    assert card["steps"] == 4
    capsys.readouterr()
    with pytest.raises(SystemExit) as exc:
        main(_tiny_cli(tmp_path / "other", "--max-steps", "4", "--resume", "last"))
    assert exc.value.code == 2 and "does not exist" in capsys.readouterr().err


def test_cli_continuing_the_shipped_weights_extends_their_card(tmp_path):
    # --checkpoint default starts from checkpoints/efnet; exporting beside its card adds to its history
    export = tmp_path / "ckpt"
    export.mkdir()
    shipped = json.loads((Path(__file__).resolve().parents[1] / "checkpoints" / "efnet.json").read_text())
    (export / "efnet.json").write_text(json.dumps(shipped))
    card = main(_tiny_cli(tmp_path, "--max-steps", "2", "--checkpoint", "default", "--export", str(export)))
    assert card["steps"] == shipped["steps"] + 2
    assert card["commands"][:-1] == shipped.get("commands", [shipped["command"]])
    assert "--checkpoint default" in card["commands"][-1] and card.get("note") == shipped.get("note")
    assert card["train_seconds"] > shipped["train_seconds"]


def test_cli_refuses_test_photographs(tmp_path, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--model", "efnet", "--photographs", "camera", "--out", str(tmp_path)])
    assert exc.value.code == 2 and "test split" in capsys.readouterr().err


@pytest.fixture(scope="module")
def delayed_pair() -> EventFrames:
    """The simulated "coins" pair (32x32, 4474 us latency) with sharp frames at REFID 4+1's 9 output times."""
    return _sim_batch("interpolation", events="delayed")


class TestCorrectedRestorationModule:
    def test_etf_only_trains_the_polynomial_and_leaves_the_network(self):
        adapter = EFNetAdapter(clamp=False)
        module = CorrectedRestorationModule(adapter, "deblur", train_network=False, num_bins=40)
        before = {k: v.clone() for k, v in adapter.state_dict().items()}
        batch = _sim_batch(events="delayed").replace(sharp=None)  # no ground truth: ETF only
        optimiser = module.configure_optimizers()["optimizer"]
        for _ in range(3):
            loss = module.training_step(batch, 0)
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
        assert module.latency_model.coefficients.abs().sum() > 0
        assert all(torch.equal(before[k], v) for k, v in adapter.state_dict().items())

    def test_supervised_trains_both(self):
        adapter = EFNetAdapter(clamp=False)
        module = CorrectedRestorationModule(adapter, "deblur", num_bins=40)
        first = next(adapter.net.parameters()).clone()
        optimiser = module.configure_optimizers()["optimizer"]
        assert [g["lr"] for g in optimiser.param_groups] == [5e-5, 0.02]
        loss = module.training_step(_sim_batch(events="delayed"), 0)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        assert not torch.equal(first, next(adapter.net.parameters()))
        assert module.latency_model.coefficients.abs().sum() > 0

    def test_constant_corrector_shifts_events_by_the_searched_latency(self):
        from evlatcorr.search import search_constant_latency

        module = CorrectedRestorationModule(EFNetAdapter(), "deblur", corrector="constant", num_bins=40)
        batch = _sim_batch(events="delayed")
        true = float(batch.meta["true_latency"][0, 0, 0, 0])  # constant, 4474 us
        corrected, loss = module.correct(batch)
        assert loss is None and corrected.latency.shape == (1, 1, 32, 32)
        latency = float(corrected.latency[0, 0, 0, 0])
        assert torch.all(corrected.latency == latency)
        searched = search_constant_latency(batch.blurry, batch.events, batch.exposure_start, batch.exposure_end,
                                           0.2, 40).latency
        assert latency == pytest.approx(float(searched), abs=1e-3)
        # measured 4007 us (-466 us) on this 32x32 frame, the same with 100 bins; the image moves about 1 px/ms,
        # so 700 us is under a pixel of motion, while leaving the events uncorrected errs by all 4474 us
        assert abs(latency - true) < 700.0
        assert torch.allclose(corrected.corrected.t.sort().values, (batch.events.t - latency).sort().values)

    def test_with_frame_gamma_the_corrector_reads_linear_frames_and_the_network_the_encoded_ones(self):
        from evlatcorr.io import linear_frames

        batch = _sim_batch(events="delayed")  # linear, as simulated
        encoded = linear_frames(batch, 1 / 2.2)  # as a file encoded for display would hold it
        plain = CorrectedRestorationModule(EFNetAdapter(), "deblur", corrector="constant", num_bins=40)
        gamma = CorrectedRestorationModule(EFNetAdapter(), "deblur", corrector="constant", num_bins=40,
                                           frame_gamma=2.2)
        expected, _ = plain.correct(batch)
        corrected, _ = gamma.correct(encoded)
        torch.testing.assert_close(corrected.latency, expected.latency, rtol=0, atol=1e-2)
        assert torch.equal(corrected.blurry, encoded.blurry)  # the network reads the frames as they came
        with pytest.raises(ValueError, match="frame_gamma must be a finite number > 0"):
            CorrectedRestorationModule(EFNetAdapter(), "deblur", frame_gamma=0.0)

    def test_interpolation_pairs_are_corrected(self, delayed_pair):
        # a polynomial fixed at the true constant latency: both frames' events move 4474 us earlier, and EDI
        # interpolation from them is the blend of the two frames' EDI latent images from the shifted events
        from torchmetrics.functional.image import peak_signal_noise_ratio

        from evlatcorr.adapters.edi import EDIAdapter

        batch = delayed_pair
        true = float(batch.meta["true_latency"][0, 0, 0, 0])
        module = CorrectedRestorationModule(EDIAdapter("interpolation", num_bins=100), "interpolation",
                                            train_corrector=False)
        with torch.no_grad():
            module.latency_model.coefficients[0] = true / 1000.0  # ms
        corrected, _ = module.correct(batch)
        assert torch.allclose(corrected.latency, torch.full_like(corrected.latency, true))
        torch.testing.assert_close(corrected.corrected.t, (batch.events.t - true).sort().values, rtol=0, atol=1e-2)
        out = module(batch).output
        shifted = batch.events.shift(true)
        mid0 = float(batch.exposure_start + batch.exposure_end) / 2
        mid1 = float(batch.exposure_start_next + batch.exposure_end_next) / 2
        reference = []
        for t in batch.target_times[0].tolist():
            time = torch.tensor([t], dtype=torch.float64)
            first = edi_deblur(batch.blurry, shifted, batch.exposure_start, batch.exposure_end, 0.2, None, 100, time)
            second = edi_deblur(batch.blurry_next, shifted, batch.exposure_start_next, batch.exposure_end_next, 0.2,
                                None, 100, time)
            w = min(max((t - mid0) / (mid1 - mid0), 0.0), 1.0)  # linear in time between the mid-exposures
            reference.append(((1 - w) * first + w * second).clamp(0, 1))
        torch.testing.assert_close(out, torch.stack(reference, 1), rtol=0, atol=1e-5)
        # against the sharp frames at the 9 output times: measured 31.9 dB corrected, 18.1 dB uncorrected
        psnr_corrected = float(peak_signal_noise_ratio(out, batch.target_frames, data_range=1.0))
        psnr_uncorrected = float(peak_signal_noise_ratio(module.adapter(batch).output, batch.target_frames,
                                                         data_range=1.0))
        assert psnr_corrected > 30.0 and psnr_corrected > psnr_uncorrected + 10.0

    def test_refid_reads_the_corrected_pair(self, delayed_pair):
        torch.manual_seed(0)
        adapter = REFIDAdapter(m=4, n=1, clamp=False)
        module = CorrectedRestorationModule(adapter, "interpolation", train_corrector=False)
        with torch.no_grad():
            module.latency_model.coefficients[0] = 3.0  # 3 ms everywhere
            out = module(delayed_pair).output
            expected = adapter(delayed_pair.replace(corrected=delayed_pair.events.shift(3000.0))).output
            uncorrected = adapter(delayed_pair).output
        assert out.shape == (1, 9, 3, 32, 32)
        torch.testing.assert_close(out, expected)
        assert (out - uncorrected).abs().max() > 1e-3

    def test_nothing_to_train_raises(self):
        with pytest.raises(ValueError, match="nothing to train"):
            CorrectedRestorationModule(EFNetAdapter(), "deblur", corrector="constant", train_network=False)


# --- recordings (--data) ---------------------------------------------------------------------------------
def _write_recording(folder: Path, sharp: bool, end_us: float | None = None) -> Path:
    """The simulated "camera" sequence (4 frames, 32x48, 20 ms exposures 25 ms apart, 3 ms latency) as a
    recording: our HDF5 with its sharp frames, or event_utils HDF5 without them (as a real camera records),
    optionally with the events cut at ``end_us``."""
    from evlatcorr.io import H5Recording, write_event_utils, write_sequence
    from evlatcorr.simulate import simulate

    seq = simulate("camera", num_frames=4, height=32, width=48, latency_us=3000.0, seed=0)
    folder.mkdir(parents=True, exist_ok=True)
    write_sequence(folder / "sim.h5", seq)
    if sharp:
        return folder / "sim.h5"
    events = seq.delayed_events if end_us is None else seq.delayed_events.select(seq.delayed_events.t < end_us)
    path = folder / ("rec.h5" if end_us is None else f"rec_{end_us:.0f}.h5")
    write_event_utils(path, events, like=H5Recording(folder / "sim.h5"))  # blurry frames and events only
    return path


@pytest.fixture(scope="module")
def recording(tmp_path_factory) -> Path:
    return _write_recording(tmp_path_factory.mktemp("rec"), sharp=False)


@pytest.fixture(scope="module")
def recording_with_sharp(tmp_path_factory) -> Path:
    return _write_recording(tmp_path_factory.mktemp("rec_sharp"), sharp=True)


class TestRecordingRestorationData:
    def test_frames_cropped_with_events_and_the_last_held_out(self, recording):
        data = RecordingRestorationData(recording, crop=(16, 24), batch_size=2, steps_per_epoch=3)
        data.setup()
        assert not data.has_truth and data.summary["frames_read"] == 4
        # fewer samples than --holdout 10: the last one is held out
        assert [s.meta["frame"] for s in data.train_samples] == [0, 1, 2]
        assert [s.meta["frame"] for s in data.val_samples] == [3]
        batch = next(iter(data.train_dataloader()))
        assert batch.batch_size == 2 and batch.sensor_size == (16, 24) and batch.sharp is None
        inside = batch.events.window(batch.exposure_start, batch.exposure_end + batch.exposure_time)
        assert (inside.counts() > 0).all()
        assert len(data.train_dataloader()) == 3
        val = next(iter(data.val_dataloader()))
        assert val.sensor_size == (32, 48)  # validation on whole frames

    def test_every_kth_sample_held_out(self, recording):
        data = RecordingRestorationData(recording, crop=(16, 16), holdout=2)
        data.read()
        assert [s.meta["frame"] for s in data.val_samples] == [1, 3]
        assert [s.meta["frame"] for s in data.train_samples] == [0, 2]

    def test_pairs_reach_the_next_exposure(self, recording):
        data = RecordingRestorationData(recording, "interpolation", crop=(16, 16), holdout=0)
        data.read()
        # the last frame has no next one; every pair's events reach the next exposure's end plus 20 ms
        assert [s.meta["frame"] for s in data.train_samples] == [0, 1, 2]
        assert data.summary["left_out_no_next"] == 1
        for s in data.train_samples:
            assert float(s.exposure_start_next[0] - s.exposure_start[0]) == 25000.0
            assert float(s.events.t.max()) > float(s.exposure_end_next[0]) + 15000.0
            assert torch.equal(s.blurry_next, data.train_samples[0].blurry_next) == (s is data.train_samples[0])

    def test_sharp_frames_are_ground_truth(self, recording_with_sharp):
        data = RecordingRestorationData(recording_with_sharp, crop=(16, 16))
        data.read()
        assert data.has_truth and data.train_samples[0].sharp.shape == (1, 3, 32, 48)
        pairs = RecordingRestorationData(recording_with_sharp, "interpolation", crop=(16, 16))
        pairs.read()
        first = pairs.train_samples[0]  # targets: both frames' sharp frames at mid-exposure
        assert pairs.has_truth and first.target_frames.shape == (1, 2, 3, 32, 48)
        assert first.target_times[0].tolist() == [30000.0, 55000.0]

    def test_a_window_past_the_last_event_is_left_out(self, recording, tmp_path):
        # frame 3's window is [95, 135) ms: with the events cut at 120 ms it is left out
        cut = _write_recording(tmp_path, sharp=False, end_us=120000.0)
        with pytest.warns(UserWarning, match="late events are missing"):
            data = RecordingRestorationData(cut, crop=(16, 16))
            data.read()
        assert data.summary["left_out_cut_short"] == [3] and data.summary["samples"] == 3

    @pytest.mark.parametrize("kwargs, match", [(dict(crop=(64, 16)), "does not fit the sensor"),
                                               (dict(crop=(16, 16), task="interpolation", max_frames=1),
                                                "usable pairs of consecutive frames: 0"),
                                               (dict(crop=(16, 16), max_frames=1), "at least 2"),
                                               (dict(crop=(16, 16), holdout=1), "leaving none to train on")])
    def test_bad_input_raises(self, recording, kwargs, match):
        with pytest.raises(ValueError, match=match):
            RecordingRestorationData(recording, **kwargs).read()

    @pytest.mark.parametrize("kwargs, match", [(dict(task="x"), "task"), (dict(holdout=-1), "holdout"),
                                               (dict(max_frames=0), "max_frames")])
    def test_bad_arguments(self, kwargs, match):
        with pytest.raises(ValueError, match=match):
            RecordingRestorationData("any.h5", **kwargs)


def _data_cli(path, out, *extra, model: str = "efnet"):
    return ["--model", model, "--data", str(path), "--crop", "32", "32", "--batch-size", "2", "--warmup-steps", "1",
            "--accelerator", "cpu", "--out", str(out), *extra]


def test_cli_data_without_truth_trains_only_the_polynomial(recording, tmp_path, capsys):
    from evlatcorr.spatial import load_curve

    card = main(_data_cli(recording, tmp_path / "run", "--checkpoint", "default", "--max-steps", "3"))
    out = capsys.readouterr().out
    assert "efnet is frozen" in out and "contrast threshold: 0.2" in out and "1 held out" in out
    assert card["steps"] == 3 and card["network"] == "frozen" and card["finetune"] == "spatial"
    assert 0.1 < card["threshold"] < 0.4  # the simulator's threshold is 0.2
    # measured: 10.94 -> 9.52 on the held-out frame
    assert card["val_objective_after"] < 0.95 * card["val_objective_before"]
    state = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    shipped = EFNetAdapter(checkpoint="default", clamp=False).state_dict()
    assert all(torch.equal(state[f"adapter.{k}"], v) for k, v in shipped.items())  # frozen: not one weight moved
    coefficients = state["latency_model.coefficients"]
    assert coefficients.abs().max() > 1e-3  # starts at zero
    torch.testing.assert_close(load_curve(tmp_path / "run" / "curve.pt").coefficients.detach(), coefficients)


def test_cli_data_estimates_the_threshold_from_the_frames_as_the_corrector_reads_them(recording, tmp_path):
    # the simulated frames are linear: raised to 2.2, two-frame consistency sees each log step 2.2 times larger
    plain = main(_data_cli(recording, tmp_path / "plain", "--max-steps", "1"))
    raised = main(_data_cli(recording, tmp_path / "raised", "--max-steps", "1", "--frame-gamma", "2.2"))
    assert 1.5 < raised["threshold"] / plain["threshold"] < 2.6


def test_cli_data_with_sharp_frames_trains_the_network(recording_with_sharp, tmp_path, capsys):
    card = main(_data_cli(recording_with_sharp, tmp_path / "run", "--checkpoint", "default", "--max-steps", "2",
                          "--threshold", "0.2"))
    assert "efnet trains by L1" in capsys.readouterr().out
    assert card["network"] == "trained" and card["threshold"] == 0.2 and card["val_psnr"] > 20
    state = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    shipped = EFNetAdapter(checkpoint="default", clamp=False).state_dict()
    moved = [k for k, v in shipped.items() if v.is_floating_point() and not torch.equal(state[f"adapter.{k}"], v)]
    assert len(moved) > 0.5 * len(shipped)
    assert state["latency_model.coefficients"].abs().max() > 1e-3


def test_cli_data_refid_trains_on_pairs(recording, tmp_path):
    card = main(_data_cli(recording, tmp_path / "run", "--max-steps", "1", "--threshold", "0.2", model="refid"))
    assert card["data"]["pairs"] and card["data"]["train_samples"] == 2 and card["data"]["val_samples"] == 1
    assert card["network"] == "frozen" and (tmp_path / "run" / "curve.pt").is_file()


@pytest.mark.parametrize("extra, match", [
    (["--data", "missing.aedat4"], "missing.aedat4: no such file"),
    (["--crop", "64", "64"], "does not fit the sensor"),
    (["--max-frames", "1"], "at least 2"),
    (["--finetune", "constant"], "nothing to train"),
    (["--finetune", "none"], "has no sharp frames"),
    (["--export", "exported"], "stays frozen"),
    (["--model", "unet"], "invalid choice: 'unet'"),
    (["--events", "delayed"], "--events choose simulated data"),
    (["--threshold", "-1"], "positive number or 'auto'"),
    (["--frame-gamma", "0"], "argument --frame-gamma: must be a finite number > 0"),
])
def test_cli_data_bad_input_exits_2_with_one_line(recording, tmp_path, capsys, extra, match):
    with pytest.raises(SystemExit) as exc:
        main(_data_cli(recording, tmp_path / "run", "--max-steps", "1") + extra)
    err = [line for line in capsys.readouterr().err.splitlines() if "error" in line]
    assert exc.value.code == 2 and len(err) == 1 and match in err[0]


def test_cli_data_unreadable_file_exits_2_without_traceback(tmp_path):
    bad = tmp_path / "broken.aedat4"
    bad.write_bytes(b"not an aedat file")
    r = subprocess.run([sys.executable, "-m", "evlatcorr.train", "--model", "efnet", "--data", str(bad)],
                       capture_output=True, text=True, timeout=120, cwd=tmp_path)
    assert r.returncode == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("evlatcorr.train: error: ")
    assert "does not start with '#!AER-DAT4.0'" in r.stderr


@pytest.mark.slow
def test_cli_data_on_a_real_davis346_recording(tmp_path):
    path = shared_data_dir() / "davis346" / "cradle_lowlight.aedat4"
    if not path.is_file():
        pytest.skip(f"{path} is absent")
    card = main(["--model", "efnet", "--checkpoint", "default", "--data", str(path), "--max-steps", "2",
                 "--crop", "32", "32", "--max-frames", "4", "--threshold", "0.5", "--warmup-steps", "1",
                 "--accelerator", "cpu", "--out", str(tmp_path / "run")])
    assert card["data"]["sensor_size"] == [260, 346] and card["data"]["train_samples"] == 3
    assert card["network"] == "frozen" and card["steps"] == 2
    assert card["val_objective_after"] < card["val_objective_before"]
    state = torch.load(tmp_path / "run" / "checkpoints" / "last.ckpt", weights_only=False)["state_dict"]
    shipped = EFNetAdapter(checkpoint="default", clamp=False).state_dict()
    assert all(torch.equal(state[f"adapter.{k}"], v) for k, v in shipped.items())
    assert state["latency_model.coefficients"].abs().max() > 1e-3


def test_validation_metrics_are_float32_under_mixed_precision():
    # bf16 autocast would run SSIM's Gaussian convolutions in bf16: the card's val SSIM must not depend on it
    module = RestorationModule("efnet")
    batch = _sim_batch()
    output = batch.replace(output=(batch.sharp + 0.05 * torch.rand_like(batch.sharp)).clamp(0, 1))

    def ssim(autocast: bool) -> float:
        module.val_ssim.reset()
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            module._validate(batch, output)
        return float(module.val_ssim.compute())

    assert ssim(True) == ssim(False)
