"""evlatcorr: event-camera latency correction for event-guided deblurring and interpolation."""

from __future__ import annotations

from evlatcorr.events import Events, polarity_to_signed
from evlatcorr.frames import EventFrames

__version__ = "0.1.0"

__all__ = ["Events", "EventFrames", "polarity_to_signed", "__version__"]
