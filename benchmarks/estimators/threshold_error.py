"""``--estimator``s for ``benchmarks/accuracy.py``: the default constant corrector given a wrong contrast threshold.

Nobody knows their camera's θ exactly. ``low`` gives the corrector 0.7 times the case's true threshold, ``high``
1.4 times it; the suite scores the latency found as usual (its EDI with the true threshold), so the figures say how
much a wrong θ moves the latency, not how much it blurs EDI. With the corrector's own estimate of θ
(``--auto-threshold``) in the same run:

    E=benchmarks/estimators/threshold_error.py
    python benchmarks/accuracy.py --split tuning --mode constant --auto-threshold --estimator $E:low --estimator $E:high
"""

from __future__ import annotations

import functools

from torch import Tensor

from evlatcorr.correction import EventLatencyCorrector
from evlatcorr.frames import EventFrames

LOW, HIGH = 0.7, 1.4


@functools.lru_cache(maxsize=16)
def _corrector(threshold: float) -> EventLatencyCorrector:
    return EventLatencyCorrector(threshold=threshold)


def _with_threshold_times(frames: EventFrames, scale: float) -> Tensor:
    return _corrector(scale * float(frames.meta["threshold"]))(frames).latency


def low(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs with 0.7 times the true threshold."""
    return _with_threshold_times(frames, LOW)


def high(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs with 1.4 times the true threshold."""
    return _with_threshold_times(frames, HIGH)
