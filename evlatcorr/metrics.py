"""Image-quality metrics as torchmetrics ``Metric`` objects (correct under DDP), LPIPS offline.

PSNR and SSIM are torchmetrics' own, averaged per image. LPIPS (AlexNet, v0.1) uses
torchmetrics' LPIPS network with its bundled linear layers; the AlexNet trunk, which torchvision
would download, is loaded from (in order) the torch hub cache, an explicit path, or the
``EVLATCORR_LPIPS_BACKBONE`` environment variable. With none, :func:`lpips_backbone_path` says why
and :class:`ImageQuality` reports LPIPS as NaN instead of crashing.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch
from torch import Tensor, nn
from torchmetrics import Metric
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from evlatcorr.checks import check_image

__all__ = ["lpips_backbone_path", "load_lpips_network", "LPIPS", "ImageQuality", "LPIPS_ENV"]

LPIPS_ENV = "EVLATCORR_LPIPS_BACKBONE"
_HUB_FILE = "alexnet-owt-7be5be79.pth"
# conv index in torchvision's alexnet.features -> LPIPS slice
_SLICE_OF_CONV = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}


def lpips_backbone_path(path: str | os.PathLike | None = None) -> tuple[Path | None, str]:
    """Where the AlexNet trunk for LPIPS comes from: ``(path or None, reason)``.

    Order: the torch hub cache (torchvision's own file), ``path``, ``$EVLATCORR_LPIPS_BACKBONE``.
    """
    hub = Path(torch.hub.get_dir()) / "checkpoints" / _HUB_FILE
    if hub.is_file():
        return hub, f"torch hub cache {hub}"
    for candidate, origin in ((path, "--lpips-backbone"), (os.environ.get(LPIPS_ENV), f"${LPIPS_ENV}")):
        if candidate:
            p = Path(candidate)
            if p.is_file():
                return p, f"{origin} {p}"
            return None, f"{origin} points to {p}, which does not exist"
    return None, (f"no AlexNet weights: not in the torch hub cache ({hub}), and neither --lpips-backbone nor "
                  f"${LPIPS_ENV} is set")


def load_lpips_network(path: str | os.PathLike | None = None) -> tuple[nn.Module | None, str]:
    """The LPIPS (alex, v0.1) network with an offline AlexNet trunk, or ``(None, reason)``."""
    from torchmetrics.functional.image.lpips import _LPIPS

    source, reason = lpips_backbone_path(path)
    if source is None:
        return None, reason
    state = torch.load(source, map_location="cpu", weights_only=True)
    if "features.0.weight" in state:  # a whole torchvision AlexNet state_dict
        state = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
    net = _LPIPS(pretrained=True, net="alex", pnet_rand=True)  # trunk random here, filled below
    for s in range(1, 6):
        part = {k: v for k, v in state.items() if _SLICE_OF_CONV.get(int(k.split(".")[0])) == s}
        getattr(net.net, f"slice{s}").load_state_dict(part, strict=True)
    net.eval().requires_grad_(False)
    return net, reason


class LPIPS(Metric):
    """Mean LPIPS (AlexNet) over images in [0, 1]; lower is better.

    Args:
        network: from :func:`load_lpips_network`.

    Example:
        >>> net, _ = load_lpips_network()  # doctest: +SKIP
        >>> LPIPS(net)(torch.rand(2, 3, 64, 64), torch.rand(2, 3, 64, 64))  # doctest: +SKIP
    """

    higher_is_better = False
    full_state_update = False

    def __init__(self, network: nn.Module, **kwargs) -> None:
        super().__init__(**kwargs)
        self.network = network
        self.add_state("total", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")

    def update(self, preds: Tensor, target: Tensor) -> None:
        if preds.shape[1] == 1:
            preds, target = preds.expand(-1, 3, -1, -1), target.expand(-1, 3, -1, -1)
        with torch.no_grad():
            scores = self.network(preds * 2 - 1, target * 2 - 1).flatten()
        self.total += scores.double().sum()
        self.count += scores.numel()

    def compute(self) -> Tensor:
        return self.total / self.count.clamp_min(1)


class ImageQuality(nn.Module):
    """PSNR, SSIM and LPIPS of restored frames against ground truth, accumulated over batches.

    Args:
        lpips_network: a network from :func:`load_lpips_network`, or None for LPIPS = NaN.

    Example:
        >>> q = ImageQuality(None)
        >>> q.update(torch.full((1, 1, 16, 16), 0.5), torch.full((1, 1, 16, 16), 0.6))
        >>> round(q.compute()["psnr"], 2)
        20.0
    """

    def __init__(self, lpips_network: nn.Module | None = None) -> None:
        super().__init__()
        self.psnr = PeakSignalNoiseRatio(data_range=1.0, reduction="elementwise_mean", dim=(1, 2, 3))
        self.ssim = StructuralSimilarityIndexMeasure(data_range=1.0)
        self.lpips = LPIPS(lpips_network) if lpips_network is not None else None

    def update(self, preds: Tensor, target: Tensor) -> None:
        check_image(preds, "preds")
        check_image(target, "target")
        if preds.shape != target.shape:
            raise ValueError(f"preds {tuple(preds.shape)} and target {tuple(target.shape)} must have the same shape")
        self.psnr.update(preds, target)
        self.ssim.update(preds, target)
        if self.lpips is not None:
            self.lpips.update(preds, target)

    def compute(self) -> dict[str, float]:
        lpips = float(self.lpips.compute()) if self.lpips is not None else float("nan")
        return {"psnr": float(self.psnr.compute()), "ssim": float(self.ssim.compute()), "lpips": lpips}

    def reset(self) -> None:
        for m in (self.psnr, self.ssim, self.lpips):
            if m is not None:
                m.reset()
