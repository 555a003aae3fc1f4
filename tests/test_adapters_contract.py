"""The contract every adapter keeps (EDI, EFNet, GEM, REFID), with small random-weight instances.

An adapter takes an EventFrames batch (anything else is a ValueError), works inside ``nn.Sequential``, reads
``frames.corrected`` when it is set, returns the batch with ``output`` in the blurry frame's channels and dtype,
clamped to [0, 1], pads sizes its network cannot take (or names ``pad=True``), shows its network in its repr,
and loads its weights strictly from official layouts, paths or the default checkpoint. What is particular to one
model (its representation, known outputs, options) is in its own test file.
"""

from __future__ import annotations

import hashlib
import json
import re

import pytest
import torch
from torch import nn

from evlatcorr import EventFrames
from evlatcorr.adapters import EDIAdapter, EFNetAdapter, GEMAdapter, NetworkAdapter, REFIDAdapter, save_weights
from evlatcorr.adapters import checkpoint as ckpt
from evlatcorr.adapters.efnet import EFNet, efnet_scer
from evlatcorr.adapters.gem import San, gem_eger
from evlatcorr.adapters.refid import REFIDNet, refid_voxel_grid
from tests.conftest import random_events, shared_data_dir

ADAPTERS = {
    "edi": lambda **kw: EDIAdapter(num_bins=20, **kw),
    "efnet": lambda **kw: EFNetAdapter(**kw),
    "gem": lambda **kw: GEMAdapter(**kw),
    "refid": lambda **kw: REFIDAdapter(m=2, n=1, **kw),  # 2m + n = 5 output frames
}
NAMES = list(ADAPTERS)
PADDING = ["efnet", "gem", "refid"]  # the adapters with pad and clamp arguments (EDI always clamps)
LEARNED = {"efnet": "efnet", "gem": "gem", "refid": "refid-2-1"}  # adapters with weights: checkpoint names
REPRESENTATIONS = {  # their event tensor builders: (events, start (B,), end (B,)) -> (B, C, H, W)
    "efnet": efnet_scer,
    "gem": gem_eger,
    "refid": lambda events, start, end: refid_voxel_grid(events, start, end, 5),
}
ODD = (14, 18)  # a multiple of none of the divisors (EFNet 4, REFID 8, GEM 16)
# the official networks' state_dicts: (our class, official class, spec in the shared specs folder, tensors,
# parameters, sha256 of "key:AxBxC;..." in state_dict order), of EFNet(wf=64, fuse_before_downsample=True) in
# AHupuJR/EFNet @7cf6737, San(3, 3, 96) in XiangZ-0/GEM @33891b3 and FinalBidirectionAttenfusion(img_chn=26) in
# AHupuJR/REFID @f94eb19
OFFICIAL_NETWORKS = {
    "efnet": (EFNet, "EFNet", "efnet_state_dict", 183, 8_466_445,
              "8b77e50ca179259831428145f02f43e4e5fd6973a3dd30a3d6962a43a8d56e7c"),
    "gem": (San, "San", "gem_san_state_dict", 118, 2_421_882,
            "661c787584f7d8fc6f3f319164800e7becf2dbd063191d3349044f91b9307fae"),
    "refid": (REFIDNet, "FinalBidirectionAttenfusion", "refid_state_dict", 183, 15_928_355,
              "138facec594431743f3a86b70d568f0b5a594525c2e380bb3368b6fcc2c3a1d1"),
}


@pytest.fixture(scope="module", autouse=True)
def _one_thread():
    """Tiny inputs: one intra-op thread is as fast, and far faster when other jobs share the cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


def make(name: str, **kwargs) -> NetworkAdapter:
    torch.manual_seed(0)  # the same random weights for every setting of one adapter
    return ADAPTERS[name](**kwargs).eval()


def make_frames(size: tuple[int, int] = (16, 16), channels: int = 3, dtype: torch.dtype = torch.float32,
                seed: int = 0) -> EventFrames:
    """Two samples: exposures [0, 100) and, for REFID's pair, [120, 220); random events over [-50, 300)."""
    events = random_events(3000, size, (-50.0, 300.0), batch_size=2, seed=seed)
    g = torch.Generator().manual_seed(seed)
    blurry, blurry_next = (torch.rand(2, channels, *size, generator=g, dtype=torch.float64).to(dtype)
                           for _ in range(2))
    return EventFrames(blurry, events, torch.zeros(2), torch.full((2,), 100.0), blurry_next=blurry_next,
                       exposure_start_next=torch.full((2,), 120.0), exposure_end_next=torch.full((2,), 220.0))


