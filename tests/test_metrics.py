from __future__ import annotations

import math

import pytest
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from evlatcorr.metrics import LPIPS_ENV, ImageQuality, load_lpips_network, lpips_backbone_path
from tests.conftest import shared_data_dir

SHARED_BACKBONE = shared_data_dir() / "lpips" / "alexnet_features.pth"


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


def test_lpips_missing_backbone(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.delenv(LPIPS_ENV, raising=False)
    net, reason = load_lpips_network(None)
    assert net is None and "no AlexNet weights" in reason
    net, reason = load_lpips_network(tmp_path / "nope.pth")
    assert net is None and "does not exist" in reason


@pytest.mark.skipif(not SHARED_BACKBONE.is_file(), reason="shared AlexNet features not on this machine")
def test_lpips_with_backbone(monkeypatch, tmp_path):
    monkeypatch.setattr(torch.hub, "get_dir", lambda: str(tmp_path))
    monkeypatch.setenv(LPIPS_ENV, str(SHARED_BACKBONE))
    path, reason = lpips_backbone_path()
    assert path == SHARED_BACKBONE and LPIPS_ENV in reason
    net, _ = load_lpips_network()
    preds, target = fixed_pair()
    q = ImageQuality(net)
    q.update(preds, target)
    score = q.compute()["lpips"]
    assert 0.0 < score < 0.5
    q.reset()
    q.update(target, target)
    assert q.compute()["lpips"] == pytest.approx(0.0, abs=1e-6)
