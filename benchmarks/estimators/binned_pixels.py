"""``--estimator``s for ``benchmarks/accuracy.py``: the latency read from the frame with its pixels binned 2x2.

Step EDI holds a pixel's level until its next event, so its latent lags the scene by part of the interval between
the pixel's events, and the sharpest candidate lies after the true latency by a scene-dependent amount. A 2x2 block
of pixels gets four pixels' events, each a quarter of a pixel's step in the block's mean log intensity: its steps are
a quarter as large and come four times as often, so its step lag is about a quarter as long where an edge crosses the
block. ``binned`` estimates the latency on the frame averaged over 2x2 blocks, with the events of each block's pixels
and a quarter of the threshold; ``both`` takes the mean of that and the default's estimate.

    E=benchmarks/estimators/binned_pixels.py
    python benchmarks/accuracy.py --split tuning --mode none --estimator $E:binned --estimator $E:both \\
        --estimator $E:default

Neither is shipped; ``docs/estimator.md`` ("Measured, not shipped: the frame binned 2x2") gives their figures.
"""

from __future__ import annotations

import torch.nn.functional as F
from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.events import Events
from evlatcorr.frames import EventFrames

FACTOR = 2


def binned_frames(frames: EventFrames, factor: int = FACTOR) -> EventFrames:
    """The frames averaged over ``factor`` x ``factor`` blocks, each block's pixels' events its own (the last rows
    and columns that fill no block dropped)."""
    height, width = (s // factor for s in frames.sensor_size)
    ev = frames.events
    keep = (ev.x < width * factor) & (ev.y < height * factor)
    events = Events(ev.x[keep] // factor, ev.y[keep] // factor, ev.t[keep], ev.p[keep], batch=ev.batch[keep],
                    sensor_size=(height, width), batch_size=frames.batch_size)
    blurry = F.avg_pool2d(frames.blurry[..., :height * factor, :width * factor], factor)
    return EventFrames(blurry, events, frames.exposure_start, frames.exposure_end, meta=dict(frames.meta))


def _per_frame(frames: EventFrames, threshold: float) -> Tensor:
    return corrector_estimator("constant", threshold)(frames).latency[:, 0, 0, 0].double()


def _as_map(per_frame: Tensor, frames: EventFrames) -> Tensor:
    height, width = frames.sensor_size
    return per_frame.float().view(-1, 1, 1, 1).expand(-1, 1, height, width).contiguous()


def binned(frames: EventFrames) -> Tensor:
    """The default corrector on the 2x2-binned frame, with a quarter of the case's threshold."""
    theta = float(frames.meta["threshold"])
    return _as_map(_per_frame(binned_frames(frames), theta / FACTOR**2), frames)


def both(frames: EventFrames) -> Tensor:
    """The mean of the default's estimate and the binned frame's."""
    theta = float(frames.meta["threshold"])
    full = _per_frame(frames, theta)
    return _as_map((full + _per_frame(binned_frames(frames), theta / FACTOR**2)) / 2, frames)


def default(frames: EventFrames) -> Tensor:
    """The default corrector, in the same run."""
    return _as_map(_per_frame(frames, float(frames.meta["threshold"])), frames)
