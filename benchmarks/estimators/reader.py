"""An ``--estimator`` for ``benchmarks/accuracy.py``: a curve reader saved by ``benchmarks/train_curve_reader.py``.

The reader at ``$EVLATCORR_READER`` (a ``.safetensors`` file; the shipped one when unset) reads the curves the search
reads (:func:`evlatcorr.search.candidate_curves`), without the overshoot's row when it was trained without it
(``--without-overshoot``), and the estimate is the centre of its probability, as the search takes it for one frame
(the search's fallbacks left out; a frame whose windows hold no events is refused). What the overshoot input adds,
on the tuning cases (the shipped reader is seed 0 with it):

    python benchmarks/train_curve_reader.py --cache /tmp/curves.pt --without-overshoot --out /tmp/without.safetensors
    python benchmarks/train_curve_reader.py --cache /tmp/curves.pt --out /tmp/with.safetensors
    EVLATCORR_READER=/tmp/without.safetensors python benchmarks/accuracy.py --split tuning --mode none \\
        --estimator benchmarks/estimators/reader.py:estimate --out /tmp/without

``estimate_before`` reads a reader trained on curves that also reach below 0 (``train_curve_reader.py --before-us
2000``: windows that start up to 2 ms before the exposure, frames that keep those events), on suite frames that keep
them too (``accuracy.py --before-us 2000``; ``$EVLATCORR_BEFORE_US`` if not 2000), and clamps its centre at 0:

    python benchmarks/train_curve_reader.py --cache /tmp/before.pt --before-us 2000 --out /tmp/before.safetensors
    EVLATCORR_READER=/tmp/before.safetensors python benchmarks/accuracy.py --split tuning --mode constant \\
        --before-us 2000 --estimator benchmarks/estimators/reader.py:estimate_before --out /tmp/before
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from evlatcorr.curve_reader import NUM_FEATURES, load_curve_reader, probability_centre, without_overshoot
from evlatcorr.frames import EventFrames
from evlatcorr.search import candidate_curves


def estimate(frames: EventFrames, before_us: float = 0.0, reader_path: str | None = None) -> Tensor:
    """The reader's latency for the first frame as a map (1, 1, H, W) µs (the case's threshold); with
    ``before_us``, from curves that also reach below 0, clamped at 0. ``reader_path``: the reader's weights
    (default ``$EVLATCORR_READER``, else the shipped one).

    Raises:
        ValueError: for more than one frame, a frame without events, or (``before_us``) none before the
            exposure.
    """
    if frames.batch_size != 1:
        raise ValueError(f"the reader estimator reads one frame, got {frames.batch_size}")
    events = frames.events.sample(0)
    if not len(events):
        raise ValueError("the frame has no events")
    start = float(frames.exposure_start[0])
    if before_us and float(events.t.min()) >= start:
        raise ValueError(f"the frame has no events before its exposure: run the suite with --before-us {before_us:.0f}")
    ensemble = load_curve_reader(reader_path or os.environ.get("EVLATCORR_READER") or None)
    candidates, curves, valid = candidate_curves(frames.blurry[:1], events, start, float(frames.exposure_end[0]),
                                                 float(frames.meta["threshold"]), before_us)
    if ensemble.members[0].net[0].in_channels < NUM_FEATURES:
        curves = without_overshoot(curves)
    with torch.no_grad():
        log_p = ensemble(curves[None], valid[None])[0].double()
    _, centre = probability_centre(log_p.masked_fill(~valid, -1e30), candidates, int(valid.sum()))
    return torch.full_like(frames.blurry[:1, :1], max(0.0, float(centre)) if before_us else centre)


def estimate_before(frames: EventFrames) -> Tensor:
    """:func:`estimate` from curves reaching ``$EVLATCORR_BEFORE_US`` (default 2000) µs below 0."""
    return estimate(frames, before_us=float(os.environ.get("EVLATCORR_BEFORE_US", "2000")))
