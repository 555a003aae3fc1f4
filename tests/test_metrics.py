from __future__ import annotations

import math
import socket
import urllib.error

import pytest
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from evlatcorr.benchmark import metrics
from evlatcorr.benchmark.metrics import LPIPS, LPIPS_ENV, ImageQuality, load_lpips_network, lpips_backbone_path
from tests.conftest import shared_data_dir

SHARED_BACKBONE = shared_data_dir() / "lpips" / "alexnet_features.pth"
# LPIPS of fixed_pair() (RGB, first channel only) with SHARED_BACKBONE, as the torchmetrics-based implementation
# this one replaced gave them: the benchmark tables must not move
FIXED_PAIR_LPIPS = (0.0023372951, 0.0016460507)


def fixed_pair():
    g = torch.Generator().manual_seed(0)
    target = torch.rand(3, 3, 32, 32, generator=g)
    preds = (target + 0.05 * torch.randn(3, 3, 32, 32, generator=g)).clamp(0, 1)
    return preds, target


def test_psnr_ssim_equal_torchmetrics_functional():
    preds, target = fixed_pair()
    q = ImageQuality(None)
    q.update(preds[:2], target[:2])
    q.update(preds[2:], target[2:])
    out = q.compute()
    psnr = peak_signal_noise_ratio(preds, target, data_range=1.0, reduction="elementwise_mean", dim=(1, 2, 3))
    ssim = structural_similarity_index_measure(preds, target, data_range=1.0)
    assert out["psnr"] == pytest.approx(float(psnr), rel=1e-6)
    assert out["ssim"] == pytest.approx(float(ssim), rel=1e-5)
    assert math.isnan(out["lpips"])


def test_psnr_known_value():
    q = ImageQuality(None)
    q.update(torch.full((1, 1, 8, 8), 0.5), torch.full((1, 1, 8, 8), 0.6))
    assert q.compute()["psnr"] == pytest.approx(20.0, abs=1e-4)


def test_bad_input():
    q = ImageQuality(None)
    with pytest.raises(ValueError, match="same shape"):
        q.update(torch.rand(1, 3, 8, 8), torch.rand(1, 3, 8, 9))
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        q.update(torch.full((1, 3, 8, 8), 2.0), torch.rand(1, 3, 8, 8))


def offline(*_):
    return "cannot reach download.pytorch.org (test)"


def must_not_call(*args, **kwargs):
    raise AssertionError("went to the network although the weights were on disk or a path was given")


@pytest.fixture
def empty_hub(monkeypatch, tmp_path):
    """No AlexNet in the torch hub cache and no $EVLATCORR_LPIPS_BACKBONE."""
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.delenv(LPIPS_ENV, raising=False)
    return tmp_path


def test_lpips_missing_backbone(monkeypatch, empty_hub):
    monkeypatch.setattr(metrics, "_probe", offline)
    net, reason = load_lpips_network(None)
    assert net is None and "no AlexNet weights" in reason and "no download: cannot reach" in reason
    monkeypatch.setattr(metrics, "_probe", must_not_call)
    net, reason = load_lpips_network(None, download=False)
    assert net is None and "no AlexNet weights" in reason
    net, reason = load_lpips_network(empty_hub / "nope.pth")  # a wrong path is reported, not replaced by a download
    assert net is None and "does not exist" in reason
    monkeypatch.setenv(LPIPS_ENV, str(empty_hub / "nope.pth"))
    net, reason = load_lpips_network(None)
    assert net is None and LPIPS_ENV in reason and "does not exist" in reason


def test_probe_gives_up_on_a_silent_server():
    with socket.socket() as server:  # accepts connections (kernel backlog) and never answers
        server.bind(("127.0.0.1", 0))
        server.listen(4)
        reason = metrics._probe(f"http://127.0.0.1:{server.getsockname()[1]}/alexnet.pth", 0.3)
    assert reason is not None and "cannot reach 127.0.0.1" in reason


