"""An ``--estimator`` for ``benchmarks/accuracy.py``: the constant corrector's latency minus step EDI's own lag.

Step EDI treats each event as a step at its timestamp, but the event stands for a change that built up
since the pixel's previous event: the staircase lags the signal by about half the interval between a
pixel's consecutive events, so EDI is sharpest when the events are read that much later than their true
latency. This estimator removes that lag from the corrector's estimate: half the median interval between
consecutive events at the same pixel, in the frame's corrected exposure window.

    python benchmarks/accuracy.py --split test --mode none --estimator benchmarks/estimators/step_lag.py:estimate

It moves the estimate towards the true latency but lowers the EDI recovery (see the README), so the
corrector does not do it by default.
"""

from __future__ import annotations

import torch
from torch import Tensor

from evlatcorr.correction import EventLatencyCorrector
from evlatcorr.frames import EventFrames

LAG_SHARE = 0.5  # of the median interval between a pixel's consecutive events


def step_lag(frames: EventFrames, latency: Tensor) -> Tensor:
    """Half the median interval between consecutive events at a pixel in ``[start + l, end + l)``, per frame (B,) µs."""
    lags = []
    for i in range(frames.batch_size):  # frames, not events or pixels
        events = frames.events.sample(i)
        low = float(frames.exposure_start[i] + latency[i])
        high = float(frames.exposure_end[i] + latency[i])
        inside = (events.t >= low) & (events.t < high)
        pixel, order = torch.sort(events.pixel_index()[inside], stable=True)
        t = events.t[inside][order]
        gaps = (t[1:] - t[:-1])[pixel[1:] == pixel[:-1]]
        lags.append(LAG_SHARE * float(gaps.median()) if len(gaps) else 0.0)
    return torch.tensor(lags, dtype=torch.float64)


def estimate(frames: EventFrames) -> Tensor:
    """The corrector's constant latency (the case's threshold) minus :func:`step_lag`, as a map (B, 1, H, W) µs."""
    latency = EventLatencyCorrector(threshold=frames.meta["threshold"])(frames).latency
    per_frame = latency[:, 0, 0, 0].double().cpu()
    lagged = (per_frame - step_lag(frames, per_frame)).clamp_min(0.0)
    return lagged.to(latency).view(-1, 1, 1, 1).expand_as(latency)
