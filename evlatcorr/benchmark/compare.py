"""EDI with ideal, delayed and corrected events against the sharp frame: the comparison every script reports.

Example:
    >>> from evlatcorr.simulate import simulate
    >>> seq = simulate("camera", num_frames=1, height=32, width=48, latency_us=4000.0, seed=0)
    >>> ideal, delayed = seq.frames("ideal"), seq.frames("delayed")
    >>> edi_psnr(ideal) > edi_psnr(delayed)  # late events blur EDI
    True
"""

from __future__ import annotations

import math

from torch import Tensor
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

from evlatcorr.edi import edi_deblur
from evlatcorr.frames import EventFrames

__all__ = ["psnr", "image_quality", "edi_latent", "edi_psnr", "recovery", "NO_GAP_DB"]

NO_GAP_DB = 0.1  # recovery is undefined when ideal events beat uncorrected ones by no more than this


def psnr(image: Tensor, target: Tensor) -> float:
    """PSNR (dB) of ``image`` clamped to [0, 1] against ``target`` in [0, 1], over the whole batch."""
    return float(peak_signal_noise_ratio(image.clamp(0, 1), target, data_range=1.0))


def image_quality(image: Tensor, target: Tensor) -> tuple[float, float]:
    """``(PSNR dB, SSIM)`` of ``image`` clamped to [0, 1] against ``target``."""
    image = image.clamp(0, 1)
    return (float(peak_signal_noise_ratio(image, target, data_range=1.0)),
            float(structural_similarity_index_measure(image, target, data_range=1.0)))


def edi_latent(frames: EventFrames, threshold: float = 0.2, latency: Tensor | float | None = None,
               **kwargs) -> Tensor:
    """EDI latent image at mid-exposure of ``frames``' own events, read ``latency`` late (None: as stamped)."""
    return edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, threshold=threshold,
                      latency=latency, **kwargs)


def edi_psnr(frames: EventFrames, threshold: float = 0.2, latency: Tensor | float | None = None, **kwargs) -> float:
    """PSNR of :func:`edi_latent` against ``frames.sharp``."""
    if frames.sharp is None:
        raise ValueError("edi_psnr needs frames with a sharp ground-truth frame")
    return psnr(edi_latent(frames, threshold, latency, **kwargs), frames.sharp)


def recovery(corrected: float, uncorrected: float, ideal: float, no_gap_db: float = NO_GAP_DB) -> float:
    """Share of the ideal events' gain that a correction recovers: ``(corr − uncorr) / (ideal − uncorr)``.

    NaN when the ideal events beat the uncorrected ones by no more than ``no_gap_db`` (nothing to recover).

    Example:
        >>> recovery(29.0, 25.0, 30.0)
        0.8
    """
    return (corrected - uncorrected) / (ideal - uncorrected) if ideal > uncorrected + no_gap_db else math.nan
