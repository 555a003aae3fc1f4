"""Adapters that feed (corrected) events to restoration models; installed as ``evlatcorr.adapters``.

Each adapter is an ``nn.Module`` taking an ``EventFrames`` batch and returning it with ``output``
filled, so ``nn.Sequential(EventLatencyCorrector(), adapter)`` works; the steps they share (input checks,
event choice, padding, output finishing, weights, repr) are in their base class :class:`NetworkAdapter`.
Adapters of learned models take ``checkpoint=None`` (random weights), ``"default"`` (shipped weights) or a
path, read by :func:`load_weights` (official BasicSR ``.pth``, Lightning ``.ckpt``, plain state_dicts, our
sharded ``.safetensors`` written by :func:`save_weights`).
"""

from __future__ import annotations

from evlatcorr.adapters.base import NetworkAdapter
from evlatcorr.adapters.checkpoint import load_weights, resolve_checkpoint, save_weights
from evlatcorr.adapters.edi import EDIAdapter
from evlatcorr.adapters.efnet import EFNetAdapter
from evlatcorr.adapters.gem import GEMAdapter
from evlatcorr.adapters.refid import REFIDAdapter

__all__ = [
    "EDIAdapter",
    "EFNetAdapter",
    "GEMAdapter",
    "NetworkAdapter",
    "REFIDAdapter",
    "load_weights",
    "resolve_checkpoint",
    "save_weights",
]
