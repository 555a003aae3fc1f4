"""Training samples of the latency polynomial: simulated frames, or tiles of a recording (no ground truth)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from evlatcorr.frames import EventFrames

__all__ = ["simulated_training_frames", "recording_training_frames"]


def simulated_training_frames(names: Sequence[str], size: tuple[int, int], seed: int = 0,
                              latency: str = "intensity_delay", **kwargs: Any) -> list[EventFrames]:
    """Single-frame training samples from the simulator's training photographs.

    Example:
        >>> frames = simulated_training_frames(["coffee"], (16, 20), exposure_us=2000.0)
        >>> len(frames), frames[0].batch_size
        (2, 1)
    """
    from evlatcorr.simulate import simulate

    frames: list[EventFrames] = []
    for i, name in enumerate(names):
        seq = simulate(name, num_frames=2, height=size[0], width=size[1], latency=latency, seed=seed + i, **kwargs)
        frames.extend(seq.frames("delayed").split())
    return frames


def recording_training_frames(path: str | Path, crop: tuple[int, int] | None = None, threshold: float | str = "auto",
                              search_high_us: float | None = None, val_every: int = 5, frame_gamma: float = 1.0
                              ) -> tuple[list[EventFrames], list[EventFrames], float]:
    """Training and validation samples from a recording (any format ``evlatcorr.io`` reads), no ground truth.

    Every frame with events in its exposure and search window becomes one sample, cut into
    non-overlapping ``crop`` tiles (None: whole frames; ``meta["tile"]`` holds each tile's
    ``(top, left)``); every ``val_every``-th frame is held out.

    Args:
        path: the recording.
        crop: ``(H, W)`` of the tiles.
        threshold: θ, or ``"auto"`` for one θ of the recording (:func:`~evlatcorr.restore.recording_threshold`).
        search_high_us: the largest latency searched (default: the exposure time); events are read
            that far past each exposure.
        val_every: every this-many-th frame goes to validation (0: none).
        frame_gamma: the frames are raised to it as they are read (2.2: frames encoded for display made linear, as
            EDI needs them; :func:`~evlatcorr.io.open_recording`).

    Returns:
        ``(train, val, θ)``.

    Raises:
        ValueError: when the recording has no frame with events, or ``crop`` is larger than the sensor.
    """
    from evlatcorr.io import open_recording
    from evlatcorr.restore import has_events, recording_threshold

    rec = open_recording(path, after_us=search_high_us, frame_gamma=frame_gamma)
    if isinstance(threshold, str):
        found = recording_threshold(rec, None if search_high_us is None else (0.0, search_high_us))
        theta = found if found is not None else 0.2
    else:
        theta = float(threshold)
    height, width = rec.sensor_size
    ch, cw = crop if crop is not None else (height, width)
    if not (0 < ch <= height and 0 < cw <= width):
        raise ValueError(f"crop {crop} must fit the sensor {rec.sensor_size} (H, W)")
    train, val, used = [], [], 0
    for batch in rec:
        if not has_events(batch):
            continue
        tiles = [_tile(batch, y, x, ch, cw)
                 for y in range(0, height - ch + 1, ch) for x in range(0, width - cw + 1, cw)]
        tiles = [t for t in tiles if has_events(t)]
        (val if val_every and used % val_every == val_every - 1 else train).extend(tiles)
        used += 1
    if not train:
        raise ValueError(f"{path}: no frame with events in its exposure and search window to train on")
    return train, val, theta


def _tile(frames: EventFrames, top: int, left: int, height: int, width: int) -> EventFrames:
    tile = frames.crop(top, left, height, width)
    return tile.replace(meta={**tile.meta, "tile": (top, left)})
