"""Restoration models on recordings: build a model by name, pair frames, pick output times.

The command line's ``deblur`` and ``interpolate`` run any model the same way: ``model(frames)``
with the stamped events and ``model(corrector(frames))`` with the corrected ones (every adapter
reads ``frames.corrected`` when a corrector filled it).
"""

from __future__ import annotations

import itertools
import math
import warnings
from collections.abc import Iterable, Iterator

import numpy as np
import torch
from torch import Tensor, nn

from evlatcorr.frames import EventFrames
from evlatcorr.sample_warnings import user_stacklevel

__all__ = ["MODELS", "INTERPOLATION_MODELS", "build_model", "needs_pairs", "pair_frames", "between_times",
           "has_events", "pair_reach_us", "pair_lead_us", "recording_threshold", "to_uint8", "side_by_side"]

MODELS = ("edi", "efnet", "gem", "refid")
INTERPOLATION_MODELS = ("edi", "refid")


def needs_pairs(model: str, task: str = "deblur") -> bool:
    """Whether ``model`` reads two consecutive frames (REFID always; EDI to interpolate)."""
    return model == "refid" or task == "interpolation"


def build_model(model: str, task: str = "deblur", checkpoint: str | None = None, threshold: float | str = 0.2,
                num_bins: int = 500) -> nn.Module:
    """A restoration model by name, in eval mode.

    Args:
        model: one of :data:`MODELS`; for ``task="interpolation"`` one of :data:`INTERPOLATION_MODELS`.
        task: ``"deblur"`` (one sharp frame per blurry frame, at mid-exposure) or ``"interpolation"``
            (frames at ``frames.target_times`` between two blurry frames).
        checkpoint: weights for the networks: ``None`` for the shipped ones (``"default"``) or a path.
        threshold: EDI's contrast threshold θ (EDI only).
        num_bins: EDI sub-intervals per exposure (EDI only).

    Raises:
        ValueError: an unknown model, a model that cannot do ``task``, or weights that do not fit it.

    Example:
        >>> build_model("edi")
        EDIAdapter(mode=deblur, threshold=0.2, num_bins=500)
    """
    from evlatcorr.adapters import EDIAdapter, EFNetAdapter, GEMAdapter, REFIDAdapter

    if model not in MODELS:
        raise ValueError(f"model must be one of {MODELS}, got {model!r}")
    if task not in ("deblur", "interpolation"):
        raise ValueError(f"task must be 'deblur' or 'interpolation', got {task!r}")
    if task == "interpolation" and model not in INTERPOLATION_MODELS:
        raise ValueError(f"{model} does not interpolate frames; use one of {INTERPOLATION_MODELS}")
    if model == "edi":
        if checkpoint is not None:
            raise ValueError("EDI has no weights: drop the checkpoint")
        return EDIAdapter(mode=task if task == "deblur" else "interpolation", threshold=threshold,
                          num_bins=num_bins).eval()
    weights = "default" if checkpoint is None else str(checkpoint)
    if model == "efnet":
        net = EFNetAdapter(checkpoint=weights)
    elif model == "gem":
        net = GEMAdapter(checkpoint=weights)
    else:  # REFID interpolation weights deblur too: the output frame nearest each target time
        net = REFIDAdapter(checkpoint=weights, select="nearest")
    return net.eval()


def pair_frames(frames: Iterable[EventFrames]) -> Iterator[tuple[EventFrames, EventFrames | None]]:
    """Each frame with the next one of its segment as ``blurry_next`` (for REFID and interpolation).

    The first frame's events must reach past the next exposure (open the recording with a large
    enough ``after_us``).

    Yields:
        ``(frames_i, paired)`` where ``paired`` is ``frames_i`` with ``blurry_next`` and the next
        exposure set, or None for the last frame of a segment (it has no next frame).
    """
    previous: EventFrames | None = None
    for current in frames:
        if previous is not None:
            same = previous.meta.get("segment", 0) == current.meta.get("segment", 0)
            yield previous, _pair(previous, current) if same else None
        previous = current
    if previous is not None:
        yield previous, None


