"""The shared pieces of evlatcorr.lightning: seeded random crops, loaders, the one CLI and the facades."""

from __future__ import annotations

import pytest
import torch

from evlatcorr import EventFrames, Events
from evlatcorr.lightning import RandomCrops, SimulatedRestorationData, frames_loader
from evlatcorr.lightning.cli import build_parser, main


def _frame(h: int = 12, w: int = 12) -> EventFrames:
    """One frame whose pixel values are their flat index, with an event on every pixel."""
    ys, xs = torch.meshgrid(torch.arange(h), torch.arange(w), indexing="ij")
    ev = Events(xs.flatten(), ys.flatten(), torch.linspace(1.0, 9.0, h * w), torch.ones(h * w), sensor_size=(h, w))
    return EventFrames(torch.arange(h * w, dtype=torch.float32).view(1, 1, h, w) / (h * w), ev, torch.zeros(1),
                       torch.full((1,), 10.0))


def _corners(items) -> list[float]:
    return [float(x.blurry[0, 0, 0, 0]) for x in items]


class TestRandomCrops:
    def test_the_seed_decides_the_crops(self):
        def crops(seed):
            data = RandomCrops([(_frame(),)], (4, 4), length=6, seed=seed)
            return _corners(data[i] for i in range(6))

        assert crops(0) == crops(0)
        assert crops(0) != crops(1)
        assert len(set(crops(0))) > 1  # a new crop per item

    def test_the_global_random_state_is_left_alone(self):
        state = torch.random.get_rng_state()
        data = RandomCrops([(_frame(), _frame())], (4, 4), length=8, seed=0)
        _ = [data[i] for i in range(8)]
        _ = list(frames_loader(data, 2, True, 0, seed=0))
        assert torch.equal(torch.random.get_rng_state(), state)

    def test_workers_draw_different_crops_reproducibly(self):
        def run():
            data = RandomCrops([(_frame(),)], (4, 4), length=8, seed=0)
            batches = list(frames_loader(data, 4, False, 2, seed=3))  # batch k comes from worker k
            return [_corners(b.split()) for b in batches]

        first, again = run(), run()
        assert first == again and first[0] != first[1]

    def test_require_events_draws_again(self):
        frame = _frame()
        one = frame.events.select(frame.events.t == frame.events.t[0])  # only pixel (0, 0) has an event
        sparse = frame.replace(events=one)
        data = RandomCrops([(sparse,)], (11, 11), length=20, seed=0, require_events=True, tries=50)
        assert all(len(data[i].events) == 1 for i in range(20))

    def test_simulated_data_uses_its_seed(self):
        def first_batch(seed):
            data = SimulatedRestorationData(photographs=["coins"], size=(24, 32), crop=(8, 8), sequences=1,
                                            num_frames=2, batch_size=2, steps_per_epoch=2, seed=seed)
            data.setup()
            return next(iter(data.train_dataloader())).blurry

        assert torch.equal(first_batch(0), first_batch(0))
        assert not torch.equal(first_batch(0), first_batch(1))


