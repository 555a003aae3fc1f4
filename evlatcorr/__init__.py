"""evlatcorr: event-camera latency correction for event-guided deblurring and interpolation.

Example:
    >>> import torch.nn as nn
    >>> from evlatcorr import EventLatencyCorrector
    >>> pipeline = nn.Sequential(EventLatencyCorrector(), nn.Identity())
"""

from __future__ import annotations

import os

# EDI and the latency search stream through tensors of hundreds of MB; on the CPU, touching them on
# 4 KB pages costs more page-fault time than arithmetic (EDI 2.5x slower). PyTorch backs large CPU
# tensors with 2 MB pages when this is set before its first large allocation (i.e. when evlatcorr
# is imported first, as by our command lines and scripts); export THP_MEM_ALLOC_ENABLE=0 to opt out.
os.environ.setdefault("THP_MEM_ALLOC_ENABLE", "1")

from evlatcorr.correction import EventLatencyCorrector, correct_constant_latency
from evlatcorr.edi import edi_deblur, edi_interpolate, estimate_threshold
from evlatcorr.etf import (
    EdgeThickness,
    EventTemporalFidelity,
    LocalContrast,
    edge_thickness,
    etf_loss,
    local_contrast,
    temporal_consistency,
)
from evlatcorr.events import Events, polarity_to_signed
from evlatcorr.frames import EventFrames
from evlatcorr.integral import cumulative_event_grid, event_histogram
from evlatcorr.search import ConstantSearchResult, search_constant_latency

__version__ = "0.1.0"

__all__ = [
    "ConstantSearchResult",
    "EdgeThickness",
    "EventFrames",
    "EventLatencyCorrector",
    "EventTemporalFidelity",
    "Events",
    "LocalContrast",
    "correct_constant_latency",
    "cumulative_event_grid",
    "edge_thickness",
    "edi_deblur",
    "edi_interpolate",
    "estimate_threshold",
    "etf_loss",
    "event_histogram",
    "local_contrast",
    "polarity_to_signed",
    "search_constant_latency",
    "temporal_consistency",
    "__version__",
]
