"""A wheel built from the repository ships the weights: after a normal install ``checkpoint="default"`` loads them.

The wheel is built offline (``--no-index --no-build-isolation``) from a copy of the sources, so no ``build/`` or
``*.egg-info`` is left in the checkout, then installed with ``--target`` into a temporary folder and imported by a
child process run outside the repository (torch and the other dependencies still come from this environment).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
# what the build reads (pyproject.toml's packages and package-dir); everything else stays behind
SOURCES = ("pyproject.toml", "README.md", "LICENSE", "MANIFEST.in", "setup.py", "setup.cfg",
           "evlatcorr", "adapters", "checkpoints")
SHIPPED = ("efnet", "gem", "refid-4-1")

CHILD = r"""
import json, sys
import torch
import evlatcorr
from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter
from evlatcorr.adapters import checkpoint as ckpt

resolved = {}
resolve = ckpt.resolve_checkpoint


def recording_resolve(name_or_path, model_name):  # the adapters import it from the module when built
    path = resolve(name_or_path, model_name)
    resolved[model_name] = path
    return path


ckpt.resolve_checkpoint = recording_resolve
adapters = {"efnet": EFNetAdapter(checkpoint="default"), "gem": GEMAdapter(checkpoint="default"),
            "refid-4-1": REFIDAdapter(checkpoint="default", m=4, n=1)}
same = {}
for name, adapter in adapters.items():
    stored = ckpt.load_state_dict_file(resolved[name])
    own = adapter.net.state_dict()
    same[name] = sorted(stored) == sorted(own) and all(
        torch.equal(own[k], v.to(own[k].dtype)) for k, v in stored.items())
from evlatcorr.tile_reader import load_tile_reader

tile_reader = len(load_tile_reader().members)  # found in the installed package, not the repository
print(json.dumps({"evlatcorr": evlatcorr.__file__, "checkpoint_module": ckpt.__file__, "tile_reader": tile_reader,
                  "dirs": [str(d) for d in ckpt.checkpoint_dirs()],
                  "resolved": {k: str(v) for k, v in resolved.items()}, "same": same}))
"""


def _run(cmd: list[str], **kwargs: object) -> subprocess.CompletedProcess[str]:
    result = subprocess.run(cmd, capture_output=True, text=True, timeout=300, **kwargs)  # type: ignore[call-overload]
    assert result.returncode == 0, f"{' '.join(cmd)} failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    return result


def _under(path: str | Path, folder: Path) -> bool:
    return Path(path).resolve().is_relative_to(folder.resolve())


@pytest.mark.slow
def test_installed_wheel_loads_the_default_checkpoints(tmp_path):
    pytest.importorskip("setuptools", minversion="77")  # the build backend, used without isolation
    src = tmp_path / "src"
    src.mkdir()
    for name in SOURCES:
        if (ROOT / name).is_dir():
            shutil.copytree(ROOT / name, src / name, symlinks=True,
                            ignore=shutil.ignore_patterns("__pycache__", "*.egg-info"))
        elif (ROOT / name).is_file():
            shutil.copy2(ROOT / name, src / name)
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check"]
    _run([*pip, "wheel", str(src), "--no-deps", "--no-build-isolation", "--no-index", "-w", str(tmp_path / "dist")])
    wheels = list((tmp_path / "dist").glob("evlatcorr-*.whl"))
    assert len(wheels) == 1, wheels

    # the wheel holds every file the cards list, the cards and the README, as package data
    names = set(zipfile.ZipFile(wheels[0]).namelist())
    for stem in SHIPPED:
        card = json.loads((ROOT / "checkpoints" / f"{stem}.json").read_text())
        for f in [*card["files"], f"{stem}.json"]:
            assert f"evlatcorr/checkpoints/{f}" in names, f"{f} is not in the wheel"
    assert "evlatcorr/checkpoints/README.md" in names
    assert "evlatcorr/adapters/checkpoint.py" in names
    # and the learned readers' weights the default search reads
    assert {"evlatcorr/checkpoints/curve-reader.safetensors", "evlatcorr/checkpoints/tile-reader.safetensors"} <= names

    site = tmp_path / "site"
    _run([*pip, "install", "--no-deps", "--no-index", "--target", str(site), str(wheels[0])])
    env = {k: v for k, v in os.environ.items() if k not in ("EVLATCORR_CHECKPOINT_DIR", "PYTHONPATH")}
    env["PYTHONPATH"] = str(site)
    run_dir = tmp_path / "elsewhere"  # outside the repository: its checkpoints/ must not be found
    run_dir.mkdir()
    out = json.loads(_run([sys.executable, "-c", CHILD], cwd=run_dir, env=env).stdout.strip().splitlines()[-1])

    assert _under(out["evlatcorr"], site), out["evlatcorr"]  # the installed copy, not the checkout
    assert _under(out["checkpoint_module"], site), out["checkpoint_module"]
    assert all(_under(d, site) for d in out["dirs"]), out["dirs"]
    assert sorted(out["resolved"]) == sorted(SHIPPED)
    for name, path in out["resolved"].items():
        assert _under(path, site / "evlatcorr" / "checkpoints"), (name, path)
        assert Path(path).name.startswith(name)
    assert out["same"] == dict.fromkeys(SHIPPED, True)  # the adapters hold the installed weights
    assert out["tile_reader"] == 5  # the default search's tile reader, from the installed package data

    # the console script pip wrote runs the command line (evlatcorr.__main__:main)
    script = site / "bin" / "evlatcorr"
    assert script.is_file(), sorted(p.name for p in (site / "bin").iterdir()) if (site / "bin").is_dir() else site
    usage = _run([sys.executable, str(script), "--help"], cwd=run_dir, env=env).stdout
    assert usage.startswith("usage: evlatcorr") and "deblur" in usage
