from __future__ import annotations

import hashlib
import json
import re
import shutil
import warnings
from pathlib import Path

import pytest
import torch
from torch import nn

from evlatcorr.adapters import checkpoint as ckpt
from evlatcorr.adapters.checkpoint import (
    card_sha256,
    file_sha256,
    load_state_dict_file,
    load_weights,
    resolve_checkpoint,
    save_weights,
)


class Hyper:
    """A non-tensor object in a checkpoint (makes ``weights_only=True`` refuse it)."""

    def __init__(self, lr: float) -> None:
        self.lr = lr


class Net(nn.Module):
    def __init__(self, width: int = 8) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(3, width, 3), nn.BatchNorm2d(width), nn.Conv2d(width, 3, 1))
        self.head = nn.Linear(4, 2)


class Wide(nn.Module):
    """Four 256x256 layers: 128 KiB per weight in fp16, to force shards."""

    def __init__(self) -> None:
        super().__init__()
        self.layers = nn.ModuleList(nn.Linear(256, 256) for _ in range(4))


def _seeded(module: nn.Module, seed: int = 0) -> nn.Module:
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for v in module.state_dict().values():
            if v.is_floating_point():
                v.copy_(torch.randn(v.shape, generator=g))
    return module


def _assert_same(a: nn.Module, b: nn.Module, dtype: torch.dtype | None = None) -> None:
    sa, sb = a.state_dict(), b.state_dict()
    assert list(sa) == list(sb)
    for k in sa:
        want = sa[k].to(dtype).to(sa[k].dtype) if dtype is not None and sa[k].is_floating_point() else sa[k]
        torch.testing.assert_close(sb[k], want, rtol=0, atol=0, msg=k)


# smoke / round trips -----------------------------------------------------------------------------
def test_safetensors_round_trip_single_file_fp16(tmp_path):
    src = _seeded(Net())
    files = save_weights(src, tmp_path / "net.safetensors")
    assert files == [tmp_path / "net.safetensors"]
    dst = Net()
    load_weights(dst, tmp_path / "net.safetensors")
    assert dst.head.weight.dtype == torch.float32  # fp16 on disk, cast to the module's dtype
    _assert_same(src, dst, torch.float16)
    assert int(dst.body[1].num_batches_tracked) == 0  # integer buffers are not cast
    raw = load_state_dict_file(tmp_path / "net.safetensors")
    assert raw["head.weight"].dtype == torch.float16


def test_safetensors_keep_dtype(tmp_path):
    src = _seeded(Net())
    save_weights(src, tmp_path / "net.safetensors", dtype=None)
    dst = Net()
    load_weights(dst, str(tmp_path / "net.safetensors"))
    _assert_same(src, dst)


def test_sharded_round_trip(tmp_path):
    src = _seeded(Wide())
    limit_mb = 0.3  # two 131 KB weights per shard at most
    files = save_weights(src, tmp_path / "wide.safetensors", max_shard_mb=limit_mb)
    shards = [f for f in files if f.suffix == ".safetensors"]
    assert [f.name for f in shards] == [f"wide-0000{i}-of-00002.safetensors" for i in (1, 2)]
    assert files[-1].name == "wide.safetensors.index.json"
    assert not (tmp_path / "wide.safetensors").exists()
    assert all(f.stat().st_size <= limit_mb * 1e6 for f in shards)
    index = json.loads(files[-1].read_text())
    assert set(index["weight_map"]) == set(src.state_dict())
    # the base name, the index and any one shard all load the whole set
    for path in (tmp_path / "wide.safetensors", files[-1], shards[1]):
        dst = Wide()
        load_weights(dst, path)
        _assert_same(src, dst, torch.float16)


def test_resave_removes_stale_shards(tmp_path):
    src = _seeded(Wide())
    save_weights(src, tmp_path / "wide.safetensors", max_shard_mb=0.15)
    assert len(list(tmp_path.glob("wide-*-of-*.safetensors"))) == 4
    save_weights(src, tmp_path / "wide.safetensors", max_shard_mb=15)
    assert sorted(f.name for f in tmp_path.iterdir()) == ["wide.safetensors"]
    load_weights(Wide(), tmp_path / "wide.safetensors")


