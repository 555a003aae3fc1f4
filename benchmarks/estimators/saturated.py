"""An ``--estimator`` for ``benchmarks/accuracy.py``: the default constant corrector on a frame that saturates.

A DAVIS frame clips where the scene is brighter than the sensor's range (a lamp, a window, the sky: 1.5 % of the
pixels of the shared street recording read 1.0), while its events still follow the unclipped scene. The suite's
simulator never clips, so this estimator makes it: it scales each frame until the brightest ``$EVLATCORR_SATURATED``
(default 0.03, a share of the pixels) reach 1 and clips them there, then runs the corrector at its defaults. A gain
in linear intensity changes no event (each stands for a change of log intensity), so the events stay those of the
clipped frame's scene; the suite scores the estimate as usual, its EDI from the unclipped frame.

    python benchmarks/accuracy.py --split dev --mode constant --estimator benchmarks/estimators/saturated.py:estimate

The ``constant`` row is the same corrector on the unclipped frames, in the same run.
"""

from __future__ import annotations

import os

import torch
from torch import Tensor

from evlatcorr.benchmark.accuracy import corrector_estimator
from evlatcorr.frames import EventFrames

DEFAULT_SHARE = 0.03


def saturate(blurry: Tensor, share: float) -> Tensor:
    """Each frame of ``blurry`` :math:`(B, 1, H, W)` scaled so its brightest ``share`` of pixels reach 1, clipped at 1.

    Raises:
        ValueError: when ``share`` is not in (0, 1).
    """
    if not 0 < share < 1:
        raise ValueError(f"the saturated share must be in (0, 1), got {share}")
    level = torch.quantile(blurry.flatten(1).float(), 1 - share, dim=1).clamp_min(1e-3)
    return (blurry / level.view(-1, 1, 1, 1).to(blurry)).clamp(0, 1)


def estimate(frames: EventFrames) -> Tensor:
    """The default corrector's latency map :math:`(B, 1, H, W)` µs on the frames saturated (the case's threshold)."""
    share = float(os.environ.get("EVLATCORR_SATURATED", DEFAULT_SHARE))
    clipped = frames.replace(blurry=saturate(frames.blurry, share))
    return corrector_estimator("constant", float(frames.meta["threshold"]))(clipped).latency
