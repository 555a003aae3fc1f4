"""Data modules of the restoration networks: simulated training photographs, or a recording."""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from evlatcorr.frames import EventFrames
from evlatcorr.lightning.data import FramesDataset, RandomCrops, frames_loader
from evlatcorr.lightning.targets import has_truth

__all__ = ["SimulatedRestorationData", "RecordingRestorationData"]


class _RestorationLoaders(L.LightningDataModule):
    """The data loaders both restoration data modules share (they fill ``train_set`` / ``val_set`` in setup)."""

    train_set: Dataset | None
    val_set: Dataset | None
    batch_size: int
    num_workers: int
    seed: int

    def train_dataloader(self) -> DataLoader:
        if self.train_set is None:
            raise RuntimeError("call setup() first")
        return frames_loader(self.train_set, self.batch_size, True, self.num_workers, self.seed,
                             persistent_workers=True)

    def val_dataloader(self) -> DataLoader:
        if self.val_set is None:
            raise RuntimeError("call setup() first")
        return frames_loader(self.val_set, 1, False, self.num_workers, self.seed)


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
        seed: base seed of the simulation and of the random crops.
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
                    # REFID's voxel grid starts before the first exposure: give it the events there, as a
                    # camera's stream (and REFID's official data) has them
                    lead = self.exposure_us
                    both = seq.pairs("ideal", before_us=lead), seq.pairs("delayed", before_us=lead)
                    if self.target_times is not None:
                        times = self.target_times(both[0]).to(torch.float64)
                        frames = seq.render(times.flatten()).view(*times.shape, *seq.blurry.shape[1:])
                        both = tuple(b.replace(target_times=times, target_frames=frames) for b in both)
                samples.extend(zip(both[0].split(), both[1].split()))
        return samples

    def setup(self, stage: str | None = None) -> None:
        if self.train_set is None:
            base = 1000 * self.seed
            train = self.simulate([base + k for k in range(self.sequences)])
            val = self.simulate([base + 500 + k for k in range(self.val_sequences)])
            self.train_set = RandomCrops(self._alternatives(train), self.crop, self.steps_per_epoch * self.batch_size,
                                         seed=self.seed)
            self.val_set = RandomCrops(self._alternatives(val), None, seed=self.seed)

    def _alternatives(self, samples: list[tuple[EventFrames, EventFrames]]) -> list[tuple[EventFrames, ...]]:
        """The (ideal, delayed) samples as :class:`RandomCrops` draws them: ``"mixed"`` picks one per item."""
        if self.events == "mixed":
            return samples
        return [(pair[0] if self.events == "ideal" else pair[1],) for pair in samples]


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
        seed: seed of the random crops and of the shuffling.

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
                 steps_per_epoch: int = 200, seed: int = 0) -> None:
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
        self.batch_size, self.num_workers, self.steps_per_epoch, self.seed = (
            batch_size, num_workers, steps_per_epoch, seed)
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
        from evlatcorr.restore import pair_lead_us, pair_reach_us

        if self.recording is not None:
            return
        rec = open_recording(self.path)
        h, w = rec.sensor_size
        if self.crop[0] > h or self.crop[1] > w:
            raise ValueError(f"crop {self.crop} does not fit the sensor of {self.path}, (H, W)=({h}, {w}); "
                             "pass a smaller --crop")
        if self.pairs:  # the first frame's events reach the next exposure's end plus the latency searched
            rec.after_us = pair_reach_us(rec)
            rec.before_us = pair_lead_us(rec)  # REFID reads before the first exposure
        frames = list(itertools.islice(rec, self.max_frames))
        samples, no_next, no_events, cut = self._usable(frames)
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

    def _usable(self, frames: list[EventFrames]) -> tuple[list[EventFrames], int, int, list[int]]:
        """The samples of ``frames`` worth training on, and how many were left out: without a next frame,
        without events in their window, and (frame indices) with a window past the segment's last event."""
        from evlatcorr.restore import has_events, pair_frames

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
        samples: list[EventFrames] = []
        no_next, no_events, cut = 0, 0, []
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
        return samples, no_next, no_events, cut

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
            self.train_set = RandomCrops([(s,) for s in self.train_samples], self.crop,
                                         self.steps_per_epoch * self.batch_size, seed=self.seed, require_events=True)
            self.val_set = FramesDataset(self.val_samples)
