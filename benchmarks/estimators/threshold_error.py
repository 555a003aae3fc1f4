"""``--estimator``s for ``benchmarks/accuracy.py``: the default constant corrector given a wrong contrast threshold.

Nobody knows their camera's θ exactly. ``low`` gives the corrector 0.7 times the case's true threshold, ``high``
1.4 times it, ``far_low`` 0.4 times and ``far_high`` 2.5 times (θ = 0.2 for a camera at 0.5); the suite scores the
latency found as usual (its EDI with the true threshold), so the figures say how much a wrong θ moves the latency,
not how much it blurs EDI. With the corrector's own estimate of θ
(``--auto-threshold``) in the same run:

    E=benchmarks/estimators/threshold_error.py
    python benchmarks/accuracy.py --split tuning --mode constant --auto-threshold --estimator $E:low --estimator $E:high
    python benchmarks/accuracy.py --split tuning --mode none --estimator $E:far_low --estimator $E:far_high
"""

from __future__ import annotations

from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.frames import EventFrames

LOW, HIGH, FAR_LOW, FAR_HIGH = 0.7, 1.4, 0.4, 2.5


def _with_threshold_times(frames: EventFrames, scale: float) -> Tensor:
    return corrector_estimator("constant", scale * float(frames.meta["threshold"]))(frames).latency


def low(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs with 0.7 times the true threshold."""
    return _with_threshold_times(frames, LOW)


def high(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs with 1.4 times the true threshold."""
    return _with_threshold_times(frames, HIGH)


def far_low(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs with 0.4 times the true threshold."""
    return _with_threshold_times(frames, FAR_LOW)


def far_high(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs with 2.5 times the true threshold."""
    return _with_threshold_times(frames, FAR_HIGH)