def _pair(first: EventFrames, second: EventFrames) -> EventFrames:
    return first.replace(blurry_next=second.blurry, exposure_start_next=second.exposure_start,
                         exposure_end_next=second.exposure_end)


def between_times(frames: EventFrames, num: int) -> Tensor:
    """``num`` times evenly spaced strictly between a pair's exposures :math:`(B, num)`, µs.

    Example:
        >>> from evlatcorr.events import Events
        >>> ev = Events(torch.tensor([0]), torch.tensor([0]), torch.tensor([5.0]), torch.tensor([1]),
        ...             sensor_size=(2, 2))
        >>> f = EventFrames(torch.zeros(1, 1, 2, 2), ev, torch.tensor([0.0]), torch.tensor([10.0]),
        ...                 blurry_next=torch.zeros(1, 1, 2, 2), exposure_start_next=torch.tensor([40.0]),
        ...                 exposure_end_next=torch.tensor([50.0]))
        >>> between_times(f, 2).tolist()
        [[20.0, 30.0]]
    """
    if num < 1:
        raise ValueError(f"num must be >= 1, got {num}")
    if frames.exposure_start_next is None:
        raise ValueError("between_times needs a pair (exposure_start_next)")
    end, start_next = frames.exposure_end, frames.exposure_start_next
    steps = torch.arange(1, num + 1, dtype=torch.float64, device=end.device) / (num + 1)
    return end[:, None] + (start_next - end)[:, None] * steps


def has_events(frames: EventFrames) -> bool:
    """Whether every sample has events in its exposure and the search window after it (the corrector needs
    some)."""
    inside = frames.events.window(frames.exposure_start, frames.exposure_end + frames.exposure_time)
    return bool((inside.counts() > 0).all())


def _longest_exposure_us(rec) -> float:
    return max((e - s for s, e, _ in rec.frame_times()), default=0.0)


def search_reach_us(rec, search_high_us: float | None = None) -> float:
    """How far past a frame's exposure end the latency search reads events: the longest exposure (the learned
    reader reads its candidates over 0 to the exposure time, whatever range bounds its answer), or the top of the
    search range where it reaches further.

    Raises:
        ValueError: when ``search_high_us`` is not a finite number (or None).
    """
    if search_high_us is not None and not math.isfinite(search_high_us):
        raise ValueError(f"search_high_us must be a finite number of us or None, got {search_high_us}")
    longest = _longest_exposure_us(rec)
    return longest if search_high_us is None else max(search_high_us, longest)


def pair_reach_us(rec, search_high_us: float | None = None) -> float:
    """How far past a frame's exposure end its events must reach for pairs: to the next exposure's end,
    plus what the latency search reads (:func:`search_reach_us`)."""
    times = rec.frame_times()
    reach = max((b[1] - a[1] for a, b in zip(times, times[1:]) if a[2] == b[2]), default=0.0)
    return reach + search_reach_us(rec, search_high_us)


def pair_lead_us(rec) -> float:
    """How far before a pair's first exposure its events must start: the longest exposure (REFID's voxel
    grid starts a fraction of a sharp-frame interval before it, and a correction moves events back)."""
    return _longest_exposure_us(rec)


