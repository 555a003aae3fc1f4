from __future__ import annotations

import csv
import subprocess
import sys
from pathlib import Path

import h5py
import numpy as np
import pytest

from evlatcorr.io import H5Recording


def run(*args: str, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "evlatcorr", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=300)


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


def test_info(simulated):
    r = run("info", str(simulated), cwd=simulated.parent)
    assert r.returncode == 0
    assert "evlatcorr-h5" in r.stdout and "(48, 64)" in r.stdout and "frames" in r.stdout


def test_correct_writes_events_and_report(simulated):
    out = simulated.parent / "corrected.h5"
    r = run("correct", str(simulated), str(out), "--num-bins", "100", cwd=simulated.parent)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert [int(row["frame"]) for row in rows] == [0, 1]
    latencies = [float(row["latency_us"]) for row in rows]
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


def test_deblur_writes_pngs(simulated, tmp_path):
    r = run("deblur", str(simulated), str(tmp_path / "png"), "--num-bins", "100", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert sorted(p.name for p in (tmp_path / "png").iterdir()) == [
        "frame_00000_blurry.png", "frame_00000_edi.png", "frame_00001_blurry.png", "frame_00001_edi.png"]


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