def output_shape(name: str, frames: EventFrames) -> tuple[int, ...]:
    """The documented shape: :math:`(B, C, H, W)`, or :math:`(B, T, C, H, W)` for REFID."""
    b, c = frames.blurry.shape[:2]
    return (b, 5, c, *frames.sensor_size) if name == "refid" else (b, c, *frames.sensor_size)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("name", NAMES)
def test_returns_the_batch_with_output_of_the_documented_shape_and_dtype(name, dtype):
    frames = make_frames(dtype=dtype)
    with torch.no_grad():
        out = nn.Sequential(nn.Identity(), make(name))(frames)
    assert isinstance(out, EventFrames)
    assert out.output.shape == output_shape(name, frames) and out.output.dtype == dtype
    assert out.events is frames.events and frames.output is None  # the input batch is left as it was


@pytest.mark.parametrize("name", NAMES)
def test_reads_corrected_events(name):
    frames = make_frames()
    latency = torch.rand(2, 1, 16, 16, generator=torch.Generator().manual_seed(1), dtype=torch.float64) * 40
    shifted = frames.events.shift(latency)
    adapter = make(name)
    with torch.no_grad():
        plain = adapter(frames).output
        corrected = adapter(frames.replace(corrected=shifted)).output
        replaced = adapter(frames.replace(events=shifted)).output
    assert not torch.equal(corrected, plain)
    assert torch.equal(corrected, replaced)


@pytest.mark.parametrize("name", NAMES)
def test_grey_in_grey_out(name):
    frames = make_frames(channels=1)
    with torch.no_grad():
        out = make(name)(frames).output
    assert out.shape == output_shape(name, frames) and out.shape[-3] == 1
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0


@pytest.mark.parametrize("name", PADDING)
def test_pad_false_refuses_a_size_the_network_cannot_take_and_pad_true_keeps_it(name):
    frames = make_frames(ODD)
    with pytest.raises(ValueError, match=r"multiples of \d+, got \(H, W\)=\(14, 18\).*pad=True"):
        make(name, pad=False)(frames)
    with torch.no_grad():
        out = make(name, pad=True)(frames).output
    assert out.shape == output_shape(name, frames) and out.shape[-2:] == ODD


@pytest.mark.parametrize("name", NAMES)
def test_refuses_anything_but_event_frames(name):
    adapter = make(name)
    with pytest.raises(ValueError, match=f"{type(adapter).__name__} takes an EventFrames batch, got Tensor"):
        adapter(torch.rand(2, 3, 16, 16))


def _spread(module: nn.Module, inputs: tuple, output):
    """Forward hook: the network's outputs standardised around 0.5, so that they leave [0, 1] for the clamp."""

    def spread(o: torch.Tensor) -> torch.Tensor:
        return 0.5 + (o - o.mean()) / o.std()

    return spread(output) if isinstance(output, torch.Tensor) else type(output)(spread(o) for o in output)


@pytest.mark.parametrize("name", NAMES)
def test_output_is_clamped_to_the_unit_range(name):
    frames = make_frames(ODD)
    adapter, raw = make(name), (make(name, clamp=False) if name in PADDING else None)
    with torch.no_grad():
        if raw is None:  # EDI always clamps
            out = adapter(frames).output
        else:
            adapter.net.register_forward_hook(_spread)
            raw.net.register_forward_hook(_spread)
            out, unclamped = adapter(frames).output, raw(frames).output
            assert float(unclamped.min()) < 0.0 and float(unclamped.max()) > 1.0
            assert torch.equal(out, unclamped.clamp(0.0, 1.0))
    assert float(out.min()) >= 0.0 and float(out.max()) <= 1.0


@pytest.mark.parametrize("name", NAMES)
def test_repr_shows_the_settings_and_the_network(name):
    adapter = make(name)
    text = repr(adapter)
    assert text.startswith(f"{type(adapter).__name__}(") and adapter.extra_repr() in text
    net = getattr(adapter, "net", None)
    if net is None:  # EDI: a model without a network
        assert text == f"EDIAdapter({adapter.extra_repr()})"
    else:
        assert f"(net): {type(net).__name__}(" in text and net.extra_repr() in text


