"""Train and fine-tune the restoration networks (EFNet, GEM, REFID) with Lightning.

Official weights cannot be downloaded everywhere, so the networks are trained here on the
simulator's training photographs (disjoint from the benchmark's test photographs): random crops,
horizontal flips, L1 loss, PSNR/SSIM validation on held-out sequences of the training photographs.
The same command runs on one CPU or, with ``--devices N --strategy ddp``, on many GPUs (bf16 mixed
precision by default on CUDA); ``--resume last`` continues from the last checkpoint, and the
trained network is exported as fp16 safetensors shards that the adapters load by name.

Command line::

    python -m evlatcorr.train --model efnet --max-steps 2000 --out runs/efnet --export checkpoints
    python -m evlatcorr.train --model efnet --out runs/efnet --resume last     # continue
    python -m evlatcorr.train --model gem --accelerator gpu --devices 4 --strategy ddp
    python -m evlatcorr.train --model refid --refid-layout 4 1                 # REFID 4+1 frames
    python -m evlatcorr.train --model efnet --checkpoint default --finetune spatial   # corrector + EFNet
    python -m evlatcorr.train --model efnet --checkpoint default --data my_camera.aedat4 --crop 96 128

``--data PATH`` fine-tunes on a recording instead (any format :func:`evlatcorr.io.open_recording`
reads, any sensor size; see :class:`RecordingRestorationData`): its frames (pairs of consecutive
frames for REFID) as random crops, every ``--holdout``-th held out to validate, the contrast
threshold estimated for the recording (``--threshold auto``). It implies ``--finetune spatial``.
Recordings of real cameras have no sharp frames: the network is then frozen (a note says so) and
only the latency polynomial trains, by the self-supervised objective, whose value on the held-out
frames is printed before and after; the polynomial is saved as ``OUT/curve.pt`` (for
``evlatcorr deblur --correct spatial --curve``). With sharp frames the network trains by L1 on them
too. A path that does not exist or cannot be read, too few usable frames or nothing to train exits
with code 2 and a one-line message.

:class:`CorrectedRestorationModule` puts a latency corrector in front of an adapter and fine-tunes
both end to end on delayed events: the network by the supervised L1 loss when sharp frames exist,
the corrector's polynomial by the self-supervised ETF objective (Eq. 21), which needs no ground
truth (the networks' event representations bin events by hard time thresholds, so no useful
gradient reaches the latency through them).
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any, NoReturn

import lightning as L
import torch
import torch.nn.functional as F
from lightning.pytorch.utilities import rank_zero_only
from torch import Tensor, nn
from torch.utils.data import DataLoader, Dataset
from torchmetrics.image import PeakSignalNoiseRatio, StructuralSimilarityIndexMeasure

from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

__all__ = [
    "MODELS",
    "build_adapter",
    "checkpoint_name",
    "crop_frames",
    "collate_frames",
    "SimulatedRestorationData",
    "RecordingRestorationData",
    "has_truth",
    "RestorationModule",
    "CorrectedRestorationModule",
    "write_checkpoint_readme",
    "main",
]

#: model name -> task solved ("deblur": one blurry frame; "interpolation": two blurry frames).
MODELS = {"efnet": "deblur", "gem": "deblur", "refid": "interpolation"}


def build_adapter(model: str, checkpoint: str | None = None, clamp: bool = False,
                  refid_layout: tuple[int, int] = (4, 1)) -> nn.Module:
    """The adapter of ``model`` (``"efnet"``, ``"gem"`` or ``"refid"``), unclamped for training by default.

    Example:
        >>> build_adapter("refid", refid_layout=(4, 1)).net.img_chn
        12
    """
    from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter

    if model == "efnet":
        return EFNetAdapter(checkpoint=checkpoint, clamp=clamp)
    if model == "gem":
        return GEMAdapter(checkpoint=checkpoint, clamp=clamp)
    if model == "refid":
        m, n = refid_layout
        return REFIDAdapter(checkpoint=checkpoint, m=m, n=n, clamp=clamp)
    raise ValueError(f"unknown model {model!r}; choose from {sorted(MODELS)}")


def checkpoint_name(model: str, refid_layout: tuple[int, int] = (4, 1)) -> str:
    """The name the adapters look for with ``checkpoint="default"`` (``refid-4-1`` for REFID 4+1)."""
    if model == "refid":
        m, n = refid_layout
        return "refid" if (m, n) == (11, 1) else f"refid-{m}-{n}"
    return model


# --------------------------------------------------------------------------------------------------
# samples
# --------------------------------------------------------------------------------------------------
def crop_frames(frames: EventFrames, top: int, left: int, height: int, width: int,
                hflip: bool = False) -> EventFrames:
    """A spatial crop (optionally mirrored left-right) of every image and of the events.

    Events outside the crop are dropped; the rest keep their times and polarities. Per-pixel fields
    (``latency`` and ``meta["true_latency"]``) are cropped too; other ``meta`` entries are kept.

    Example:
        >>> ev = Events(torch.tensor([1, 3]), torch.tensor([0, 2]), torch.tensor([1.0, 2.0]), torch.ones(2),
        ...             sensor_size=(4, 4))
        >>> fr = EventFrames(torch.rand(1, 1, 4, 4), ev, torch.tensor([0.0]), torch.tensor([5.0]))
        >>> out = crop_frames(fr, 1, 2, 3, 2, hflip=True)
        >>> out.sensor_size, out.events.x.tolist(), out.events.y.tolist()
        ((3, 2), [0], [1])
    """
    h, w = frames.sensor_size
    if not (0 <= top and 0 <= left and height >= 1 and width >= 1 and top + height <= h and left + width <= w):
        raise ValueError(f"crop ({top}, {left}, {height}, {width}) does not fit in (H, W)=({h}, {w})")

    def image(t: Tensor | None) -> Tensor | None:
        if t is None:
            return None
        t = t[..., top:top + height, left:left + width]
        return (t.flip(-1) if hflip else t).contiguous()

    def events(ev: Events | None) -> Events | None:
        if ev is None:
            return None
        keep = (ev.x >= left) & (ev.x < left + width) & (ev.y >= top) & (ev.y < top + height)
        x = ev.x[keep] - left
        x = (width - 1 - x) if hflip else x
        return Events._trusted(x, ev.y[keep] - top, ev.t[keep], ev.p[keep], ev.batch[keep], (height, width),
                               ev.batch_size)

    meta = dict(frames.meta)
    for key in ("true_latency", "true_latency_next"):
        if isinstance(meta.get(key), Tensor):
            meta[key] = image(meta[key])
    return frames.replace(blurry=image(frames.blurry), events=events(frames.events),
                          corrected=events(frames.corrected), latency=image(frames.latency),
                          latent=image(frames.latent), sharp=image(frames.sharp),
                          blurry_next=image(frames.blurry_next), target_frames=image(frames.target_frames),
                          output=image(frames.output), meta=meta)


def _cat(values: list[Any]) -> Any:
    if all(v is None for v in values):
        return None
    if any(v is None for v in values):
        raise ValueError("cannot batch samples where a field is set on some and missing on others")
    return torch.cat(values)


def collate_frames(items: Sequence[EventFrames]) -> EventFrames:
    """Batch ``EventFrames`` samples of one size (every image field, events, exposures, targets).

    ``meta`` entries that are tensors with a batch dimension are concatenated; others are dropped.
    """
    if not items:
        raise ValueError("cannot collate an empty list of EventFrames")
    sizes = {x.sensor_size for x in items}
    if len(sizes) != 1:
        raise ValueError(f"samples must share one (H, W) to be batched, got {sorted(sizes)}; crop them first")
    fields = ("blurry", "exposure_start", "exposure_end", "latency", "latent", "sharp", "blurry_next",
              "exposure_start_next", "exposure_end_next", "target_times", "target_frames")
    kwargs = {f: _cat([getattr(x, f) for x in items]) for f in fields}
    corrected = None if items[0].corrected is None else Events.cat([x.corrected for x in items])
    meta = {}
    for key in ("true_latency", "true_latency_next"):
        if all(isinstance(x.meta.get(key), Tensor) for x in items):
            meta[key] = torch.cat([x.meta[key] for x in items])
    return EventFrames(events=Events.cat([x.events for x in items]), corrected=corrected, meta=meta, **kwargs)


class _Samples(Dataset):
    """Pairs (ideal, delayed) of one-sample batches, served as random crops or whole."""

    def __init__(self, samples: list[tuple[EventFrames, EventFrames]], events: str, crop: tuple[int, int] | None,
                 length: int | None = None) -> None:
        self.samples, self.events, self.crop = samples, events, crop
        self.length = length or len(samples)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> EventFrames:
        ideal, delayed = self.samples[index % len(self.samples)]
        if self.events == "mixed":
            frames = ideal if bool(torch.randint(2, ()).item()) else delayed
        else:
            frames = ideal if self.events == "ideal" else delayed
        if self.crop is None:
            return frames
        h, w = frames.sensor_size
        ch, cw = self.crop
        top = int(torch.randint(h - ch + 1, ()).item())
        left = int(torch.randint(w - cw + 1, ()).item())
        return crop_frames(frames, top, left, ch, cw, hflip=bool(torch.randint(2, ()).item()))


class _RestorationLoaders(L.LightningDataModule):
    """The data loaders both restoration data modules share (they fill ``train_set`` / ``val_set`` in setup)."""

    def train_dataloader(self) -> DataLoader:
        assert self.train_set is not None, "call setup() first"
        return DataLoader(self.train_set, batch_size=self.batch_size, shuffle=True, num_workers=self.num_workers,
                          collate_fn=collate_frames, persistent_workers=self.num_workers > 0)

    def val_dataloader(self) -> DataLoader:
        assert self.val_set is not None, "call setup() first"
        return DataLoader(self.val_set, batch_size=1, shuffle=False, num_workers=self.num_workers,
                          collate_fn=collate_frames)


class SimulatedRestorationData(_RestorationLoaders):
    """Training and validation samples simulated from the training photographs.

    Each photograph is simulated ``sequences`` times (different seeds, so different motions, thresholds
    and latencies) with ideal and delayed events; validation uses other seeds of the same photographs,
    so no test photograph (:data:`~evlatcorr.simulate.PHOTOGRAPHS_TEST`) is ever seen. Simulation is
    deterministic by ``seed`` (every DDP rank builds the same samples) and takes seconds.

    Args:
        task: ``"deblur"`` (one sample per frame, target the mid-exposure sharp frame) or
            ``"interpolation"`` (one sample per frame pair, targets at ``target_times``).
        photographs: photograph names to simulate.
        size: simulated (H, W).
        crop: training crop (H, W); validation uses whole frames.
        sequences: sequences per photograph for training.
        val_sequences: sequences per photograph for validation.
        num_frames: frames per sequence.
        exposure_us, interval_us: exposure time and frame interval, µs.
        latency_us: range of the constant latency drawn for each sequence's delayed events, µs.
        events: which events the samples carry: ``"ideal"`` (exact timestamps, as the networks were
            originally trained), ``"delayed"`` or ``"mixed"``.
        target_times: for interpolation, a function ``EventFrames -> (B, T)`` µs of the frames to
            supervise (e.g. REFID's output times); default the gap midpoint.
        batch_size, num_workers: data loading.
        steps_per_epoch: training batches per epoch (samples are drawn with random crops).
        seed: base seed.
    """

    def __init__(self, task: str = "deblur", photographs: Sequence[str] | None = None,
                 size: tuple[int, int] = (128, 160), crop: tuple[int, int] = (64, 64), sequences: int = 2,
                 val_sequences: int = 1, num_frames: int = 3, exposure_us: float = 20000.0,
                 interval_us: float = 25000.0, latency_us: tuple[float, float] = (1000.0, 8000.0),
                 events: str = "ideal", target_times: Any = None, batch_size: int = 4, num_workers: int = 0,
                 steps_per_epoch: int = 200, seed: int = 0) -> None:
        super().__init__()
        from evlatcorr.simulate import PHOTOGRAPHS_TRAIN

        if task not in ("deblur", "interpolation"):
            raise ValueError(f"task must be 'deblur' or 'interpolation', got {task!r}")
        if events not in ("ideal", "delayed", "mixed"):
            raise ValueError(f"events must be 'ideal', 'delayed' or 'mixed', got {events!r}")
        if crop[0] > size[0] or crop[1] > size[1]:
            raise ValueError(f"crop {tuple(crop)} is larger than the simulated size {tuple(size)}")
        if task == "interpolation" and num_frames < 2:
            raise ValueError("interpolation needs num_frames >= 2")
        self.task, self.photographs = task, list(photographs or PHOTOGRAPHS_TRAIN)
        self.size, self.crop = (int(size[0]), int(size[1])), (int(crop[0]), int(crop[1]))
        self.sequences, self.val_sequences, self.num_frames = sequences, val_sequences, num_frames
        self.exposure_us, self.interval_us, self.latency_us = exposure_us, interval_us, latency_us
        self.events, self.target_times = events, target_times
        self.batch_size, self.num_workers, self.steps_per_epoch, self.seed = (
            batch_size, num_workers, steps_per_epoch, seed)
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None

    def simulate(self, seeds: Sequence[int]) -> list[tuple[EventFrames, EventFrames]]:
        """(ideal, delayed) one-sample batches for every photograph and seed."""
        from evlatcorr.simulate import simulate

        samples = []
        for name_index, name in enumerate(self.photographs):
            for seed in seeds:
                g = torch.Generator().manual_seed(10_000 * seed + name_index)
                lo, hi = self.latency_us
                latency = lo + (hi - lo) * float(torch.rand((), generator=g))
                seq = simulate(name, num_frames=self.num_frames, height=self.size[0], width=self.size[1],
                               exposure_us=self.exposure_us, frame_interval_us=self.interval_us,
                               latency="constant", latency_us=latency, seed=10_000 * seed + name_index)
                if self.task == "deblur":
                    both = seq.frames("ideal"), seq.frames("delayed")
                else:
                    both = seq.pairs("ideal"), seq.pairs("delayed")
                    if self.target_times is not None:
                        times = self.target_times(both[0]).to(torch.float64)
                        frames = seq.render(times.flatten()).view(*times.shape, *seq.blurry.shape[1:])
                        both = tuple(b.replace(target_times=times, target_frames=frames) for b in both)
                for i in range(both[0].batch_size):
                    samples.append(tuple(_one(b, i) for b in both))
        return samples

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            base = 1000 * self.seed
            train = self.simulate([base + k for k in range(self.sequences)])
            val = self.simulate([base + 500 + k for k in range(self.val_sequences)])
            self.train_set = _Samples(train, self.events, self.crop, self.steps_per_epoch * self.batch_size)
            self.val_set = _Samples(val, self.events, None)



def has_truth(frames: EventFrames, task: str) -> bool:
    """Whether a batch carries the ground truth of ``task``: ``sharp`` (deblur) or ``target_frames``.

    Example:
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([1.0]), torch.ones(1), sensor_size=(2, 2))
        >>> fr = EventFrames(torch.rand(1, 1, 2, 2), ev, torch.tensor([0.0]), torch.tensor([5.0]))
        >>> has_truth(fr, "deblur"), has_truth(fr.replace(sharp=fr.blurry), "deblur")
        (False, True)
    """
    if task == "deblur":
        return frames.sharp is not None
    return frames.target_frames is not None and frames.target_times is not None


class _RecordingSamples(Dataset):
    """Random crops (mirrored at random) of whole-frame samples; a crop without events is drawn again."""

    def __init__(self, samples: list[EventFrames], crop: tuple[int, int], length: int, tries: int = 10) -> None:
        self.samples, self.crop, self.length, self.tries = samples, crop, length, tries

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int) -> EventFrames:
        from evlatcorr.restore import has_events

        frames = self.samples[index % len(self.samples)]
        h, w = frames.sensor_size
        ch, cw = self.crop
        for _ in range(self.tries):  # dark or static tiles of a real scene may hold no events
            top = int(torch.randint(h - ch + 1, ()).item())
            left = int(torch.randint(w - cw + 1, ()).item())
            out = crop_frames(frames, top, left, ch, cw, hflip=bool(torch.randint(2, ()).item()))
            if has_events(out):
                break
        return out


class RecordingRestorationData(_RestorationLoaders):
    """Training and validation samples from a recording (any format :func:`evlatcorr.io.open_recording` reads).

    Each frame (``"deblur"``) or pair of consecutive frames of one segment (``"interpolation"``; the first
    frame's events then reach the next exposure's end plus the latency searched,
    :func:`~evlatcorr.restore.pair_reach_us`) is one sample. Samples are left out when their exposure
    and latency-search window (0 to the exposure time past its end) hold no events, or when their
    event window runs past the last event of the recording (it stopped during the window). Every
    ``holdout``-th sample is held out for validation (the last one when there are fewer than
    ``holdout``); the others are served as random ``crop`` tiles, mirrored left-right at random, like
    :class:`SimulatedRestorationData`. Validation uses whole frames.

    Ground truth: deblurring uses the ``sharp`` frames; interpolation the recording's ``target_frames``
    or, failing those, the ``sharp`` frames of the pair's two frames at mid-exposure. It is kept only
    when every sample has it (:attr:`has_truth`), else dropped from all; real cameras record none.

    Args:
        path: the recording (a file or folder).
        task: ``"deblur"`` or ``"interpolation"``.
        crop: training crop (H, W); must fit the sensor.
        holdout: every this-many-th sample goes to validation (0: none).
        max_frames: read at most this many frames (None: all; bounds the memory on long recordings).
        batch_size, num_workers: data loading.
        steps_per_epoch: training batches per epoch.

    Example:
        >>> data = RecordingRestorationData("cradle_lowlight.aedat4", crop=(64, 64))  # doctest: +SKIP
        >>> data.read()  # doctest: +SKIP
        >>> len(data.train_samples), len(data.val_samples), data.has_truth  # doctest: +SKIP
        (11, 1, False)
    """

    #: a window counts as cut short when it ends this fraction of its length after the recording's last event
    COVERAGE_SLACK = 0.02

    def __init__(self, path: str | Path, task: str = "deblur", crop: tuple[int, int] = (64, 64), holdout: int = 10,
                 max_frames: int | None = None, batch_size: int = 4, num_workers: int = 0,
                 steps_per_epoch: int = 200) -> None:
        super().__init__()
        if task not in ("deblur", "interpolation"):
            raise ValueError(f"task must be 'deblur' or 'interpolation', got {task!r}")
        if len(crop) != 2 or min(crop) < 1:
            raise ValueError(f"crop must be two sizes (H, W) >= 1, got {tuple(crop)}")
        if holdout < 0:
            raise ValueError(f"holdout must be >= 0 (0: no validation), got {holdout}")
        if max_frames is not None and max_frames < 1:
            raise ValueError(f"max_frames must be >= 1 or None, got {max_frames}")
        if batch_size < 1 or steps_per_epoch < 1:
            raise ValueError(f"batch_size and steps_per_epoch must be >= 1, got {batch_size} and {steps_per_epoch}")
        self.path, self.task, self.crop = Path(path), task, (int(crop[0]), int(crop[1]))
        self.holdout, self.max_frames = holdout, max_frames
        self.batch_size, self.num_workers, self.steps_per_epoch = batch_size, num_workers, steps_per_epoch
        self.train_samples: list[EventFrames] = []
        self.val_samples: list[EventFrames] = []
        self.has_truth = False
        self.recording: Any = None
        #: what :meth:`read` found: frames read, samples used, left out and why
        self.summary: dict[str, Any] = {}
        self.train_set: Dataset | None = None
        self.val_set: Dataset | None = None

    @property
    def pairs(self) -> bool:
        return self.task == "interpolation"

    def read(self) -> None:
        """Read the recording into training and validation samples (once; every DDP rank reads the same).

        Raises:
            FileNotFoundError: the path does not exist.
            ValueError: (``RecordingError`` included) an unreadable recording, a crop larger than the
                sensor, or fewer usable samples than training and validation need.
        """
        from evlatcorr.io import open_recording
        from evlatcorr.restore import has_events, pair_frames, pair_reach_us

        if self.recording is not None:
            return
        rec = open_recording(self.path)
        h, w = rec.sensor_size
        if self.crop[0] > h or self.crop[1] > w:
            raise ValueError(f"crop {self.crop} does not fit the sensor of {self.path}, (H, W)=({h}, {w}); "
                             "pass a smaller --crop")
        if self.pairs:  # the first frame's events reach the next exposure's end plus the latency searched
            rec.after_us = pair_reach_us(rec)
        frames = list(itertools.islice(rec, self.max_frames))
        if self.pairs:
            nexts = [f for _, f in itertools.zip_longest(frames, frames[1:])]
            candidates = [(pair, nxt) for (_, pair), nxt in zip(pair_frames(frames), nexts)]
        else:
            candidates = [(f, None) for f in frames]
        last_event: dict[int, float] = {}
        for f in frames:
            if len(f.events):
                segment = f.meta.get("segment", 0)
                last_event[segment] = max(last_event.get(segment, -math.inf), float(f.events.t[-1]))
        samples, no_next, no_events, cut = [], 0, 0, []
        for sample, nxt in candidates:
            if sample is None:
                no_next += 1
                continue
            lo, hi = sample.meta["window_us"]
            if hi - last_event.get(sample.meta.get("segment", 0), -math.inf) > self.COVERAGE_SLACK * (hi - lo):
                cut.append(sample.meta["frame"])
                continue
            if not has_events(sample):
                no_events += 1
                continue
            samples.append(self._truth(sample, nxt))
        self.has_truth = bool(samples) and all(has_truth(s, self.task) for s in samples)
        with_truth = sum(has_truth(s, self.task) for s in samples)
        if not self.has_truth:
            samples = [s.replace(sharp=None, target_times=None, target_frames=None) for s in samples]
        what = "pairs of consecutive frames" if self.pairs else "frames"
        need = 2 if self.holdout else 1
        if len(samples) < need:
            reasons = [f"{len(frames)} frames read"]
            if no_next:
                reasons.append(f"{no_next} without a next frame of their segment")
            if no_events:
                reasons.append(f"{no_events} without events in the exposure and latency-search window")
            if cut:
                reasons.append(f"{len(cut)} whose event window runs past the end of the events")
            raise ValueError(f"{self.path}: usable {what}: {len(samples)} ({', '.join(reasons)}); fine-tuning needs "
                             f"at least {need}" + (" (one to train, one held out for validation; --holdout 0 "
                                                   "validates on none)" if self.holdout else ""))
        val_index = set(range(self.holdout - 1, len(samples), self.holdout)) if self.holdout else set()
        if self.holdout and not val_index:
            val_index = {len(samples) - 1}
        if len(val_index) == len(samples):
            raise ValueError(f"holdout {self.holdout} holds out all {len(samples)} usable {what}, leaving none "
                             "to train on; pass a larger --holdout")
        self.val_samples = [s for i, s in enumerate(samples) if i in val_index]
        self.train_samples = [s for i, s in enumerate(samples) if i not in val_index]
        self.recording = rec
        self.summary = {"format": rec.format_name, "sensor_size": [h, w], "frames_read": len(frames),
                        "samples": len(samples), "train": len(self.train_samples), "val": len(self.val_samples),
                        "samples_with_truth": int(with_truth), "left_out_no_events": no_events,
                        "left_out_cut_short": cut, "left_out_no_next": no_next, "pairs": self.pairs}

    def _truth(self, sample: EventFrames, nxt: EventFrames | None) -> EventFrames:
        """Interpolation targets from the pair's sharp frames when the recording has no target frames."""
        if not self.pairs:
            return sample.replace(target_times=None, target_frames=None)
        if sample.target_frames is not None or sample.sharp is None or nxt is None or nxt.sharp is None:
            return sample
        mid = torch.stack([(sample.exposure_start + sample.exposure_end) / 2,
                           (nxt.exposure_start + nxt.exposure_end) / 2], dim=1)
        return sample.replace(target_times=mid, target_frames=torch.stack([sample.sharp, nxt.sharp], dim=1))

    def setup(self, stage: str | None = None) -> None:
        self.read()
        if self.train_set is None:
            self.train_set = _RecordingSamples(self.train_samples, self.crop, self.steps_per_epoch * self.batch_size)
            self.val_set = _ListSamples(self.val_samples)



