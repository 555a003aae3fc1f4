from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest
import torch

from tests.conftest import shared_data_dir

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_quick_benchmark_end_to_end(tmp_path):
    backbone = shared_data_dir() / "lpips" / "alexnet_features.pth"
    cmd = [sys.executable, str(ROOT / "benchmarks" / "run.py"), "--quick", "--out", str(tmp_path / "out")]
    if backbone.is_file():
        cmd += ["--lpips-backbone", str(backbone)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path,
                       env={"EVLATCORR_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"})
    assert r.returncode == 0, r.stderr[-3000:]
    out = tmp_path / "out"
    results = json.loads((out / "results.json").read_text())
    rows = {(row["method"], row["input"]): row for row in results["table"]}
    methods = ["EDI deblurring", "EFNet", "GEM", "EDI interpolation", "REFID"]
    inputs = ["GT input", "W/o corr.", "W/ corr. const.", "W/ corr. spatial"]
    assert [row["method"] for row in results["table"]] == [m for m in methods for _ in inputs]
    assert set(rows) == {(m, i) for m in methods for i in inputs}
    assert rows[("EDI deblurring", "GT input")]["psnr"] > rows[("EDI deblurring", "W/o corr.")]["psnr"]
    for method in ("EFNet", "GEM", "REFID"):  # the shipped checkpoints are found and run
        assert all(rows[(method, i)]["psnr"] == rows[(method, i)]["psnr"] for i in inputs), results["failures"]
    assert set(results["latency_error"]) == {"W/ corr. const.", "W/ corr. spatial"}
    md = (out / "results.md").read_text()
    assert "Diff (%) const." in md and "| PSNR ↑ | SSIM ↑ | LPIPS ↓ |" in md
    for name in ("results.csv", "etf_vs_latency.png", "restored.png", "latency_maps.png"):
        assert (out / name).is_file()
    # the cache is reused: a second run simulates nothing
    r2 = subprocess.run(cmd + ["--methods", "edi"], capture_output=True, text=True, timeout=600, cwd=tmp_path,
                        env={"EVLATCORR_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"})
    assert r2.returncode == 0 and "simulating" not in r2.stdout


@pytest.mark.slow
def test_ddp_on_two_cpu_processes_gives_the_same_table(tmp_path):
    # 3 scenes on 2 processes: no scene may be counted twice (a DistributedSampler would pad)
    args = [sys.executable, str(ROOT / "benchmarks" / "run.py"), "--size", "64", "80", "--num-bins", "100",
            "--spatial-steps", "5", "--scenes", "3", "--methods", "edi,edi-interp"]
    env = {"EVLATCORR_CACHE": str(tmp_path / "cache"), "PATH": "/usr/bin:/bin"}
    tables = []
    for extra in ([], ["--devices", "2", "--strategy", "ddp"]):
        out = tmp_path / f"out{len(tables)}"
        for _attempt in range(2):
            r = subprocess.run(args + extra + ["--out", str(out)], capture_output=True, text=True, timeout=600,
                               cwd=tmp_path, env=env)
            # gloo occasionally aborts a rank at start-up or teardown ("terminate called without an active
            # exception", killed by a signal, seen 1 run in 4 on 2 cores): run once more; any error exit fails
            if r.returncode >= 0:
                break
        assert r.returncode == 0, r.stderr[-3000:]
        tables.append(json.loads((out / "results.json").read_text())["table"])
    assert [(r["method"], r["input"]) for r in tables[0]] == [(r["method"], r["input"]) for r in tables[1]]
    for single, ddp in zip(*tables):  # the same up to the order of floating-point sums
        assert single["psnr"] == pytest.approx(ddp["psnr"], rel=1e-5)
        assert single["ssim"] == pytest.approx(ddp["ssim"], rel=1e-5)


@pytest.mark.parametrize("argv, message", [
    (["--latency-us", "-5"], "--latency-us must be between 0 and 1000000 us, got -5.0"),
    (["--device", "tpu"], "--device must be cpu or cuda, got 'tpu'"),
    (["--data", "/no/such/recording"], "--data /no/such/recording: no such file or directory"),
    (["--frame-gamma", "0"], "argument --frame-gamma: must be a finite number > 0, got '0'"),
    (["--frame-gamma", "2.2"], "--frame-gamma is for --data recordings whose frames are encoded for display"),
    (["--scenes", "9"], "--scenes must be between 1 and 8"),  # given beside --quick, it wins
    (["--num-bins", "1"], "--num-bins >= 2"),
    (["--ckpt", "efnet"], "--ckpt takes NAME=PATH"),
    (["--ckpt", "efnet=/no/such.pth"], "--ckpt efnet=/no/such.pth: no such file"),
    (["--lpips-backbone", "/no/such.pth"], "--lpips-backbone /no/such.pth: no such file"),
] + ([] if torch.cuda.is_available() else
     [(["--device", "cuda"], "--device cuda: CUDA is not available on this machine")]))
def test_bad_options_are_refused_before_any_scene(argv, message, capsys, tmp_path):
    # argparse's exit 2 and a line saying what is wrong, before a scene is simulated or read (no traceback)
    from evlatcorr.benchmark.table1 import main

    with pytest.raises(SystemExit) as exit_:
        main([*argv, "--quick", "--out", str(tmp_path / "out")])
    assert exit_.value.code == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_options_given_beside_quick_win_and_an_unwritable_out_is_refused(tmp_path, capsys):
    from evlatcorr.benchmark.table1 import main, parse_args

    args = parse_args(["--quick", "--num-bins", "40", "--out", str(tmp_path / "a")])
    assert (args.scenes, tuple(args.size), args.num_bins, args.spatial_steps) == (2, (64, 80), 40, 10)
    args = parse_args(["--out", str(tmp_path / "b")])
    assert (args.scenes, tuple(args.size), args.num_bins, args.spatial_steps) == (3, (256, 336), 500, 30)
    (tmp_path / "file").write_text("")
    with pytest.raises(SystemExit) as exit_:
        main(["--quick", "--out", str(tmp_path / "file" / "out")])
    assert exit_.value.code == 2 and "--out: " in capsys.readouterr().err
