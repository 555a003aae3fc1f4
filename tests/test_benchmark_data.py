"""Benchmark scenes from recorded data: latency injected into real-format recordings (HighREV layout)."""

from __future__ import annotations

import importlib
import json
import sys
from pathlib import Path

import pytest
import torch

from evlatcorr.benchmark.recording import delay_events, intensity_latency, scenes_from_recording
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames
from evlatcorr.io import RecordingError, write_sequence
from evlatcorr.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]


def _script(name: str):
    """A script of ``benchmarks/`` as a module (it imports its ``_setup`` from there)."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        return importlib.import_module(name)
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))


def _highrev_folder(tmp_path_factory, gamma: float = 1.0) -> Path:
    root = tmp_path_factory.mktemp("highrev") / "val"
    script = _script("display_gamma_table1")  # its writer and scenes: what the benchmark measures, tested here
    script.write_highrev_split(root, script.simulated_scenes((36, 52)), gamma)
    return root


@pytest.fixture(scope="module")
def highrev(tmp_path_factory):
    return _highrev_folder(tmp_path_factory)


@pytest.fixture(scope="module")
def highrev_encoded(tmp_path_factory):
    """The same scenes as ``highrev``, their PNGs encoded for display (gamma 2.2)."""
    return _highrev_folder(tmp_path_factory, gamma=2.2)




def test_delay_events_known_answer():
    ev = Events(torch.tensor([0, 1, 1]), torch.zeros(3), torch.tensor([-2500.0, 100.0, 9000.0]), torch.ones(3),
                sensor_size=(1, 2))
    fr = EventFrames(torch.rand(1, 1, 1, 2), ev, torch.tensor([0.0]), torch.tensor([5000.0]))
    # per-pixel latency: pixel 0 lags 3 ms (its early event enters the window), pixel 1 lags 2 ms
    out = delay_events(fr, torch.tensor([[[[3000.0, 2000.0]]]]))
    assert out.events.t.tolist() == [500.0, 2100.0]  # 9000 + 2000 falls past end + exposure (10 ms)
    assert out.events.x.tolist() == [0, 1]


def test_intensity_latency_follows_the_simulator_law():
    lat = intensity_latency(torch.tensor([1.0, 0.5, 0.01]).view(1, 1, 1, 3))
    assert lat.flatten().tolist() == [500.0, 1000.0, 10000.0]


def test_scenes_from_highrev_inject_the_latency(highrev):
    scenes = list(scenes_from_recording(highrev, latency_us=3000.0, frames_per_scene=2))
    assert [s.name for s in scenes] == ["camera", "rocket"]
    for s in scenes:
        assert s.frames_ideal.sensor_size == (32, 48)  # centre crop to multiples of 16
        assert s.pairs_ideal is None and s.pairs_delayed is None
        assert s.true_latency.shape == (2, 1, 32, 48) and bool((s.true_latency == 3000.0).all())
        # every delayed event is an ideal one 3 ms late
        ideal, delayed = s.frames_ideal.events, s.frames_delayed.events
        assert len(delayed) > 0
        start, end = s.frames_ideal.exposure_start, s.frames_ideal.exposure_end
        lo, hi = start + 1.0, end + (end - start) - 3001.0  # inside both windows, away from their edges
        early = delayed.shift(3000.0)
        early = early.select((early.t >= lo[early.batch]) & (early.t < hi[early.batch]))
        same = ideal.window(lo, hi)
        torch.testing.assert_close(early.t, same.t)
        assert early.x.tolist() == same.x.tolist() and early.batch.tolist() == same.batch.tolist()
    one = list(scenes_from_recording(highrev, latency="intensity", max_scenes=1))
    assert len(one) == 1 and one[0].true_latency.min() >= 500.0 and one[0].true_latency.max() <= 10000.0


def test_scenes_from_frames_encoded_for_display_are_held_linear(highrev, highrev_encoded):
    linear = list(scenes_from_recording(highrev, latency="intensity", frames_per_scene=2))
    encoded = list(scenes_from_recording(highrev_encoded, latency="intensity", frames_per_scene=2, frame_gamma=2.2))
    assert [s.frame_gamma for s in linear] == [1.0, 1.0] and [s.frame_gamma for s in encoded] == [2.2, 2.2]
    for a, b in zip(linear, encoded):
        # the same linear frames, to the 8-bit files' rounding; the intensity law reads them linear too
        torch.testing.assert_close(b.frames_ideal.blurry, a.frames_ideal.blurry, rtol=0, atol=0.012)
        torch.testing.assert_close(b.frames_ideal.sharp, a.frames_ideal.sharp, rtol=0, atol=0.012)
        assert (b.true_latency - a.true_latency).abs().median() < 50.0


def test_benchmark_on_frames_encoded_for_display(tmp_path, capsys):
    # benchmarks/display_gamma_table1.py: the same scenes linear, encoded and read as they are, and encoded and read
    # with --frame-gamma, through run.py --data
    results = _script("display_gamma_table1").main(["--out", str(tmp_path)])
    linear, as_encoded, read = results.values()
    # the correctors read the same linear frames, so they estimate the same latencies (to the files' rounding);
    # read as encoded, the estimates are milliseconds off (6599 against 451 us at the time of writing)
    for name in ("W/ corr. const.", "W/ corr. spatial"):
        assert abs(read["latency_error"][name]["mae_us"] - linear["latency_error"][name]["mae_us"]) < 300.0
        assert as_encoded["latency_error"][name]["mae_us"] > read["latency_error"][name]["mae_us"] + 2000.0
    rows = {(r["method"], r["input"]): r for r in read["table"]}
    assert rows[("EDI deblurring", "W/ corr. const.")]["psnr"] > rows[("EDI deblurring", "W/o corr.")]["psnr"]
    assert "read linear with frame_gamma 2.2" in (tmp_path / "run2" / "results.md").read_text()
    assert read["config"]["frame_gamma"] == 2.2 and linear["config"]["frame_gamma"] == 1.0
    assert "| encoded, --frame-gamma 2.2 | " in capsys.readouterr().out


def test_recording_without_sharp_frames_is_a_clear_error(highrev, tmp_path):
    import shutil

    shutil.copytree(highrev, tmp_path / "val")
    shutil.rmtree(tmp_path / "val" / "sharp")
    with pytest.raises(RecordingError, match="no frame has a ground-truth sharp frame"):
        list(scenes_from_recording(tmp_path / "val"))


def _run_benchmark(*argv: str) -> dict:
    from evlatcorr.benchmark.table1 import main

    assert main(list(argv)) == 0
    out = Path(argv[argv.index("--out") + 1])
    return json.loads((out / "results.json").read_text())


def test_benchmark_on_a_highrev_folder(highrev, tmp_path):
    results = _run_benchmark("--data", str(highrev), "--methods", "edi,edi-interp", "--num-bins", "100",
                             "--spatial-steps", "3", "--out", str(tmp_path / "out"))
    rows = {(r["method"], r["input"]): r for r in results["table"]}
    assert rows[("EDI deblurring", "GT input")]["psnr"] > rows[("EDI deblurring", "W/o corr.")]["psnr"]
    assert rows[("EDI deblurring", "W/ corr. const.")]["psnr"] > rows[("EDI deblurring", "W/o corr.")]["psnr"]
    assert "no ground truth between exposures" in results["failures"]["EDI interpolation"]
    assert results["data"] == ["camera", "rocket"]
    assert "injected into the recorded events" in (tmp_path / "out" / "results.md").read_text()


def test_benchmark_skips_an_unreadable_sequence_file(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    write_sequence(data / "a.h5", simulate("camera", num_frames=2, height=32, width=48, exposure_us=20000.0,
                                           frame_interval_us=25000.0, latency="constant", latency_us=3000.0))
    write_sequence(data / "b.h5", simulate("rocket", num_frames=2, height=32, width=48, exposure_us=20000.0,
                                           frame_interval_us=25000.0, latency="constant", latency_us=3000.0))
    import h5py

    with h5py.File(data / "b.h5", "a") as f:  # damaged after it was listed: its sharp frames are gone
        del f["frames/sharp"]
    results = _run_benchmark("--data", str(data), "--methods", "edi", "--num-bins", "100", "--spatial-steps", "3",
                             "--out", str(tmp_path / "out"))
    assert list(results["unreadable"]) == [f"{data / 'b.h5'}:0"]
    assert results["table"][0]["psnr"] == results["table"][0]["psnr"]  # a.h5 was still scored


def test_frame_gamma_is_refused_for_our_linear_sequence_files(tmp_path):
    import argparse

    from evlatcorr.benchmark.scenes import data_sources

    write_sequence(tmp_path / "a.h5", simulate("camera", num_frames=2, height=16, width=16, latency="none"))
    args = argparse.Namespace(data=tmp_path / "a.h5", frame_gamma=2.2, scenes=None)
    with pytest.raises(SystemExit, match="holds our HDF5 sequences, whose frames are linear"):
        data_sources(args)
    assert data_sources(argparse.Namespace(data=tmp_path / "a.h5", frame_gamma=1.0, scenes=None)) == [
        (tmp_path / "a.h5", 0)]