@pytest.mark.parametrize("name", REPRESENTATIONS)
def test_representation_takes_a_window_per_sample_and_refuses_bad_ones(name):
    build = REPRESENTATIONS[name]
    events = random_events(200, (4, 4), (0.0, 100.0), batch_size=2, seed=3)
    start = torch.tensor([[0.0, 1.0], [0.0, 1.0]])[:, 0]  # non-contiguous views
    end = torch.tensor([[100.0, 1.0], [90.0, 1.0]])[:, 0]
    assert not end.is_contiguous()
    out = build(events, start, end)
    assert out.shape[0] == 2 and out.shape[-2:] == (4, 4) and out.dtype == torch.float32
    assert torch.equal(out, build(events, start.clone(), end.clone()))
    assert not torch.equal(out[1], build(events, start, end - torch.tensor([0.0, 40.0]))[1])  # each its own window
    with pytest.raises(ValueError, match="end must (be after|not be before)"):
        build(events, end, start)
    with pytest.raises(ValueError, match=r"start must have shape \(2,\)"):
        build(events, torch.zeros(3), end)
    with pytest.raises(ValueError, match="events must be evlatcorr.Events, got Tensor"):
        build(torch.zeros(4), start, end)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("name", NAMES)
def test_runs_on_cuda_as_on_the_cpu(name):
    frames = make_frames(ODD)
    adapter = make(name)
    with torch.no_grad():
        cpu = adapter(frames).output
        gpu = adapter.cuda()(frames.to("cuda")).output
    assert gpu.device.type == "cuda"
    torch.testing.assert_close(gpu.cpu(), cpu, rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("name", LEARNED)
def test_network_has_the_official_state_dict_layout(name):
    cls, official, spec_name, tensors, parameters, sha256 = OFFICIAL_NETWORKS[name]
    net = cls()
    items = [(k, tuple(v.shape)) for k, v in net.state_dict().items()]
    fingerprint = ";".join(f"{k}:{'x'.join(map(str, s))}" for k, s in items)
    assert len(items) == tensors and hashlib.sha256(fingerprint.encode()).hexdigest() == sha256
    assert sum(p.numel() for p in net.parameters()) == parameters and not list(net.buffers())
    spec_file = shared_data_dir().parent / "specs" / f"{spec_name}.json"
    if spec_file.is_file():  # the full spec, where the project's shared folder is present: a readable diff
        spec = json.loads(spec_file.read_text())
        assert [(k, list(s)) for k, s in items] == [(k, s) for k, s in spec["tensors"]]
        assert spec["num_parameters"] == parameters and spec["source"]["class"] == official


@pytest.mark.parametrize("layout", ["basicsr", "lightning"])
@pytest.mark.parametrize("name", LEARNED)
def test_loads_official_checkpoint_layouts_strictly(tmp_path, name, layout):
    g = torch.Generator().manual_seed(1)
    state = {k: torch.randn(v.shape, generator=g) for k, v in make(name).net.state_dict().items()}
    payload = {"params": state} if layout == "basicsr" else {  # BasicSR .pth, Lightning .ckpt
        "epoch": 1, "state_dict": {f"model.{k}": v for k, v in state.items()}}
    torch.save(payload, tmp_path / "weights.pth")
    loaded = make(name, checkpoint=str(tmp_path / "weights.pth")).net.state_dict()
    assert list(loaded) == list(state) and all(torch.equal(loaded[k], v) for k, v in state.items())


@pytest.mark.parametrize("name", LEARNED)
def test_loads_the_default_checkpoint_from_the_checkpoint_folders(tmp_path, monkeypatch, name):
    torch.manual_seed(1)
    source = make(name).net
    for p in source.parameters():
        p.data.uniform_(-1.0, 1.0)  # other weights than make's
    files = save_weights(source, tmp_path / f"{LEARNED[name]}.safetensors", max_shard_mb=3)  # fp16, sharded
    assert len(files) > 2  # shards and their index
    monkeypatch.setattr(ckpt, "checkpoint_dirs", lambda: [tmp_path])
    loaded = make(name, checkpoint="default").net.state_dict()
    assert all(torch.equal(loaded[k], v.half().float()) for k, v in source.state_dict().items())
    monkeypatch.setattr(ckpt, "checkpoint_dirs", lambda: [tmp_path / "empty"])
    with pytest.raises(FileNotFoundError, match=f"no default checkpoint for {LEARNED[name]}"):
        make(name, checkpoint="default")


@pytest.mark.parametrize("name", LEARNED)
def test_refuses_a_checkpoint_that_does_not_match_or_does_not_exist(tmp_path, name):
    state = dict(make(name).net.state_dict())
    last = list(state)[-1]
    state.pop(last)
    state["extra.weight"] = torch.zeros(1)
    torch.save({"params": state}, tmp_path / "bad.pth")
    keys = rf"(?s)missing keys \(1\): {re.escape(last)}.*unexpected keys \(1\): extra.weight"
    with pytest.raises(ValueError, match=keys):
        make(name, checkpoint=str(tmp_path / "bad.pth"))
    with pytest.raises(FileNotFoundError):
        make(name, checkpoint=str(tmp_path / "missing.pth"))
