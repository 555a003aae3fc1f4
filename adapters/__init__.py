"""Adapters that feed (corrected) events to restoration models; installed as ``evlatcorr.adapters``.

Each adapter is an ``nn.Module`` taking an ``EventFrames`` batch and returning it with ``output``
filled, so ``nn.Sequential(EventLatencyCorrector(), adapter)`` works. EFNet, GEM and REFID
adapters are not written yet.
"""

from __future__ import annotations

from evlatcorr.adapters.edi import EDIAdapter

__all__ = ["EDIAdapter"]
