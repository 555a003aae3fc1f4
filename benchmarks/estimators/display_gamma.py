"""An ``--estimator`` for ``benchmarks/accuracy.py``: the default constant corrector given frames encoded for display.

EDI takes a frame as linear intensity, as a DAVIS gives its raw frames. PNG exports and video frames are encoded for
display instead (sRGB, close to ``linear ** (1 / 2.2)``). This estimator encodes each frame with the gamma
``$EVLATCORR_DISPLAY_GAMMA`` (default 2.2; the events stay the scene's) and runs the corrector at its defaults on
it, as a user who passed such frames would; ``linear`` is the same corrector on the frames as the suite made them,
and ``linearised`` the encoded frames made linear again as ``open_recording(path, frame_gamma=2.2)`` /
``--frame-gamma 2.2`` read them. The suite scores every estimate as usual, its EDI from the linear frame.

    E=benchmarks/estimators/display_gamma.py
    python benchmarks/accuracy.py --split dev --mode none --estimator $E:linear --estimator $E:encoded \
        --estimator $E:linearised                # --auto-threshold: θ estimated from the frames too
"""

from __future__ import annotations

import os

from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.frames import EventFrames
from evlatcorr.gamma import check_frame_gamma, linear_frames

DEFAULT_GAMMA = 2.2


def _gamma() -> float:
    return check_frame_gamma(float(os.environ.get("EVLATCORR_DISPLAY_GAMMA", DEFAULT_GAMMA)))


def _latency(frames: EventFrames) -> Tensor:
    threshold = frames.meta["threshold"]  # the case's, or "auto" with --auto-threshold
    return corrector_estimator("constant", threshold if threshold == "auto" else float(threshold))(frames).latency


def encode(frames: EventFrames, gamma: float) -> EventFrames:
    """``frames`` with their images encoded for display: raised to ``1 / gamma``."""
    return linear_frames(frames, 1 / gamma)


def linear(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs on the linear frames (the case's threshold)."""
    return _latency(frames)


def encoded(frames: EventFrames) -> Tensor:
    """The same on the frames encoded for display."""
    return _latency(encode(frames, _gamma()))


def linearised(frames: EventFrames) -> Tensor:
    """The same on the encoded frames made linear again, as ``frame_gamma`` reads them."""
    gamma = _gamma()
    return _latency(linear_frames(encode(frames, gamma), gamma))
