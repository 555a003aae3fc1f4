"""The summary of a recording printed by ``evlatcorr info``: frames, exposures, event counts and span."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from evlatcorr.checks import FEW_EVENTS

__all__ = ["event_summary", "frame_summary"]


def event_summary(chunks: Iterable[Any], times: list[tuple[float, float, int]] | None = None) -> dict[str, Any]:
    """Count, ON fraction and time span (µs) of the events of ``chunks``, one chunk in memory at a time.

    With ``times`` (each frame's exposure start, end and segment, as ``Recording.frame_times``), also the events
    inside each frame's exposure (lowest, median, highest) and the frames with none, and the events of each frame's
    exposure and default search window (the exposure and one exposure time after it, what the latency is estimated
    from) with the frames that hold under :data:`~evlatcorr.checks.FEW_EVENTS` there: where a scene is still or dark,
    latency has little to go on. The chunks then come in time order within each segment, with any other object (a
    segment's end marker) between segments.

    Example:
        >>> chunk = np.array([(0, 0, 5.0, 1), (0, 0, 15.0, -1), (0, 0, 16.0, 1)],
        ...                  dtype=[("x", "u2"), ("y", "u2"), ("t", "f8"), ("p", "i1")])
        >>> summary = event_summary([chunk], [(0.0, 10.0, 0), (10.0, 20.0, 0), (20.0, 30.0, 0)])
        >>> summary["events in each exposure (min, median, max)"], summary["frames without events in their exposure"]
        ((0, 1, 2), '1 of 3')
        >>> summary["events in each exposure and search window (min, median, max)"]
        (0, 2, 3)
        >>> summary["frames under 100 events there (too few to tell a latency)"]
        '3 of 3'
    """
    count, first, last, on = 0, None, None, 0
    segments = np.array([segment for _, _, segment in times or []], dtype=np.int64)
    starts = np.array([start for start, _, _ in times or []], dtype=np.float64)
    ends = np.array([end for _, end, _ in times or []], dtype=np.float64)
    reach = ends + (ends - starts)  # the default search range: up to one exposure time late
    inside = np.zeros(len(segments), dtype=np.int64)
    searched = np.zeros(len(segments), dtype=np.int64)
    segment = 0
    for chunk in chunks:
        if not isinstance(chunk, np.ndarray):  # the end of a segment: the next chunks are the next segment's
            segment += 1
            continue
        if len(chunk):
            count += len(chunk)
            on += int((chunk["p"] > 0).sum())
            first = float(chunk["t"][0]) if first is None else min(first, float(chunk["t"][0]))
            last = float(chunk["t"][-1]) if last is None else max(last, float(chunk["t"][-1]))
            if len(inside):  # each frame's share of this chunk, from its sorted times: one pass over the events
                mine = segments == segment
                t = chunk["t"]
                from_start = np.searchsorted(t, starts[mine])
                inside[mine] += np.searchsorted(t, ends[mine]) - from_start
                searched[mine] += np.searchsorted(t, reach[mine]) - from_start
    summary = {"events": count, "on_fraction": on / count if count else None,
               "event_time_us (first, last)": (first, last)}
    if len(inside):
        summary["events in each exposure (min, median, max)"] = (int(inside.min()), int(np.median(inside)),
                                                                 int(inside.max()))
        summary["frames without events in their exposure"] = f"{int((inside == 0).sum())} of {len(inside)}"
        summary["events in each exposure and search window (min, median, max)"] = (
            int(searched.min()), int(np.median(searched)), int(searched.max()))
        summary[f"frames under {FEW_EVENTS} events there (too few to tell a latency)"] = (
            f"{int((searched < FEW_EVENTS).sum())} of {len(searched)}")
    return summary


def frame_summary(times: list[tuple[float, float, int]]) -> dict[str, Any]:
    """Frame count, shortest and longest exposure, first and last exposure start (µs)."""
    exposures = [e - s for s, e, _ in times]
    return {
        "frames": len(times),
        "exposure_us (min, max)": (min(exposures), max(exposures)) if exposures else None,
        "frame_exposure_start_us (first, last)": (times[0][0], times[-1][0]) if times else None,
    }
