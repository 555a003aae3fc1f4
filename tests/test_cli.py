from __future__ import annotations

import argparse
import csv
import os
import re
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import h5py
import numpy as np
import pytest
import torch
from PIL import Image

from evlatcorr.io import H5Recording, write_sequence
from evlatcorr.simulate import simulate
from tests.commands import run_command

DAVIS = Path(__file__).resolve().parents[2] / "shared" / "data" / "davis346"


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    """``evlatcorr ARGS``, in this process (``test_help`` and the signal tests start real ones)."""
    return run_command(*args, cwd=cwd)


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    d = tmp_path_factory.mktemp("cli")
    r = run("simulate", str(d / "sim.h5"), "--frames", "2", "--size", "48", "64", "--image", "coffee",
            "--latency-us", "3000", cwd=d)
    assert r.returncode == 0, r.stderr
    assert "2 frames 64x48" in r.stdout
    return d / "sim.h5"


def test_help_reads_well():
    r = subprocess.run([sys.executable, "-m", "evlatcorr", "--help"], capture_output=True, text=True)
    assert r.returncode == 0
    for command in ("correct", "deblur", "simulate", "info"):
        assert command in r.stdout


def test_every_command_and_argument_says_what_it_is():
    from evlatcorr.cli.parser import build_parser

    parser = build_parser()
    commands = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for name, sub in commands.choices.items():
        assert sub.description, name
        for action in sub._actions:
            if not isinstance(action, argparse._HelpAction):
                assert action.help, f"{name} {action.dest}"


def test_info(simulated):
    r = run("info", str(simulated), cwd=simulated.parent)
    assert r.returncode == 0
    assert "evlatcorr-h5" in r.stdout and "(48, 64)" in r.stdout and "frames" in r.stdout


def test_an_exposure_option_is_refused_unless_positive_and_said_unused_where_frames_carry_their_own(simulated):
    for bad in ("-5", "0", "nan", "inf"):
        r = run("info", str(simulated), "--exposure-us", bad, cwd=simulated.parent)
        assert r.returncode == 2 and "argument --exposure-us: must be a" in r.stderr
    r = run("info", str(simulated), "--exposure-us", "5000", cwd=simulated.parent)
    assert r.returncode == 0, r.stderr
    assert "--exposure-us is not used: evlatcorr-h5 recordings stamp each frame's exposure" in r.stderr


def test_correct_writes_events_and_report(simulated):
    out = simulated.parent / "corrected.h5"
    r = run("correct", str(simulated), str(out), "--num-bins", "100", cwd=simulated.parent)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert [int(row["frame"]) for row in rows] == [0, 1]
    latencies = [float(row["latency_us"]) for row in rows]
    # 3000 us injected: measured 4199 and 3947 us (+1199, +947). The image moves at most 1.5 px/ms, so the ETF
    # resolves the latency to about a pixel of motion, 1 to 1.5 ms, at 48x64; uncorrected, the error is 3000 us
    assert all(abs(latency - 3000.0) < 1500.0 for latency in latencies), latencies
    assert [row["source"] for row in rows] == ["reader", "reader"] and [row["fallback"] for row in rows] == [
        "0", "0"]
    assert [row["hot_pixels"] for row in rows] == ["0", "0"]
    assert all(float(row["spread_us"]) > 0 for row in rows)  # the learned reader's, µs
    # the latency of each frame is fused with its neighbour's evidence; the report keeps each frame's own estimate
    own = [float(row["frame_latency_us"]) for row in rows]
    assert all(abs(latency - 3000.0) < 1500.0 for latency in own), own
    with h5py.File(simulated) as f:
        original_t = f["events/t"][:]
        starts = f["frames/exposure_start"][:]
    with h5py.File(out) as f:
        corrected_t = f["events/t"][:]
        np.testing.assert_allclose(f["frames/estimated_latency"][:], latencies, atol=0.1)
    # every event kept, sorted, and shifted by its frame's latency
    assert len(corrected_t) == len(original_t) and np.all(np.diff(corrected_t) >= 0)
    frame = np.clip(np.searchsorted(starts, original_t, side="right") - 1, 0, 1)
    expected = np.sort(original_t - np.array(latencies)[frame])
    np.testing.assert_allclose(corrected_t, expected, atol=0.2)
    assert len(list(H5Recording(out).frames())) == 2
    assert not list(simulated.parent.glob(".*.tmp"))
    assert Image.open(out.with_suffix(".png")).format == "PNG"  # the latencies drawn
    assert f"and {out.with_suffix('.png')}" in r.stdout
    for written in (out, out.with_suffix(".csv"), out.with_suffix(".png")):  # the umask's mode, not mkstemp's 0600
        assert os.stat(written).st_mode & 0o777 == 0o666 & ~_umask()


