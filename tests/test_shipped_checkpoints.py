"""The weights shipped under checkpoints/ load by name and restore an unseen simulated scene on the CPU."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pytest
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio

from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter
from evlatcorr.adapters.checkpoint import file_sha256
from evlatcorr.curve_reader import WEIGHTS_NAME
from evlatcorr.simulate import PHOTOGRAPHS_TEST, simulate
from evlatcorr.tile_reader import TILE_WEIGHTS_NAME

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = {
    "efnet": lambda: EFNetAdapter(checkpoint="default"),
    "gem": lambda: GEMAdapter(checkpoint="default"),
    "refid-4-1": lambda: REFIDAdapter(checkpoint="default", m=4, n=1),
}


def _psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    return float(peak_signal_noise_ratio(image.clamp(0, 1), target, data_range=1.0))


def test_checkpoint_cards_list_their_files_and_stay_under_the_size_limits():
    # the curve and tile readers' provenance (curve-reader.json, tile-reader.json) is not a network card: see
    # test_curve_reader.py and test_tiles.py
    cards = [p for p in sorted((ROOT / "checkpoints").glob("*.json"))
             if not p.name.endswith(".index.json") and p.stem not in (WEIGHTS_NAME, TILE_WEIGHTS_NAME)]
    assert {c.stem for c in cards} == set(SHIPPED)
    total = 0
    for card in cards:
        meta = json.loads(card.read_text())
        assert meta["steps"] > 0 and meta["val_psnr"] > meta["val_blurry_psnr"]
        assert not set(meta["data"]["photographs"]) & set(PHOTOGRAPHS_TEST)  # never trained on test scenes
        for name in meta["files"]:
            size = (ROOT / "checkpoints" / name).stat().st_size
            assert size <= 15_000_000
            total += size
    assert total < 100_000_000


def test_checkpoint_cards_list_the_sha256_of_every_weight_file():
    for stem in SHIPPED:
        meta = json.loads((ROOT / "checkpoints" / f"{stem}.json").read_text())
        weights = [name for name in meta["files"] if name.endswith(".safetensors")]
        assert weights and sorted(meta["sha256"]) == sorted(weights)
        for name in weights:
            assert meta["sha256"][name] == file_sha256(ROOT / "checkpoints" / name), name


def test_modified_copy_of_shipped_weights_is_refused(tmp_path):
    # GEM segfaulted on the NaN weights a corrupted file gave: one flipped bit is enough to be refused
    for name in ("gem.safetensors", "gem.json"):
        shutil.copy(ROOT / "checkpoints" / name, tmp_path / name)
    GEMAdapter(checkpoint=tmp_path / "gem.safetensors")  # the intact copy loads
    raw = bytearray((tmp_path / "gem.safetensors").read_bytes())
    raw[len(raw) // 2] ^= 0x10
    (tmp_path / "gem.safetensors").write_bytes(bytes(raw))
    with pytest.raises(ValueError, match=f"{re.escape(str(tmp_path / 'gem.safetensors'))} is corrupt or modified"):
        GEMAdapter(checkpoint=tmp_path / "gem.safetensors")


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_shipped_weights_beat_the_blurry_input(name):
    torch.manual_seed(0)
    adapter = SHIPPED[name]().eval()
    seq = simulate("camera", num_frames=2, height=96, width=128, exposure_us=20000.0, frame_interval_us=25000.0,
                   latency="none", seed=3)
    with torch.no_grad():
        if name.startswith("refid"):
            pairs = seq.pairs("ideal", before_us=20000.0)  # the events before the exposure, as trained
            out = adapter(pairs)
            times = out.meta["output_times"]
            index = int((times[0] - pairs.target_times[0, 0]).abs().argmin())
            restored, target = out.output[:, index], pairs.target_frames[:, 0]
        else:
            frames = seq.frames("ideal")
            restored, target = adapter(frames).output, frames.sharp
    blurry = _psnr(seq.blurry[:1], target)
    assert _psnr(restored, target) > blurry + 1.0
