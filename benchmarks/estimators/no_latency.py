"""An ``--estimator`` for ``benchmarks/accuracy.py``: the default corrector, but no shift where its learned reader
keeps no latency likely.

With ideal events (no latency) the default answers a median 0.8 ms over the tuning cases: step EDI is sharpest a
little late. This estimator asks the reader's own probability instead (``meta["latency_log_probability"]``, the
frame's alone): where more than ``$EVLATCORR_NO_LATENCY_MASS`` (default 0.1) of it lies on the candidates whose
centre would reach no latency (:func:`evlatcorr.temporal.no_latency_share`: 0-400 µs at a 20 ms exposure), it answers
0; elsewhere the default's estimate stands. ``fuse_latencies(..., no_latency_mass=)`` applies the same rule to
several frames' fused evidence.

    EVLATCORR_NO_LATENCY_MASS=0.15 python benchmarks/accuracy.py --split tuning --mode none \\
        --estimator benchmarks/estimators/no_latency.py:estimate

``docs/estimator.md`` has what it measured (not shipped: it trades the delayed frames' small latencies for the
ideal events).
"""

from __future__ import annotations

import os

from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.frames import EventFrames
from evlatcorr.temporal import frame_evidence, no_latency_share

DEFAULT_MASS = 0.1


def estimate(frames: EventFrames) -> Tensor:
    """The latency map :math:`(B, 1, H, W)` µs: the default corrector's (the case's threshold), 0 for a frame whose
    reader gives its no-latency candidates more than ``$EVLATCORR_NO_LATENCY_MASS`` of its probability.

    Raises:
        ValueError: when ``$EVLATCORR_NO_LATENCY_MASS`` is not in (0, 1).
    """
    threshold = float(os.environ.get("EVLATCORR_NO_LATENCY_MASS", DEFAULT_MASS))
    if not 0 < threshold < 1:
        raise ValueError(f"EVLATCORR_NO_LATENCY_MASS must be in (0, 1), got {threshold}")
    out = corrector_estimator("constant", float(frames.meta["threshold"]))(frames)
    latency = out.latency.clone()
    for b, (_, candidates, log_probability) in enumerate(frame_evidence(out)):  # frames, not pixels or events
        if log_probability is not None and no_latency_share(log_probability, candidates) > threshold:
            latency[b] = 0.0
    return latency