class _ListSamples(Dataset):
    def __init__(self, samples: list[EventFrames]) -> None:
        self.samples = samples

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> EventFrames:
        return self.samples[index]


def _one(frames: EventFrames, i: int) -> EventFrames:
    """Sample ``i`` of a batch as a one-sample batch."""
    def pick(t: Tensor | None) -> Tensor | None:
        return None if t is None else t[i:i + 1].clone()

    meta = {k: pick(v) for k, v in frames.meta.items() if k in ("true_latency", "true_latency_next")}
    return EventFrames(pick(frames.blurry), frames.events.sample(i), pick(frames.exposure_start),
                       pick(frames.exposure_end), sharp=pick(frames.sharp), blurry_next=pick(frames.blurry_next),
                       exposure_start_next=pick(frames.exposure_start_next),
                       exposure_end_next=pick(frames.exposure_end_next), target_times=pick(frames.target_times),
                       target_frames=pick(frames.target_frames), meta=meta)


# --------------------------------------------------------------------------------------------------
# modules
# --------------------------------------------------------------------------------------------------
def restoration_pair(output: EventFrames, task: str) -> tuple[Tensor, Tensor] | None:
    """(prediction, target) of an adapter's output, or None when the batch has no ground truth.

    Deblurring compares ``output`` with ``sharp``. Interpolation compares with ``target_frames``: an
    output with one frame per target time is compared frame by frame; an output with its own times
    (``meta["output_times"]``, REFID) is compared at the output frame nearest each target time.
    """
    pred = output.output
    if pred is None:
        raise ValueError("the model did not fill frames.output")
    if task == "deblur":
        return None if output.sharp is None else (pred, output.sharp)
    if output.target_frames is None or output.target_times is None:
        return None
    if pred.dim() == 5 and pred.shape[1] != output.target_times.shape[1]:
        times = output.meta["output_times"].to(output.target_times)
        index = (times[:, None, :] - output.target_times[:, :, None]).abs().argmin(-1)
        pred = torch.stack([pred[b, index[b]] for b in range(pred.shape[0])])
    return pred, output.target_frames


