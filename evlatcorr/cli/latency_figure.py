"""Every frame's latency over a recording, drawn from the per-frame CSV rows of the commands: what ``evlatcorr
correct`` writes beside its report and ``deblur`` / ``interpolate --correct`` into their folder.

A recording of hundreds of frames is easier to judge by eye than by its CSV: whether the latency is steady, where
single frames stray from their neighbours, how sure the reader was (its spread) and which frames had too little
to go on (few events, none, a black frame)."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

__all__ = ["latency_figure", "write_figure_or_warn", "write_latency_figure"]

#: sources of a latency that did not come from the frame's own search (``meta["latency_source"]``, or the CLI's
#: ``skipped`` column), drawn with a marker of their own
_MARKED = {"fallback": ("x", "C3", "fallback (no clear minimum)"),
           "clipped": ("X", "C3", "black or saturated frame"),
           "flat": ("D", "C3", "flat frame (no structure above noise)"),
           "no events": ("v", "0.45", "no events: the previous latency")}


def latency_figure(rows: Sequence[Mapping[str, Any]], title: str = ""):
    """A figure of every frame's latency (top) and its events (bottom) against the time of its exposure.

    Args:
        rows: the commands' per-frame CSV rows (:func:`evlatcorr.cli.common.latency_row`; strings or numbers):
            ``exposure_start_us``, ``exposure_end_us``, ``latency_us`` (the latency written), and where present
            ``frame_latency_us`` (each frame's own estimate, where the written one is fused), ``pair_latency_us``
            (where the frame and the next agree best, when their agreement was fused too), ``latency_min_us`` /
            ``latency_max_us`` (a map's range), ``spread_us``, ``source``, ``skipped`` and ``events_in_window``.
            Rows without a latency (a frame not corrected) are left out.
        title: the figure's title (e.g. the recording's name).

    Returns:
        a :class:`matplotlib.figure.Figure` (not registered with pyplot).

    Raises:
        ValueError: when no row has a latency.

    Example:
        >>> rows = [{"exposure_start_us": 25000.0 * i, "exposure_end_us": 25000.0 * i + 20000.0,
        ...          "latency_us": 3000.0 + 100 * i, "spread_us": 400.0, "events_in_window": 5000} for i in range(5)]
        >>> fig = latency_figure(rows, "my recording")
        >>> [ax.get_ylabel() for ax in fig.axes]
        ['latency (ms)', 'events in window']
    """
    from matplotlib.figure import Figure

    rows = [r for r in rows if math.isfinite(_number(r.get("latency_us")))]
    if not rows:
        raise ValueError("no frame has a latency to draw")
    middle = [0.5 * (_number(r["exposure_start_us"]) + _number(r["exposure_end_us"])) for r in rows]
    time_s = [(t - middle[0]) / 1e6 for t in middle]
    written = _column(rows, "latency_us")
    own = _column(rows, "frame_latency_us")
    fused = any(math.isfinite(v) for v in own)
    centre = own if fused else written
    spread = _column(rows, "spread_us")
    low, high = _column(rows, "latency_min_us"), _column(rows, "latency_max_us")

    fig = Figure(figsize=(9, 5.2))
    top, bottom = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    style = {"markersize": 3 if len(rows) <= 300 else 1.5, "linewidth": 1}
    if any(math.isfinite(s) for s in spread):
        top.fill_between(time_s, [(c - s) / 1e3 for c, s in zip(centre, spread)],
                         [(c + s) / 1e3 for c, s in zip(centre, spread)], color="C1", alpha=0.2, linewidth=0,
                         label="± the reader's spread")
    if any(h > lo for lo, h in zip(low, high)):  # spatial mode: each frame's map spans a range
        top.fill_between(time_s, [v / 1e3 for v in low], [v / 1e3 for v in high], color="C0", alpha=0.15,
                         linewidth=0, label="the map's range")
    if fused:
        top.plot(time_s, [v / 1e3 for v in own], "o", color="C1", markerfacecolor="none", label="each frame alone",
                 **style)
    pairs = [(t, v) for t, v in zip(time_s, _column(rows, "pair_latency_us")) if math.isfinite(v)]
    if pairs:
        top.plot([t for t, _ in pairs], [v / 1e3 for _, v in pairs], "x", color="C2",
                 label="agreement with the next frame", **style)
    top.plot(time_s, [v / 1e3 for v in written], "-o", color="C0",
             label="written (fused with nearby frames)" if fused else "written", **style)
    for kind, (marker, colour, label) in _MARKED.items():
        picked = [(t, v) for t, v, r in zip(time_s, written, rows)
                  if kind in (str(r.get("source", "")), str(r.get("skipped", "")))]
        if picked:
            top.plot([t for t, _ in picked], [v / 1e3 for _, v in picked], marker, color=colour, markersize=7,
                     linestyle="none", label=f"{label}: {len(picked)}")
    top.set_ylabel("latency (ms)")
    top.set_ylim(bottom=min(0.0, min(written) / 1e3, *(v / 1e3 for v in own if math.isfinite(v)),
                            *(v / 1e3 for _, v in pairs)))
    top.grid(alpha=0.3)
    top.legend(fontsize=8, loc="best")
    median = sorted(written)[len(written) // 2] / 1e3
    top.set_title(f"{title + ': ' if title else ''}{len(rows)} frames, median latency {median:.2f} ms", fontsize=10)

    events = _column(rows, "events_in_window")
    bottom.plot(time_s, events, "-", color="0.3", linewidth=1)
    if any(v == 0 for v in events):  # logarithmic, with a frame without events still drawn, at 0
        bottom.set_yscale("symlog", linthresh=1.0)
        bottom.set_ylim(bottom=0.0)
    elif any(v > 0 for v in events):
        bottom.set_yscale("log")
    bottom.set_ylabel("events in window")
    bottom.set_xlabel("time of the exposure's middle, from the first frame's (s)")
    bottom.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def write_latency_figure(rows: Sequence[Mapping[str, Any]], path: str | Path, title: str = "") -> Path:
    """:func:`latency_figure` of ``rows`` as a PNG at ``path`` (written whole or not at all); returns ``path``."""
    from evlatcorr.io.h5 import atomic_path

    figure = latency_figure(rows, title)
    with atomic_path(path) as tmp:
        figure.savefig(tmp, dpi=90, format="png")
    return Path(path)


def _number(value: Any) -> float:
    """A CSV cell as a float; NaN where it is empty or not a number."""
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _column(rows: Sequence[Mapping[str, Any]], key: str) -> list[float]:
    return [_number(r.get(key)) for r in rows]


def write_figure_or_warn(rows: Sequence[Mapping[str, Any]], path: str | Path, title: str = "") -> Path | None:
    """:func:`write_latency_figure`, for the commands: the figure comes after the data it draws is written, so a
    figure that cannot be drawn or written costs a warning, not the corrected recording. Returns the path written,
    or None (also when no frame has a latency)."""
    import warnings

    if not any(math.isfinite(_number(r.get("latency_us"))) for r in rows):
        return None
    try:
        return write_latency_figure(rows, path, title)
    except (OSError, ValueError, RuntimeError) as exc:  # a full disk, a read-only folder, a backend's failure
        warnings.warn(f"the latency figure {path} was not written: {exc}", stacklevel=2)
        return None