def test_probe_refused_connection():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # closed again before the probe: nothing listens there
    reason = metrics._probe(f"http://127.0.0.1:{port}/alexnet.pth", 2.0)
    assert reason is not None and "cannot reach 127.0.0.1" in reason


def test_lpips_download_failure_is_reported(monkeypatch, empty_hub):
    def fail(url, dst, *args, **kwargs):
        raise urllib.error.URLError("connection reset (test)")

    monkeypatch.setattr(metrics, "_probe", lambda *_: None)
    monkeypatch.setattr(torch.hub, "download_url_to_file", fail)
    net, reason = load_lpips_network(None)
    assert net is None and "download of" in reason and "connection reset (test)" in reason
    assert not any(empty_hub.rglob("*.pth"))


def lpips_of_fixed_pair(net) -> tuple[float, float]:
    preds, target = fixed_pair()
    rgb, grey = LPIPS(net), LPIPS(net)
    rgb.update(preds, target)
    grey.update(preds[:, :1], target[:, :1])
    return float(rgb.compute()), float(grey.compute())


@pytest.mark.skipif(not SHARED_BACKBONE.is_file(), reason="shared AlexNet features not on this machine")
def test_lpips_with_backbone(monkeypatch, empty_hub):
    monkeypatch.setattr(metrics, "_probe", must_not_call)
    monkeypatch.setenv(LPIPS_ENV, str(SHARED_BACKBONE))
    path, reason = lpips_backbone_path()
    assert path == SHARED_BACKBONE and LPIPS_ENV in reason
    net, _ = load_lpips_network()
    assert lpips_of_fixed_pair(net) == pytest.approx(FIXED_PAIR_LPIPS, abs=1e-6)
    preds, target = fixed_pair()
    q = ImageQuality(net)
    q.update(preds, target)
    assert q.compute()["lpips"] == pytest.approx(FIXED_PAIR_LPIPS[0], abs=1e-6)
    q.reset()
    q.update(target, target)
    assert q.compute()["lpips"] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.skipif(not SHARED_BACKBONE.is_file(), reason="shared AlexNet features not on this machine")
def test_lpips_download_as_lpips_does(monkeypatch, empty_hub):
    """With nothing on disk, torchvision downloads a whole AlexNet into the hub cache, and later runs use it."""
    features = torch.load(SHARED_BACKBONE, weights_only=True)

    def fake_download(url, dst, *args, **kwargs):
        import torchvision

        # features are the shared copy; the classifier, which LPIPS never uses, is stored as one expanded zero
        state = {k: torch.zeros(1).expand(v.shape) for k, v in torchvision.models.alexnet().state_dict().items()}
        state.update({f"features.{k}": v for k, v in features.items()})
        torch.save(state, dst)

    monkeypatch.setattr(metrics, "_probe", lambda *_: None)
    monkeypatch.setattr(torch.hub, "download_url_to_file", fake_download)
    net, reason = load_lpips_network()
    assert net is not None and "downloaded by torchvision" in reason
    assert lpips_of_fixed_pair(net) == pytest.approx(FIXED_PAIR_LPIPS, abs=1e-6)
    monkeypatch.setattr(metrics, "_probe", must_not_call)
    monkeypatch.setattr(torch.hub, "download_url_to_file", must_not_call)
    path, reason = lpips_backbone_path()
    assert path is not None and path.parent.parent == empty_hub and "hub cache" in reason
    net, _ = load_lpips_network()
    assert lpips_of_fixed_pair(net) == pytest.approx(FIXED_PAIR_LPIPS, abs=1e-6)


@pytest.mark.skipif(not SHARED_BACKBONE.is_file(), reason="shared AlexNet features not on this machine")
def test_lpips_device(device):
    net, _ = load_lpips_network(SHARED_BACKBONE)
    preds, target = fixed_pair()
    q = ImageQuality(net).to(device)
    q.update(preds.to(device), target.to(device))
    assert q.compute()["lpips"] == pytest.approx(FIXED_PAIR_LPIPS[0], abs=1e-5)
