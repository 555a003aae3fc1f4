"""One latency from several frames of a recording: the evidence of neighbouring frames, combined.

A camera's latency follows the light, which changes over seconds, so consecutive frames of a recording share it,
while one frame's estimate scatters with its scene (a few frames of a sequence can be off by milliseconds while
their neighbours are right). The learned reader (``score="learned"``, the default) gives each frame a
log-probability over the candidate latencies (``meta["latency_log_probability"]``); :func:`fuse_latencies` sums
those of a frame and its neighbours, as independent evidence of one latency, and takes the centre of the result
as the search does for one frame. Each frame keeps its own candidates that could be scored: the fused latency
never needs events past the frame's last one. A frame whose windows held no events at all (its events stop at
its exposure's end) takes its neighbours' latency instead of no shift. Where pairs of consecutive frames are fused
too (their agreement, :mod:`evlatcorr.pair_evidence`), the readers choose the neighbourhood and the pairs place the
latency in it (:data:`DEFAULT_PAIR_REFINE`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor, nn

from evlatcorr.checks import NoEventsError
from evlatcorr.config import DEFAULT_PAIR_WEIGHT
from evlatcorr.curve_reader import CENTRE_HALF_WIDTH, probability_centre
from evlatcorr.frames import EventFrames
from evlatcorr.pair_evidence import pair_log_odds
from evlatcorr.sample_warnings import SampleWarning, user_stacklevel

__all__ = ["fuse_latencies", "frame_evidence", "no_latency_share", "LatencyHistory", "StreamingLatencyCorrector",
           "DEFAULT_FUSED_FRAMES", "DEFAULT_NO_LATENCY_MASS", "DEFAULT_PAIR_REFINE", "PAIR_REFINE_HALF_WIDTH"]

# frames either side whose evidence a frame takes: on 6-frame sequences of the accuracy suite's tuning cases
# (constant and photoreceptor latency), 2 either side lowered the constant-latency median error from 664 to 513 µs,
# the 90th percentile from 4966 to 2942 µs, and raised the 10th percentile of the EDI recovery from 10 to 42 %
DEFAULT_FUSED_FRAMES = 2
# a frame whose fused reader probability keeps more than this share on the candidates whose centre reaches no latency
# gets none (no_latency_share): on the tuning cases' 6-frame sequences (fused ±2) their ideal events within 150 µs of 0
# went from 29 to 404 of 943 and their mean EDI PSNR loss from 0.32 to 0.22 dB, the delayed frames' mean PSNR moved by
# 0.001 dB (docs/estimator.md); 0.1 cost the delayed frames more, 0.3 gained less
DEFAULT_NO_LATENCY_MASS = 0.2
# the pairs place the latency, the frames' readers choose where: within PAIR_REFINE_HALF_WIDTH candidates of the fused
# latency (±1 ms at 20 ms) the pairs' log-odds count DEFAULT_PAIR_REFINE times. A pair's agreement (ramps) is not late
# as one frame's sharpness is, but it can be wrong far away, where the readers outvote it. On the tuning cases'
# 6-frame sequences (2 either side, pairs at weight 10) the constant-latency median error fell from 278 to 143 µs
# (30x: 126 µs) with the p90 about the same; on dev, 30x cost EFNet and EDI 0.05-0.07 dB on average, 10x 0.01-0.04
# dB, and both raised the 10th-percentile recovery (docs/estimator.md)
DEFAULT_PAIR_REFINE = 10.0
PAIR_REFINE_HALF_WIDTH = 5


def fuse_latencies(latency: Tensor, candidates: Tensor | Sequence[Tensor],
                   log_probability: Tensor | Sequence[Tensor | None] | None,
                   before: int = DEFAULT_FUSED_FRAMES, after: int = DEFAULT_FUSED_FRAMES,
                   no_latency_mass: float | None = DEFAULT_NO_LATENCY_MASS,
                   pair_log_odds: Sequence[Tensor | None] | None = None,
                   pair_refine: float | None = DEFAULT_PAIR_REFINE) -> Tensor:
    """Each frame's latency from its own and its neighbours' reader log-probabilities.

    Args:
        latency: the frames' own estimates :math:`(N,)` µs, in recording order. A frame with no log-probability
            (another score, or nothing could be scored) takes its neighbours' fused latency instead, or keeps its own
            when no frame of its window has one.
        candidates: each frame's candidate latencies :math:`(N, K)` µs, sorted (``meta["etf_curve"][0]``),
            :math:`(K,)` when all frames share them, or a list of N such rows (their lengths may differ). Frames
            with other candidates (another exposure time) are interpolated onto the frame's own.
        log_probability: :math:`(N, K)` or a list of N rows (``meta["latency_log_probability"]``): −inf where a
            candidate could not be scored (uninformative for the other frames, excluded for the frame itself), a
            NaN row or None for a frame with none. None: nothing to fuse, ``latency`` is returned.
        before: earlier frames that count (0 or more).
        after: later frames that count (0 for a stream, where the next frames are not there yet).
        no_latency_mass: in (0, 1), or None for no such rule: a frame whose fused probability gives the candidates
            whose centre reaches no latency (0 and the :data:`~evlatcorr.curve_reader.CENTRE_HALF_WIDTH` above it,
            :func:`no_latency_share`) more than this share gets 0, where at least two frames' evidence is fused. One
            frame's curves barely tell no latency from a little; a few frames' together do better
            (:data:`DEFAULT_NO_LATENCY_MASS`, ``docs/estimator.md``).
        pair_log_odds: N rows or None: frame ``k``'s with frame ``k + 1``'s agreement over frame ``k``'s candidates
            (:func:`evlatcorr.pair_evidence.pair_log_odds`), added to frame ``k``'s evidence wherever both are
            there; None for a frame without one (the last, or a pair that tells nothing).
        pair_refine: at least 1, or None: within :data:`PAIR_REFINE_HALF_WIDTH` candidates of the fused latency,
            the window's pair log-odds count this many times, and the centre of that sharpened evidence is the
            latency (:data:`DEFAULT_PAIR_REFINE`). The frames' readers choose the neighbourhood; the pairs, whose
            agreement is not late as one frame's sharpness is, place the latency in it. None or 1: the fused
            evidence's centre as it is.

    Returns:
        :math:`(N,)` float64 µs, on ``latency``'s device.

    Raises:
        ValueError: for shapes that do not match, a negative window, non-finite latencies or a ``no_latency_mass``
            outside (0, 1), or a ``pair_refine`` under 1.

    Example:
        >>> cand = torch.arange(0.0, 2000.0, 100.0)
        >>> def belief(mean, sigma):  # a frame's log-probability over the candidates
        ...     return torch.log_softmax(-((cand - mean) / sigma) ** 2, 0)
        >>> log_p = torch.stack([belief(400.0, 150.0), belief(1500.0, 1000.0), belief(400.0, 150.0)])
        >>> own = torch.tensor([400.0, 1500.0, 400.0])  # the middle frame, unsure, is off on its own
        >>> fuse_latencies(own, cand, log_p, before=1, after=1).round()
        tensor([422., 412., 422.], dtype=torch.float64)
    """
    if latency.dim() != 1 or not bool(torch.isfinite(latency).all()):
        raise ValueError(f"latency must be (N,) and finite, got {tuple(latency.shape)}")
    if isinstance(before, bool) or isinstance(after, bool) or not (isinstance(before, int) and isinstance(after, int)
                                                                   and before >= 0 and after >= 0):
        raise ValueError(f"before and after must be whole numbers >= 0, got {before!r} and {after!r}")
    if no_latency_mass is not None and not 0 < no_latency_mass < 1:
        raise ValueError(f"no_latency_mass must be in (0, 1) or None, got {no_latency_mass!r}")
    if pair_refine is not None and (isinstance(pair_refine, bool) or not isinstance(pair_refine, (int, float))
                                    or not math.isfinite(pair_refine) or pair_refine < 1):
        raise ValueError(f"pair_refine must be a finite number >= 1 or None, got {pair_refine!r}")
    out = latency.detach().to("cpu", torch.float64).clone()
    if log_probability is None:
        return out.to(latency.device)
    n = len(latency)
    log_p = _rows(log_probability, n, "log_probability")
    cand = _rows(candidates.expand(n, -1) if isinstance(candidates, Tensor) and candidates.dim() == 1 else candidates,
                 n, "candidates")
    for k in range(n):
        if log_p[k] is not None and (cand[k] is None or cand[k].shape != log_p[k].shape or log_p[k].dim() != 1):
            raise ValueError(f"frame {k}: candidates and log_probability must be rows of one length, got "
                             f"{None if cand[k] is None else tuple(cand[k].shape)} and {tuple(log_p[k].shape)}")
    has_row = [r is not None and not bool(torch.isnan(r).any()) and bool(torch.isfinite(r).any()) for r in log_p]
    evidence = [_uninformative_filled(log_p[j]) if has_row[j] else None for j in range(n)]
    pairs: list[Tensor | None] = [None] * n
    if pair_log_odds is not None:
        pairs = _rows(pair_log_odds, n, "pair_log_odds")
        for j in range(n):
            if pairs[j] is None or not has_row[j]:
                pairs[j] = None
                continue
            if pairs[j].shape != cand[j].shape or not bool(torch.isfinite(pairs[j]).all()):
                raise ValueError(f"frame {j}: pair_log_odds must be finite, one per candidate "
                                 f"{tuple(cand[j].shape)}, got {tuple(pairs[j].shape)}")
            evidence[j] = evidence[j] + pairs[j]
    for k in range(n):  # frames, not events or pixels: a recording has a few thousand
        window = [j for j in range(max(0, k - before), min(n, k + after + 1)) if has_row[j]]
        if not window:
            continue
        # a frame with no evidence of its own reads its neighbours' on the nearest one's candidates (the earlier
        # on a tie): their latency is a better guess for its late events than no shift
        own = k if has_row[k] else min(window, key=lambda j: (abs(j - k), j))
        total = torch.zeros_like(log_p[own])
        for j in window:
            total += _on_candidates(evidence[j], cand[j], cand[own])
        scored = torch.isfinite(log_p[own])
        total = torch.where(scored, total, -math.inf)
        # several frames' evidence only: one frame's curves barely tell no latency from a little
        if no_latency_mass is not None and len(window) > 1 and no_latency_share(total, cand[own]) > no_latency_mass:
            out[k] = 0.0
            continue
        out[k] = probability_centre(total, cand[own], int(scored.sum()))[1]
        with_pairs = [j for j in window if pairs[j] is not None]
        if pair_refine is not None and pair_refine != 1 and with_pairs:
            agreement = sum(_on_candidates(pairs[j], cand[j], cand[own]) for j in with_pairs)
            out[k] = _refined(total + (pair_refine - 1) * agreement, cand[own], float(out[k]))
    return out.to(latency.device)


def _refined(log_p: Tensor, candidates: Tensor, latency: float) -> float:
    """The centre of ``log_p`` (−inf where not scored) kept to within :data:`PAIR_REFINE_HALF_WIDTH` candidates of
    the one nearest ``latency``, µs; ``latency`` itself where none of them was scored."""
    nearest = int((candidates - latency).abs().argmin())
    near = (torch.arange(len(candidates)) - nearest).abs() <= PAIR_REFINE_HALF_WIDTH
    scored = torch.isfinite(log_p)
    if not bool((near & scored).any()):
        return latency
    return probability_centre(torch.where(near, log_p, -math.inf), candidates, int(scored.sum()))[1]


def frame_evidence(out: EventFrames) -> list[tuple[float, Tensor, Tensor | None]]:
    """What :func:`fuse_latencies` takes of each frame of a constant corrector's output: its own latency (µs, the
    mean of its map), its candidates :math:`(K,)` and the reader's log-probability :math:`(K,)` (None for another
    score, or where nothing could be scored), on the CPU.

    Raises:
        ValueError: when ``out`` is not a constant corrector's output (no ``meta["etf_curve"]`` or latency).

    Example:
        >>> from evlatcorr.correction import EventLatencyCorrector
        >>> from evlatcorr.simulate import simulate
        >>> out = EventLatencyCorrector()(simulate("camera", num_frames=2, height=24, width=32, seed=0).frames())
        >>> [(len(candidates), log_p is not None) for _, candidates, log_p in frame_evidence(out)]
        [(101, True), (101, True)]
    """
    if not isinstance(out, EventFrames) or out.latency is None or "etf_curve" not in out.meta:
        raise ValueError("frame_evidence takes the output of a constant-mode EventLatencyCorrector (its latency and "
                         "meta['etf_curve'])")
    own = out.latency.flatten(1).mean(1).double().cpu()
    candidates = out.meta["etf_curve"][0].double().cpu()
    log_p = out.meta.get("latency_log_probability")
    rows = [None] * len(own) if log_p is None else list(log_p.double().cpu())
    return [(float(own[b]), candidates[b], None if rows[b] is None or bool(torch.isnan(rows[b]).any()) else rows[b])
            for b in range(len(own))]


def _rows(values: Tensor | Sequence[Tensor | None], n: int, name: str) -> list[Tensor | None]:
    """``values`` as N float64 rows on the CPU (None kept)."""
    if isinstance(values, Tensor) and values.dim() != 2:
        raise ValueError(f"{name} must be (N, K) or a list of N rows, got {tuple(values.shape)}")
    rows = list(values)
    if len(rows) != n:
        raise ValueError(f"{name} must have one row per frame ({n}), got {len(rows)}")
    return [None if r is None else r.detach().to("cpu", torch.float64) for r in rows]


def no_latency_share(log_probability: Tensor, candidates: Tensor) -> float:
    """The probability that a reader's log-odds :math:`(K,)` give the candidates :math:`(K,)` µs whose centre reaches
    no latency: 0 and the :data:`~evlatcorr.curve_reader.CENTRE_HALF_WIDTH` candidates above it (0 where the
    candidates do not start at 0). Candidates that could not be scored (−inf or NaN) get none.

    Raises:
        ValueError: when the two are not 1-D of one length, a log-probability is +inf, or no candidate could be
            scored.

    Example:
        >>> round(no_latency_share(torch.log(torch.tensor([0.2, 0.1, 0.1, 0.6])), torch.arange(4.0)), 6)
        0.4
    """
    if log_probability.dim() != 1 or candidates.shape != log_probability.shape:
        raise ValueError(f"log_probability and candidates must be 1-D of one length, got "
                         f"{tuple(log_probability.shape)} and {tuple(candidates.shape)}")
    log_probability = log_probability.double().nan_to_num(nan=-math.inf, posinf=math.inf, neginf=-math.inf)
    if bool((log_probability == math.inf).any()) or not bool(torch.isfinite(log_probability).any()):
        raise ValueError("no_latency_share needs finite log-probabilities, -inf or NaN where a candidate could not be "
                         "scored, and at least one candidate scored")
    if float(candidates[0]) != 0.0:
        return 0.0
    return float(torch.softmax(log_probability, 0)[:CENTRE_HALF_WIDTH + 1].sum())


def _uninformative_filled(log_p: Tensor) -> Tensor:
    """A frame's log-probabilities with the candidates it could not score set to the median of those it could: it
    says nothing about them (its events stopped before their windows end)."""
    scored = torch.isfinite(log_p)
    return torch.where(scored, log_p, log_p[scored].median())


def _on_candidates(values: Tensor, source: Tensor, target: Tensor) -> Tensor:
    """``values`` given at the sorted ``source`` candidates, linearly interpolated at ``target`` (held at the ends)."""
    if source.shape == target.shape and torch.equal(source, target):
        return values
    right = torch.searchsorted(source, target).clamp(1, len(source) - 1)
    left = right - 1
    span = (source[right] - source[left]).clamp_min(1e-12)
    weight = ((target - source[left]) / span).clamp(0.0, 1.0)
    return values[left] + weight * (values[right] - values[left])


class LatencyHistory:
    """The evidence of a stream's latest frames: each new frame's latency fused with that of the ``before`` frames
    before it (:func:`fuse_latencies` with ``after=0``).

    The constant search takes one (``frames.meta["latency_history"]``, as :class:`StreamingLatencyCorrector` passes
    it) and reads each frame's latent image at its fused latency, from the frame's own integral: no second pass
    over its events.

    Example:
        >>> cand = torch.arange(0.0, 2000.0, 100.0)
        >>> history = LatencyHistory(before=1)
        >>> sure = torch.log_softmax(-((cand - 400.0) / 150.0) ** 2, 0)
        >>> unsure = torch.log_softmax(-((cand - 1500.0) / 1000.0) ** 2, 0)
        >>> round(history.fuse(400.0, cand, sure)), round(history.fuse(1500.0, cand, unsure))
        (400, 422)
    """

    def __init__(self, before: int = DEFAULT_FUSED_FRAMES) -> None:
        if isinstance(before, bool) or not isinstance(before, int) or before < 0:
            raise ValueError(f"before must be a whole number >= 0, got {before!r}")
        self.before = before
        self._rows: list[tuple[float, Tensor, Tensor | None, Tensor | None]] = []
        self._pairs: list[tuple[EventFrames | None, float, float]] = []  # the next frames' pairs, θ and weight
        #: where the last frame's pair agreed best, µs (NaN where it had none or the pair told nothing)
        self.pair_latency_us = math.nan

    def reset(self) -> None:
        """Forget the earlier frames: the next frame starts a new recording."""
        self._rows.clear()
        self._pairs.clear()

    def expect_pairs(self, pairs: Sequence[EventFrames | None], threshold: float | Sequence[float] = 0.2,
                     weight: float = DEFAULT_PAIR_WEIGHT) -> None:
        """The next frames' pairs, in the order :meth:`fuse` takes them: each frame with the next one
        (``blurry_next`` set, events up to past the next exposure; None for a frame without one), whose agreement
        (:func:`evlatcorr.pair_evidence.pair_log_odds` at θ ``threshold``, one or one per pair, and ``weight``)
        :meth:`fuse` adds to the frame's evidence. Replaces any not taken yet; ``[]`` clears them.

        The constant corrector calls it for a batch of pairs (``SearchConfig.pair_weight``)."""
        thresholds = [threshold] * len(pairs) if isinstance(threshold, (int, float)) else list(threshold)
        if len(thresholds) != len(pairs):
            raise ValueError(f"expect_pairs takes one threshold or one per pair ({len(pairs)}), got {len(thresholds)}")
        self._pairs = [(pair, float(theta), float(weight)) for pair, theta in zip(pairs, thresholds)]

    def fuse(self, latency: float, candidates: Tensor, log_probability: Tensor | None) -> float:
        """Take the next frame: its own latency (µs), its candidates :math:`(K,)` and the reader's log-probability of
        each :math:`(K,)` (None, or a NaN row, where it has none); returns its fused latency, µs."""
        row = None if log_probability is None else log_probability.detach().to("cpu", torch.float64)
        if row is not None and bool(torch.isnan(row).any()):
            row = None
        candidates = candidates.detach().to("cpu", torch.float64)
        pair, theta, weight = self._pairs.pop(0) if self._pairs else (None, 0.0, 0.0)
        agreement = None if pair is None or row is None else pair_log_odds(pair, theta, candidates, weight=weight)
        self.pair_latency_us = math.nan if agreement is None else float(candidates[agreement.argmax()])
        if self.before == 0 and agreement is None:  # nothing to fuse the frame's own estimate with
            return float(latency)
        self._rows.append((float(latency), candidates, row, agreement))
        del self._rows[:-(self.before + 1)]
        return float(fuse_latencies(torch.tensor([r[0] for r in self._rows], dtype=torch.float64),
                                    [r[1] for r in self._rows], [r[2] for r in self._rows], self.before, 0,
                                    pair_log_odds=[r[3] for r in self._rows])[-1])


class StreamingLatencyCorrector(nn.Module):
    """A constant-latency corrector for the frames of one recording, passed in order, call after call.

    Each frame's latency is fused with the evidence of the ``before`` frames before it (:func:`fuse_latencies`
    with ``after=0``: a stream has no later frames; 0 where that evidence keeps no latency likely), and its events are
    corrected and its latent image made with the fused latency. The frames of a batch are taken as consecutive, in
    batch order, after those of the previous call. :meth:`reset` starts a new recording; a frame that starts before
    the last one passed starts one too, with a warning. A frame with no events in its exposure and search window (the
    scene still) keeps the latency of the frame before it (0 at a recording's start), with a warning, and adds no
    evidence, as ``evlatcorr correct`` does: its ``meta["latency_source"]`` is ``"no events"`` and its latent image
    the blurry frame (no events, no change to undo). For frames that are not one
    recording's (a shuffled training batch) use the :class:`~evlatcorr.correction.EventLatencyCorrector` itself.

    Its warnings name frames by their number in the stream (from 0, again after :meth:`reset`): ``"frame 12"``, not
    the call's ``"sample 0"``. A problem that lasts, such as a still scene's frames with no events or too few, is
    named at the first frame of the run, not at every frame after it (each frame's ``meta`` still says it:
    ``meta["events_in_window"]`` counts the events a latency was read from).

    Args:
        corrector: a constant-mode :class:`~evlatcorr.correction.EventLatencyCorrector` (default: one made with
            ``settings``, the learned reader); other scores have no evidence to fuse, and each frame keeps its own.
        before: earlier frames whose evidence counts (default 2).
        name_frames: name frames in warnings as above; False passes the corrector's warnings as they are, with
            each call's sample numbers and every frame named (for a caller that groups them itself, as the command
            line does, or streams run in several threads: the renaming catches warnings with
            :class:`warnings.catch_warnings`, which holds for the whole process).
        **settings: the arguments of the :class:`~evlatcorr.correction.EventLatencyCorrector` to make when no
            ``corrector`` is given, e.g. ``threshold=0.5, search_range=(0.0, 5000.0)``.

    ``meta["frame_latency_us"]`` :math:`(B,)` holds each frame's own estimate. Frames passed as pairs
    (``blurry_next`` set, events past the next exposure, as interpolation and REFID read them) add each pair's
    agreement to its first frame's evidence (:func:`evlatcorr.pair_evidence.pair_log_odds`, as ``evlatcorr correct``
    does; about 0.6 s per DAVIS346 pair on 2 CPU cores, 5-7x the corrector per frame), unless the corrector's
    ``pair_weight`` is 0.

    Raises:
        ValueError: for a spatial corrector, a negative ``before``, or both a ``corrector`` and ``settings``.

    Example:
        >>> from evlatcorr.simulate import simulate
        >>> seq = simulate("camera", num_frames=3, height=32, width=48, latency_us=3000.0, seed=0)
        >>> stream = StreamingLatencyCorrector()
        >>> outs = [stream(frame) for frame in seq.frames("delayed").split()]  # frame by frame, as they come
        >>> all(abs(float(o.latency.mean()) - 3000.0) < 1000.0 for o in outs)
        True
    """

    def __init__(self, corrector: nn.Module | None = None, before: int = DEFAULT_FUSED_FRAMES, *,
                 name_frames: bool = True, **settings: Any) -> None:
        super().__init__()
        from evlatcorr.correction import EventLatencyCorrector

        if corrector is not None and settings:
            raise ValueError(f"give a corrector or its settings ({', '.join(settings)}), not both")
        corrector = EventLatencyCorrector(**settings) if corrector is None else corrector
        if not isinstance(corrector, EventLatencyCorrector) or corrector.mode != "constant":
            raise ValueError("StreamingLatencyCorrector takes a constant-mode EventLatencyCorrector")
        self.corrector, self.history = corrector, LatencyHistory(before)
        self._last_start: float | None = None  # the exposure start of the last frame passed, µs
        self._last_latency: Tensor | None = None  # the last corrected frame's latency, µs (read only when needed)
        self.name_frames = name_frames
        self._frames_seen = 0  # frames passed since the start or the last reset
        self._last_kinds: frozenset[str] = frozenset()  # the kinds of warning that named the last frame

    @property
    def before(self) -> int:
        return self.history.before

    def reset(self) -> None:
        """Forget the earlier frames: the next frame starts a new recording."""
        self.history.reset()
        self._last_start = None
        self._last_latency = None
        self._frames_seen = 0
        self._last_kinds = frozenset()

    def extra_repr(self) -> str:
        return f"before={self.before}"

    @torch.compiler.disable  # as the corrector's: a compiled pipeline compiles the network behind it
    def forward(self, frames: EventFrames) -> EventFrames:
        first, last = frames.exposure_start[[0, -1]].tolist()  # one read of the device
        if self._last_start is not None and first < self._last_start:
            # earlier than the frames before: another recording (or the same again), whose latency those frames do
            # not tell
            warnings.warn(f"StreamingLatencyCorrector: a frame's exposure starts at {first:.0f} us, before the last "
                          f"frame's ({self._last_start:.0f} us): taken as a new recording, the earlier frames "
                          "forgotten; call reset() between recordings", stacklevel=user_stacklevel())
            self.reset()
        self._last_start = last
        if not self.name_frames:
            return self._correct_or_carry_over(frames)
        caught: list[warnings.WarningMessage] = []
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")  # the user's filters apply when they are said again below
                return self._correct_or_carry_over(frames)
        finally:
            self._say(caught, frames.batch_size)

    def _correct_or_carry_over(self, frames: EventFrames) -> EventFrames:
        try:
            return self._correct(frames)
        except NoEventsError:  # checked before the search: nothing was fused yet
            if frames.batch_size == 1:
                return self._carry_over(frames)
            return EventFrames.cat([self._frame_or_carry_over(frame, i) for i, frame in enumerate(frames.split())])

    def _say(self, caught: list[warnings.WarningMessage], batch_size: int) -> None:
        """Say the warnings of a call on ``batch_size`` frames again, their samples named as the stream's frames, and
        leave out those whose every frame continues a run of the same kind of warning."""
        first = self._frames_seen
        kinds: list[set[str]] = [set() for _ in range(batch_size)]
        for w in caught:
            if isinstance(w.message, SampleWarning):
                for i in w.message.samples:
                    kinds[i].add(w.message.kind)
        before = [self._last_kinds, *kinds[:-1]]
        self._frames_seen += batch_size
        self._last_kinds = frozenset(kinds[-1])
        for w in caught:
            message = w.message
            if isinstance(message, SampleWarning):
                if all(message.kind in before[i] for i in message.samples):
                    continue
                message = SampleWarning(message.kind, [first + i for i in message.samples],
                                        message.text + " (the frames right after it with the same are not named)",
                                        message.summary, noun="frame")
            warnings.warn(message, w.category, stacklevel=user_stacklevel())

    def _correct(self, frames: EventFrames) -> EventFrames:
        # the search fuses each frame's evidence with the history's as it decides, and reads the frame's latent image
        # at the fused latency from the frame's own integral
        out = self.corrector(frames.replace(meta={**frames.meta, "latency_history": self.history}))
        self._last_latency = out.latency[-1, 0, 0, 0]
        meta = {key: value for key, value in out.meta.items() if key != "latency_history"}
        return out.replace(meta=meta)

    def _frame_or_carry_over(self, frame: EventFrames, index: int) -> EventFrames:
        try:
            return self._correct(frame)
        except NoEventsError:
            return self._carry_over(frame, index)

    def _carry_over(self, frame: EventFrames, index: int = 0) -> EventFrames:
        """A frame without events (sample ``index`` of the call): the previous frame's latency (0 at the start), its
        events shifted by it."""
        latency = 0.0 if self._last_latency is None else float(self._last_latency)
        warnings.warn(SampleWarning(
            "no_events", [index], "{which}: no events in its exposure and search window: its events keep the previous "
            f"frame's latency ({latency:.0f} us)", "no events in the exposure and search window: the previous "
            "frame's latency"), stacklevel=user_stacklevel())
        height, width = frame.sensor_size
        # on the frame's device, as the corrector's are: a batch's frames are put back together with torch.cat
        nan = torch.full((1,), math.nan, dtype=torch.float64, device=frame.device)
        meta = {**frame.meta, "latency_source": ["no events"],
                "latency_fallback": torch.ones(1, dtype=torch.bool, device=frame.device),
                "latency_confidence": torch.zeros(1, dtype=torch.float64, device=frame.device),
                "latency_spread_us": nan, "frame_latency_us": nan.clone(), "pair_latency_us": nan.clone(),
                "events_in_window": torch.zeros(1, dtype=torch.int64)}
        shift = torch.full((1,), latency, dtype=torch.float64, device=frame.device)
        return frame.with_outputs(latency=torch.full((1, 1, height, width), latency, device=frame.device),
                                  corrected=frame.events.shift(shift), latent=frame.blurry.clone(), meta=meta)
