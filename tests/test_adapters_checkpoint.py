from __future__ import annotations

import json
import re

import pytest
import torch
from torch import nn

from evlatcorr.adapters import checkpoint as ckpt
from evlatcorr.adapters.checkpoint import load_state_dict_file, load_weights, resolve_checkpoint, save_weights


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
