"""EDI as a model: deblurring and frame interpolation from the (corrected) events, no weights."""

from __future__ import annotations

import torch

from evlatcorr.adapters.base import NetworkAdapter
from evlatcorr.edi import edi_deblur, edi_interpolate
from evlatcorr.frames import EventFrames

__all__ = ["EDIAdapter"]


class EDIAdapter(NetworkAdapter):
    """The Event-based Double Integral as a restoration model.

    Reads ``frames.corrected`` when a corrector filled it, else ``frames.events``, so
    ``nn.Sequential(EventLatencyCorrector(), EDIAdapter())`` deblurs with corrected events.

    Args:
        mode: ``"deblur"`` (latent image at mid-exposure, or at ``frames.target_times`` when set) or
            ``"interpolation"`` (frames at ``frames.target_times`` between ``blurry`` and ``blurry_next``).
        threshold: contrast threshold θ, or ``"auto"`` (deblurring only).
        num_bins: sub-intervals of each exposure.

    Returns (forward):
        ``frames`` with ``output`` in [0, 1]: :math:`(B, C, H, W)` for deblurring,
        :math:`(B, T, C, H, W)` for interpolation.

    Example:
        >>> EDIAdapter(mode="interpolation")
        EDIAdapter(mode=interpolation, threshold=0.2, num_bins=500)
    """

    model_name = "EDI"

    def __init__(self, mode: str = "deblur", threshold: float | str = 0.2, num_bins: int = 500) -> None:
        super().__init__()
        if mode not in ("deblur", "interpolation"):
            raise ValueError(f"mode must be 'deblur' or 'interpolation', got {mode!r}")
        if mode == "interpolation" and isinstance(threshold, str):
            raise ValueError("threshold='auto' is supported for mode='deblur' only")
        self.mode, self.threshold, self.num_bins = mode, threshold, num_bins

    def extra_repr(self) -> str:
        return f"mode={self.mode}, threshold={self.threshold}, num_bins={self.num_bins}"

    @torch.compiler.disable  # EDI reads events of data-dependent sizes: traced, it breaks the graph at every step
    def forward(self, frames: EventFrames) -> EventFrames:
        self.check_frames(frames, image=False)  # edi_deblur / edi_interpolate check the frames themselves
        events = self.input_events(frames)
        if self.mode == "deblur":
            time = None if frames.target_times is None else frames.target_times[:, 0]
            out = edi_deblur(frames.blurry, events, frames.exposure_start, frames.exposure_end, self.threshold,
                             None, self.num_bins, time)
        else:
            if frames.target_times is None:
                raise ValueError("EDIAdapter(mode='interpolation') needs frames.target_times (B, T) in us")
            out = edi_interpolate(frames.replace(corrected=None, events=events, latency=None), frames.target_times,
                                  self.threshold, None, None, self.num_bins)
        return frames.replace(output=torch.clamp(out, 0.0, 1.0))
