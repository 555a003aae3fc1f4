"""evlatcorr: event-camera latency correction for event-guided deblurring and interpolation.

Importing the package loads nothing else and changes nothing in the process: each public name below
imports its module on first use.

Example:
    >>> import torch.nn as nn
    >>> from evlatcorr import EventLatencyCorrector
    >>> pipeline = nn.Sequential(EventLatencyCorrector(), nn.Identity())
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from evlatcorr._lazy import lazy_attributes

__version__ = "0.1.0"

_ORIGINS = {
    "ConstantSearchResult": "evlatcorr.search",
    "EdgeThickness": "evlatcorr.etf",
    "EventFrames": "evlatcorr.frames",
    "EventLatencyCorrector": "evlatcorr.correction",
    "EventTemporalFidelity": "evlatcorr.etf",
    "Events": "evlatcorr.events",
    "LocalContrast": "evlatcorr.etf",
    "correct_constant_latency": "evlatcorr.correction",
    "cumulative_event_grid": "evlatcorr.integral",
    "edge_thickness": "evlatcorr.etf",
    "edi_deblur": "evlatcorr.edi",
    "edi_interpolate": "evlatcorr.edi",
    "estimate_threshold": "evlatcorr.edi",
    "etf_loss": "evlatcorr.etf",
    "event_histogram": "evlatcorr.integral",
    "keep_freed_memory": "evlatcorr.pages",
    "local_contrast": "evlatcorr.etf",
    "polarity_to_signed": "evlatcorr.events",
    "prefer_fast_memory": "evlatcorr.pages",
    "prefer_large_pages": "evlatcorr.pages",
    "prefer_short_spin": "evlatcorr.pages",
    "search_constant_latency": "evlatcorr.search",
    "temporal_consistency": "evlatcorr.etf",
}

__all__ = [*_ORIGINS, "__version__"]

__getattr__, __dir__ = lazy_attributes(__name__, _ORIGINS)

if TYPE_CHECKING:  # what type checkers and IDEs see (`X as X`: re-exported)
    from evlatcorr.correction import EventLatencyCorrector as EventLatencyCorrector
    from evlatcorr.correction import correct_constant_latency as correct_constant_latency
    from evlatcorr.edi import edi_deblur as edi_deblur
    from evlatcorr.edi import edi_interpolate as edi_interpolate
    from evlatcorr.edi import estimate_threshold as estimate_threshold
    from evlatcorr.etf import EdgeThickness as EdgeThickness
    from evlatcorr.etf import EventTemporalFidelity as EventTemporalFidelity
    from evlatcorr.etf import LocalContrast as LocalContrast
    from evlatcorr.etf import edge_thickness as edge_thickness
    from evlatcorr.etf import etf_loss as etf_loss
    from evlatcorr.etf import local_contrast as local_contrast
    from evlatcorr.etf import temporal_consistency as temporal_consistency
    from evlatcorr.events import Events as Events
    from evlatcorr.events import polarity_to_signed as polarity_to_signed
    from evlatcorr.frames import EventFrames as EventFrames
    from evlatcorr.integral import cumulative_event_grid as cumulative_event_grid
    from evlatcorr.integral import event_histogram as event_histogram
    from evlatcorr.pages import keep_freed_memory as keep_freed_memory
    from evlatcorr.pages import prefer_fast_memory as prefer_fast_memory
    from evlatcorr.pages import prefer_large_pages as prefer_large_pages
    from evlatcorr.pages import prefer_short_spin as prefer_short_spin
    from evlatcorr.search import ConstantSearchResult as ConstantSearchResult
    from evlatcorr.search import search_constant_latency as search_constant_latency
