"""Benchmark scenes from recorded datasets: the paper's synthetic protocol on real events.

A recording with ground-truth sharp frames (HighREV, event_utils-style HDF5 with sharp images, ...)
has events whose latency is unknown but small against the one injected here, so its events serve
as the "GT input" and the same events delayed by a known latency as "W/o corr." (the paper's
synthetic protocol on real data). Sharp frames exist only at mid-exposure, so such data scores
the deblurring rows; interpolation rows need frames between exposures (our HDF5 sequences).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import torch
from torch import Tensor

from evlatcorr.benchmark.loop import BenchmarkScene
from evlatcorr.frames import EventFrames
from evlatcorr.lightning.data import collate_event_frames
from evlatcorr.simulate import luminance

__all__ = ["delay_events", "intensity_latency", "scenes_from_recording"]

#: the simulator's intensity-dependent latency range (µs): bright pixels lag 0.5 ms, dim ones up to 10 ms
LATENCY_RANGE_US = (500.0, 10000.0)


def intensity_latency(blurry: Tensor, latency_range_us: tuple[float, float] = LATENCY_RANGE_US) -> Tensor:
    """Per-pixel latency :math:`(B, 1, H, W)` µs that grows as light falls: ``clip(lo / I, lo, hi)``.

    The simulator's model (``I`` the frame's luminance in [0, 1]), so real and simulated data share
    one latency law.

    Example:
        >>> intensity_latency(torch.tensor([1.0, 0.25, 0.0]).view(1, 1, 1, 3)).flatten().tolist()
        [500.0, 2000.0, 10000.0]
    """
    lo, hi = latency_range_us
    lum = luminance(blurry) if blurry.shape[1] == 3 else blurry
    return (lo / lum.clamp_min(1e-12)).clamp(lo, hi)


def delay_events(frames: EventFrames, latency: Tensor | float, after_us: float | None = None) -> EventFrames:
    """Stamp every event late by ``latency`` (µs: a scalar, ``(B,)`` or ``(B, 1, H, W)``) and keep
    those of ``[exposure_start, exposure_end + after)`` (``after`` defaults to the exposure time).

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0, 0]), torch.tensor([0, 0]), torch.tensor([-300.0, 500.0]),
        ...             torch.ones(2), sensor_size=(1, 1))
        >>> fr = EventFrames(torch.rand(1, 1, 1, 1), ev, torch.tensor([0.0]), torch.tensor([1000.0]))
        >>> delay_events(fr, 400.0).events.t.tolist()
        [100.0, 900.0]
    """
    exposure = frames.exposure_end - frames.exposure_start
    after = exposure if after_us is None else torch.full_like(exposure, float(after_us))
    shifted = frames.events.shift(-latency)  # shift() removes a latency: a negative one adds it
    return frames.replace(events=shifted.window(frames.exposure_start, frames.exposure_end + after))


def _center_crop(frames: EventFrames, multiple: int) -> EventFrames:
    h, w = frames.sensor_size
    ch, cw = h - h % multiple, w - w % multiple
    if ch == 0 or cw == 0:
        raise ValueError(f"frames of (H, W)=({h}, {w}) are smaller than the networks' multiple {multiple}")
    if (ch, cw) == (h, w):
        return frames
    return frames.crop((h - ch) // 2, (w - cw) // 2, ch, cw)


def scenes_from_recording(path: str | Path, *, latency: str = "constant", latency_us: float = 4000.0,
                          frames_per_scene: int = 4, max_scenes: int | None = None,
                          multiple: int = 16, frame_gamma: float = 1.0) -> Iterator[BenchmarkScene]:
    """Benchmark scenes from a recording with sharp frames, one per segment (sequence).

    Args:
        path: anything :func:`evlatcorr.io.open_recording` reads (HighREV folder, HDF5, ...).
        latency: ``"constant"`` (``latency_us`` everywhere) or ``"intensity"`` (:func:`intensity_latency`
            of each blurry frame).
        latency_us: the injected constant latency, µs.
        frames_per_scene: frames with a sharp frame taken from each segment.
        max_scenes: stop after this many scenes.
        multiple: frames are centre-cropped to multiples of this (the networks' divisor).
        frame_gamma: the recording's frames are encoded for display as ``linear ** (1 / frame_gamma)`` (2.2: sRGB,
            PNG or video frames; 1: linear, as a DAVIS's raw frames are). The scenes hold them linear, as EDI, the
            correctors and the intensity-dependent latency need them, and carry the value so that the networks
            read, and every row is scored on, the frames as the file has them.

    Yields:
        :class:`BenchmarkScene` with ``pairs_ideal = pairs_delayed = None`` (no ground truth between
        exposures); its ``true_latency`` is the injected one.

    Raises:
        evlatcorr.io.RecordingError: unreadable data, or no frame with a sharp frame.

    Example:
        >>> scenes = list(scenes_from_recording("HighREV/val", max_scenes=2))  # doctest: +SKIP
    """
    from evlatcorr.io import RecordingError, open_recording

    if latency not in ("constant", "intensity"):
        raise ValueError(f"latency must be 'constant' or 'intensity', got {latency!r}")
    before = float(latency_us) if latency == "constant" else LATENCY_RANGE_US[1]
    rec = open_recording(path, before_us=before, frame_gamma=frame_gamma)
    names = rec.segment_names or [Path(path).stem]
    taken: dict[int, list[EventFrames]] = {}
    for batch in rec:
        if batch.sharp is None:
            continue
        segment = int(batch.meta.get("segment", 0))
        group = taken.setdefault(segment, [])
        if len(group) < frames_per_scene:
            group.append(_center_crop(batch, multiple))
        full = [s for s, g in taken.items() if len(g) == frames_per_scene]
        if max_scenes is not None and len(full) >= max_scenes:
            break
    scenes = [(s, g) for s, g in taken.items() if g]
    if not scenes:
        raise RecordingError(f"{path}: no frame has a ground-truth sharp frame; the benchmark scores "
                             "restorations against them (use `evlatcorr deblur` on data without)")
    for segment, group in scenes[:max_scenes]:
        frames = collate_event_frames(group)
        exposure = frames.exposure_end - frames.exposure_start
        ideal = frames.replace(events=frames.events.window(frames.exposure_start, frames.exposure_end + exposure))
        if latency == "constant":
            true_latency = torch.full((frames.batch_size, 1, *frames.sensor_size), float(latency_us))
        else:
            true_latency = intensity_latency(frames.blurry)
        delayed = delay_events(frames, true_latency)
        name = names[segment] if segment < len(names) else f"{Path(path).stem}_{segment}"
        yield BenchmarkScene(name, ideal, delayed, None, None, true_latency, frame_gamma=rec.frame_gamma)