class TestCommandLine:
    def test_subcommands_share_the_flags_of_the_old_commands(self):
        args = build_parser().parse_args(["restore", "--model", "gem", "--crop", "16", "16", "--threshold", "0.3"])
        assert (args.command, args.model, args.crop, args.threshold) == ("restore", "gem", [16, 16], 0.3)
        args = build_parser().parse_args(["latency", "--size", "24", "32", "--max-steps", "2"])
        assert (args.command, args.size, args.max_steps) == ("latency", [24, 32], 2)

    @pytest.mark.parametrize("argv, message", [
        ([], "python -m evlatcorr.lightning: error: the following arguments are required: COMMAND"),
        (["restore", "--model", "unet"], "python -m evlatcorr.lightning restore: error: argument --model"),
        (["restore", "--model", "efnet", "--max-steps", "0"], "--max-steps, --batch-size and --val-every"),
        # latency: what used to be a traceback, or a curve saved without a step of training
        (["latency", "--epochs", "0"], "nothing would be trained"),
        (["latency", "--max-steps", "0"], "nothing would be trained"),
        (["latency", "--order", "-1"], "--order and --constant-epochs must be >= 0"),
        (["latency", "--num-bins", "1"], "--num-bins >= 2"),
        (["latency", "--lr", "nan"], "--lr must be a positive number"),
        (["latency", "--data", "x.aedat4", "--threshold", "-1"], "argument --threshold: must be a positive number"),
        (["latency", "--data", "x.aedat4", "--val-every", "-1"], "--val-every must be >= 0"),
        (["latency", "--data", "x.aedat4", "--crop", "4", "4"], "--crop must be at least 8 8"),
        (["latency", "--crop", "16", "16", "--threshold", "0.3"], "--crop, --threshold apply to --data"),
        (["latency", "--frame-gamma", "2.2"], "--frame-gamma applies to --data"),
        (["latency", "--scenes", "nosuch"], "unknown --scenes ['nosuch']"),
        (["latency", "--scenes", "moon", "camera"], "['camera'] belong to the benchmark's test split"),
        (["latency", "--size", "3", "3"], "--size must be at least 8 8"),
        (["restore", "--model", "efnet", "--lr", "nan"], "--lr must be a positive number"),
        (["restore", "--model", "efnet", "--gradient-clip", "-1"], "--gradient-clip must be a positive number"),
        (["restore", "--model", "efnet", "--sequences", "0"], "--sequences, --num-frames and --size must be >= 1"),
        (["restore", "--model", "efnet", "--num-workers", "-1"], "--num-workers must be >= 0"),
        (["restore", "--model", "refid", "--refid-layout", "0", "1"], "--refid-layout M N needs M >= 1"),
        (["restore", "--model", "efnet", "--photographs", "nosuch"], "unknown --photographs ['nosuch']"),
    ])
    def test_bad_arguments_one_line_exit_2(self, argv, message, capsys):
        with pytest.raises(SystemExit) as exc:
            main(argv)
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and message in err[0]

    @pytest.mark.parametrize("setting, message", [
        (["--devices", "0"], "`Trainer(devices=0)` value is not a valid input"),
        (["--strategy", "nope"], "invalid strategy name"),
    ])
    def test_settings_lightning_refuses_are_bad_input(self, setting, message, tmp_path, capsys):
        # one line and exit 2, before any frame is simulated (latency) or a step taken (restore), not a traceback
        for argv in (["latency"], ["restore", "--model", "efnet", "--max-steps", "1"]):
            with pytest.raises(SystemExit) as exc:
                main([*argv, *setting, "--out", str(tmp_path / argv[0])])
            err = capsys.readouterr().err.strip().splitlines()
            assert exc.value.code == 2 and err[-1].startswith(f"evlatcorr.lightning {argv[0]}: error: ")
            assert message in err[-1]
            assert not (tmp_path / argv[0] / "last.ckpt").exists()

    def test_bad_input_names_the_subcommand(self, tmp_path, capsys):
        with pytest.raises(SystemExit) as exc:
            main(["latency", "--data", str(tmp_path / "missing.aedat4"), "--out", str(tmp_path)])
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and err[-1].startswith("evlatcorr.lightning latency: error: ")


def test_the_facades_re_export_the_same_objects():
    import evlatcorr.lightning as new
    from evlatcorr import train, training

    assert train.RestorationModule is new.RestorationModule
    assert train.CorrectedRestorationModule is new.CorrectedRestorationModule
    assert training.LatencyCorrectionModule is new.LatencyCorrectionModule
    assert training.collate_event_frames is new.collate_event_frames
    for module in (train, training):
        assert module.__doc__.splitlines()[0].startswith("Kept for compatibility")


def test_a_run_prints_lightnings_messages_but_not_its_adverts(tmp_path):
    # Lightning's cloud tips, its note on TensorBoard and the "weights_only was not set" line say nothing a user of
    # the command can act on; what it found (devices) and the run's own lines stay, and last.ckpt stays resumable
    import subprocess
    import sys

    run = subprocess.run([sys.executable, "-m", "evlatcorr.lightning", "latency", "--epochs", "1", "--size", "32", "40",
                          "--max-steps", "1", "--out", str(tmp_path)], capture_output=True, text=True, timeout=600)
    output = run.stdout + run.stderr
    assert run.returncode == 0, output
    assert "GPU available" in output and "saved" in output
    for noise in ("Tip:", "litlogger", "tensorboardX", "weights_only", "LeafSpec"):
        assert noise not in output
    assert "optimizer_states" in torch.load(tmp_path / "last.ckpt", map_location="cpu", weights_only=False)


@pytest.mark.parametrize("command", [["latency"], ["restore", "--model", "efnet"]])
def test_an_output_folder_that_cannot_be_written_is_refused_before_training(command, tmp_path, capsys):
    # a file where the folder should be: found before the first step, not when the trained weights are saved
    (tmp_path / "taken").write_text("")
    for flag in ("--out", "--export") if command[0] == "restore" else ("--out",):
        out = [] if flag == "--out" else ["--out", str(tmp_path / "out")]
        with pytest.raises(SystemExit) as exc:
            main([*command, *out, flag, str(tmp_path / "taken" / "run")])
        err = capsys.readouterr().err.strip().splitlines()
        assert exc.value.code == 2 and len(err) == 1 and f"{flag}: " in err[0] and "cannot be written" in err[0]


def test_check_writable_folder_makes_the_folder_and_leaves_it_empty(tmp_path):
    from evlatcorr.io.outputs import check_writable_folder

    check_writable_folder(tmp_path / "a" / "b")
    assert (tmp_path / "a" / "b").is_dir() and not any((tmp_path / "a" / "b").iterdir())
    (tmp_path / "file").write_text("")
    with pytest.raises(ValueError, match="cannot be written"):
        check_writable_folder(tmp_path / "file")
