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
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from evlatcorr.curve_reader import NUM_FEATURES, load_curve_reader, probability_centre, without_overshoot
from evlatcorr.frames import EventFrames
from evlatcorr.search import candidate_curves


def estimate(frames: EventFrames) -> Tensor:
    """The reader's latency for the first frame as a map (1, 1, H, W) µs (the case's threshold).

    Raises:
        ValueError: for more than one frame or a frame without events.
    """
    if frames.batch_size != 1:
        raise ValueError(f"the reader estimator reads one frame, got {frames.batch_size}")
    events = frames.events.sample(0)
    if not len(events):
        raise ValueError("the frame has no events")
    ensemble = load_curve_reader(os.environ.get("EVLATCORR_READER") or None)
    candidates, curves, valid = candidate_curves(frames.blurry[:1], events, float(frames.exposure_start[0]),
                                                 float(frames.exposure_end[0]), float(frames.meta["threshold"]))
    if ensemble.members[0].net[0].in_channels < NUM_FEATURES:
        curves = without_overshoot(curves)
    with torch.no_grad():
        log_p = ensemble(curves[None], valid[None])[0].double()
    _, centre = probability_centre(log_p.masked_fill(~valid, -1e30), candidates, int(valid.sum()))
    return torch.full_like(frames.blurry[:1, :1], centre)
