from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter
from evlatcorr.adapters.refid import refid_output_times
from evlatcorr.simulate import PHOTOGRAPHS_TEST
from evlatcorr.train import (
    CorrectedRestorationModule,
    RestorationModule,
    SimulatedRestorationData,
    build_adapter,
    checkpoint_name,
    collate_frames,
    crop_frames,
    main,
    restoration_pair,
)

from .conftest import random_events


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
def test_cli_trains_exports_and_resumes(tmp_path):
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
    with pytest.raises(SystemExit, match="does not exist"):
        main(_tiny_cli(tmp_path / "other", "--max-steps", "4", "--resume", "last"))


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
        module = CorrectedRestorationModule(EFNetAdapter(), "deblur", corrector="constant", num_bins=40)
        batch = _sim_batch(events="delayed")
        corrected, loss = module.correct(batch)
        assert loss is None and corrected.latency.shape == (1, 1, 32, 32)
        latency = float(corrected.latency[0, 0, 0, 0])
        assert torch.all(corrected.latency == latency) and 0.0 <= latency <= 20000.0
        assert torch.allclose(corrected.corrected.t.sort().values, (batch.events.t - latency).sort().values)

    def test_interpolation_pairs_are_corrected(self):
        module = CorrectedRestorationModule(REFIDAdapter(m=4, n=1, clamp=False), "interpolation",
                                            train_corrector=False)
        out = module(_sim_batch("interpolation", events="delayed"))
        assert out.output.shape == (1, 9, 3, 32, 32)

    def test_nothing_to_train_raises(self):
        with pytest.raises(ValueError, match="nothing to train"):
            CorrectedRestorationModule(EFNetAdapter(), "deblur", corrector="constant", train_network=False)
