"""The benchmark's Lightning test loop: every method on every input of each scene, metrics accumulated.

Each test sample is a :class:`BenchmarkScene`: consecutive blurry frames with their ideal
events (ground truth timing) and delayed events, plus the frame pairs used for interpolation.
For every method (EDI deblurring, EFNet, GEM, EDI interpolation, REFID) and every input
("GT input", "W/o corr.", "W/ corr. const.", "W/ corr. spatial") the restored frames are scored
by torchmetrics PSNR, SSIM and LPIPS, which reduce across processes, so the same code gives the
same table on one CPU or on many GPUs with DDP.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import lightning as L
import torch
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset, Subset

from evlatcorr.adapters.edi import EDIAdapter
from evlatcorr.benchmark.metrics import ImageQuality, LatencyError
from evlatcorr.frames import EventFrames
from evlatcorr.gamma import display_image, linear_frames

__all__ = [
    "INPUTS",
    "BenchmarkScene",
    "Method",
    "BenchmarkModule",
    "SceneDataModule",
    "pair_with_latency",
]

GT, NO_CORR, CONST, SPATIAL = "GT input", "W/o corr.", "W/ corr. const.", "W/ corr. spatial"
INPUTS = (GT, NO_CORR, CONST, SPATIAL)


@dataclass
class BenchmarkScene:
    """One test scene.

    Attributes:
        name: scene name.
        frames_ideal: deblurring batch (F frames) with ideal events and ``sharp`` at mid-exposure.
        frames_delayed: the same frames with delayed events.
        pairs_ideal: interpolation batch (F-1 pairs) with ideal events, ``target_times`` (P, 1) and
            ``target_frames`` (P, 1, C, H, W); ``None`` when the data has no frames between exposures
            (the interpolation rows are then n/a).
        pairs_delayed: the same pairs with delayed events (``None`` with ``pairs_ideal``).
        true_latency: (F, 1, H, W) µs.
        events_before_us: how long before the first exposure the pairs' events begin (ideal and
            delayed alike); corrected pairs are cut to the same window in corrected time.
        frame_gamma: how the source file encoded its frames (``linear ** (1 / gamma)``; 1: linear). The scene's
            frames are held linear, as EDI and the correctors need them; a network reads them, and every row is
            scored, encoded back as in the file.
    """

    name: str
    frames_ideal: EventFrames
    frames_delayed: EventFrames
    pairs_ideal: EventFrames | None
    pairs_delayed: EventFrames | None
    true_latency: Tensor
    extra: dict[str, Any] = field(default_factory=dict)
    events_before_us: float = 0.0
    frame_gamma: float = 1.0

    def to(self, device: torch.device | str, non_blocking: bool = False) -> BenchmarkScene:
        """Move every batch and the true latency to ``device`` (Lightning's default batch transfer calls this)."""
        def move(frames: EventFrames | None) -> EventFrames | None:
            return None if frames is None else frames.to(device, non_blocking)

        return BenchmarkScene(self.name, move(self.frames_ideal), move(self.frames_delayed), move(self.pairs_ideal),
                              move(self.pairs_delayed), self.true_latency.to(device, non_blocking=non_blocking),
                              self.extra, self.events_before_us, self.frame_gamma)


@dataclass
class Method:
    """A row group of the table: a model and the task it solves (``"deblur"`` or ``"interpolation"``).

    ``linear``: the model reads and writes linear intensity (EDI; the default for an
    :class:`~evlatcorr.adapters.edi.EDIAdapter`), where a network reads frames as its dataset encoded them.
    """

    name: str
    model: nn.Module
    task: str
    linear: bool | None = None

    def __post_init__(self) -> None:
        if self.linear is None:
            self.linear = isinstance(self.model, EDIAdapter)


def pair_with_latency(pairs: EventFrames, latency_first: Tensor, latency_second: Tensor,
                      window_start: Tensor | None = None) -> EventFrames:
    """Correct the events of interpolation pairs with the latencies estimated on their two frames.

    Events up to the midpoint between the two exposures take the first frame's latency map, later
    ones the second's (for a constant latency both are the same).

    Args:
        pairs: the interpolation batch, its events as stamped.
        latency_first: latency of each pair's first frame, :math:`(B,)` or :math:`(B, 1, H, W)` µs.
        latency_second: the same for the second frame.
        window_start: :math:`(B,)` µs, where the stamped events were cut: corrected events earlier
            than it are dropped, so the corrected input spans the same window (in corrected time) as
            ideal events cut there would. Without it, a correction moves events from after the cut to
            before it, which inputs that read before the exposure (REFID's first bin) would see and
            ideal events would not.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> pairs = simulate("camera", num_frames=2, height=8, width=8, exposure_us=2000.0,
        ...                  latency_us=500.0).pairs("delayed")
        >>> out = pair_with_latency(pairs, torch.tensor([500.0]), torch.tensor([500.0]), pairs.exposure_start)
        >>> bool((out.corrected.t >= pairs.exposure_start[0]).all())
        True
    """
    assert pairs.exposure_end_next is not None and pairs.exposure_start_next is not None
    split = (pairs.exposure_end + pairs.exposure_start_next) / 2
    ev = pairs.events
    first = ev.select(ev.t < split[ev.batch]).shift(latency_first)
    second = ev.select(ev.t >= split[ev.batch]).shift(latency_second)
    from evlatcorr.events import Events

    merged = Events.cat([first, second])
    batch = torch.cat([first.batch, second.batch])
    merged = Events(merged.x, merged.y, merged.t, merged.p, batch, sensor_size=ev.sensor_size,
                    batch_size=ev.batch_size, sort=True)
    if window_start is not None:
        merged = merged.since(window_start)
    return pairs.replace(corrected=merged)


class BenchmarkModule(L.LightningModule):
    """Runs every method on every input of each scene and accumulates the metrics.

    Args:
        methods: the table's row groups.
        correctors: input name -> corrector module for ``"W/ corr. const."`` / ``"W/ corr. spatial"``.
        lpips_network: LPIPS network or None (LPIPS reported as NaN).
        on_scene: optional callback ``(scene, outputs) -> None`` for figures; ``outputs`` holds
            ``latency[input]``, ``restored[(method, input)]``, ``target[method]`` and ``meta[input]``.
    """

    def __init__(self, methods: Sequence[Method], correctors: dict[str, nn.Module],
                 lpips_network: nn.Module | None = None,
                 on_scene: Callable[[BenchmarkScene, dict[str, Any]], None] | None = None) -> None:
        super().__init__()
        self.methods = list(methods)
        self.models = nn.ModuleDict({m.name: m.model for m in methods})
        self.correctors = nn.ModuleDict({_key('corrector', k): v for k, v in correctors.items()})
        self.inputs = [GT, NO_CORR] + [name for name in (CONST, SPATIAL) if name in correctors]
        self.quality = nn.ModuleDict({
            _key(m.name, i): ImageQuality(lpips_network) for m in methods for i in self.inputs})
        self.latency_error = nn.ModuleDict({_key("latency", i): LatencyError() for i in self.inputs[2:]})
        self.on_scene = on_scene
        self.failures: dict[str, str] = {}
        # wall seconds per stage of the test loop (correctors, each method's forward pass, metrics, figures)
        self.stage_seconds: dict[str, float] = {}

    @contextmanager
    def _stage(self, name: str) -> Iterator[None]:
        if self.device.type == "cuda":  # the work queued before the stage is not its time
            torch.cuda.synchronize(self.device)
        start = time.perf_counter()
        yield
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.stage_seconds[name] = self.stage_seconds.get(name, 0.0) + time.perf_counter() - start

    def test_step(self, scene: BenchmarkScene | None, batch_idx: int) -> None:
        if scene is None:  # unreadable: the data module's loader already said why
            return
        outputs: dict[str, Any] = {"latency": {}, "restored": {}}
        frames = {GT: scene.frames_ideal, NO_CORR: scene.frames_delayed}
        pairs = {GT: scene.pairs_ideal, NO_CORR: scene.pairs_delayed}
        for name in self.inputs[2:]:
            with self._stage(f"corrector: {name}"):
                corrected = self.correctors[_key('corrector', name)](scene.frames_delayed)
            frames[name] = corrected
            latency = corrected.latency
            outputs["latency"][name] = latency
            self.latency_error[_key("latency", name)].update(latency, scene.true_latency.expand_as(latency))
            if scene.pairs_delayed is not None:
                start = scene.pairs_delayed.exposure_start - scene.events_before_us
                pairs[name] = pair_with_latency(scene.pairs_delayed, latency[:-1], latency[1:], start)
            outputs.setdefault("meta", {})[name] = corrected.meta
        for method in self.methods:
            for name in self.inputs:
                key = _key(method.name, name)
                if method.name in self.failures:
                    continue
                batch = frames[name] if method.task == "deblur" else pairs[name]
                if batch is None:
                    self.failures[method.name] = f"scene {scene.name} has no ground truth between exposures"
                    continue
                try:
                    with self._stage(f"{method.name} forward"):
                        restored, target = _run(method, batch, scene.frame_gamma)
                except torch.cuda.OutOfMemoryError as exc:  # keep the other rows
                    self.failures[method.name] = f"out of GPU memory ({exc})"
                    torch.cuda.empty_cache()
                    continue
                with self._stage("metrics (PSNR, SSIM, LPIPS)"):
                    self.quality[key].update(restored, target)
                outputs["restored"][(method.name, name)] = restored
                outputs.setdefault("target", {})[method.name] = target
        if self.on_scene is not None:
            with self._stage("figures"):
                self.on_scene(scene, outputs)

    def results(self) -> dict[str, Any]:
        """Every metric after the test loop: ``table`` rows and latency errors."""
        table = []
        for method in self.methods:
            for name in self.inputs:
                if method.name in self.failures:
                    row = {"psnr": math.nan, "ssim": math.nan, "lpips": math.nan}
                else:
                    row = self.quality[_key(method.name, name)].compute()
                table.append({"method": method.name, "input": name, **row})
        latency = {name: {k: float(v) for k, v in self.latency_error[_key("latency", name)].compute().items()}
                   for name in self.inputs[2:]}
        return {"table": table, "latency_error": latency, "failures": dict(self.failures)}


def _key(a: str, b: str) -> str:
    # ModuleDict keys may not contain "."
    return f"{a}|{b}".replace(".", "_")


def _run(method: Method, batch: EventFrames, frame_gamma: float = 1.0) -> tuple[Tensor, Tensor]:
    """The method's restored frames and their targets, both encoded as the scene's file had its frames."""
    if method.linear:
        restored, target = _restore(method, batch)
        return display_image(restored, frame_gamma), display_image(target, frame_gamma)
    return _restore(method, linear_frames(batch, 1 / frame_gamma))  # a network reads the file's encoding


def _restore(method: Method, batch: EventFrames) -> tuple[Tensor, Tensor]:
    with torch.no_grad():
        out = method.model(batch)
    restored = out.output
    if method.task == "deblur":
        assert batch.sharp is not None
        return restored.clamp(0, 1), batch.sharp
    assert batch.target_frames is not None and batch.target_times is not None
    if restored.dim() == 5 and restored.shape[1] != batch.target_times.shape[1]:
        # models that output a fixed set of frames (REFID) say when: pick the one nearest each target
        times = out.meta["output_times"].to(batch.target_times)
        index = (times[:, None, :] - batch.target_times[:, :, None]).abs().argmin(-1)  # (B, T)
        restored = torch.stack([restored[b, index[b]] for b in range(restored.shape[0])])
    restored = restored.clamp(0, 1).flatten(0, 1)
    return restored, batch.target_frames.flatten(0, 1)


class _SceneList(Dataset):
    def __init__(self, load: Callable[[int], BenchmarkScene], size: int) -> None:
        self.load, self.size = load, size

    def __len__(self) -> int:
        return self.size

    def __getitem__(self, index: int) -> BenchmarkScene:
        return self.load(index)


class SceneDataModule(L.LightningDataModule):
    """Test scenes, one per step (a scene already holds a batch of frames).

    Under DDP each process takes every ``world_size``-th scene, with no scene repeated (a
    ``DistributedSampler`` would pad with repeats and bias the means), so run the ``Trainer`` with
    ``use_distributed_sampler=False``.
    """

    def __init__(self, load: Callable[[int], BenchmarkScene], size: int, num_workers: int = 0) -> None:
        super().__init__()
        if size < 1:
            raise ValueError("the benchmark needs at least one scene")
        self.dataset = _SceneList(load, size)
        self.num_workers = num_workers

    def test_dataloader(self) -> DataLoader:
        trainer = self.trainer
        rank, world = (trainer.global_rank, trainer.world_size) if trainer is not None else (0, 1)
        if world > 1 and getattr(trainer._accelerator_connector, "use_distributed_sampler", False):
            raise ValueError("SceneDataModule splits the scenes across processes itself: build the Trainer "
                             "with use_distributed_sampler=False")
        mine = Subset(self.dataset, list(range(rank, len(self.dataset), world)))
        return DataLoader(mine, batch_size=None, shuffle=False, num_workers=self.num_workers,
                          collate_fn=lambda scene: scene)
