"""The summary of a recording printed by ``evlatcorr info``: frames, exposures, event counts and span."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

__all__ = ["event_summary", "frame_summary"]


def event_summary(chunks: Iterable[np.ndarray]) -> dict[str, Any]:
    """Count, ON fraction and time span (µs) of the events of ``chunks``, one chunk in memory at a time."""
    count, first, last, on = 0, None, None, 0
    for chunk in chunks:
        if len(chunk):
            count += len(chunk)
            on += int((chunk["p"] > 0).sum())
            first = float(chunk["t"][0]) if first is None else min(first, float(chunk["t"][0]))
            last = float(chunk["t"][-1]) if last is None else max(last, float(chunk["t"][-1]))
    return {"events": count, "on_fraction": on / count if count else None, "event_time_us (first, last)": (first, last)}


def frame_summary(times: list[tuple[float, float, int]]) -> dict[str, Any]:
    """Frame count, shortest and longest exposure, first and last exposure start (µs)."""
    exposures = [e - s for s, e, _ in times]
    return {
        "frames": len(times),
        "exposure_us (min, max)": (min(exposures), max(exposures)) if exposures else None,
        "frame_exposure_start_us (first, last)": (times[0][0], times[-1][0]) if times else None,
    }
