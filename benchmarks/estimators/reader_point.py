"""``--estimator``s for ``benchmarks/accuracy.py``: other points of the shipped reader's probability than its centre.

The search takes the centre of the reader's probability over its likeliest candidate and two neighbours on each
side (``centre``, as :mod:`benchmarks.estimators.reader` without ``$EVLATCORR_READER``). The others read the same
probability over every candidate that could be scored: its mean (``mean``), its median (``median``), and the mean
of the probability squared and renormalised (``tempered``: between the mean and the likeliest candidate). Where
latency varies with intensity the probability is broad and the mean is a compromise between its modes; where one
latency holds, the mean is pulled by a second mode. All four in one run (the curves are read once per frame):

    E=benchmarks/estimators/reader_point.py
    python benchmarks/accuracy.py --split tuning --mode none \\
        --estimator $E:centre --estimator $E:mean --estimator $E:median --estimator $E:tempered

``centre_1``, ``centre_3`` and ``centre_5`` take the centre over 1, 3 or 5 neighbours each side instead of 2.
``docs/estimator.md`` has the figures: none is better than the search's centre across the board.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.curve_reader import load_curve_reader, probability_centre
from evlatcorr.frames import EventFrames
from evlatcorr.search import candidate_curves

_last: dict[tuple, tuple[Tensor, Tensor, int]] = {}


def reader_probability(frames: EventFrames) -> tuple[Tensor, Tensor, int]:
    """The first frame's candidates (K,) µs, the shipped reader's log-odds (K,) (−1e30 where not scored) and how
    many were scored; the last frame's kept, so the four estimators read each frame's curves once.

    Raises:
        ValueError: for more than one frame, or a frame none of whose candidates could be scored.
    """
    if frames.batch_size != 1:
        raise ValueError(f"the reader estimators read one frame, got {frames.batch_size}")
    events = frames.events.sample(0)
    key = (float(frames.exposure_start[0]), len(events), float(frames.blurry.sum()), float(events.t.sum()))
    if key not in _last:
        _last.clear()
        candidates, curves, valid = candidate_curves(frames.blurry[:1], events, float(frames.exposure_start[0]),
                                                     float(frames.exposure_end[0]), float(frames.meta["threshold"]))
        if not bool(valid.any()):
            raise ValueError("no candidate's window holds events")
        with torch.no_grad():
            log_p = load_curve_reader()(curves[None], valid[None])[0].double()
        _last[key] = (candidates.double(), log_p.masked_fill(~valid, -1e30), int(valid.sum()))
    return _last[key]


def _as_map(frames: EventFrames, latency: float | Tensor) -> Tensor:
    return torch.full_like(frames.blurry[:1, :1], float(latency))


def centre(frames: EventFrames) -> Tensor:
    """The search's point: the centre around the likeliest candidate, as a map (1, 1, H, W) µs."""
    candidates, log_p, num_valid = reader_probability(frames)
    return _as_map(frames, probability_centre(log_p, candidates, num_valid)[1])


def mean(frames: EventFrames) -> Tensor:
    """The mean of the reader's probability over all candidates."""
    candidates, log_p, _ = reader_probability(frames)
    return _as_map(frames, (torch.softmax(log_p, 0) * candidates).sum())


def median(frames: EventFrames) -> Tensor:
    """The median of the reader's probability (the first candidate at or past half of it)."""
    candidates, log_p, _ = reader_probability(frames)
    cumulative = torch.cumsum(torch.softmax(log_p, 0), 0)
    k = int(torch.searchsorted(cumulative, torch.tensor(0.5, dtype=cumulative.dtype)))
    return _as_map(frames, candidates[min(k, len(candidates) - 1)])


def tempered(frames: EventFrames) -> Tensor:
    """The mean of the reader's probability squared (log-odds doubled) and renormalised."""
    candidates, log_p, _ = reader_probability(frames)
    return _as_map(frames, (torch.softmax(2 * log_p, 0) * candidates).sum())


def _centre_of(frames: EventFrames, half_width: int) -> Tensor:
    candidates, log_p, num_valid = reader_probability(frames)
    return _as_map(frames, probability_centre(log_p, candidates, num_valid, half_width=half_width)[1])


def centre_1(frames: EventFrames) -> Tensor:
    """The centre over the likeliest candidate and 1 neighbour each side (the search: 2)."""
    return _centre_of(frames, 1)


def centre_3(frames: EventFrames) -> Tensor:
    """The centre over the likeliest candidate and 3 neighbours each side."""
    return _centre_of(frames, 3)


def centre_5(frames: EventFrames) -> Tensor:
    """The centre over the likeliest candidate and 5 neighbours each side."""
    return _centre_of(frames, 5)
