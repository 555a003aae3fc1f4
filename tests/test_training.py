from __future__ import annotations

import subprocess
import sys
import warnings

import lightning as L
import pytest
import torch

from evlatcorr import EventFrames
from evlatcorr.simulate import simulate
from evlatcorr.spatial import load_curve
from evlatcorr.training import (
    EventFramesDataModule,
    LatencyCorrectionModule,
    collate_event_frames,
    simulated_training_frames,
    split_frames,
)
from tests.conftest import random_events

SIM = dict(exposure_us=10000.0, frame_interval_us=12000.0, latency_range_us=(300.0, 4000.0))


def quiet_trainer(**kw) -> L.Trainer:
    return L.Trainer(accelerator="cpu", devices=1, logger=False, enable_checkpointing=False,
                     enable_progress_bar=False, enable_model_summary=False, **kw)


def test_split_and_collate_round_trip():
    ev = random_events(300, (6, 8), (0.0, 300.0), batch_size=3)
    frames = EventFrames(torch.rand(3, 1, 6, 8), ev, torch.zeros(3), torch.full((3,), 100.0))
    parts = split_frames(frames)
    assert [p.batch_size for p in parts] == [1, 1, 1]
    back = collate_event_frames(parts)
    assert torch.equal(back.blurry, frames.blurry) and torch.equal(back.events.t, frames.events.t)
    assert back.events.batch.tolist() == frames.events.batch.tolist()


def test_data_module_takes_a_dataset():
    class Lazy(torch.utils.data.Dataset):
        def __len__(self):
            return 3

        def __getitem__(self, i):
            ev = random_events(50, (6, 8), (0.0, 300.0), seed=i)
            return EventFrames(torch.full((1, 1, 6, 8), i / 3), ev, torch.zeros(1), torch.full((1,), 100.0))

    dm = EventFramesDataModule(Lazy(), batch_size=2)
    batches = list(dm.train_dataloader())
    assert [b.batch_size for b in batches] == [2, 1]
    assert sorted(float(b.blurry[j].mean()) for b in batches for j in range(b.batch_size)) == pytest.approx(
        [0.0, 1 / 3, 2 / 3])
    assert int(batches[0].events.counts().sum()) == 100


def test_bad_configurations():
    with pytest.raises(ValueError, match="empty"):
        EventFramesDataModule([])
    with pytest.raises(ValueError, match="order"):
        LatencyCorrectionModule(order=-1)
    with pytest.raises(ValueError, match="exposure"):
        # an exposure of zero length is refused where the batch is built
        EventFrames(torch.rand(1, 1, 4, 4), random_events(5, (4, 4), (0.0, 10.0)), torch.zeros(1), torch.zeros(1))


def test_schedule_constant_then_linear_decay():
    module = LatencyCorrectionModule(lr=0.1, constant_epochs=2, decay_epochs=3)
    sched = module.configure_optimizers()["lr_scheduler"]["scheduler"]
    lrs = []
    for _ in range(6):
        lrs.append(sched.optimizer.param_groups[0]["lr"])
        sched.optimizer.step()  # no gradients: a no-op, keeps torch's call order
        sched.step()
    assert lrs == pytest.approx([0.1, 0.1, 0.075, 0.05, 0.025, 0.0])


