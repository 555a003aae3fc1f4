"""An ``--estimator`` for ``benchmarks/accuracy.py``: the default corrector, but no shift where its learned reader
keeps no latency likely.

With ideal events (no latency) the default answers a median 0.8 ms over the tuning cases: step EDI is sharpest a
little late. This estimator asks the reader's own probability instead (``meta["latency_log_probability"]``, the
frame's alone): where more than ``$EVLATCORR_NO_LATENCY_MASS`` (default 0.1) of it lies on the candidates whose
centre would reach no latency (0 and the :data:`~evlatcorr.curve_reader.CENTRE_HALF_WIDTH` above it: 0-400 µs at a
20 ms exposure), it answers 0; elsewhere the default's estimate stands.

    EVLATCORR_NO_LATENCY_MASS=0.15 python benchmarks/accuracy.py --split tuning --mode none \\
        --estimator benchmarks/estimators/no_latency.py:estimate

``docs/estimator.md`` has what it measured (not shipped: it trades the delayed frames' small latencies for the
ideal events).
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.curve_reader import CENTRE_HALF_WIDTH
from evlatcorr.frames import EventFrames
from evlatcorr.temporal import frame_evidence

DEFAULT_MASS = 0.1


def no_latency_mass(log_probability: Tensor, candidates: Tensor) -> float:
    """The probability :math:`(K,)` log-odds give the candidates :math:`(K,)` µs whose centre reaches 0: 0 and the
    :data:`~evlatcorr.curve_reader.CENTRE_HALF_WIDTH` candidates above it (0 when the candidates do not start at 0).

    Raises:
        ValueError: when the two are not 1-D of one length, or no candidate could be scored.

    Example:
        >>> round(no_latency_mass(torch.log(torch.tensor([0.2, 0.1, 0.1, 0.6])), torch.arange(4.0)), 6)
        0.4
    """
    if log_probability.dim() != 1 or candidates.shape != log_probability.shape:
        raise ValueError(f"log_probability and candidates must be 1-D of one length, got "
                         f"{tuple(log_probability.shape)} and {tuple(candidates.shape)}")
    if not bool(torch.isfinite(log_probability).any()):
        raise ValueError("no candidate could be scored (every log-probability is -inf or NaN)")
    if float(candidates[0]) != 0.0:
        return 0.0
    probability = torch.softmax(log_probability.double().nan_to_num(nan=-torch.inf), 0)
    return float(probability[:CENTRE_HALF_WIDTH + 1].sum())


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
        if log_probability is not None and no_latency_mass(log_probability, candidates) > threshold:
            latency[b] = 0.0
    return latency
