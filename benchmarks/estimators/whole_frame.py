"""An ``--estimator`` for ``benchmarks/accuracy.py``: the default corrector reading the whole frame's curves alone
(``EventLatencyCorrector(tiles=False)``), the estimator before the tile reader (:mod:`evlatcorr.tile_reader`), to
measure what the tiles add in one run:

    python benchmarks/accuracy.py --split tuning --mode none --estimator benchmarks/estimators/whole_frame.py:estimate
"""

from __future__ import annotations

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.frames import EventFrames


def estimate(frames: EventFrames) -> EventFrames:
    """The default corrector's output without the tiles (the case's threshold)."""
    return corrector_estimator("constant", float(frames.meta["threshold"]), tiles=False)(frames)
