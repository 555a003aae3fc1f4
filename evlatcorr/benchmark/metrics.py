"""The benchmark's metrics as torchmetrics objects (correct under DDP): image quality (PSNR, SSIM, LPIPS through
the ``lpips`` package) and latency error.

PSNR and SSIM are torchmetrics' own, averaged per image. LPIPS is ``lpips.LPIPS(net="alex", version="0.1")`` with
the linear layers bundled in that package. Its AlexNet trunk comes from (in order) the torch hub cache, an explicit
path (``--lpips-backbone``), ``$EVLATCORR_LPIPS_BACKBONE``, or a download by torchvision, as ``lpips`` does by
itself. The download starts only after a short probe reaches the server, so an offline machine gets
``(None, reason)`` within seconds and :class:`ImageQuality` reports LPIPS as NaN instead of hanging or crashing.
"""

from __future__ import annotations

import os
import threading
import urllib.error
import urllib.request
import warnings
from pathlib import Path
from urllib.parse import urlparse

import torch
from torch import Tensor, nn
from torchmetrics import Metric, MetricCollection
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from evlatcorr.checks import check_image

__all__ = ["lpips_backbone_path", "load_lpips_network", "LPIPS", "ImageQuality", "LatencyError", "LPIPS_ENV"]

LPIPS_ENV = "EVLATCORR_LPIPS_BACKBONE"
_PROBE_TIMEOUT_S = 3.0  # a reachable server answers a HEAD in well under a second
# conv index in torchvision's alexnet.features -> lpips.pretrained_networks.alexnet.slice<N>
_SLICE_OF_CONV = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}


def _weights_url() -> str:
    """The AlexNet weights ``lpips`` asks torchvision for (``alexnet(pretrained=True)`` = IMAGENET1K_V1)."""
    from torchvision.models import AlexNet_Weights

    return AlexNet_Weights.IMAGENET1K_V1.url


def _hub_file() -> Path:
    """Where torchvision keeps (or would download) those weights."""
    return Path(torch.hub.get_dir()) / "checkpoints" / os.path.basename(urlparse(_weights_url()).path)


def lpips_backbone_path(path: str | os.PathLike | None = None) -> tuple[Path | None, str]:
    """Where the AlexNet trunk for LPIPS is on disk: ``(path or None, reason)``.

    Order: the torch hub cache (torchvision's own file), ``path``, ``$EVLATCORR_LPIPS_BACKBONE``.
    """
    hub = _hub_file()
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


def _probe(url: str, timeout: float) -> str | None:
    """None when ``url``'s server answers within ``timeout`` seconds, else why not.

    torch.hub downloads with no timeout, so an unreachable server would hang it; the probe runs in a daemon
    thread because name resolution ignores socket timeouts.
    """
    host = urlparse(url).hostname
    outcome: list[str | None] = []

    def ask() -> None:
        try:
            urllib.request.urlopen(urllib.request.Request(url, method="HEAD"), timeout=timeout).close()
            outcome.append(None)
        except urllib.error.HTTPError:
            outcome.append(None)  # the server answered; the download reports its own error
        except (OSError, ValueError) as exc:
            outcome.append(f"cannot reach {host} ({getattr(exc, 'reason', exc)})")

    asker = threading.Thread(target=ask, name="lpips-weights-probe", daemon=True)
    asker.start()
    asker.join(timeout)
    return outcome[0] if outcome else f"cannot reach {host} (no answer within {timeout:g} s)"


def _alex_lpips(trunk: dict[str, Tensor] | None) -> nn.Module:
    """``lpips.LPIPS`` (alex, v0.1) with the given ``features`` state dict, or torchvision's weights if None."""
    import lpips

    with warnings.catch_warnings():  # lpips passes torchvision's deprecated `pretrained=`
        warnings.filterwarnings("ignore", message=r".*(pretrained|weight enum)", category=UserWarning)
        net = lpips.LPIPS(net="alex", version="0.1", pnet_rand=trunk is not None, verbose=False)
    if trunk is not None:
        for s in range(1, 6):
            part = {k: v for k, v in trunk.items() if _SLICE_OF_CONV.get(int(k.split(".")[0])) == s}
            getattr(net.net, f"slice{s}").load_state_dict(part, strict=True)
    return net.eval().requires_grad_(False)