def test_shard_set_without_index(tmp_path):
    src = _seeded(Wide())
    save_weights(src, tmp_path / "wide.safetensors", max_shard_mb=0.15)
    (tmp_path / "wide.safetensors.index.json").unlink()
    dst = Wide()
    load_weights(dst, tmp_path / "wide.safetensors")
    _assert_same(src, dst, torch.float16)
    (tmp_path / "wide-00003-of-00004.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match=r"shards \[3\] are missing"):
        load_weights(Wide(), tmp_path / "wide.safetensors")


# official formats ----------------------------------------------------------------------------------
@pytest.mark.parametrize("layout", ["basicsr", "basicsr_ema", "lightning", "plain", "dataparallel", "module"])
def test_torch_formats(tmp_path, layout):
    src = _seeded(Net())
    sd = src.state_dict()
    payload = {
        "basicsr": {"params": sd},
        "basicsr_ema": {"params_ema": sd},
        # a Lightning checkpoint: prefixed keys, other entries, and weights of another submodule (a loss net)
        "lightning": {"epoch": 3, "global_step": 10, "state_dict": {
            **{f"model.{k}": v for k, v in sd.items()}, "loss_fn.vgg.weight": torch.zeros(2)}},
        "plain": sd,
        "dataparallel": {f"module.{k}": v for k, v in sd.items()},
        "module": src,
    }[layout]
    path = tmp_path / ("net.ckpt" if layout == "lightning" else "net.pth")
    if layout == "module":
        with pytest.warns(UserWarning, match="weights_only=False"):
            torch.save(payload, path)
            load_weights(dst := Net(), path)
    else:
        torch.save(payload, path)
        load_weights(dst := Net(), path)
    _assert_same(src, dst)


def test_basicsr_prefers_params_over_ema(tmp_path):
    a, b = _seeded(Net(), 1), _seeded(Net(), 2)
    torch.save({"params": a.state_dict(), "params_ema": b.state_dict()}, tmp_path / "net.pth")
    load_weights(dst := Net(), tmp_path / "net.pth")
    _assert_same(a, dst)
    load_weights(dst, tmp_path / "net.pth", key="params_ema")
    _assert_same(b, dst)


def test_fp16_checkpoint_loads_into_fp32_and_fp64(tmp_path):
    src = _seeded(Net())
    torch.save({"params": {k: v.half() for k, v in src.state_dict().items()}}, tmp_path / "half.pth")
    dst = Net().double()
    load_weights(dst, tmp_path / "half.pth")
    assert dst.head.weight.dtype == torch.float64
    torch.testing.assert_close(dst.head.weight, src.head.weight.half().double(), rtol=0, atol=0)


def test_bare_network_into_wrapper(tmp_path):
    class Wrapper(nn.Module):
        def __init__(self) -> None:
            super().__init__()
            self.net = Net()

    src = _seeded(Net())
    torch.save(src.state_dict(), tmp_path / "net.pth")
    load_weights(dst := Wrapper(), tmp_path / "net.pth")
    _assert_same(src, dst.net)


def test_non_tensor_payload_falls_back_with_warning(tmp_path):
    src = _seeded(Net())
    torch.save({"state_dict": {f"net.{k}": v for k, v in src.state_dict().items()}, "hparams": Hyper(0.1)},
               tmp_path / "net.ckpt")
    with pytest.warns(UserWarning, match="only load checkpoints you trust"):
        load_weights(dst := Net(), tmp_path / "net.ckpt")
    _assert_same(src, dst)


# exceptions ------------------------------------------------------------------------------------------
def test_missing_and_unexpected_keys_are_listed(tmp_path):
    sd = dict(_seeded(Net()).state_dict())
    sd.pop("head.bias")
    sd["extra.weight"] = torch.zeros(3)
    torch.save({"params": sd}, tmp_path / "bad.pth")
    with pytest.raises(ValueError) as info:
        load_weights(Net(), tmp_path / "bad.pth")
    msg = str(info.value)
    assert "missing keys (1): head.bias" in msg
    assert "unexpected keys (1): extra.weight" in msg
    load_weights(Net(), tmp_path / "bad.pth", strict=False)  # tolerated when not strict


def test_shape_mismatch_always_raises(tmp_path):
    save_weights(Net(width=4), tmp_path / "net.safetensors")
    msg = re.escape("body.0.weight: checkpoint (4, 3, 3, 3) vs module (8, 3, 3, 3)")
    with pytest.raises(ValueError, match=msg):
        load_weights(Net(width=8), tmp_path / "net.safetensors", strict=False)


def test_long_key_lists_are_truncated(tmp_path):
    torch.save({f"x{i}.weight": torch.zeros(1) for i in range(40)}, tmp_path / "other.pth")
    with pytest.raises(ValueError, match=r"unexpected keys \(40\): .*\(30 more\)"):
        load_weights(Net(), tmp_path / "other.pth")


def test_missing_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_weights(Net(), tmp_path / "nope.pth")
    with pytest.raises(FileNotFoundError, match="checkpoint not found"):
        load_weights(Net(), tmp_path / "nope.safetensors")


def test_not_a_state_dict(tmp_path):
    torch.save({"optimizer": {"lr": 0.1}, "epoch": 1}, tmp_path / "opt.pth")
    with pytest.raises(ValueError, match="no recognisable state_dict; top-level keys: optimizer, epoch"):
        load_weights(Net(), tmp_path / "opt.pth")
    with pytest.raises(ValueError, match="has no entry 'params'"):
        load_weights(Net(), tmp_path / "opt.pth", key="params")


def test_save_errors(tmp_path):
    with pytest.raises(ValueError, match="<stem>.safetensors"):
        save_weights(Net(), tmp_path / "net.pth")
    with pytest.raises(ValueError, match="larger than max_shard_mb"):
        save_weights(Wide(), tmp_path / "wide.safetensors", max_shard_mb=0.1)


# verification: unreadable, corrupt and modified files ----------------------------------------------------
def _data_range(path: Path, key: str) -> tuple[int, int]:
    """The byte range of tensor ``key`` in a safetensors file (read from its header)."""
    raw = path.read_bytes()
    header_len = int.from_bytes(raw[:8], "little")
    begin, end = json.loads(raw[8:8 + header_len])[key]["data_offsets"]
    return 8 + header_len + begin, 8 + header_len + end


def _overwrite(path: Path, key: str, data: bytes) -> None:
    """Overwrite ``len(data)`` bytes in the middle of tensor ``key`` of a safetensors file."""
    begin, end = _data_range(path, key)
    start = (begin + end - len(data)) // 2 // 2 * 2  # fp16 aligned
    assert begin <= start and start + len(data) <= end
    raw = bytearray(path.read_bytes())
    raw[start:start + len(data)] = data
    path.write_bytes(bytes(raw))


def _saved_copy(tmp_path: Path, **kwargs: float) -> tuple[Wide, Path]:
    """Save a seeded ``Wide`` to ``tmp_path/orig`` and return it and a copy of its folder's file(s)."""
    src = _seeded(Wide())
    save_weights(src, tmp_path / "orig" / "wide.safetensors", **kwargs)
    shutil.copytree(tmp_path / "orig", tmp_path / "copy")
    return src, tmp_path / "copy" / "wide.safetensors"


def test_file_sha256_matches_known_digests(tmp_path):
    (tmp_path / "abc.bin").write_bytes(b"abc")
    (tmp_path / "empty.bin").write_bytes(b"")
    assert file_sha256(tmp_path / "abc.bin") == "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
    assert file_sha256(str(tmp_path / "empty.bin")) == (
        "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855")
    data = torch.randint(0, 256, (3_000_001,), dtype=torch.uint8, generator=torch.Generator().manual_seed(0))
    (tmp_path / "big.bin").write_bytes(data.numpy().tobytes())  # several 1 MiB blocks
    assert file_sha256(tmp_path / "big.bin") == hashlib.sha256(data.numpy().tobytes()).hexdigest()
    with pytest.raises(FileNotFoundError, match="nope.bin"):
        file_sha256(tmp_path / "nope.bin")
    with pytest.raises(ValueError, match="cannot read"):
        file_sha256(tmp_path)  # a folder


def test_card_sha256_lists_the_weight_files(tmp_path):
    files = save_weights(_seeded(Wide()), tmp_path / "wide.safetensors", max_shard_mb=0.3)
    entry = card_sha256(files)
    assert list(entry) == ["wide-00001-of-00002.safetensors", "wide-00002-of-00002.safetensors"]  # no index
    assert entry["wide-00002-of-00002.safetensors"] == hashlib.sha256(files[1].read_bytes()).hexdigest()


def test_overwritten_bytes_are_refused_by_the_non_finite_check(tmp_path):
    src, copy = _saved_copy(tmp_path)
    _overwrite(copy, "layers.2.weight", b"\xff" * 1000)  # 500 fp16 0xFFFF = NaN, no card beside it
    message = f"{re.escape(str(copy))} holds non-finite values .* 'layers.2.weight': 500 of 65536 elements"
    with pytest.raises(ValueError, match=message):
        load_weights(Wide(), copy)
    with pytest.raises(ValueError, match=message):
        load_state_dict_file(copy)
    load_weights(Wide(), tmp_path / "orig" / "wide.safetensors")  # the original is fine
    raw = load_state_dict_file(copy, check_finite=False)  # loads when asked to
    assert int(raw["layers.2.weight"].isnan().sum()) == 500
    assert int(raw["layers.1.weight"].isnan().sum()) == 0


def test_overwritten_bytes_are_refused_by_the_card_hash(tmp_path):
    _, copy = _saved_copy(tmp_path)
    card = {"name": "wide", "sha256": card_sha256([tmp_path / "orig" / "wide.safetensors"])}
    (copy.parent / "wide.json").write_text(json.dumps(card))
    load_weights(Wide(), copy)  # unchanged: the hash matches
    _overwrite(copy, "layers.2.weight", bytes(1000))  # zeros: finite, only the hash can tell
    listed = card["sha256"]["wide.safetensors"]
    with pytest.raises(ValueError, match=f"{re.escape(str(copy))} is corrupt or modified: its SHA-256 is "
                                         f"{file_sha256(copy)} but its card wide.json lists {listed}"):
        load_weights(Wide(), copy)
    (copy.parent / "wide.json").unlink()
    load_weights(dst := Wide(), copy)  # without the card nothing else notices
    assert int((dst.layers[2].weight == 0).sum()) == 500


def test_modified_shard_is_named(tmp_path):
    _, copy = _saved_copy(tmp_path, max_shard_mb=0.3)
    files = sorted(copy.parent.glob("wide-*.safetensors"))
    (copy.parent / "wide.json").write_text(json.dumps({"sha256": card_sha256(files)}))
    load_weights(Wide(), copy)
    raw = bytearray(files[1].read_bytes())
    raw[len(raw) // 2] ^= 1  # one bit
    files[1].write_bytes(bytes(raw))
    for path in (copy, copy.with_name("wide.safetensors.index.json"), files[0], files[1]):
        with pytest.raises(ValueError, match=f"{re.escape(str(files[1]))} is corrupt or modified"):
            load_weights(Wide(), path)


def test_card_hash_of_a_torch_file(tmp_path):
    torch.save({"params": _seeded(Net()).state_dict()}, tmp_path / "net.pth")
    (tmp_path / "net.json").write_text(json.dumps({"sha256": {"net.pth": file_sha256(tmp_path / "net.pth")}}))
    load_weights(Net(), tmp_path / "net.pth")
    (tmp_path / "net.json").write_text(json.dumps({"sha256": {"net.pth": "0" * 64}}))
    with pytest.raises(ValueError, match=f"{re.escape(str(tmp_path / 'net.pth'))} is corrupt or modified"):
        load_weights(Net(), tmp_path / "net.pth")


def test_bad_cards(tmp_path):
    save_weights(Net(), tmp_path / "net.safetensors")
    card = tmp_path / "net.json"
    card.write_text(json.dumps({"name": "net"}))  # a card without hashes: nothing to verify
    load_weights(Net(), tmp_path / "net.safetensors")
    card.write_text(json.dumps({"sha256": {"other.safetensors": "0" * 64}}))  # hashes of other files only
    load_weights(Net(), tmp_path / "net.safetensors")
    card.write_text(json.dumps({"sha256": {"net.safetensors": "xyz"}}))
    with pytest.raises(ValueError, match=f"card {re.escape(str(card))} lists an invalid SHA-256 for net.safetensors"):
        load_weights(Net(), tmp_path / "net.safetensors")
    card.write_text('{"sha256": ')
    with pytest.raises(ValueError, match=f"cannot read {re.escape(str(card))}, the checkpoint card of"):
        load_weights(Net(), tmp_path / "net.safetensors")


@pytest.mark.parametrize("fmt", ["safetensors", "pth"])
@pytest.mark.parametrize("value", [float("nan"), float("inf"), -float("inf")])
def test_non_finite_parameter_is_refused(tmp_path, fmt, value):
    src = _seeded(Net())
    with torch.no_grad():
        src.head.weight[1, 2] = value
    if fmt == "safetensors":
        path = save_weights(src, tmp_path / "net.safetensors")[0]
    else:
        path = tmp_path / "net.pth"
        torch.save({"params": src.state_dict()}, path)
    with pytest.raises(ValueError, match=f"{re.escape(str(path))} holds non-finite values \\(NaN or inf\\) in "
                                         "tensor 'head.weight': 1 of 8 elements"):
        load_weights(Net(), path)
    load_weights(dst := Net(), path, check_finite=False)
    assert int((~torch.isfinite(dst.head.weight)).sum()) == 1
    assert dst.head.weight[1, 2].item() == value or (value != value and dst.head.weight[1, 2].isnan())


def test_truncated_safetensors_is_named(tmp_path):
    _, copy = _saved_copy(tmp_path)
    raw = copy.read_bytes()
    for size in (len(raw) // 2, 20, 0):
        copy.write_bytes(raw[:size])
        with pytest.raises(ValueError, match=f"cannot read {re.escape(str(copy))}: .*truncated, corrupt or not a "
                                             "safetensors file"):
            load_weights(Wide(), copy)
    _, sharded = _saved_copy(tmp_path / "sharded", max_shard_mb=0.3)
    shard = sharded.with_name("wide-00002-of-00002.safetensors")
    shard.write_bytes(shard.read_bytes()[:-100])
    with pytest.raises(ValueError, match=f"cannot read {re.escape(str(shard))}"):
        load_weights(Wide(), sharded)


def test_garbage_torch_files_are_named(tmp_path):
    torch.save({"params": Net().state_dict()}, tmp_path / "good.pth")
    zipped = (tmp_path / "good.pth").read_bytes()
    payloads = {
        "text.pth": b"this is not a checkpoint\n" * 20,
        "pickle.pth": b"\x80\x02" + b"garbage after a pickle header" * 20,  # reaches torch.load and fails there
        "truncated.pth": zipped[: len(zipped) // 2],
        "empty.pth": b"",
    }
    for name, payload in payloads.items():
        (tmp_path / name).write_bytes(payload)
        with warnings.catch_warnings():  # the pickle may first be retried with weights_only=False
            warnings.simplefilter("ignore")
            with pytest.raises(ValueError, match=re.escape(str(tmp_path / name))):
                load_weights(Net(), tmp_path / name)


def test_wrong_format_is_named(tmp_path):
    save_weights(Net(), tmp_path / "net.safetensors")
    shutil.copy(tmp_path / "net.safetensors", tmp_path / "net.pth")
    with pytest.raises(ValueError, match=f"{re.escape(str(tmp_path / 'net.pth'))} is not a torch.save checkpoint"
                                         ".*looks like a safetensors file"):
        load_weights(Net(), tmp_path / "net.pth")
    torch.save(Net().state_dict(), tmp_path / "torch.safetensors")
    with pytest.raises(ValueError, match=f"cannot read {re.escape(str(tmp_path / 'torch.safetensors'))}: .*not a "
                                         "safetensors file"):
        load_weights(Net(), tmp_path / "torch.safetensors")


def test_broken_index_is_named(tmp_path):
    save_weights(_seeded(Wide()), tmp_path / "wide.safetensors", max_shard_mb=0.15)
    index_path = tmp_path / "wide.safetensors.index.json"
    good = json.loads(index_path.read_text())

    index_path.write_text(index_path.read_text()[:100])
    with pytest.raises(ValueError, match=f"cannot read the safetensors index {re.escape(str(index_path))}"):
        load_weights(Wide(), tmp_path / "wide.safetensors")

    moved = json.loads(json.dumps(good))
    moved["weight_map"]["layers.0.weight"] = "wide-00004-of-00004.safetensors"
    index_path.write_text(json.dumps(moved))
    with pytest.raises(ValueError, match=f"{re.escape(str(index_path))} does not match its shards \\(1 keys\\): "
                                         "layers.0.weight \\(listed in wide-00004-of-00004.safetensors, found in "
                                         "wide-00001-of-00004.safetensors\\)"):
        load_weights(Wide(), index_path)

    escaping = json.loads(json.dumps(good))
    escaping["weight_map"]["layers.0.weight"] = "../other.safetensors"
    index_path.write_text(json.dumps(escaping))
    with pytest.raises(ValueError, match=f"{re.escape(str(index_path))} lists invalid shard file names"):
        load_weights(Wide(), index_path)

    index_path.write_text(json.dumps(good))
    load_weights(Wide(), index_path)
    (tmp_path / "wide-00003-of-00004.safetensors").unlink()
    with pytest.raises(FileNotFoundError, match=f"{re.escape(str(index_path))} lists shard files that do not "
                                                "exist: wide-00003-of-00004.safetensors"):
        load_weights(Wide(), tmp_path / "wide.safetensors")


# resolve_checkpoint ------------------------------------------------------------------------------------
def test_resolve_none_and_paths(tmp_path):
    assert resolve_checkpoint(None, "efnet") is None
    torch.save(Net().state_dict(), tmp_path / "a.pth")
    assert resolve_checkpoint(str(tmp_path / "a.pth"), "efnet") == tmp_path / "a.pth"
    with pytest.raises(FileNotFoundError, match="checkpoint for efnet not found"):
        resolve_checkpoint(tmp_path / "b.pth", "efnet")
    save_weights(Wide(), tmp_path / "wide.safetensors", max_shard_mb=0.15)
    assert resolve_checkpoint(tmp_path / "wide.safetensors", "wide") == tmp_path / "wide.safetensors"


def test_resolve_default(tmp_path, monkeypatch):
    monkeypatch.setenv("EVLATCORR_CHECKPOINT_DIR", str(tmp_path))
    monkeypatch.setattr(ckpt, "checkpoint_dirs", lambda: [tmp_path])
    with pytest.raises(FileNotFoundError, match="no default checkpoint for efnet"):
        resolve_checkpoint("default", "efnet")
    save_weights(_seeded(Wide()), tmp_path / "efnet.safetensors", max_shard_mb=0.15)
    path = resolve_checkpoint("default", "efnet")
    assert path == tmp_path / "efnet.safetensors.index.json"
    save_weights(Net(), tmp_path / "gem_gopro.safetensors")
    assert resolve_checkpoint("default", "gem") == tmp_path / "gem_gopro.safetensors"
    save_weights(Net(), tmp_path / "gem_reblur.safetensors")
    with pytest.raises(ValueError, match="several default checkpoints for gem"):
        resolve_checkpoint("default", "gem")
    # "<model>-<variant>" files are other layouts (REFID 4+1): only their exact name finds them
    save_weights(Net(), tmp_path / "refid-4-1.safetensors")
    with pytest.raises(FileNotFoundError, match="no default checkpoint for refid"):
        resolve_checkpoint("default", "refid")
    assert resolve_checkpoint("default", "refid-4-1") == tmp_path / "refid-4-1.safetensors"


def test_checkpoint_dirs_env(tmp_path, monkeypatch):
    monkeypatch.setenv("EVLATCORR_CHECKPOINT_DIR", str(tmp_path))
    dirs = ckpt.checkpoint_dirs()
    assert dirs[0] == tmp_path
    assert any(d.name == "checkpoints" for d in dirs[1:])