class _RestorationBase(L.LightningModule):
    """Shared optimisation and validation of the restoration modules."""

    def __init__(self, task: str, lr: float, weight_decay: float, warmup_steps: int, max_steps: int) -> None:
        super().__init__()
        if task not in ("deblur", "interpolation"):
            raise ValueError(f"task must be 'deblur' or 'interpolation', got {task!r}")
        if lr <= 0 or warmup_steps < 0 or max_steps < 1:
            raise ValueError("lr must be > 0, warmup_steps >= 0 and max_steps >= 1")
        self.task = task
        self.val_psnr = PeakSignalNoiseRatio(data_range=1.0)
        self.val_ssim = StructuralSimilarityIndexMeasure(data_range=1.0)
        self.val_input_psnr = PeakSignalNoiseRatio(data_range=1.0)

    def transfer_batch_to_device(self, batch: Any, device: torch.device, dataloader_idx: int) -> Any:
        return batch.to(device) if isinstance(batch, EventFrames) else super().transfer_batch_to_device(
            batch, device, dataloader_idx)

    def _validate(self, batch: EventFrames, output: EventFrames) -> None:
        pair = restoration_pair(output, self.task)
        if pair is None:
            return
        pred, target = pair
        pred, target = pred.float().clamp(0, 1).flatten(0, -4), target.float().flatten(0, -4)
        self.val_psnr.update(pred, target)
        self.val_ssim.update(pred, target)
        # the blurry frame itself (the left one for interpolation) as a baseline
        blurry = batch.blurry.float()
        if target.shape[0] != blurry.shape[0]:
            blurry = blurry.repeat_interleave(target.shape[0] // blurry.shape[0], 0)
        self.val_input_psnr.update(blurry, target)
        kw = dict(batch_size=batch.batch_size, on_epoch=True, sync_dist=True)
        self.log("val/psnr", self.val_psnr, prog_bar=True, **kw)
        self.log("val/ssim", self.val_ssim, **kw)
        self.log("val/blurry_psnr", self.val_input_psnr, **kw)

    def configure_optimizers(self):
        hp = self.hparams
        optimiser = torch.optim.AdamW(self.param_groups(), lr=hp.lr, weight_decay=hp.weight_decay, betas=(0.9, 0.99))

        def factor(step: int) -> float:  # linear warm-up, then cosine decay to 1 % at max_steps
            if step < hp.warmup_steps:
                return (step + 1) / hp.warmup_steps
            progress = min(1.0, (step - hp.warmup_steps) / max(1, hp.max_steps - hp.warmup_steps))
            return 0.01 + 0.99 * 0.5 * (1.0 + math.cos(math.pi * progress))

        scheduler = torch.optim.lr_scheduler.LambdaLR(optimiser, factor)
        return {"optimizer": optimiser, "lr_scheduler": {"scheduler": scheduler, "interval": "step"}}

    def param_groups(self) -> list[dict[str, Any]]:
        return [{"params": [p for p in self.parameters() if p.requires_grad]}]


class RestorationModule(_RestorationBase):
    """An adapter's network trained with L1 loss on simulated frames.

    Args:
        model: ``"efnet"``, ``"gem"`` or ``"refid"`` (see :data:`MODELS`).
        checkpoint: initial weights (``None``: random; ``"default"``; a path), see the adapters.
        lr: AdamW learning rate (peak, after ``warmup_steps``; cosine decay to 1 % at ``max_steps``).
        weight_decay: AdamW weight decay.
        warmup_steps, max_steps: learning-rate schedule, in optimiser steps.
        refid_layout: REFID's ``(m, n)``: ``m`` sharp frames per exposure, ``n`` in the gap.

    Example:
        >>> module = RestorationModule("efnet")
        >>> module.task, type(module.adapter).__name__
        ('deblur', 'EFNetAdapter')
    """

    def __init__(self, model: str = "efnet", checkpoint: str | None = None, lr: float = 2e-4,
                 weight_decay: float = 1e-4, warmup_steps: int = 100, max_steps: int = 2000,
                 refid_layout: tuple[int, int] = (4, 1)) -> None:
        if model not in MODELS:
            raise ValueError(f"unknown model {model!r}; choose from {sorted(MODELS)}")
        super().__init__(MODELS[model], lr, weight_decay, warmup_steps, max_steps)
        self.save_hyperparameters()
        self.adapter = build_adapter(model, checkpoint, clamp=False, refid_layout=tuple(refid_layout))

    def forward(self, frames: EventFrames) -> EventFrames:
        return self.adapter(frames)

    def training_step(self, batch: EventFrames, batch_idx: int) -> Tensor:
        pair = restoration_pair(self(batch), self.task)
        if pair is None:
            raise ValueError("training batches need ground truth (sharp or target_frames)")
        loss = F.l1_loss(pair[0].float(), pair[1].float())
        self.log("train/l1", loss, prog_bar=True, batch_size=batch.batch_size)
        return loss

    def validation_step(self, batch: EventFrames, batch_idx: int) -> None:
        self._validate(batch, self(batch))


class CorrectedRestorationModule(_RestorationBase):
    """A latency corrector in front of an adapter, fine-tuned end to end on delayed events.

    The corrector is a :class:`~evlatcorr.spatial.PolynomialLatency` of the blurry frame's intensity
    (``"spatial"``, trainable) or the one-pass constant search (``"constant"``, no parameters). Each
    step corrects the batch's events with the current latency map and runs the adapter on them.

    - Supervised (the batch has ``sharp`` or ``target_frames``): the network is trained by L1 loss on
      its output from the corrected events.
    - The polynomial is trained by the self-supervised objective of Eq. (21) (ETF of the
      latency-differentiable EDI, bound, MSE to ``l_const`` and deviation terms), which needs no
      ground truth: on batches without sharp frames this is the only loss ("ETF-only").

    Args:
        adapter: any adapter (``nn.Module`` taking and returning ``EventFrames``).
        task: ``"deblur"`` or ``"interpolation"`` (what the adapter does).
        corrector: ``"spatial"`` or ``"constant"``.
        curve: initial polynomial (path of a saved curve or Lightning checkpoint), spatial only.
        train_corrector: optimise the polynomial.
        train_network: optimise the adapter's parameters.
        corrector_weight: weight of the corrector's objective in the total loss.
        lr, corrector_lr: learning rates of the network and of the polynomial.
        threshold, num_bins: contrast threshold and EDI sub-intervals of the correction.

    Example:
        >>> from evlatcorr.adapters import EFNetAdapter
        >>> module = CorrectedRestorationModule(EFNetAdapter(), "deblur", train_network=False)
        >>> sum(p.requires_grad for p in module.parameters())
        1
    """

    def __init__(self, adapter: nn.Module, task: str, corrector: str = "spatial", curve: str | Path | None = None,
                 train_corrector: bool = True, train_network: bool = True, corrector_weight: float = 1.0,
                 lr: float = 5e-5, corrector_lr: float = 0.02, weight_decay: float = 0.0, warmup_steps: int = 0,
                 max_steps: int = 1000, threshold: float = 0.2, num_bins: int = 100) -> None:
        super().__init__(task, lr, weight_decay, warmup_steps, max_steps)
        from evlatcorr.spatial import LossWeights, PolynomialLatency, load_curve

        if corrector not in ("spatial", "constant"):
            raise ValueError(f"corrector must be 'spatial' or 'constant', got {corrector!r}")
        if corrector == "constant" and train_corrector:
            train_corrector = False  # nothing to train: the constant is searched per frame
        if not (train_corrector or train_network):
            raise ValueError("nothing to train: set train_corrector and/or train_network")
        self.save_hyperparameters(ignore=["adapter"])
        self.adapter = adapter
        self.latency_model = load_curve(curve) if curve is not None else PolynomialLatency()
        self.weights = LossWeights()
        self.adapter.requires_grad_(train_network)
        self.latency_model.requires_grad_(train_corrector)

    def correct(self, frames: EventFrames) -> tuple[EventFrames, Tensor | None]:
        """``frames`` with ``corrected`` events and ``latency``, and the corrector's loss (or None)."""
        from evlatcorr.benchmark import pair_with_latency
        from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
        from evlatcorr.search import search_constant_latency
        from evlatcorr.spatial import constant_reference, spatial_objective

        hp = self.hparams
        first = EventFrames(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end)
        loss = None
        if hp.corrector == "constant":
            latency = search_constant_latency(first.blurry, first.events, first.exposure_start, first.exposure_end,
                                              hp.threshold, hp.num_bins).latency
            latency = latency.to(frames.blurry).view(-1, 1, 1, 1).expand(-1, 1, *frames.sensor_size).contiguous()
            latency_next = latency
        else:
            high = frames.exposure_time.to(frames.blurry).view(-1, 1, 1, 1)
            if hp.train_corrector:
                with torch.enable_grad():
                    l_const, etf_const = constant_reference(first, hp.threshold, hp.num_bins, None, 100,
                                                            DEFAULT_EPSILON, DEFAULT_WINDOW, DEFAULT_SIGMA_US)
                    terms = spatial_objective(self.latency_model, first, l_const, first.exposure_time, etf_const,
                                              hp.threshold, hp.num_bins, self.weights)
                loss = terms["total"]
            latency = torch.minimum(self.latency_model(frames.blurry).clamp_min(0.0), high).detach()
            latency_next = latency if frames.blurry_next is None else torch.minimum(
                self.latency_model(frames.blurry_next).clamp_min(0.0), high).detach()
        if self.task == "interpolation":
            corrected = pair_with_latency(frames, latency.double(), latency_next.double())
            return corrected.replace(latency=latency), loss
        return frames.replace(corrected=frames.events.shift(latency.double()), latency=latency), loss

    def forward(self, frames: EventFrames) -> EventFrames:
        corrected, _ = self.correct(frames)
        return self.adapter(corrected)

    def training_step(self, batch: EventFrames, batch_idx: int) -> Tensor:
        corrected, corrector_loss = self.correct(batch)
        total = torch.zeros((), device=batch.device)
        if self.hparams.train_network:
            pair = restoration_pair(self.adapter(corrected), self.task)
            if pair is not None:
                l1 = F.l1_loss(pair[0].float(), pair[1].float())
                self.log("train/l1", l1, prog_bar=True, batch_size=batch.batch_size)
                total = total + l1
        if corrector_loss is not None:
            self.log("train/corrector", corrector_loss, batch_size=batch.batch_size)
            total = total + self.hparams.corrector_weight * corrector_loss
        if not total.requires_grad:  # e.g. network-only training on a batch without ground truth
            total = sum(p.sum() * 0.0 for p in self.parameters() if p.requires_grad)
        return total

    def validation_step(self, batch: EventFrames, batch_idx: int) -> None:
        corrected, corrector_loss = self.correct(batch)
        if corrector_loss is not None:  # the self-supervised objective (Eq. 21) on held-out frames
            self.log("val/corrector", corrector_loss, batch_size=batch.batch_size, on_epoch=True, sync_dist=True,
                     prog_bar=True)
        if has_truth(batch, self.task):  # without ground truth the network's output has nothing to be scored on
            self._validate(batch, self.adapter(corrected))

    def param_groups(self) -> list[dict[str, Any]]:
        # the polynomial's 6 coefficients (ms) take a much larger step than the network's weights
        network = [p for p in self.adapter.parameters() if p.requires_grad]
        poly = [p for p in self.latency_model.parameters() if p.requires_grad]
        groups = [{"params": network}] if network else []
        if poly:
            groups.append({"params": poly, "lr": self.hparams.corrector_lr, "weight_decay": 0.0})
        return groups


# --------------------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """Bad arguments: one line on stderr and exit code 2 (the usage is long; ``--help`` shows it)."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message} (see --help)\n")


def _threshold(text: str) -> float | str:
    """``--threshold``: ``auto`` or a positive number."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a positive number or 'auto', got {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number or 'auto', got {text!r}")
    return value


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    p = _Parser(prog="python -m evlatcorr.train", description=__doc__,
                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", choices=sorted(MODELS), required=True)
    p.add_argument("--checkpoint", help="initial weights: 'default' (shipped) or a path; default random")
    p.add_argument("--data", type=Path, default=None, metavar="PATH",
                   help="train on this recording instead of simulated photographs: any format evlatcorr.io reads "
                        "(AEDAT4, our HDF5, event_utils HDF5, GEM npz, a HighREV folder), any sensor size. Implies "
                        "--finetune spatial. Without ground truth (sharp frames; real cameras record none) the "
                        "network is frozen and only the latency polynomial trains, by the self-supervised "
                        "objective (Eq. 21); with sharp frames the network trains by L1 on them too")
    p.add_argument("--finetune", choices=("none", "constant", "spatial"), default=None,
                   help="put a corrector in front and fine-tune on delayed events (CorrectedRestorationModule); "
                        "default: none on simulated data, spatial with --data")
    p.add_argument("--freeze-network", action="store_true", help="with --finetune spatial: train the polynomial only")
    p.add_argument("--curve", type=Path, default=None,
                   help="with --finetune spatial: initial latency polynomial (a curve.pt or checkpoint of "
                        "python -m evlatcorr.training); default zero latency")
    p.add_argument("--threshold", type=_threshold, default="auto",
                   help="contrast threshold of the correction: a number, or 'auto' (default): with --data one "
                        "threshold estimated for the recording (evlatcorr.restore.recording_threshold, printed), "
                        "on simulated data 0.2")
    p.add_argument("--holdout", type=int, default=10,
                   help="--data: every K-th usable frame (pair for REFID) is held out for validation, at least one "
                        "(0: none)")
    p.add_argument("--max-frames", type=int, default=None, help="--data: read at most this many frames")
    p.add_argument("--events", choices=("ideal", "delayed", "mixed"), default=None,
                   help="simulated data: events of the training samples (default: ideal; delayed with --finetune)")
    p.add_argument("--max-steps", type=int, default=2000)
    p.add_argument("--max-time", default=None, help="stop after this wall time, DD:HH:MM:SS")
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--crop", type=int, nargs=2, default=(64, 64), metavar=("H", "W"),
                   help="training crop (random position, mirrored at random); validation uses whole frames")
    p.add_argument("--size", type=int, nargs=2, default=(128, 160), metavar=("H", "W"), help="simulated size")
    p.add_argument("--photographs", nargs="+", default=None, help="training photographs (default: the training "
                   "split, disjoint from the benchmark's test photographs)")
    p.add_argument("--allow-test-photographs", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--sequences", type=int, default=2, help="simulated training sequences per photograph")
    p.add_argument("--num-frames", type=int, default=3, help="frames per simulated sequence")
    p.add_argument("--lr", type=float, default=None,
                   help="network learning rate, default 2e-4 (5e-5 when fine-tuning or with --data)")
    p.add_argument("--warmup-steps", type=int, default=100)
    p.add_argument("--gradient-clip", type=float, default=None, help="clip the gradient norm (REFID: 0.5)")
    p.add_argument("--refid-layout", type=int, nargs=2, default=(4, 1), metavar=("M", "N"),
                   help="REFID sharp frames per exposure and in the gap (4 1 fits 20 ms exposures 25 ms apart)")
    p.add_argument("--val-every", type=int, default=200, help="validate every N training steps")
    p.add_argument("--accelerator", default="auto")
    p.add_argument("--devices", default="1")
    p.add_argument("--strategy", default="auto")
    p.add_argument("--precision", default=None, help="default bf16-mixed on GPU, 32-true on CPU")
    p.add_argument("--num-workers", type=int, default=0)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/train"))
    p.add_argument("--resume", default=None, help="'last' or a .ckpt path")
    p.add_argument("--export", type=Path, default=None, help="folder for the fp16 safetensors of the network")
    args = p.parse_args(argv)
    if args.max_steps < 1 or args.batch_size < 1 or args.val_every < 1:
        p.error("--max-steps, --batch-size and --val-every must be >= 1")
    if min(args.crop) < 1:
        p.error(f"--crop must be two sizes >= 1, got {list(args.crop)}")
    if args.holdout < 0:
        p.error(f"--holdout must be >= 0 (0: no validation), got {args.holdout}")
    if args.max_frames is not None and args.max_frames < 1:
        p.error(f"--max-frames must be >= 1, got {args.max_frames}")
    if args.finetune is None:
        args.finetune = "spatial" if args.data is not None else "none"
    if args.data is not None and (args.photographs or args.events):
        p.error("--photographs and --events choose simulated data; --data trains on the recording's events as "
                "stamped")
    from evlatcorr.simulate import PHOTOGRAPHS_TEST

    leaked = sorted(set(args.photographs or ()) & set(PHOTOGRAPHS_TEST))
    if leaked and not args.allow_test_photographs:
        p.error(f"{leaked} belong to the benchmark's test split; training on them would inflate its scores")
    if args.freeze_network and args.finetune != "spatial":
        p.error("--freeze-network needs --finetune spatial (otherwise nothing is trained)")
    if args.curve is not None and args.finetune != "spatial":
        p.error("--curve needs --finetune spatial (the polynomial it starts)")
    return args


def write_checkpoint_readme(folder: str | Path) -> Path:
    """Render the JSON cards of a checkpoint folder (written by ``--export``) as its ``README.md``."""
    folder = Path(folder)
    cards = [json.loads(p.read_text()) for p in sorted(folder.glob("*.json")) if not p.name.endswith(".index.json")]
    lines = [
        "# Shipped weights",
        "",
        "Trained here by `python -m evlatcorr.train` on the simulator's training photographs "
        "(`evlatcorr.simulate.PHOTOGRAPHS_TRAIN`, disjoint from the benchmark's test photographs), ideal events, "
        "L1 loss; validated on other simulated sequences of the same training photographs. fp16 safetensors, "
        "sharded at 15 MB; the adapters load them with `checkpoint=\"default\"` "
        "(REFID: `REFIDAdapter(checkpoint=\"default\", m=4, n=1)`). Each `<name>.json` holds every detail.",
        "",
        "Each card lists the SHA-256 of its weight files under `sha256`; every load checks them (a corrupt or "
        "modified file raises a ValueError naming it). `pip install .` installs this folder as "
        "`evlatcorr/checkpoints/`, where `checkpoint=\"default\"` finds it.",
        "",
        "| name | model | steps | train time | device | val PSNR (blurry input) | val SSIM | files |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for c in cards:
        lines.append(f"| {c['name']} | {c['model']} | {c['steps']} | {c['train_seconds'] / 60:.0f} min | "
                     f"{c['device']} | {c['val_psnr']:.2f} dB ({c['val_blurry_psnr']:.2f} dB) | {c['val_ssim']:.3f} | "
                     f"{len(c.get('files', []))} |")
    # Data settings shared by every card once, then what differs per checkpoint.
    shared = {k: v for k, v in cards[0]["data"].items() if all(c["data"].get(k) == v for c in cards)} if cards else {}
    lines += ["", "Data: " + ", ".join(f"{k}={v}" for k, v in shared.items()), ""]
    for c in cards:
        own = {k: v for k, v in c["data"].items() if k not in shared}
        if own:
            lines.append(f"- {c['name']}: " + ", ".join(f"{k}={v}" for k, v in own.items()))
        if c.get("note"):
            lines.append(f"- {c['name']}: {c['note']}")
    lines += ["", "Commands, in order (run from the repository root):", ""]
    for c in cards:
        for command in c.get("commands", [c["command"]]):
            lines.append(f"    {command}")
    path = folder / "README.md"
    path.write_text("\n".join(lines) + "\n")
    return path


def _precision(args: argparse.Namespace) -> str:
    if args.precision is not None:
        return args.precision
    gpu = args.accelerator in ("gpu", "cuda") or (args.accelerator == "auto" and torch.cuda.is_available())
    return "bf16-mixed" if gpu else "32-true"


@rank_zero_only
def _note(message: str) -> None:
    """A line for the user, printed once (by the first process under DDP)."""
    print(message, flush=True)


def _resume_path(args: argparse.Namespace) -> Path | None:
    if args.resume == "last":
        resume = args.out / "checkpoints" / "last.ckpt"
        if not resume.is_file():
            raise ValueError(f"--resume last, but {resume} does not exist")
        return resume
    if args.resume:
        resume = Path(args.resume)
        if not resume.is_file():
            raise ValueError(f"--resume: checkpoint {resume} not found")
        return resume
    return None


def _refid_targets(args: argparse.Namespace) -> Any:
    if args.model != "refid":
        return None
    from evlatcorr.adapters.refid import refid_output_times

    m, n = args.refid_layout

    def target_times(frames: EventFrames) -> Tensor:  # supervise every REFID output frame
        return refid_output_times(frames, m, n)

    return target_times


def _corrected_module(args: argparse.Namespace, task: str, train_network: bool, threshold: float,
                      adapter: nn.Module | None = None) -> CorrectedRestorationModule:
    if adapter is None:
        adapter = build_adapter(args.model, args.checkpoint, clamp=False, refid_layout=tuple(args.refid_layout))
    return CorrectedRestorationModule(
        adapter, task, corrector=args.finetune, curve=args.curve, train_network=train_network,
        lr=args.lr or 5e-5, warmup_steps=min(args.warmup_steps, args.max_steps - 1), max_steps=args.max_steps,
        threshold=threshold)


def _simulated_setup(args: argparse.Namespace) -> tuple[L.LightningDataModule, L.LightningModule, dict[str, Any]]:
    """Data and module for training on the simulator's training photographs."""
    task = MODELS[args.model]
    finetune = args.finetune != "none"
    events = args.events or ("delayed" if finetune else "ideal")
    data = SimulatedRestorationData(task, photographs=args.photographs, size=tuple(args.size), crop=tuple(args.crop),
                                    sequences=args.sequences, num_frames=args.num_frames, events=events,
                                    target_times=_refid_targets(args), batch_size=args.batch_size,
                                    num_workers=args.num_workers, steps_per_epoch=min(args.val_every, args.max_steps),
                                    seed=args.seed)
    if finetune:
        threshold = 0.2 if args.threshold == "auto" else float(args.threshold)
        module: L.LightningModule = _corrected_module(args, task, not args.freeze_network, threshold)
    else:
        module = RestorationModule(args.model, args.checkpoint, lr=args.lr or 2e-4,
                                   warmup_steps=min(args.warmup_steps, args.max_steps - 1),
                                   max_steps=args.max_steps, refid_layout=tuple(args.refid_layout))
    info = {"events": events, "truth": True, "network": "trained" if not args.freeze_network else "frozen",
            "data": {"photographs": data.photographs, "size": list(data.size), "crop": list(data.crop),
                     "sequences": data.sequences, "num_frames": data.num_frames, "exposure_us": data.exposure_us,
                     "interval_us": data.interval_us, "latency_us": list(data.latency_us), "seed": args.seed}}
    return data, module, info


def _threshold_device(args: argparse.Namespace) -> str:
    """Where to estimate the threshold: the current GPU when training runs on GPUs, else the CPU."""
    gpu = args.accelerator in ("gpu", "cuda") or (args.accelerator == "auto" and torch.cuda.is_available())
    return "cuda" if gpu and torch.cuda.is_available() else "cpu"


def _recording_setup(args: argparse.Namespace) -> tuple[L.LightningDataModule, L.LightningModule, dict[str, Any]]:
    """``--data``: samples from the recording; the network trains only where it has ground truth."""
    from evlatcorr.restore import recording_threshold

    task = MODELS[args.model]
    adapter = None
    if args.finetune != "none":  # weights that do not load fail before the recording is read
        adapter = build_adapter(args.model, args.checkpoint, clamp=False, refid_layout=tuple(args.refid_layout))
    data = RecordingRestorationData(args.data, task, tuple(args.crop), args.holdout, args.max_frames,
                                    args.batch_size, args.num_workers,
                                    steps_per_epoch=min(args.val_every, args.max_steps))
    data.read()
    found = data.summary
    what = "pairs of consecutive frames" if data.pairs else "frames"
    left = [f"{found['left_out_no_events']} without events in the exposure and latency-search window"] \
        if found["left_out_no_events"] else []
    if found["left_out_cut_short"]:
        left.append(f"frame(s) {found['left_out_cut_short']}, whose event window runs past the end of the events")
    _note(f"{args.data}: {found['format']}, (H, W)={tuple(found['sensor_size'])}, {found['frames_read']} frames read; "
          f"{found['train']} {what} to train on (random {args.crop[0]}x{args.crop[1]} crops), {found['val']} held out "
          f"for validation" + (f"; left out: {'; '.join(left)}" if left else ""))
    truth = "sharp frames" if task == "deblur" else "target frames (or sharp frames)"
    if not data.has_truth and found["samples_with_truth"]:
        _note(f"only {found['samples_with_truth']} of {found['samples']} samples have {truth}: they are ignored")
    # what trains, decided (and refused) before the threshold is estimated
    if args.finetune == "none":
        if not data.has_truth:
            raise ValueError(f"{args.data} has no {truth}, so --finetune none has nothing to train {args.model} on; "
                             "use --finetune spatial (the default with --data) to train the latency polynomial")
        network = "trained"
    else:
        network = "trained" if data.has_truth and not args.freeze_network else "frozen"
        if not data.has_truth and args.finetune == "constant":
            raise ValueError(f"nothing to train: {args.data} has no {truth}, so {args.model} stays frozen, and "
                             "--finetune constant has no parameters (it searches one latency per frame); use "
                             "--finetune spatial")
    if args.export is not None and network == "frozen":
        raise ValueError(f"--export writes the network's weights, but {args.model} stays frozen on {args.data}; "
                         f"the trained latency polynomial is saved as {args.out / 'curve.pt'}")
    if not data.has_truth:
        _note(f"note: {args.data} has no {truth}: {args.model} is frozen (its weights are not changed) and only "
              "the latency polynomial trains, by the self-supervised objective (Eq. 21)")
    elif network == "trained":
        _note(f"{args.data} has {truth}: {args.model} trains by L1 on them" + (
            ", the latency polynomial by the self-supervised objective (Eq. 21)" if args.finetune == "spatial" else ""))
    threshold = 0.2
    if args.finetune != "none":
        if args.threshold == "auto":
            with warnings.catch_warnings():  # the reader's notes on windows were given by the read above
                warnings.simplefilter("ignore")
                estimated = recording_threshold(data.recording, device=_threshold_device(args))
            if estimated is None:
                _note("contrast threshold: 0.2 (auto: no pair of consecutive frames with events to estimate one)")
            else:
                threshold = float(estimated)
                _note(f"contrast threshold: {threshold:.3f} (auto: two-frame consistency of the first frames)")
        else:
            threshold = float(args.threshold)
    if args.finetune == "none":
        module: L.LightningModule = RestorationModule(
            args.model, args.checkpoint, lr=args.lr or 5e-5, warmup_steps=min(args.warmup_steps, args.max_steps - 1),
            max_steps=args.max_steps, refid_layout=tuple(args.refid_layout))
    else:
        module = _corrected_module(args, task, network == "trained", threshold, adapter)
    info = {"events": "recorded", "truth": data.has_truth, "network": network,
            "threshold": None if args.finetune == "none" else round(threshold, 4),
            "data": {"recording": str(args.data), **{k: found[k] for k in ("format", "sensor_size", "frames_read")},
                     "crop": list(data.crop), "train_samples": found["train"], "val_samples": found["val"],
                     "pairs": data.pairs, "holdout": args.holdout, "max_frames": args.max_frames, "seed": args.seed}}
    return data, module, info


def _metric(metrics: dict[str, Any], key: str, digits: int) -> float | None:
    return round(float(metrics[key]), digits) if key in metrics else None


def main(argv: Sequence[str] | None = None) -> dict[str, Any]:
    """Run the command line; returns the card (validation metrics, steps, configuration).

    Bad input (a missing or unreadable recording, too few usable frames, a checkpoint that does not
    fit, nothing to train) prints one line on stderr and exits with code 2, like bad arguments.
    """
    from lightning.pytorch.callbacks import ModelCheckpoint

    args = parse_args(argv)
    L.seed_everything(args.seed, workers=True)
    try:
        resume = _resume_path(args)
        data, module, info = _recording_setup(args) if args.data is not None else _simulated_setup(args)
    except (ValueError, OSError) as exc:  # RecordingError is a ValueError; FileNotFoundError an OSError
        print(f"evlatcorr.train: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    task = MODELS[args.model]
    layout = tuple(args.refid_layout)
    has_val = args.data is None or bool(data.val_samples)
    if info["truth"]:
        monitor, mode = "val/psnr", "max"
    elif has_val:
        monitor, mode = "val/corrector", "min"
    else:
        monitor, mode = None, "min"
    checkpointing = ModelCheckpoint(dirpath=args.out / "checkpoints", save_last=True, monitor=monitor, mode=mode,
                                    save_top_k=1, filename="best-{step}")
    devices: int | str = int(args.devices) if str(args.devices).isdigit() else args.devices
    trainer = L.Trainer(max_steps=args.max_steps, max_time=args.max_time, max_epochs=-1,
                        accelerator=args.accelerator, devices=devices, strategy=args.strategy,
                        precision=_precision(args), default_root_dir=args.out, callbacks=[checkpointing],
                        gradient_clip_val=args.gradient_clip, limit_val_batches=None if has_val else 0,
                        log_every_n_steps=10, enable_model_summary=False, num_sanity_val_steps=0,
                        inference_mode=False)  # no_grad: metric states of a validation before fit stay trainable
    before: dict[str, Any] = {}
    if args.data is not None and has_val:  # the held-out objective of the starting point
        before = trainer.validate(module, data, ckpt_path=resume, verbose=False)[0]
    start = time.perf_counter()
    trainer.fit(module, data, ckpt_path=resume)
    seconds = time.perf_counter() - start
    final = trainer.validate(module, data, verbose=False)[0] if has_val else {}
    if args.data is not None:
        trainer.save_checkpoint(args.out / "checkpoints" / "last.ckpt")  # every rank: it synchronises
    card = {
        "model": args.model, "name": checkpoint_name(args.model, layout), "task": task,
        "command": "python -m evlatcorr.train " + " ".join(sys.argv[1:] if argv is None else argv),
        "steps": int(trainer.global_step), "train_seconds": round(seconds, 1),
        "val_psnr": _metric(final, "val/psnr", 3), "val_ssim": _metric(final, "val/ssim", 4),
        "val_blurry_psnr": _metric(final, "val/blurry_psnr", 3), "events": info["events"], "data": info["data"],
        "world_size": trainer.world_size, "precision": str(trainer.precision),
        "device": torch.cuda.get_device_name() if torch.cuda.is_available() and trainer.on_gpu else
        f"CPU, {torch.get_num_threads()} threads", "torch": torch.__version__,
    }
    if args.model == "refid":
        card["refid_layout"] = list(layout)
    if args.data is not None:
        card.update(finetune=args.finetune, network=info["network"], threshold=info["threshold"],
                    val_objective_before=_metric(before, "val/corrector", 5),
                    val_objective_after=_metric(final, "val/corrector", 5))
    if trainer.is_global_zero:
        if args.data is not None and args.finetune == "spatial":
            from evlatcorr.spatial import save_curve

            card["curve"] = str(args.out / "curve.pt")
            save_curve(module.latency_model, card["curve"], scenes=[str(args.data)], threshold=info["threshold"],
                       network=args.model, steps=card["steps"])
        if card.get("val_objective_before") is not None:
            print(f"self-supervised objective (Eq. 21) on {len(data.val_samples)} held-out sample(s): "
                  f"{card['val_objective_before']:.5f} before, {card['val_objective_after']:.5f} after "
                  f"{card['steps']} steps ({seconds:.1f} s)")
        if args.export is not None:
            from evlatcorr.adapters.checkpoint import card_sha256, save_weights

            previous = args.export / f"{card['name']}.json"
            # a resumed run, or one continuing the shipped weights of this name, extends their history
            continued = resume is not None or args.checkpoint == "default"
            if continued and previous.is_file():
                old = json.loads(previous.read_text())
                card["commands"] = old.get("commands", [old["command"]]) + [card["command"]]
                card["train_seconds"] = round(card["train_seconds"] + old["train_seconds"], 1)
                if "note" in old:
                    card["note"] = old["note"]
                if resume is None:  # the step count restarted on top of the shipped weights
                    card["steps"] += int(old["steps"])

            adapter = module.adapter
            files = save_weights(adapter.net, args.export / f"{card['name']}.safetensors")
            card["files"] = [f.name for f in files]
            card["sha256"] = card_sha256(files)  # checked at every load
            (args.export / f"{card['name']}.json").write_text(json.dumps(card, indent=2) + "\n")
            write_checkpoint_readme(args.export)
        print(json.dumps(card, indent=2))
    return card


if __name__ == "__main__":
    main()