def load_lpips_network(path: str | os.PathLike | None = None, *, download: bool = True,
                       timeout: float = _PROBE_TIMEOUT_S) -> tuple[nn.Module | None, str]:
    """The LPIPS (alex, v0.1) network, or ``(None, reason)`` when its AlexNet trunk cannot be had.

    Args:
        path: AlexNet weights: ``alexnet().features`` or a whole torchvision AlexNet state dict.
        download: with no weights on disk (and no ``path`` or ``$EVLATCORR_LPIPS_BACKBONE`` given), let
            torchvision download them into the hub cache, as ``lpips`` does.
        timeout: seconds the server has to answer the probe before the download is given up.
    """
    source, reason = lpips_backbone_path(path)
    if source is None:
        if not download or path or os.environ.get(LPIPS_ENV):  # a path given but wrong is the user's to fix
            return None, reason
        url = _weights_url()
        unreachable = _probe(url, timeout)
        if unreachable is not None:
            return None, f"{reason}; no download: {unreachable}"
        try:
            return _alex_lpips(None), f"{url} downloaded by torchvision to {_hub_file()}"
        except (OSError, RuntimeError) as exc:  # URLError, timeouts, torch.hub's hash check
            return None, f"{reason}; download of {url} failed: {exc}"
    state = torch.load(source, map_location="cpu", weights_only=True)
    if "features.0.weight" in state:  # a whole torchvision AlexNet state_dict
        state = {k[len("features."):]: v for k, v in state.items() if k.startswith("features.")}
    return _alex_lpips(state), reason


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


class ImageQuality(MetricCollection):
    """PSNR, SSIM and LPIPS of restored frames against ground truth, accumulated over batches.

    A torchmetrics ``MetricCollection`` (every state reduces across DDP processes); :meth:`compute` gives
    plain floats, with LPIPS NaN when no LPIPS network is given.

    Args:
        lpips_network: a network from :func:`load_lpips_network`, or None for LPIPS = NaN.

    Example:
        >>> q = ImageQuality(None)
        >>> q.update(torch.full((1, 1, 16, 16), 0.5), torch.full((1, 1, 16, 16), 0.6))
        >>> round(q.compute()["psnr"], 2)
        20.0
    """

    def __init__(self, lpips_network: nn.Module | None = None) -> None:
        metrics: dict[str, Metric] = {
            "psnr": PeakSignalNoiseRatio(data_range=1.0, reduction="elementwise_mean", dim=(1, 2, 3)),
            "ssim": StructuralSimilarityIndexMeasure(data_range=1.0),
        }
        if lpips_network is not None:
            metrics["lpips"] = LPIPS(lpips_network)
        # no compute groups: the metrics share no states, and grouping would inspect them after each update
        super().__init__(metrics, compute_groups=False)

    def update(self, preds: Tensor, target: Tensor) -> None:  # type: ignore[override]
        check_image(preds, "preds")
        check_image(target, "target")
        if preds.shape != target.shape:
            raise ValueError(f"preds {tuple(preds.shape)} and target {tuple(target.shape)} must have the same shape")
        super().update(preds, target)

    def compute(self) -> dict[str, float]:  # type: ignore[override]
        values = {name: float(value) for name, value in super().compute().items()}
        values.setdefault("lpips", float("nan"))
        return values


class LatencyError(Metric):
    """Mean and largest absolute error of estimated latency maps against the true ones, µs.

    Each :meth:`update` (one scene's frames) counts once in the mean: the mean over updates of their mean
    pixel error, so a scene with more frames does not weigh more.

    Example:
        >>> m = LatencyError()
        >>> m.update(torch.full((2, 1, 4, 4), 3000.0), torch.full((2, 1, 4, 4), 2500.0))
        >>> m.update(torch.full((1, 1, 4, 4), 1000.0), torch.full((1, 1, 4, 4), 3000.0))
        >>> {k: round(float(v)) for k, v in m.compute().items()}  # (500 + 2000) / 2
        {'mae_us': 1250, 'max_us': 2000}
    """

    higher_is_better = False
    full_state_update = False

    def __init__(self, **kwargs) -> None:
        super().__init__(**kwargs)
        self.add_state("total", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="sum")
        self.add_state("count", default=torch.tensor(0, dtype=torch.long), dist_reduce_fx="sum")
        self.add_state("largest", default=torch.tensor(0.0, dtype=torch.float64), dist_reduce_fx="max")

    def update(self, latency: Tensor, true_latency: Tensor) -> None:
        if latency.shape != true_latency.shape:
            raise ValueError(f"latency {tuple(latency.shape)} and true_latency {tuple(true_latency.shape)} must "
                             "have the same shape")
        err = (latency.double() - true_latency.double()).abs()
        self.total += err.mean()
        self.count += 1
        self.largest = torch.maximum(self.largest, err.max() if err.numel() else self.largest)

    def compute(self) -> dict[str, Tensor]:
        return {"mae_us": self.total / self.count.clamp_min(1), "max_us": self.largest}