def test_short_training_lowers_latency_error(tmp_path):
    # self-supervised (no ground truth) on 3 training scenes; evaluated on a held-out photograph whose true
    # per-pixel latency map is known (intensity_delay model: 0.3 ms bright .. 4 ms dark)
    warnings.simplefilter("ignore")
    frames = simulated_training_frames(["camera", "coffee", "brick"], (48, 64), seed=0, **SIM)
    test = simulate("astronaut", num_frames=1, height=48, width=64, latency="intensity_delay", seed=9, **SIM)
    blurry, truth = test.frames("delayed").blurry, test.true_latency
    L.seed_everything(0)
    module = LatencyCorrectionModule(order=3, lr=0.05, num_bins=50, constant_epochs=3, decay_epochs=2)

    def error() -> float:
        with torch.no_grad():
            return float((module.latency_model(blurry).clamp(0, 10000) - truth).abs().mean())

    before = error()
    trainer = quiet_trainer(max_epochs=5, limit_val_batches=1)
    trainer.fit(module, EventFramesDataModule(frames, val=frames[:1]))
    after = error()
    assert {"train/total", "val/total", "val/etf"} <= set(trainer.callback_metrics)
    assert after < 0.6 * before  # measured: 1833 us -> 609 us
    ramp = torch.linspace(0.01, 1.0, 100)
    assert float(module.latency_model.slope(ramp).max()) <= 0.0  # the learned curve falls with intensity
    # checkpoint round trip: the Lightning checkpoint loads as a curve for inference
    trainer.save_checkpoint(tmp_path / "m.ckpt")
    curve = load_curve(tmp_path / "m.ckpt")
    torch.testing.assert_close(curve(blurry), module.latency_model(blurry))


@pytest.mark.slow
def test_ddp_two_cpu_processes(tmp_path):
    r = subprocess.run(
        [sys.executable, "-m", "evlatcorr.training", "--scenes", "motorcycle_left", "coins", "--size", "24", "32",
         "--epochs", "1", "--devices", "2", "--strategy", "ddp", "--accelerator", "cpu", "--num-bins", "30",
         "--out", str(tmp_path / "run")],
        capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "world_size=2" in r.stdout
    assert (tmp_path / "run" / "curve.pt").is_file() and (tmp_path / "run" / "last.ckpt").is_file()
    assert load_curve(tmp_path / "run" / "curve.pt").order == 5


@pytest.fixture(scope="module")
def recording_without_ground_truth(tmp_path_factory):
    """An event_utils HDF5 recording (events and blurry frames only, no sharp frames), 32x48."""
    from evlatcorr.io import H5Recording, write_event_utils, write_sequence

    seq = simulate("camera", num_frames=4, height=32, width=48, latency_us=3000.0, seed=0)
    folder = tmp_path_factory.mktemp("rec")
    write_sequence(folder / "sim.h5", seq)
    path = folder / "rec.h5"
    write_event_utils(path, seq.delayed_events, like=H5Recording(folder / "sim.h5"))  # frames only, no sharp ones
    return path


def test_training_frames_from_a_recording_are_read_linear_with_frame_gamma(recording_without_ground_truth):
    # the curve maps intensity to latency: it must be trained on the intensities it will read (evlatcorr --frame-gamma)
    from evlatcorr.lightning.latency_data import recording_training_frames

    as_stored, _, _ = recording_training_frames(recording_without_ground_truth, threshold=0.2, val_every=0)
    linear, _, _ = recording_training_frames(recording_without_ground_truth, threshold=0.2, val_every=0,
                                             frame_gamma=2.2)
    assert len(linear) == len(as_stored) > 0
    for a, b in zip(as_stored, linear):
        torch.testing.assert_close(b.blurry, a.blurry.clamp(0, 1) ** 2.2)
    with pytest.raises(ValueError, match="frame_gamma must be a finite number > 0"):
        recording_training_frames(recording_without_ground_truth, threshold=0.2, frame_gamma=0.0)


def test_curve_trains_on_a_recording(recording_without_ground_truth, tmp_path, recwarn):
    from evlatcorr.spatial import PolynomialLatency
    from evlatcorr.training import main as train_curve

    train_curve(["--data", str(recording_without_ground_truth), "--crop", "16", "24", "--epochs", "1",
                 "--max-steps", "2", "--val-every", "0", "--out", str(tmp_path / "curve")])
    # no frame held out: no validation loop, and no warning of an empty one
    assert not [w for w in recwarn if "Total length of" in str(w.message)]
    saved = torch.load(tmp_path / "curve" / "curve.pt", weights_only=False)
    assert saved["scenes"] == [str(recording_without_ground_truth)] and 0.02 < saved["threshold"] < 1.5
    start = PolynomialLatency(saved["order"], saved["eps"], saved["scale_us"]).coefficients
    assert not torch.allclose(saved["coefficients"], start)  # the objective moved the polynomial