def recording_threshold(rec, search_range: tuple[float, float] | None = None, num_bins: int = 200,
                        device: torch.device | str = "cpu", max_pairs: int = 3, scan_frames: int = 12) -> float | None:
    """One contrast threshold θ for a recording, from its first frames (two-frame consistency).

    Among the first ``scan_frames`` frame pairs, the ``max_pairs`` with the most events in the first
    exposure are used: each gets its latency from the constant corrector (θ = 0.2 for the search),
    then :func:`~evlatcorr.consistency.estimate_recording_threshold`; the median θ is returned.

    Args:
        rec: a :class:`~evlatcorr.io.Recording`; its ``after_us`` is changed for the pass and restored.
        search_range: the latency search range, µs (default: 0 to the exposure time).
        num_bins: EDI sub-intervals per exposure.
        device: where to compute.
        max_pairs: pairs used.
        scan_frames: frames looked at.

    Returns:
        θ, or None when the recording has no pair of frames with events (use a per-frame estimate). A θ at either
        end of :data:`~evlatcorr.consistency.THRESHOLD_BOUNDS` comes with a warning: at the low end the pairs agree
        best with hardly any deblurring (few events beside noise, or a latency the search missed), and EDI with it
        leaves the frames about as blurred as they are.
    """
    from evlatcorr.blank_frames import blank_pairs
    from evlatcorr.checks import FEW_EVENTS
    from evlatcorr.consistency import THRESHOLD_BOUNDS, estimate_recording_threshold
    from evlatcorr.correction import EventLatencyCorrector

    saved = rec.after_us
    rec.after_us = pair_reach_us(rec, None if search_range is None else search_range[1])
    try:
        candidates = []
        for _, pair in itertools.islice(pair_frames(itertools.islice(rec, scan_frames + 1)), scan_frames):
            # a blank frame (black, saturated or flat) agrees with its neighbour at no θ (the search skips it too)
            if pair is not None and has_events(pair) and not bool(blank_pairs(pair.blurry, pair.blurry_next)[0]):
                inside = pair.events.window(pair.exposure_start, pair.exposure_end)
                candidates.append((len(inside), pair))
    finally:
        rec.after_us = saved
    candidates.sort(key=lambda c: -c[0])
    corrector = EventLatencyCorrector(threshold=0.2, num_bins=num_bins, search_range=search_range)
    thetas, most_events = [], 0
    for _, pair in candidates[:max_pairs]:
        pair = pair.to(device)
        found = corrector(pair)
        most_events = max(most_events, int(found.meta["events_in_window"].max()))
        thetas.append(estimate_recording_threshold(pair, latency=found.latency.mean(dim=(1, 2, 3)), num_bins=num_bins))
    if not thetas:
        return None
    theta = sorted(thetas)[len(thetas) // 2]
    if most_events < FEW_EVENTS:
        warnings.warn(f"the recording's contrast threshold {theta:.3f} is estimated from frames with at most "
                      f"{most_events} events in their exposure and search window (under {FEW_EVENTS}): too few to "
                      "tell it; give the camera's threshold if you know it (--threshold, threshold=)",
                      stacklevel=user_stacklevel())
    low, high = THRESHOLD_BOUNDS
    if not low * 1.02 < theta < high / 1.02:  # the golden-section search ends within a hair of a bound it ran into
        edge = "low" if theta <= low * 1.02 else "high"
        effect = ("EDI with it leaves the frames about as blurred as they are (the first frames' pairs agree best "
                  "with hardly any deblurring: few events beside noise, or a latency the search missed)"
                  if edge == "low" else "EDI with it may overshoot every change")
        warnings.warn(f"the recording's contrast threshold estimate {theta:.3f} lies at the {edge} end of its search "
                      f"range {low:g}-{high:g}: {effect}; give the camera's threshold if you know it (--threshold, "
                      "threshold=)", stacklevel=user_stacklevel())
    return theta


def to_uint8(image: Tensor) -> np.ndarray:
    """One image :math:`(C, H, W)` in [0, 1] as ``uint8`` :math:`(H, W)` (grey) or :math:`(H, W, 3)`."""
    a = (image.detach().float().clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
    return a[0] if a.shape[0] == 1 else a.transpose(1, 2, 0)


def side_by_side(images: list[Tensor], gap: int = 2) -> np.ndarray:
    """Images :math:`(C, H, W)` next to each other with a white gap, as ``uint8`` :math:`(H, W', 3)`.

    Example:
        >>> side_by_side([torch.zeros(1, 4, 4), torch.ones(3, 4, 4)]).shape
        (4, 10, 3)
    """
    parts = []
    for k, image in enumerate(images):
        a = to_uint8(image)
        a = np.repeat(a[..., None], 3, axis=2) if a.ndim == 2 else a
        if k:
            parts.append(np.full((a.shape[0], gap, 3), 255, dtype=np.uint8))
        parts.append(a)
    return np.concatenate(parts, axis=1)
