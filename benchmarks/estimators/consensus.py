"""An ``--estimator`` for ``benchmarks/accuracy.py`` and ``benchmarks/network_check.py``: the constant corrector
with the previous default score, ``score="consensus"`` (the median of the three sparsity scores' minima), to
compare with the learned curve reader that is the default now.

    python benchmarks/network_check.py --split test --estimator benchmarks/estimators/consensus.py:estimate
"""

from __future__ import annotations

from torch import Tensor

from evlatcorr.correction import EventLatencyCorrector
from evlatcorr.frames import EventFrames


def estimate(frames: EventFrames) -> Tensor:
    """The constant corrector's latency map :math:`(B, 1, H, W)` µs, ``score="consensus"``, the case's threshold."""
    return EventLatencyCorrector(threshold=frames.meta["threshold"], score="consensus")(frames).latency
