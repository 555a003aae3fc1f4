"""Figures of the benchmark's first scene: the score curve, restored crops and latency maps (PNG files)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from evlatcorr.benchmark.loop import CONST, BenchmarkScene
from evlatcorr.gamma import display_image

__all__ = ["Figures", "sharpest_window"]


class Figures:
    """Collects the first scene's outputs for the figures."""

    def __init__(self) -> None:
        self.first: tuple[BenchmarkScene, dict[str, Any]] | None = None

    def __call__(self, scene: BenchmarkScene, outputs: dict[str, Any]) -> None:
        if self.first is None:
            self.first = (scene.to("cpu"), {k: _cpu(v) for k, v in outputs.items()})

    @staticmethod
    def _write_crops(out: Path, scene: BenchmarkScene, outputs: dict[str, Any]) -> str:
        """restored.png: a row per method (its blurry input and ground truth, then the result of each
        input), cropped to the first frame's most textured 96x128 window, where latency shows."""
        from matplotlib.figure import Figure

        restored, targets = outputs["restored"], outputs["target"]
        top, left = sharpest_window(scene.frames_ideal.sharp[0], 96, 128)
        crop = (slice(None), slice(top, top + 96), slice(left, left + 128))
        methods = list(dict.fromkeys(method for method, _ in restored))
        inputs = list(dict.fromkeys(name for _, name in restored))
        cols = 2 + len(inputs)
        fig = Figure(figsize=(2.4 * cols, 2.1 * len(methods)))
        axes = fig.subplots(len(methods), cols, squeeze=False)
        for ax in axes.flat:
            ax.axis("off")
        for row, method in zip(axes, methods):
            blurry = display_image(scene.frames_ideal.blurry[0], scene.frame_gamma)  # as the file has it
            panels = [("blurry input", blurry), ("ground truth", targets[method][0])]
            panels += [(name, restored[(method, name)][0]) for name in inputs if (method, name) in restored]
            for ax, (title, image) in zip(row, panels):
                ax.imshow(image[crop].permute(1, 2, 0).clamp(0, 1).numpy(), interpolation="nearest")
                ax.set_title(f"{method}\n{title}", fontsize=8)
        fig.suptitle(f"{scene.name}, frame 0 (interpolation: the first gap's frame), 96x128 crop at "
                     f"y={top}, x={left}", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / "restored.png", dpi=90)
        return "restored.png"

    def write(self, out: Path) -> list[str]:
        """etf_vs_latency.png, restored.png and latency_maps.png of the first scene; the names written."""
        if self.first is None:
            return []
        from matplotlib.figure import Figure

        scene, outputs = self.first
        written = []
        meta = outputs.get("meta", {}).get(CONST)
        if meta is not None and "etf_curve" in meta:
            cand, etf = meta["etf_curve"]
            fig = Figure(figsize=(5, 3.5))
            ax = fig.subplots()
            ax.plot(cand[0].numpy() / 1000, etf[0].numpy())
            ax.axvline(float(scene.true_latency[0].mean()) / 1000, color="g", ls="-", label="true")
            ax.axvline(float(outputs["latency"][CONST][0].mean()) / 1000, color="r", ls="--", label="estimated")
            ax.set_xlabel("candidate latency (ms)")
            ax.set_ylabel(f"{meta.get('score', 'etf')} score (lower = sharper)")
            ax.set_title(f"{scene.name}, frame 0")
            ax.legend()
            fig.tight_layout()
            fig.savefig(out / "etf_vs_latency.png", dpi=100)
            written.append("etf_vs_latency.png")
        if outputs["restored"]:
            written.append(self._write_crops(out, scene, outputs))
        maps = [("true", scene.true_latency[0, 0])] + [(k, v[0, 0]) for k, v in outputs["latency"].items()]
        fig = Figure(figsize=(3.4 * len(maps), 2.8))
        axes = fig.subplots(1, len(maps), squeeze=False)
        vmax = max(float(m.max()) for _, m in maps) / 1000
        for ax, (title, m) in zip(axes[0], maps):
            im = ax.imshow(m.numpy() / 1000, vmin=0, vmax=vmax, cmap="viridis")
            ax.set_title(f"{title} (ms)", fontsize=9)
            ax.axis("off")
        fig.colorbar(im, ax=list(axes[0]), shrink=0.8)
        fig.savefig(out / "latency_maps.png", dpi=90)
        written.append("latency_maps.png")
        return written


def sharpest_window(image: torch.Tensor, height: int, width: int) -> tuple[int, int]:
    """Top-left corner of the ``height x width`` window of ``image`` (C, H, W) with the most gradient
    energy: where latency errors show."""
    gray = image.mean(0)
    energy = (gray[1:, :-1] - gray[:-1, :-1]) ** 2 + (gray[:-1, 1:] - gray[:-1, :-1]) ** 2
    h, w = min(height, energy.shape[0]), min(width, energy.shape[1])
    sums = torch.nn.functional.avg_pool2d(energy[None, None], (h, w), stride=8)[0, 0]
    index = int(sums.flatten().argmax())
    return (index // sums.shape[1]) * 8, (index % sums.shape[1]) * 8


def _cpu(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: _cpu(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return tuple(_cpu(v) for v in value)
    return value