def test_correct_adds_each_pairs_agreement_unless_told_not_to(simulated, tmp_path):
    out = tmp_path / "paired.h5"
    r = run("correct", str(simulated), str(out), "--num-bins", "100", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    # the first frame and the second agree best at about the injected 3000 us; the last frame has no next one
    assert abs(float(rows[0]["pair_latency_us"]) - 3000.0) <= 500.0 and rows[1]["pair_latency_us"] == ""
    alone = tmp_path / "alone.h5"
    r = run("correct", str(simulated), str(alone), "--num-bins", "100", "--no-pairs", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    alone_rows = list(csv.DictReader(open(alone.with_suffix(".csv"))))
    assert "pair_latency_us" not in alone_rows[0]
    assert [row["frame_latency_us"] for row in alone_rows] == [row["frame_latency_us"] for row in rows]
    assert [row["latency_us"] for row in alone_rows] != [row["latency_us"] for row in rows]


def test_deblur_writes_pngs(simulated, tmp_path):
    r = run("deblur", str(simulated), str(tmp_path / "png"), "--num-bins", "100", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == [
        "frame_00000_blurry.png", "frame_00000_edi.png", "frame_00001_blurry.png", "frame_00001_edi.png",
        "frames.csv", "side_by_side.gif"]
    assert os.stat(tmp_path / "png").st_mode & 0o777 == 0o777 & ~_umask()
    assert os.stat(tmp_path / "png" / "frames.csv").st_mode & 0o777 == 0o666 & ~_umask()


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _check_restored(outdir: Path, model: str, frames: int, size: tuple[int, int], corrected: bool,
                    per_frame: int = 1, blurry: bool = True) -> list[dict]:
    rows = list(csv.DictReader(open(outdir / "frames.csv")))
    assert len(rows) == frames
    outputs = sorted(outdir.glob(f"frame_*_{model}.png"))
    assert len(sorted(outdir.glob(f"frame_*_{model}_corrected.png"))) == (len(outputs) if corrected else 0)
    done = [r for r in rows if not r["skipped"]]
    assert len(outputs) == len(done) * per_frame and done
    assert len(list(outdir.glob("frame_*_blurry.png"))) == (len(done) if blurry else 0)
    for path in outputs[:2]:
        assert Image.open(path).size == (size[1], size[0])  # PIL: (W, H)
    gif = Image.open(outdir / "side_by_side.gif")
    assert gif.size == ((size[1] * (3 if corrected else 2) + (4 if corrected else 2)), size[0])
    if corrected:
        assert all(float(r["latency_us"]) >= 0 and r["threshold"] and int(r["events_in_window"]) > 0 for r in done)
    assert (outdir / "latency.png").exists() == corrected  # the latencies drawn where there are some
    return rows


def test_deblur_fuses_each_frames_latency_with_the_frames_before_and_its_pair(simulated, tmp_path):
    args = ("--model", "edi", "--correct", "--num-bins", "100")
    for name, extra in (("paired", ()), ("fused", ("--no-pairs",)), ("alone", ("--fuse-frames", "0", "--no-pairs"))):
        r = run("deblur", str(simulated), str(tmp_path / name), *args, *extra, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
    paired, fused, alone = (list(csv.DictReader(open(tmp_path / name / "frames.csv")))
                            for name in ("paired", "fused", "alone"))
    assert "frame_latency_us" not in alone[0] and "pair_latency_us" not in fused[0]
    assert [row["latency_us"] for row in alone] == [row["frame_latency_us"] for row in fused]
    # each frame's own estimate is the same (the paired run's frames hold more events after their window)
    np.testing.assert_allclose([float(row["frame_latency_us"]) for row in paired],
                               [float(row["frame_latency_us"]) for row in fused], atol=5.0)
    # a stream: the first frame has no earlier evidence, the second takes the first's too
    assert abs(float(fused[0]["latency_us"]) - float(fused[0]["frame_latency_us"])) < 1.0
    assert all(abs(float(row["latency_us"]) - 3000.0) < 1500.0 for row in fused + paired)
    # the model reads single frames, the corrector each frame with the next (the last frame has none): their
    # agreement is in the report and moves the latency
    assert all(row["pair_latency_us"] for row in paired[:-1]) and paired[-1]["pair_latency_us"] == ""
    assert [row["latency_us"] for row in paired[:-1]] != [row["latency_us"] for row in fused[:-1]]
    assert paired[-1]["skipped"] == "" and sorted(p.name for p in (tmp_path / "paired").glob("*.png")) == sorted(
        p.name for p in (tmp_path / "fused").glob("*.png"))
    bad = run("deblur", str(simulated), str(tmp_path / "bad"), *args, "--fuse-frames", "-2", cwd=tmp_path)
    assert bad.returncode == 2 and "--fuse-frames must be 0 or more" in bad.stderr


@pytest.mark.slow
@pytest.mark.parametrize("model", ["edi", "efnet", "gem", "refid"])
def test_deblur_every_model(simulated, tmp_path, model):
    out = tmp_path / model
    r = run("deblur", str(simulated), str(out), "--model", model, "--correct", "constant", "--num-bins", "100",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rows = _check_restored(out, model, 2, (48, 64), corrected=True)
    # REFID reads two frames: the last one has no next frame and is reported as skipped
    assert [r["skipped"] for r in rows] == (["", "no next frame"] if model == "refid" else ["", ""])


@pytest.mark.slow
@pytest.mark.parametrize("model", ["edi", "refid"])
def test_interpolate(simulated, tmp_path, model):
    out = tmp_path / model
    r = run("interpolate", str(simulated), str(out), "--model", model, "--num", "3" if model == "edi" else "1",
            "--num-bins", "100", *(["--correct"] if model == "edi" else []), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _check_restored(out, model, 2, (48, 64), corrected=model == "edi", per_frame=3 if model == "edi" else 1,
                    blurry=False)


def test_interpolate_adds_each_pairs_agreement_unless_told_not_to(simulated, tmp_path):
    args = ("--model", "edi", "--num", "1", "--num-bins", "100", "--correct")
    latencies = {}
    for name, extra in (("paired", ()), ("alone", ("--no-pairs",))):
        r = run("interpolate", str(simulated), str(tmp_path / name), *args, *extra, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        rows = list(csv.DictReader(open(tmp_path / name / "frames.csv")))
        latencies[name] = [float(row["latency_us"]) for row in rows if row["latency_us"]]
    # the one pair: its first frame takes the two frames' agreement too, about the injected 3000 us
    assert latencies["paired"] != latencies["alone"]
    assert all(abs(v - 3000.0) < 1500.0 for v in latencies["paired"]), latencies


@pytest.mark.slow
@pytest.mark.skipif(not (DAVIS / "cradle_lowlight.aedat4").is_file(), reason="shared DAVIS346 data absent")
@pytest.mark.parametrize("model", ["edi", "efnet", "gem", "refid"])
def test_deblur_a_davis346_recording(tmp_path, model):
    out = tmp_path / model
    r = run("deblur", str(DAVIS / "cradle_lowlight.aedat4"), str(out), "--model", model, "--correct",
            "--max-frames", "2", "--num-bins", "100", "--threshold", "0.5", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    _check_restored(out, model, 2, (260, 346), corrected=True)  # 346 is no multiple of 4, 8 or 16: padded


def _first_frame_empty(folder: Path, num_frames: int, seed: int) -> Path:
    """A recording whose first frame has no events in its window (a static start): none before 20 ms past its
    exposure's end, as far as the search reads (the exposure time), even with ``--search-us 0 5000``."""
    seq = simulate("coffee", num_frames=num_frames, height=32, width=48, latency_us=2000.0, seed=seed)
    ev = seq.delayed_events
    keep = ev.t > float(seq.exposure_end[0]) + 20000.0
    seq.delayed_events = type(ev)(ev.x[keep], ev.y[keep], ev.t[keep], ev.p[keep], sensor_size=ev.sensor_size)
    path = folder / "first_frame_empty.h5"
    write_sequence(path, seq)
    return path


def test_a_recording_with_too_few_events_to_tell_a_latency_or_threshold_says_so(tmp_path):
    # a still scene: a few dozen events a frame (the static DAVIS346 street recording has about 30)
    seq = simulate("coffee", num_frames=3, height=32, width=48, latency_us=2000.0, seed=3)
    ev = seq.delayed_events
    keep = torch.rand(len(ev), generator=torch.Generator().manual_seed(0)) < 0.004
    seq.delayed_events = type(ev)(ev.x[keep], ev.y[keep], ev.t[keep], ev.p[keep], sensor_size=ev.sensor_size)
    write_sequence(tmp_path / "still.h5", seq)
    r = run("correct", str(tmp_path / "still.h5"), str(tmp_path / "out.h5"), "--no-figure", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert re.search(r"the recording's contrast threshold \d\.\d+ is estimated from frames with at most \d+ events "
                     r"in their exposure and search window \(under 100\): too few to tell it", r.stderr), r.stderr
    first = re.findall(r"frame (\d+): only (\d+) event\(s\) in its exposure and search window, too few \(under 100\)",
                       r.stderr)
    assert len(first) == 1 and int(first[0][1]) < 100, r.stderr
    rest = re.findall(r"(\d+) more frames? \(([\d, -]+)\): under 100 events in the exposure and search window",
                      r.stderr)
    assert len(rest) == 1 and int(rest[0][0]) == 2, r.stderr  # each frame named once, the others in one line
    rows = list(csv.DictReader(open(tmp_path / "out.csv")))
    assert len(rows) == 3 and all(int(row["events_in_window"]) < 100 for row in rows)
    assert "3 with under 100 events in the window: their latency is a guess" in r.stdout


@pytest.fixture(scope="module")
def first_frame_empty(tmp_path_factory):
    return _first_frame_empty(tmp_path_factory.mktemp("empty"), 3, seed=3)


def test_correct_fuses_frames_unless_told_not_to(simulated, tmp_path):
    fused, alone = tmp_path / "fused.h5", tmp_path / "alone.h5"
    assert run("correct", str(simulated), str(fused), "--num-bins", "100", cwd=tmp_path).returncode == 0
    r = run("correct", str(simulated), str(alone), "--num-bins", "100", "--fuse-frames", "0", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    fused_rows = list(csv.DictReader(open(fused.with_suffix(".csv"))))
    alone_rows = list(csv.DictReader(open(alone.with_suffix(".csv"))))
    assert "frame_latency_us" not in alone_rows[0]
    # each frame alone gives what the fused run reports as the frame's own estimate
    assert [row["latency_us"] for row in alone_rows] == [row["frame_latency_us"] for row in fused_rows]
    bad = run("correct", str(simulated), str(tmp_path / "bad.h5"), "--fuse-frames", "-1", cwd=tmp_path)
    assert bad.returncode == 2 and "--fuse-frames must be 0 or more" in bad.stderr
    assert not (tmp_path / "bad.h5").exists()


def test_correct_keeps_going_past_a_frame_without_events(first_frame_empty, tmp_path):
    out = tmp_path / "c.h5"
    r = run("correct", str(first_frame_empty), str(out), "--num-bins", "100", "--search-us", "0", "5000",
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "frame 0: no events" in r.stderr
    # warnings are one line each, once per message, without Python's file and source line
    warned = [line for line in r.stderr.splitlines() if "warning" in line.lower()]
    assert warned and all(line.startswith("evlatcorr correct: warning: ") for line in warned), r.stderr
    assert len(warned) == len(set(warned)) and "UserWarning" not in r.stderr
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert [r["skipped"] for r in rows] == ["no events", "", ""]
    assert float(rows[0]["latency_us"]) == 0.0 and float(rows[1]["latency_us"]) > 0.0


def _snapshot(path: Path) -> bytes:
    return path.read_bytes()


def test_correct_refuses_outputs_that_destroy_files(simulated, tmp_path):
    before = _snapshot(simulated)
    r = run("correct", str(simulated), str(simulated), cwd=tmp_path)  # output == input
    assert r.returncode == 2 and "is the input" in r.stderr and "Traceback" not in r.stderr
    assert _snapshot(simulated) == before
    r = run("correct", str(simulated), str(tmp_path / "out.h5"), "--report", str(tmp_path / "out.h5"),
            cwd=tmp_path)  # report == output
    assert r.returncode == 2 and "would replace" in r.stderr
    assert not (tmp_path / "out.h5").exists()
    for command, args in (("correct", (str(simulated),)), ("simulate", ())):  # HDF5 named as another format
        r = run(command, *args, str(tmp_path / "events.txt"), cwd=tmp_path)
        assert r.returncode == 2 and "events.txt: this command writes HDF5; name it .h5" in r.stderr, r.stderr
        assert "Traceback" not in r.stderr and not (tmp_path / "events.txt").exists()
    (tmp_path / "o.csv").mkdir()  # the report's name is a folder; o.h5 holds a user's file
    (tmp_path / "o.h5").write_bytes(b"precious")
    r = run("correct", str(simulated), str(tmp_path / "o.h5"), cwd=tmp_path)
    assert r.returncode == 2 and "is a directory" in r.stderr and "Traceback" not in r.stderr
    assert (tmp_path / "o.h5").read_bytes() == b"precious"
    assert not list(tmp_path.glob(".*.tmp"))
    (tmp_path / "file").write_text("x")
    r = run("correct", str(simulated), str(tmp_path / "file" / "out.h5"), cwd=tmp_path)  # parent is a file
    assert r.returncode == 2 and "not a folder" in r.stderr


def test_correct_makes_display_encoded_frames_linear_with_frame_gamma(simulated, tmp_path):
    # the frames written are those the corrector saw: linear, as our format holds them
    r = run("correct", str(simulated), str(tmp_path / "out.h5"), "--frame-gamma", "2.2", "--no-figure",
            "--threshold", "0.2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with h5py.File(simulated) as src, h5py.File(tmp_path / "out.h5") as out:
        np.testing.assert_allclose(out["frames/blurry"][:], np.clip(src["frames/blurry"][:], 0, 1) ** 2.2,
                                   rtol=1e-5, atol=1e-6)


def test_deblur_with_frame_gamma_writes_pngs_encoded_as_the_files_frames(simulated, tmp_path):
    # the frames are read linear for EDI; the PNGs are encoded back, so they look as the file's frames do
    from evlatcorr.restore import to_uint8

    r = run("deblur", str(simulated), str(tmp_path / "png"), "--frame-gamma", "2.2", "--num-bins", "100",
            "--max-frames", "1", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with h5py.File(simulated) as src:
        expected = to_uint8(torch.from_numpy(src["frames/blurry"][0]))
    written = np.asarray(Image.open(tmp_path / "png" / "frame_00000_blurry.png")).astype(int)
    assert np.abs(written - expected.astype(int)).max() <= 1


@pytest.mark.parametrize(("linear_model", "expected_power"), [(True, 1.0), (False, 1 / 2.2)])
def test_with_frame_gamma_edi_reads_the_frames_linear_and_a_network_as_the_file_has_them(linear_model,
                                                                                          expected_power):
    from types import SimpleNamespace

    from evlatcorr.cli.restoration import _as_in_the_file, _Restoration, _restored_outputs

    frames = simulate("astronaut", num_frames=2, height=16, width=20, seed=0).pairs("delayed")  # as read: linear
    seen = []

    class Spy(torch.nn.Module):
        def forward(self, frames):
            seen.append((frames.blurry, frames.blurry_next))
            return SimpleNamespace(output=frames.blurry)

    run = _Restoration(SimpleNamespace(before_us=0.0), Spy(), None, 0.2, False, torch.device("cpu"), 2.2,
                       linear_model)
    plain, _ = _restored_outputs(run, frames, None)
    torch.testing.assert_close(seen[0][0], frames.blurry.clamp(0, 1) ** expected_power)
    torch.testing.assert_close(seen[0][1], frames.blurry_next.clamp(0, 1) ** expected_power)  # a pair's both frames
    blurry, written, corrected = _as_in_the_file(run, frames.blurry[0], plain, None)
    # what is written is in the file's encoding either way: the identity network writes the file's frame back
    torch.testing.assert_close(blurry, frames.blurry[0].clamp(0, 1) ** (1 / 2.2))
    torch.testing.assert_close(written[0], blurry)
    assert corrected is None


def test_deblur_refuses_bad_options_with_exit_2(simulated, tmp_path):
    cases = [
        (["--device", "foo"], "unknown device"),
        (["--model", "unet"], "invalid choice"),
        (["--num-bins", "0"], "argument --num-bins: must be a whole number >= 2, got '0'"),
        (["--num-bins", "x"], "argument --num-bins: must be a whole number >= 2, got 'x'"),
        (["--search-us", "0", "nan"], "argument --search-us: must be a finite number of us, got 'nan'"),
        (["--frame-gamma", "0"], "argument --frame-gamma: must be a finite number > 0, got '0'"),
        (["--correct", "spatial", "--curve", str(simulated)], "not a latency curve"),
    ]
    if not torch.cuda.is_available():
        cases.append((["--device", "cuda"], "CUDA is not available"))
    for extra, message in cases:
        r = run("deblur", str(simulated), str(tmp_path / "o"), *extra, cwd=tmp_path)
        assert r.returncode == 2 and message in r.stderr and "Traceback" not in r.stderr, (extra, r.stderr)
        assert not (tmp_path / "o").exists()
    (tmp_path / "full").mkdir()
    (tmp_path / "full" / "mine.png").write_bytes(b"x")
    r = run("deblur", str(simulated), str(tmp_path / "full"), cwd=tmp_path)
    assert r.returncode == 2 and "not empty" in r.stderr
    assert sorted(p.name for p in (tmp_path / "full").iterdir()) == ["mine.png"]


@pytest.mark.slow
def test_deblur_with_the_weights_of_another_model_exits_2(simulated, tmp_path):
    from evlatcorr.adapters.checkpoint import resolve_checkpoint

    efnet = resolve_checkpoint("default", "efnet")
    r = run("deblur", str(simulated), str(tmp_path / "o"), "--model", "gem", "--ckpt", str(efnet), cwd=tmp_path)
    assert r.returncode == 2 and "does not match" in r.stderr and "Traceback" not in r.stderr
    assert not (tmp_path / "o").exists()


@pytest.mark.slow
def test_sigterm_leaves_nothing_behind(simulated, tmp_path):
    out = tmp_path / "o"
    proc = subprocess.Popen([sys.executable, "-m", "evlatcorr", "deblur", str(simulated), str(out), "--model",
                             "efnet", "--correct"], cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    deadline = time.monotonic() + 120
    while not list(tmp_path.glob(".o.*.tmp/*.png")) and time.monotonic() < deadline and proc.poll() is None:
        time.sleep(0.05)  # until the first PNG is written
    assert proc.poll() is None, proc.communicate()
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 128 + signal.SIGTERM and "no output was written" in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


def test_bad_input_exit_code(tmp_path):
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"nothing")
    r = run("correct", str(junk), str(tmp_path / "out.h5"), cwd=tmp_path)
    assert r.returncode == 2 and "unknown format" in r.stderr
    assert not (tmp_path / "out.h5").exists()
    r = run("info", str(tmp_path / "missing.aedat4"), cwd=tmp_path)
    assert r.returncode == 2 and "no such file" in r.stderr
    r = run("deblur", str(junk), str(tmp_path / "o"), "--threshold", "-1", cwd=tmp_path)
    assert r.returncode == 2


@pytest.mark.parametrize("text", ["-1", "0", "inf", "nan", "abc"])
def test_a_bad_threshold_is_refused_before_any_reading(text):
    # the same rule as the training commands: a positive finite number or 'auto'
    from evlatcorr.cli.common import parse_threshold

    with pytest.raises(ValueError, match=r"^--threshold must be a positive number or 'auto', got"):
        parse_threshold(text)
    assert parse_threshold("0.3") == 0.3 and parse_threshold("auto") == "auto"


def test_correct_estimates_the_recordings_threshold_by_default(tmp_path):
    seq = simulate("astronaut", num_frames=3, height=64, width=80, threshold=0.5, latency_us=3000.0, seed=1)
    write_sequence(tmp_path / "theta05.h5", seq)
    r = run("correct", str(tmp_path / "theta05.h5"), str(tmp_path / "c.h5"), "--num-bins", "200", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "contrast threshold" in r.stderr
    rows = list(csv.DictReader(open(tmp_path / "c.csv")))
    thresholds = {float(row["threshold"]) for row in rows}
    assert len(thresholds) == 1 and abs(thresholds.pop() - 0.5) < 0.075  # one θ per recording, within 15 %


def test_corrected_pairs_start_where_the_stamped_events_do():
    # REFID reads events before the first exposure: a correction must not move events there that the stamped
    # input (read from before_us ahead of the exposure) cannot have
    from types import SimpleNamespace

    from evlatcorr.cli.restoration import _corrected_frames, _Restoration, _restored_outputs

    seq = simulate("astronaut", num_frames=2, height=32, width=40, exposure_us=4000.0, latency_us=1500.0, seed=0)
    seen = []

    class Spy(torch.nn.Module):
        def forward(self, frames):
            seen.append(frames.corrected if frames.corrected is not None else frames.events)
            return SimpleNamespace(output=torch.zeros(1))

    class ShiftBy(torch.nn.Module):
        def forward(self, frames):
            return frames.replace(corrected=frames.events.shift(torch.full((1,), 1500.0, dtype=torch.float64)))

    for before_us, is_pair in ((0.0, True), (500.0, True), (0.0, False)):
        seen.clear()
        pairs = seq.pairs("delayed", before_us=before_us)
        run = _Restoration(SimpleNamespace(before_us=before_us), Spy(), ShiftBy(), 0.2, is_pair, torch.device("cpu"))
        _restored_outputs(run, pairs, _corrected_frames(run, [pairs])[0])
        stamped, corrected = seen
        start = float(pairs.exposure_start[0]) - before_us
        assert float(stamped.t.min()) >= start
        if is_pair:
            assert float(corrected.t.min()) >= start
            assert len(corrected) < len(stamped)  # those moved before the start are left out
        else:  # single frames keep every corrected event (the deblurring networks read inside the exposure)
            assert float(corrected.t.min()) < start


def test_pair_reach_and_lead_cover_refids_window(simulated):
    from evlatcorr.adapters.refid import refid_window
    from evlatcorr.restore import pair_frames, pair_lead_us, pair_reach_us

    rec = H5Recording(simulated)
    exposure = max(e - s for s, e, _ in rec.frame_times())
    assert pair_lead_us(rec) == exposure
    rec.after_us, rec.before_us = pair_reach_us(rec), pair_lead_us(rec)
    pair = next(p for _, p in pair_frames(iter(rec)) if p is not None)
    start, end, _ = refid_window(pair, m=4, n=1)
    # the window REFID reads lies inside the events read, with room for a correction of up to half an exposure
    assert float(pair.events.t.min()) <= float(start[0]) - exposure / 2
    assert float(pair.events.t.max()) >= float(end[0])


@pytest.fixture(scope="module")
def four_frames_first_empty(tmp_path_factory):
    return _first_frame_empty(tmp_path_factory.mktemp("four"), 4, seed=4)


def test_csv_report_keeps_columns_that_rows_after_the_first_add(tmp_path):
    # a recording whose first frame has no events: its row has no fused estimate, the next rows do (the shared street
    # recording failed `deblur --correct` at its end over this, after all the work, and wrote nothing)
    from evlatcorr.cli.common import write_csv

    write_csv(tmp_path / "r.csv", [{"frame": 0, "skipped": "no events"},
                                   {"frame": 1, "skipped": "", "frame_latency_us": "15.7"}])
    assert list(csv.DictReader(open(tmp_path / "r.csv"))) == [
        {"frame": "0", "skipped": "no events", "frame_latency_us": ""},
        {"frame": "1", "skipped": "", "frame_latency_us": "15.7"}]


@pytest.mark.parametrize("command", ["deblur", "interpolate"])
def test_deblur_and_interpolate_search_several_frames_per_call_as_frame_by_frame(four_frames_first_empty, tmp_path,
                                                                                 monkeypatch, command):
    # what an accelerator does, forced on this CPU: two frames with events per call (frames 1-2 together; frame 3
    # alone at the end, or, for pairs, the last frame has no next one), frame 0 has no events; the same rows and
    # images as frame by frame, in the same order
    from PIL import Image

    from evlatcorr import cli, search_batched
    from evlatcorr.cli import restoration

    args = [command, str(four_frames_first_empty), "--model", "edi", "--correct", "constant", "--num-bins", "100",
            "--search-us", "0", "5000"] + (["--num", "1"] if command == "interpolate" else [])
    assert cli.main([*args[:2], str(tmp_path / "alone"), *args[2:]]) == 0
    calls = []
    corrected_frames = restoration._corrected_frames
    monkeypatch.setattr(restoration, "_corrected_frames",
                        lambda run, frames: calls.append(len(frames)) or corrected_frames(run, frames))
    monkeypatch.setattr(restoration, "frames_per_call", lambda device, mode: 2)
    monkeypatch.setattr(search_batched, "ON_CPU", True)
    assert cli.main([*args[:2], str(tmp_path / "batched"), *args[2:]]) == 0
    assert calls == ([2, 1] if command == "deblur" else [2])
    alone = list(csv.DictReader(open(tmp_path / "alone" / "frames.csv")))
    batched = list(csv.DictReader(open(tmp_path / "batched" / "frames.csv")))
    assert [r["frame"] for r in batched] == [r["frame"] for r in alone] == ["0", "1", "2", "3"]
    assert [r["skipped"] for r in batched] == [r["skipped"] for r in alone]
    keys = ("latency_us", "frame_latency_us") + (("pair_latency_us",) if command == "interpolate" else ())
    for key in keys:
        np.testing.assert_allclose([float(r[key] or "nan") for r in batched], [float(r[key] or "nan") for r in alone],
                                   atol=0.2, equal_nan=True)
    assert "pair_latency_us" in alone[0]  # deblur reads each frame with the next for the corrector too
    images = sorted(p.name for p in (tmp_path / "alone").glob("*.png"))
    assert images == sorted(p.name for p in (tmp_path / "batched").glob("*.png")) and images
    for name in images:
        a = np.asarray(Image.open(tmp_path / "alone" / name), dtype=np.int16)
        b = np.asarray(Image.open(tmp_path / "batched" / name), dtype=np.int16)
        assert np.abs(a - b).max() <= 1, name


def test_correct_searches_several_frames_per_call_as_frame_by_frame(four_frames_first_empty, tmp_path,
                                                                     monkeypatch):
    # what an accelerator does (frames searched in one pass, evlatcorr.search_batched), forced on this CPU: two
    # frames per call, so frames 1-2 share a call, frame 3 is corrected alone at the end and frame 0 has no events
    from evlatcorr import cli, search_batched
    from evlatcorr.cli import correct

    args = ["correct", str(four_frames_first_empty), "--num-bins", "100", "--search-us", "0", "5000"]
    assert cli.main([*args[:2], str(tmp_path / "alone.h5"), *args[2:]]) == 0
    calls = []
    corrector = correct.build_corrector

    def counting(*a, **k):
        inner = corrector(*a, **k)

        def run(frames):
            calls.append(frames.batch_size)
            return inner(frames)
        return run

    monkeypatch.setattr(correct, "frames_per_call", lambda device, mode: 2)
    monkeypatch.setattr(correct, "build_corrector", counting)
    monkeypatch.setattr(search_batched, "ON_CPU", True)
    together = search_batched.search_frames_together
    passes = []
    monkeypatch.setattr(search_batched, "search_frames_together", lambda *a, **k: passes.append(1) or together(*a, **k))
    assert cli.main([*args[:2], str(tmp_path / "batched.h5"), *args[2:]]) == 0
    assert calls == [2, 1] and passes == [1]  # frames 1-2 in one pass
    alone = list(csv.DictReader(open(tmp_path / "alone.csv")))
    batched = list(csv.DictReader(open(tmp_path / "batched.csv")))
    assert [r["skipped"] for r in batched] == ["no events", "", "", ""] == [r["skipped"] for r in alone]
    for key in ("latency_us", "frame_latency_us", "spread_us", "confidence"):  # empty (nan): the skipped frame
        np.testing.assert_allclose([float(r[key] or "nan") for r in batched], [float(r[key] or "nan") for r in alone],
                                   atol=0.2, equal_nan=True)
    assert [r["source"] for r in batched] == [r["source"] for r in alone]
    with h5py.File(tmp_path / "alone.h5") as a, h5py.File(tmp_path / "batched.h5") as b:
        np.testing.assert_allclose(b["events/t"][:], a["events/t"][:], atol=0.2)
        np.testing.assert_array_equal(b["events/x"][:], a["events/x"][:])


def test_the_search_reads_the_exposure_time_past_each_frame_even_with_a_narrower_range(simulated):
    # the learned reader reads its candidates over 0 to the exposure time; --search-us only bounds its answer
    from evlatcorr.restore import pair_reach_us, search_reach_us

    rec = H5Recording(simulated)
    exposure = max(e - s for s, e, _ in rec.frame_times())
    assert search_reach_us(rec) == search_reach_us(rec, 5000.0) == exposure
    assert search_reach_us(rec, 2 * exposure) == 2 * exposure
    assert pair_reach_us(rec, 5000.0) == pair_reach_us(rec)
    with pytest.raises(ValueError, match="search_high_us"):
        search_reach_us(rec, float("nan"))


def test_command_line_warnings_print_each_message_once_as_one_line(capsys):
    from evlatcorr.cli import common

    show = common.WarningPrinter("correct")
    for _ in range(2):  # the same message noticed in two places
        show(UserWarning("frame 3: no events"), UserWarning, "/somewhere/reader.py", 10)
        show(UserWarning("frame 3: no events"), UserWarning, "/elsewhere/tqdm.py", 99)
    show(UserWarning("frame 4: no events"), UserWarning, "/somewhere/reader.py", 10)
    assert capsys.readouterr().err.splitlines() == ["evlatcorr correct: warning: frame 3: no events",
                                                    "evlatcorr correct: warning: frame 4: no events"]


def test_frame_warnings_are_said_in_full_once_a_kind_and_the_other_frames_in_one_line(capsys):
    from evlatcorr.cli import common
    from evlatcorr.sample_warnings import FrameWarning

    show = common.WarningPrinter("correct")
    for frame in (2, 3, 4, 7):
        show(FrameWarning("empty", frame, f"frame {frame}: no events in [{frame}0, {frame}9) us", "no events"),
             FrameWarning, "/somewhere/reader.py", 10)
    show(FrameWarning("late", 5, "frame 5: events end early", "the events end early"), FrameWarning, "x.py", 1)
    show.summarise()
    assert capsys.readouterr().err.splitlines() == ["evlatcorr correct: warning: frame 2: no events in [20, 29) us",
                                                    "evlatcorr correct: warning: frame 5: events end early",
                                                    "evlatcorr correct: warning: 3 more frames (3-4, 7): no events"]
    show.summarise()  # said once
    assert capsys.readouterr().err == ""


def test_a_recording_without_events_warns_in_a_few_lines_whatever_its_length(tmp_path):
    seq = simulate("coffee", num_frames=6, height=24, width=32, latency_us=2000.0, seed=1)
    ev = seq.delayed_events
    none = torch.zeros(0, dtype=torch.long)
    seq.delayed_events = type(ev)(none, none, none.double(), none, sensor_size=ev.sensor_size)
    write_sequence(tmp_path / "still.h5", seq)
    r = run("correct", str(tmp_path / "still.h5"), str(tmp_path / "out.h5"), "--no-figure", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    warned = [line for line in r.stderr.splitlines() if "warning" in line]
    assert "evlatcorr correct: warning: 5 more frames (1-5): no events in the exposure and search window; the " \
           "events keep the previous frame's latency" in warned
    assert len(warned) <= 8, r.stderr  # one line a kind in full, one a kind for the other frames; not one a frame
    # the threshold's pass says its own when it ends, before what comes of it
    threshold_pass = ("evlatcorr correct: warning: 5 more frames (1-5): estimating the contrast threshold from the "
                      "first frames: no events at all in the segment")
    assert warned.index(threshold_pass) < next(i for i, line in enumerate(warned) if "no pair of consecutive" in line)
    assert "6 without events kept the previous latency" in r.stdout


def test_a_range_that_holds_the_estimate_at_its_edge_is_said_of_the_frames_once(simulated, tmp_path):
    # 3 ms late, searched within 0-1000 us: the first frame's warning in full, by its number, and one line for the rest
    r = run("correct", str(simulated), str(tmp_path / "out.h5"), "--search-us", "0", "1000", "--num-bins", "100",
            "--threshold", "0.2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert any(re.match(r"evlatcorr correct: warning: frame 0: the learned reader finds the latency likeliest at "
                        r"\d+ us, outside --search-us 0-1000 us", line) for line in lines), r.stderr
    assert ("evlatcorr correct: warning: 1 more frame (1): the learned reader finds the latency likelier outside "
            "--search-us 0-1000 us: the estimate is held at the range's edge") in lines
    assert "sample" not in r.stderr
    assert [row["latency_us"] for row in csv.DictReader(open(tmp_path / "out.csv"))] == ["1000.0", "1000.0"]


def test_sample_warnings_are_reworded_with_frame_numbers_and_summarised():
    from evlatcorr.cli import common
    from evlatcorr.sample_warnings import SampleWarning

    class Batch:
        def __init__(self, frame):
            self.meta = {"frame": frame}

    said = common.FrameWarnings()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for first in (3, 5, 9):
            with said.naming([Batch(first), Batch(first + 1)]):
                warnings.warn(SampleWarning("fallback", [1], "{which}: fallback 0 us", "the fallback"), stacklevel=1)
                warnings.warn("something else", stacklevel=1)
        said.summarise()
    assert [str(w.message) for w in caught] == ["frame 4: fallback 0 us", "something else", "something else",
                                                "something else", "2 more frames (6, 10): the fallback"]
    assert not any(isinstance(w.message, SampleWarning) for w in caught)  # a plain warning, for the printer
    assert common._number_ranges([7, 1, 2, 3, 9, 10]) == "1-3, 7, 9-10"


def test_correct_keeps_a_number_per_frame_and_writes_the_frames_as_they_come(simulated, tmp_path, monkeypatch):
    # a recording of thousands of frames must not keep thousands of images and latency maps until the end
    from evlatcorr import cli
    from evlatcorr.cli import correct

    kept, appended = [], []
    write, append = correct._write_corrected, correct._append_frame
    monkeypatch.setattr(correct, "_write_corrected", lambda *a: kept.extend(a[4]) or write(*a))  # its latencies
    monkeypatch.setattr(correct, "_append_frame", lambda h5, name, image: appended.append(len(kept)) or append(h5, name,
                                                                                                          image))
    out = tmp_path / "out.h5"
    assert cli.main(["correct", str(simulated), str(out), "--num-bins", "100", "--threshold", "0.2"]) == 0
    assert len(kept) == 2 and all(latency.dim() == 0 for latency in kept)
    assert appended == [0, 0]  # each frame's image written before the events
    with h5py.File(out) as f, h5py.File(simulated) as src:
        np.testing.assert_array_equal(f["frames/blurry"][:], src["frames/blurry"][:])
        np.testing.assert_allclose(f["frames/estimated_latency"][:], [float(v) for v in kept], rtol=1e-6)


def test_spatial_correct_writes_each_frames_map_and_shifts_the_events_by_it(simulated, tmp_path):
    from evlatcorr import cli

    out = tmp_path / "spatial.h5"
    assert cli.main(["correct", str(simulated), str(out), "--mode", "spatial", "--num-bins", "100",
                     "--threshold", "0.2"]) == 0
    with h5py.File(out) as f, h5py.File(simulated) as src:
        maps = f["frames/estimated_latency_map"][:]
        assert maps.shape == (2, 1, 48, 64) and maps.dtype == np.float32
        np.testing.assert_allclose(maps.mean(axis=(1, 2, 3)), f["frames/estimated_latency"][:], rtol=1e-5)
        starts = f["frames/exposure_start"][:]
        x, y, t = src["events/x"][:].astype(np.int64), src["events/y"][:].astype(np.int64), src["events/t"][:]
        frame = np.clip(np.searchsorted(starts, t, side="right") - 1, 0, len(starts) - 1)
        np.testing.assert_allclose(f["events/t"][:], np.sort(t - maps[frame, 0, y, x]), rtol=0, atol=1e-6)


def test_spatial_mode_reads_pairs_unless_told_not_to(simulated, tmp_path):
    # without --curve, spatial mode is constant mode plus one slope over intensity for the recording, fitted to its
    # first pairs' agreement: none on this constant-latency recording, so correct and deblur write constant mode's
    # latencies (correct as maps); --no-pairs: the sharpness fit on every frame
    base = ("--num-bins", "100", "--threshold", "0.2")
    rows = {}
    for name, args in (("constant", ("correct", "c.h5")), ("spatial", ("correct", "c.h5", "--mode", "spatial")),
                       ("spatial alone", ("correct", "c.h5", "--mode", "spatial", "--no-pairs")),
                       ("deblur constant", ("deblur", "d", "--correct", "constant")),
                       ("deblur", ("deblur", "d", "--correct", "spatial")),
                       ("deblur alone", ("deblur", "d", "--correct", "spatial", "--no-pairs"))):
        folder = tmp_path / name.replace(" ", "_")
        r = run(args[0], str(simulated), str(folder / args[1]), *args[2:], *base, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
        assert ("latency over intensity: no slope" in r.stderr) == (name in ("spatial", "deblur")), r.stderr
        report = folder / ("c.csv" if args[0] == "correct" else "d/frames.csv")
        rows[name] = list(csv.DictReader(open(report)))
    for spatial, constant in (("spatial", "constant"), ("deblur", "deblur constant")):
        assert [r["latency_us"] for r in rows[spatial]] == [r["latency_us"] for r in rows[constant]]
        assert all(r["latency_min_us"] == r["latency_max_us"] == r["latency_us"] for r in rows[spatial])
    with h5py.File(tmp_path / "spatial" / "c.h5") as f:
        maps = f["frames/estimated_latency_map"][:]
        assert maps.shape == (2, 1, 48, 64) and f.attrs["corrected_mode"] == "spatial"
        np.testing.assert_allclose(maps.mean(axis=(1, 2, 3)), [float(r["latency_us"]) for r in rows["constant"]],
                                   atol=0.06)
    for alone in ("spatial alone", "deblur alone"):
        assert [r["source"] for r in rows[alone]] == ["fit", "fit"]


@pytest.mark.slow
def test_spatial_correct_finds_dim_pixels_later(tmp_path):
    # a recording whose dim pixels are later (0.5 ms at white to 8 ms at black): one slope for the recording, and each
    # frame's map the fused constant latency plus its departure
    from evlatcorr.pair_curve import fit_pair_curve

    seq = simulate("astronaut", num_frames=3, height=48, width=64, latency="intensity_delay",
                   latency_range_us=(500.0, 8000.0), max_speed_px_per_ms=1.0, seed=0)
    write_sequence(tmp_path / "delay.h5", seq)
    for name, extra in (("constant", ()), ("spatial", ("--mode", "spatial"))):
        r = run("correct", str(tmp_path / "delay.h5"), str(tmp_path / f"{name}.h5"), "--num-bins", "100",
                "--threshold", "0.2", *extra, cwd=tmp_path)
        assert r.returncode == 0, r.stderr
    assert "latency over intensity: " in r.stderr and "us later at black than at white" in r.stderr
    fit = fit_pair_curve(seq.pairs(), 0.2)
    constant = [float(r["latency_us"]) for r in csv.DictReader(open(tmp_path / "constant.csv"))]
    with h5py.File(tmp_path / "spatial.h5") as f:
        maps = torch.from_numpy(f["frames/estimated_latency_map"][:]).double()
    expected = (torch.tensor(constant, dtype=torch.float64).view(-1, 1, 1, 1)
                + fit.departure(seq.frames().blurry).double()).clamp(0.0, 20000.0)
    torch.testing.assert_close(maps, expected, atol=0.06, rtol=0.0)
    truth = seq.frames().meta["true_latency"].double()
    flat = torch.tensor(constant, dtype=torch.float64).view(-1, 1, 1, 1)
    assert float((maps - truth).abs().mean()) < 0.7 * float((flat - truth).abs().mean())
    # deblur adds the same slope to its stream of constant latencies: each frame's map spans a range
    r = run("deblur", str(tmp_path / "delay.h5"), str(tmp_path / "d"), "--correct", "spatial", "--num-bins", "100",
            "--threshold", "0.2", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    deblurred = list(csv.DictReader(open(tmp_path / "d" / "frames.csv")))
    spans = [float(d["latency_max_us"]) - float(d["latency_min_us"]) for d in deblurred]
    assert len(spans) == 3 and min(spans) > 4000.0, spans


def test_a_cut_off_recording_is_corrected_and_its_warnings_said_once(tmp_path):
    # the cradle recording cut inside a packet: read up to it; the file's warning is said once, and those the contrast
    # threshold's estimate raises about its frames say they come from it
    from tests.conftest import shared_data_dir

    cradle = shared_data_dir() / "davis346" / "cradle_lowlight.aedat4"
    if not cradle.is_file():
        pytest.skip("shared DAVIS recordings absent")
    cut = tmp_path / "cut.aedat4"
    cut.write_bytes(cradle.read_bytes()[:2_000_000])
    r = run("correct", str(cut), str(tmp_path / "out.h5"), "--num-bins", "100", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    lines = r.stderr.splitlines()
    assert sum("the file ends inside the packet after packet" in line for line in lines) == 1, r.stderr
    assert any(line.startswith("evlatcorr correct: warning: estimating the contrast threshold from the first frames: "
                               f"{cut}: frame ") for line in lines), r.stderr
    assert len(list(csv.DictReader(open(tmp_path / "out.csv")))) == 7


@pytest.fixture(scope="module")
def event_utils_recording(simulated, tmp_path_factory):
    """The simulated recording in event_utils layout (µs, its frames as uint8 images)."""
    from evlatcorr.io import write_event_utils

    rec = H5Recording(simulated)
    path = tmp_path_factory.mktemp("eu") / "eu.h5"
    write_event_utils(path, rec.events_between(-1e18, 1e18), like=rec, time_unit="us")
    return path


@pytest.mark.parametrize("mode", ["constant", "spatial"])
def test_correct_an_event_utils_recording_streams_its_events_and_keeps_numbers(event_utils_recording, tmp_path,
                                                                               monkeypatch, mode):
    # the corrected events go to an event_utils file chunk by chunk, and a spatial map per frame goes to a scratch
    # file, not to memory: a long recording keeps one number per frame
    import evlatcorr.io as io
    from evlatcorr import cli
    from evlatcorr.cli import correct
    from evlatcorr.events import Events
    from evlatcorr.io import EventUtilsRecording

    kept, given = [], []
    write, write_event_utils = correct._write_corrected, io.write_event_utils
    monkeypatch.setattr(correct, "_write_corrected", lambda *a: kept.extend(a[4]) or write(*a))
    monkeypatch.setattr(io, "write_event_utils", lambda path, events, **k: given.append(events)
                        or write_event_utils(path, events, **k))
    scratch_dirs = []
    temporary_directory = correct.tempfile.TemporaryDirectory
    monkeypatch.setattr(correct.tempfile, "TemporaryDirectory", lambda **k: scratch_dirs.append(k.get("dir"))
                        or temporary_directory(**k))
    out = tmp_path / "results" / "corrected.h5"
    # (spatial: the sharpness fit, whose maps vary; with pairs this recording's maps would be one latency each)
    assert cli.main(["correct", str(event_utils_recording), str(out), "--mode", mode, "--num-bins", "100",
                     "--threshold", "0.2", *(["--no-pairs"] if mode == "spatial" else [])]) == 0
    assert len(kept) == 2 and all(latency.dim() == 0 for latency in kept)
    # the scratch maps lie beside the output (not in a temp folder that may be in memory), and are gone after
    assert scratch_dirs == ([out.parent] if mode == "spatial" else [])
    assert sorted(p.name for p in out.parent.iterdir()) == ["corrected.csv", "corrected.h5", "corrected.png"]
    assert len(given) == 1 and not isinstance(given[0], (Events, np.ndarray, list))  # chunks as they come
    source, corrected = EventUtilsRecording(event_utils_recording), EventUtilsRecording(out)
    before, after = source.events_between(-1e18, 1e18), corrected.events_between(-1e18, 1e18)
    assert len(after) == len(before) and corrected.num_frames == source.num_frames == 2
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    starts = np.array([float(r["exposure_start_us"]) for r in rows])
    frame = np.clip(np.searchsorted(starts, before.t.numpy(), side="right") - 1, 0, 1)
    if mode == "constant":  # every event of a frame moved by the frame's (fused) latency
        latency = np.array([float(r["latency_us"]) for r in rows])  # the report rounds it to 0.1 us
        np.testing.assert_allclose(np.sort(after.t.numpy()), np.sort(before.t.numpy() - latency[frame]), atol=0.06)
    else:  # by its pixel's latency: within the frame's map's range, and not all alike
        low, high = (np.array([float(r[k]) for r in rows]) for k in ("latency_min_us", "latency_max_us"))
        assert float(low.min()) < float(high.max())
        lo = np.sort(before.t.numpy() - high[frame])
        hi = np.sort(before.t.numpy() - low[frame])
        moved = np.sort(after.t.numpy())
        # (the report rounds the map's range to 0.1 us: a frame whose map is one latency, read with its pair, sits
        # on the rounded bound)
        assert bool((moved >= lo[0] - 0.06).all() and (moved <= hi[-1] + 0.06).all())
        assert abs(float(np.mean(before.t.numpy() - after.t.numpy())) - float(np.mean(kept))) < float(high.max())


def test_a_black_frame_neither_gets_a_latency_of_its_own_nor_sets_the_threshold(tmp_path):
    # the recording's θ used to come from the pair holding the black frame too: 1.497 for a true 0.2, and hot pixels
    # named on every frame
    seq = simulate("astronaut", num_frames=4, height=48, width=64, exposure_us=10_000.0, frame_interval_us=12_000.0,
                   latency_us=2500.0, seed=1)
    seq.blurry[1] = 0.0
    write_sequence(tmp_path / "black.h5", seq)
    r = run("correct", str(tmp_path / "black.h5"), str(tmp_path / "out.h5"), "--num-bins", "100", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    theta = float(re.search(r"contrast threshold: ([0-9.]+)", r.stderr).group(1))
    assert 0.15 < theta < 0.3
    assert "frame 1: black or saturated in nearly every pixel" in r.stderr and "hot pixels" not in r.stderr
    # its own latency is the fallback, the one written its neighbours' fused: the warning says both
    assert "the fallback 0 us; the latency written is fused with the frames either side (--fuse-frames" in r.stderr
    rows = list(csv.DictReader(open(tmp_path / "out.csv")))
    assert [row["source"] for row in rows] == ["reader", "clipped", "reader", "reader"]


def test_correct_draws_the_latencies_where_told_or_not_at_all(simulated, tmp_path):
    figure = tmp_path / "plots" / "latency.png"
    r = run("correct", str(simulated), str(tmp_path / "a.h5"), "--num-bins", "100", "--figure", str(figure),
            cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert Image.open(figure).format == "PNG" and not (tmp_path / "a.png").exists()
    r = run("correct", str(simulated), str(tmp_path / "b.h5"), "--num-bins", "100", "--no-figure", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert (tmp_path / "b.csv").exists() and not (tmp_path / "b.png").exists()
    r = run("correct", str(simulated), str(tmp_path / "c.h5"), "--figure", str(tmp_path / "c.csv"), cwd=tmp_path)
    assert r.returncode == 2 and "two outputs have the same name" in r.stderr  # the figure would replace the report
    assert not (tmp_path / "c.h5").exists()


def test_a_figure_that_cannot_be_written_costs_a_warning_not_the_corrected_recording(simulated, tmp_path,
                                                                                      monkeypatch, capsys):
    from evlatcorr import cli
    from evlatcorr.cli import latency_figure

    def failing(rows, path, title=""):
        raise OSError("No space left on device")

    monkeypatch.setattr(latency_figure, "write_latency_figure", failing)
    out = tmp_path / "out.h5"
    assert cli.main(["correct", str(simulated), str(out), "--num-bins", "100", "--threshold", "0.2"]) == 0
    printed = capsys.readouterr()
    assert "warning: the latency figure" in printed.err and "No space left on device" in printed.err
    assert out.exists() and out.with_suffix(".csv").exists() and not out.with_suffix(".png").exists()
    assert "out.png" not in printed.out
