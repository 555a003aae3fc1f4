"""``--estimator``s for ``benchmarks/accuracy.py``: two ways to take the scene's own bias off the default's estimate.

The default's constant-latency error is a bias of each scene (step EDI is sharpest at a scene-dependent distance
from the true latency), not a bias of the suite: its signed median is near 0. Both estimators look for that bias in
the frame itself.

- ``bootstrap``: a parametric bootstrap. At the default's estimate ``l``, build the frame a world of linear ramps
  would have given (each event the end of a ramp from the pixel's previous event, as the ``"linear"`` integral
  reads it; its latent at mid-exposure the step EDI's): ``B · exp(log R_linear(l) − log R_step(l))``, scaled into
  [0, 1]. There the true latency is ``l``; estimating again gives ``l'``, and ``l − (l' − l)`` takes off the bias
  seen there.
- ``thresholds``: the median of the default's estimates with 0.8, 1 and 1.25 times the case's threshold: three
  readings of the same curves' shapes, in case their errors do not move together.

    E=benchmarks/estimators/self_calibration.py
    python benchmarks/accuracy.py --split tuning --mode none --cases '*const*' --estimator $E:bootstrap \\
        --estimator $E:thresholds --estimator $E:default

Neither is shipped; ``docs/estimator.md`` ("Measured, not shipped: the frame's own bias") gives their figures.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.edi import edi_log_ratio
from evlatcorr.frames import EventFrames

THRESHOLD_SCALES = (0.8, 1.0, 1.25)


def _per_frame(latency: Tensor) -> Tensor:
    return latency[:, 0, 0, 0].double()


def _as_map(per_frame: Tensor, like: Tensor) -> Tensor:
    return per_frame.to(like).view(-1, 1, 1, 1).expand_as(like)


def ramp_world_frame(frames: EventFrames, latency: Tensor) -> EventFrames:
    """``frames`` with the blurry frame a world of linear ramps would give at ``latency`` :math:`(B,)` µs."""
    args = (frames.events, frames.exposure_start, frames.exposure_end, float(frames.meta["threshold"]))
    step = edi_log_ratio(*args, latency=latency, integral="step", dtype=torch.float64)
    ramps = edi_log_ratio(*args, latency=latency, integral="linear", dtype=torch.float64)
    blurry = frames.blurry.double() * torch.exp(ramps - step)
    blurry = blurry / blurry.amax(dim=(1, 2, 3), keepdim=True).clamp_min(1.0)
    return frames.replace(blurry=blurry.to(frames.blurry.dtype))


def default(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs (the case's threshold)."""
    return corrector_estimator("constant", float(frames.meta["threshold"]))(frames).latency


def bootstrap(frames: EventFrames) -> Tensor:
    """The default's latency less the bias it shows in the ramp world at its own estimate, as a map µs."""
    latency = default(frames)
    first = _per_frame(latency)
    again = _per_frame(default(ramp_world_frame(frames, first)))
    return _as_map((2 * first - again).clamp_min(0.0), latency)


def thresholds(frames: EventFrames) -> Tensor:
    """The median of the default's latencies with :data:`THRESHOLD_SCALES` times the case's threshold, as a map µs."""
    theta = float(frames.meta["threshold"])
    maps = [corrector_estimator("constant", s * theta)(frames).latency for s in THRESHOLD_SCALES]
    return _as_map(torch.stack([_per_frame(m) for m in maps]).median(0).values, maps[0])
