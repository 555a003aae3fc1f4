"""``EventLatencyCorrector``: an ``nn.Module`` placed in front of any event-guided model."""

from __future__ import annotations

import warnings
from typing import Any

import torch
from torch import Tensor, nn

from evlatcorr.blank_frames import BLANK_KINDS, blank_pairs
from evlatcorr.checks import FEW_EVENTS, check_batch_vector, check_has_events, check_search_size, check_threshold
from evlatcorr.config import DEFAULT_GHOST_CONFIDENCE, DEFAULT_PAIR_WEIGHT, DEFAULT_SCORE, SearchConfig
from evlatcorr.edi import _edi_deblur, _estimate_threshold
from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW
from evlatcorr.frames import EventFrames
from evlatcorr.sample_warnings import SampleWarning, user_stacklevel
from evlatcorr.search import ConstantSearchResult, _search_constant_latency, fallback_warning, few_events_warning
from evlatcorr.search_candidates import HOT_PIXEL_LOG_RANGE
from evlatcorr.temporal import LatencyHistory

__all__ = ["EventLatencyCorrector", "ConstantLatencyCorrector", "SlopedLatencyCorrector", "correct_constant_latency",
           "SearchConfig"]

_MODES = ("constant", "spatial")


def correct_constant_latency(
    frames: EventFrames,
    threshold: float | str = 0.2,
    config: SearchConfig | None = None,
    previous_latency: Tensor | None = None,
    history: LatencyHistory | None = None,
    **settings: Any,
) -> EventFrames:
    """Estimate one latency per frame and remove it from the events (functional form).

    Args:
        frames: the batch; each sample's events must reach ``exposure_end`` plus the exposure time (the learned
            reader's candidates), or plus ``search_range[1]`` where that is further.
        threshold: contrast threshold θ, or ``"auto"``: for pairs (``blurry_next`` set) one θ for the batch
            that makes both frames' reconstructions agree
            (:func:`~evlatcorr.consistency.estimate_recording_threshold`), else per frame by
            :func:`~evlatcorr.edi.estimate_threshold` (a black, saturated or flat frame, which has nothing to deblur,
            gets 0.2, as a batch of blank pairs does); both at the latency found with θ = 0.2.
        config: the search settings (:class:`~evlatcorr.config.SearchConfig`: bins, range, candidates,
            refinement, score); default ``SearchConfig()``.
        previous_latency: ``l'`` :math:`(B,)` µs for the temporal prior (e.g. the previous frame's).
        history: the frames are the next of a stream, in order: each frame's latency is fused with the
            ``history.before`` frames before it (:class:`~evlatcorr.temporal.LatencyHistory`), and its events and
            latent image follow the fused latency; ``meta["frame_latency_us"]`` :math:`(B,)` keeps each frame's
            own estimate and ``meta["pair_latency_us"]`` :math:`(B,)` where each frame's pair agreed best (NaN where
            the frames came without the next one, or the pair told nothing; also for pairs without a history, with
            ``pair_weight`` > 0).
        **settings: fields of :class:`~evlatcorr.config.SearchConfig` to change, e.g. ``num_bins=100``.

    Returns:
        ``frames`` with ``latency`` :math:`(B, 1, H, W)`, ``corrected`` events, ``latent`` (EDI at
        mid-exposure from the corrected events) filled; ``meta["etf_curve"]`` holds the candidates
        and their scores :math:`(B, K)` (``meta["score"]`` names the score; inf: not scored),
        ``meta["threshold"]`` the θ used,
        ``meta["latency_confidence"]`` :math:`(B,)` how clear each score curve's minimum was and
        ``meta["latency_fallback"]`` :math:`(B,)` which frames had none and got the fallback
        (``previous_latency``, else the range's lower end); a warning names them.
        ``meta["latency_source"]`` says per frame what set the latency: ``"reader"`` (the learned curve reader's
        estimate, the default score), ``"sharpness"`` (another score's minimum), ``"ghost"`` (a flat score curve,
        decided by :mod:`evlatcorr.ghost`'s cue) or ``"fallback"``. ``meta["hot_pixels"]`` counts per frame the hot
        pixels the search left out (a warning names them). ``meta["latency_spread_us"]`` :math:`(B,)` is, for the
        learned reader (the default score), the standard deviation of its probability over the candidates: how unsure it
        is (NaN for other scores). On the suite's tuning cases (20 ms exposures) the highest third of spreads (above
        about 2.4 ms) held most of the estimates off by more than 2 ms, the lowest third (below about 1 ms) none.
        ``meta["latency_log_probability"]`` :math:`(B, K)` is the reader's log-probability of each candidate of
        ``meta["etf_curve"][0]`` from the frame alone (None for other scores): consecutive frames of a recording
        share their latency, and :func:`evlatcorr.temporal.fuse_latencies` combines their evidence.
        ``meta["latency_outside_range_us"]`` :math:`(B,)`: with a ``search_range`` and the learned reader, where the
        reader puts more than half its probability outside the range, its likeliest latency there (the estimate is
        held at the range's edge; a warning names the frames), NaN elsewhere. ``meta["events_in_window"]``
        :math:`(B,)` int64 on the host: each frame's events in ``[exposure_start, exposure_end + exposure time)``;
        under :data:`FEW_EVENTS` a warning names the frame (its events do not tell its latency).

    Raises:
        ValueError: when a sample has no events in ``[exposure_start, exposure_end + exposure time)``
            (nothing to estimate a latency from), or for a bad argument.
    """
    config = (config or SearchConfig()).replace(**settings) if settings else (config or SearchConfig())
    # an EventFrames batch was checked when it was made: only what it does not hold is checked here
    if isinstance(threshold, str) and threshold != "auto":
        raise ValueError(f"threshold must be a positive number or 'auto', got {threshold!r}")
    b = frames.batch_size
    theta_vector = None if isinstance(threshold, str) else check_threshold(threshold, b)
    previous = None if previous_latency is None else check_batch_vector(previous_latency, b, "previous_latency")
    check_search_size(frames.sensor_size)
    counts = check_has_events(frames)
    _warn_if_short(frames, config)
    theta: float | Tensor = threshold
    # θ and the latency are picked by searches, which no gradient flows through: no graph over their candidates
    # (the latent below stays differentiable in the blurry frames)
    with torch.no_grad():
        if theta_vector is None:
            theta = _auto_threshold(frames, config, previous)
            theta_vector = _threshold_vector(theta, b)
        history = _with_pairs(frames, theta_vector, config, history)
        try:
            result = _search_constant_latency(frames.blurry, frames.events, frames.exposure_start,
                                              frames.exposure_end, theta_vector, config, previous, history=history)
        finally:
            if history is not None:
                history.expect_pairs([])  # a stream's next call may bring single frames
    _warn_about_samples(result, config)
    _warn_if_few_events(result, counts)
    height, width = frames.sensor_size
    latency = result.latency.to(frames.device, torch.float32).view(-1, 1, 1, 1).expand(-1, 1, height, width)
    corrected = frames.events.shift(result.latency)
    # the latent image exact in continuous time, as the search scored it (no bins), from the search's own integral
    if result.log_ratio is not None:
        latent = frames.blurry * torch.exp(-result.log_ratio).to(frames.blurry.dtype)
    else:
        mid = (frames.exposure_start + frames.exposure_end) / 2
        latent = _edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end, mid,
                             theta_vector, result.latency, config.num_bins, integral="continuous")
    meta = dict(frames.meta)
    meta["etf_curve"] = (result.candidates, result.etf)
    meta["threshold"] = theta
    meta["score"] = config.score
    meta["latency_confidence"] = result.confidence
    meta["latency_fallback"] = result.fallback
    meta["latency_source"] = result.source
    meta["hot_pixels"] = result.ignored_pixels
    meta["latency_spread_us"] = result.latency_spread
    meta["latency_log_probability"] = result.log_probability
    meta["latency_outside_range_us"] = result.outside_range
    meta["events_in_window"] = counts
    if result.own_latency is not None:
        meta["frame_latency_us"] = result.own_latency
    if result.pair_latency is not None:
        meta["pair_latency_us"] = result.pair_latency
    return frames.with_outputs(latency=latency.contiguous(), corrected=corrected, latent=latent, meta=meta)


def _warn_about_samples(result: ConstantSearchResult, config: SearchConfig) -> None:
    """What the search did to some samples that their user must hear of: a fallback latency, hot pixels left out, an
    estimate held at the edge of the user's range (:class:`~evlatcorr.sample_warnings.SampleWarning`: the command
    line names the frames)."""
    blank = []
    for kind in BLANK_KINDS:
        frames = [i for i, source in enumerate(result.source or []) if source == kind]
        if frames:
            warnings.warn(fallback_warning(kind, frames, "{its} latency is the fallback "
                                           f"{_microseconds(result.latency, frames)}"), stacklevel=user_stacklevel())
        blank += frames
    if result.fallback is not None and bool(result.fallback.any()):
        which = [i for i in torch.nonzero(result.fallback).flatten().tolist() if i not in blank]
    else:
        which = []
    if which:
        warnings.warn(fallback_warning("fallback", which, "{its} latency is the fallback "
                                       f"{_microseconds(result.latency, which)}"), stacklevel=user_stacklevel())
    if result.ignored_pixels and any(result.ignored_pixels):
        which = [i for i, n in enumerate(result.ignored_pixels) if n]
        counts = [result.ignored_pixels[i] for i in which]
        warnings.warn(SampleWarning(
            "hot_pixels", which, f"{{which}}: hot pixels (events spanning more than e^{HOT_PIXEL_LOG_RANGE:.0f} of "
            f"intensity, which no scene does) left out of the latency search: {', '.join(map(str, counts))}; "
            "their events are corrected like the others", "hot pixels left out of the latency search"),
            stacklevel=user_stacklevel())
    if result.outside_range is not None and bool(torch.isfinite(result.outside_range).any()):
        which = torch.nonzero(torch.isfinite(result.outside_range)).flatten().tolist()
        span = _range_text(*config.search_range)
        likeliest = _microseconds(result.outside_range, which)
        warnings.warn(SampleWarning(
            "outside_range", which, f"{{which}}: the learned reader finds the latency likeliest at {likeliest}, "
            f"outside search_range {span} "
            f"(more than half its probability lies outside): the estimate is held at the range's edge "
            f"({_microseconds(result.latency, which)}); widen the range if the latency may lie there",
            f"the learned reader finds the latency likelier outside search_range {span}: the "
            "estimate is held at the range's edge"), stacklevel=user_stacklevel())


def _warn_if_few_events(result: ConstantSearchResult, counts: Tensor) -> None:
    """Name the samples with fewer than :data:`FEW_EVENTS` events in their window: their latency is a guess (a
    sample the search did not score, e.g. a blank frame, was named already)."""
    few = [i for i, n in enumerate(counts.tolist())
           if n < FEW_EVENTS and (result.source is None or result.source[i] not in (*BLANK_KINDS, "fallback"))]
    if few:
        numbers = ", ".join(str(int(counts[i])) for i in few)
        warnings.warn(few_events_warning(few, numbers, "the estimate", f" ({_microseconds(result.latency, few)})"),
                      stacklevel=user_stacklevel())


def _range_text(low: float, high: float) -> str:
    """``"low-high us"``, with decimals where the range is too narrow for whole µs to tell its ends apart."""
    digits = 0 if high - low >= 10 else 2
    return f"{low:.{digits}f}-{high:.{digits}f} us"


def _check_spatial_options(options: dict[str, Any]) -> None:
    """Refuse keyword arguments that are no option of the spatial corrector (a misspelt constant-mode setting would
    otherwise read as a spatial option).

    Raises:
        TypeError: naming them and the spatial corrector's options.
    """
    import inspect

    from evlatcorr.spatial import SpatialLatencyCorrector

    known = [name for name in inspect.signature(SpatialLatencyCorrector.__init__).parameters
             if name not in ("self", "curve", "threshold", "config")]
    unknown = sorted(set(options) - set(known))
    if unknown:
        raise TypeError(f"EventLatencyCorrector got unexpected keyword argument(s) {', '.join(unknown)} (its spatial "
                        f"options: {', '.join(known)})")


def _microseconds(values: Tensor, which: list[int]) -> str:
    """The samples' values as a warning says them, in the order of its samples: ``"2600 us"``, ``"80, 120 us"``."""
    return ", ".join(str(round(float(values[i]))) for i in which) + " us"


def _auto_threshold(frames: EventFrames, config: SearchConfig, previous: Tensor | None) -> float | Tensor:
    """θ for ``threshold="auto"``, estimated at the latency found with θ = 0.2 (inputs already checked)."""
    first = _search_constant_latency(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                                     _threshold_vector(0.2, frames.batch_size), config.replace(refine=False), previous)
    if frames.blurry_next is not None and frames.exposure_start_next is not None:
        # pairs: one θ that makes both frames' reconstructions agree between the exposures
        from evlatcorr.consistency import estimate_recording_threshold

        # a blank frame (black, saturated or flat) agrees with its neighbour at no θ: its pair is left out (all
        # left out: the frames are not searched anyway)
        kept = torch.nonzero(~blank_pairs(frames.blurry, frames.blurry_next)).flatten().tolist()
        if not kept:
            return 0.2
        if len(kept) < frames.batch_size:
            parts = frames.split()
            frames = EventFrames.cat([parts[i] for i in kept])
        return estimate_recording_threshold(frames, latency=first.latency[kept])
    warnings.warn("threshold='auto' on single frames estimates θ from each frame alone, which the accuracy suite "
                  "measures as worse than a guess 1.4x off (tuning cases: median latency error 616 against 480 us "
                  "with the true θ, 488 us with 1.4x it): give the camera's θ (threshold=, --threshold) or a guess, "
                  "or frame pairs (blurry_next) for the two-frame estimate", stacklevel=user_stacklevel())
    start = frames.exposure_start.to(frames.events.device)
    end = frames.exposure_end.to(frames.events.device)
    theta = _estimate_threshold(frames.blurry, frames.events, start, end, first.latency, config.num_bins)
    # a blank frame (black, saturated or flat) has nothing to deblur for its θ to be told from: 0.2, as pairs of
    # blank frames get (its latency is the fallback too)
    blank = [i for i, source in enumerate(first.source or []) if source in BLANK_KINDS]
    if blank:
        theta = theta.clone()
        theta[blank] = 0.2
    return theta


def _with_pairs(frames: EventFrames, theta: Tensor, config: SearchConfig,
                history: LatencyHistory | None) -> LatencyHistory | None:
    """The history the search fuses with, told the batch's pairs where the frames come with the next one
    (``blurry_next``) and the learned reader's evidence can take their agreement (``config.pair_weight`` > 0): a
    stream's, or one of the frame alone (``before=0``)."""
    if frames.blurry_next is None or config.pair_weight == 0 or config.score != "learned":
        return history
    history = LatencyHistory(before=0) if history is None else history
    history.expect_pairs(frames.split() if frames.batch_size > 1 else [frames], theta.tolist(), config.pair_weight)
    return history


def _threshold_vector(theta: float | Tensor, batch_size: int) -> Tensor:
    """A threshold the package computed (a float or :math:`(B,)`) as float64 :math:`(B,)`, unchecked."""
    theta = torch.as_tensor(theta, dtype=torch.float64)
    return theta.expand(batch_size) if theta.dim() == 0 else theta


class ConstantLatencyCorrector(nn.Module):
    """One latency per frame, searched and removed (:func:`correct_constant_latency` as a module).

    Args:
        threshold: contrast threshold θ, or ``"auto"``.
        config: the search settings; default ``SearchConfig()``.

    ``frames.meta["previous_latency"]`` (:math:`(B,)` µs), when set, is the temporal prior's ``l'``.

    Example:
        >>> ConstantLatencyCorrector(0.25, SearchConfig(num_candidates=50))
        ConstantLatencyCorrector(threshold=0.25, num_bins=500, search_range=None, num_candidates=50)
    """

    def __init__(self, threshold: float | str = 0.2, config: SearchConfig | None = None) -> None:
        super().__init__()
        if not (threshold == "auto" or (isinstance(threshold, (int, float)) and threshold > 0)):
            raise ValueError(f"threshold must be a positive number or 'auto', got {threshold!r}")
        self.threshold = threshold
        self.config = config or SearchConfig()

    def extra_repr(self) -> str:
        c = self.config
        return (f"threshold={self.threshold}, num_bins={c.num_bins}, search_range={c.search_range}, "
                f"num_candidates={c.num_candidates}")

    def forward(self, frames: EventFrames) -> EventFrames:
        return correct_constant_latency(frames, self.threshold, self.config, frames.meta.get("previous_latency"),
                                        frames.meta.get("latency_history"))


class EventLatencyCorrector(nn.Module):
    """Estimate and remove event latency, in front of any event-guided model.

    ``mode="constant"`` finds one latency per frame: the one whose EDI latent image is sharpest
    (see :func:`~evlatcorr.search.search_constant_latency`), searched in one pass over the events
    (a :class:`ConstantLatencyCorrector`). ``mode="spatial"`` gives a per-pixel map from a polynomial
    of intensity (a :class:`~evlatcorr.spatial.SpatialLatencyCorrector`). Given pairs (``blurry_next`` set) and no
    trained ``curve``, spatial mode takes each frame's constant latency (with its pair's agreement) and adds how
    much later dim pixels are, fitted to the pair's agreement pixel by pixel (:mod:`evlatcorr.pair_curve`; where the
    pair shows no such slope the map is the constant latency): ``meta["pair_curves"]`` holds each pair's fit (None
    where the pair told nothing), ``meta["latency_slope_us"]`` :math:`(B,)` its slope.

    The events of each sample must reach past ``exposure_end`` by the largest latency searched
    (late events of an exposure are stamped after it ends): by default the search range is 0 to
    the exposure time, so events up to ``exposure_end + exposure time`` are needed. A warning is
    raised when they stop earlier.

    Args:
        mode: ``"constant"`` (one latency per frame) or ``"spatial"`` (a per-pixel map).
        threshold: contrast threshold θ of the events, or ``"auto"`` (see :func:`correct_constant_latency`;
            spatial mode estimates θ the same way, then fits with it; for a recording the command line estimates one
            θ from its first frame pairs).
        num_bins: sub-intervals of the exposure used by EDI (paper: 500).
        search_range: ``(low, high)`` µs, finite, ``high > low``; default 0 to each frame's exposure time. A
            range inside that one bounds the estimate (the learned reader still reads its candidates over 0
            to the exposure time, as it was trained); one beyond it is read as given, with a warning.
        num_candidates: coarse candidates over the search range (default 100).
        refine: refine the best candidate below the candidate spacing (the learned reader: the centre of its
            probability around its pick).
        epsilon: ETF edge amplifier ε.
        window: ETF local-contrast window.
        sigma_us: σ of the ETF temporal prior (used when ``frames.meta["previous_latency"]`` is set).
        score: sharpness score of the search: ``"learned"`` (default: :mod:`evlatcorr.curve_reader` reads the
            sparsity curves), ``"consensus"``, a single sparsity score or ``"etf"`` (the paper's); see
            :func:`~evlatcorr.search.search_constant_latency`.
        ghost_confidence: frames whose score curve's confidence is at most this get the ghost-moment cue's
            latency where it is clear (:mod:`evlatcorr.ghost`); 0: only frames with no minimum and no
            previous latency (which would get no shift); None: never.
        tiles: ``score="learned"``: also read the frame's 3x3 tiles and weigh them against the whole frame with
            the tile reader (default; :mod:`evlatcorr.tile_reader`); False: the whole frame's curves alone.
        pair_weight: frames given with the next one (``blurry_next`` set, their events past the next exposure, as
            interpolation and REFID read them): each pair's agreement (:func:`evlatcorr.pair_evidence.pair_log_odds`)
            joins its first frame's reader evidence with this weight (default 10); 0: each frame alone. About 0.6 s
            per DAVIS346 pair on 2 CPU cores, 5-7x the search of a frame (``benchmarks/speed.py --part recording``).
        curve: ``mode="spatial"`` only: a trained latency curve checkpoint.
        frame_gamma: the frames are encoded as ``linear ** (1 / frame_gamma)`` (2.2: encoded for display, as PNG
            exports and video frames are; default 1: linear, as a DAVIS's frames). The estimate reads them made
            linear, as EDI needs them; the output keeps the frames as given, for the model behind it, and its
            ``latent`` is encoded as they are. Frames read with ``open_recording(path, frame_gamma=...)`` are
            linear already: leave this at 1.
        **spatial_kwargs: ``mode="spatial"`` only: options of the spatial corrector (``steps``, ``lr``,
            ``train_bins``, ``order``, ``weights``, ``progress``: :class:`~evlatcorr.spatial.SpatialLatencyCorrector`);
            any other keyword is a :class:`TypeError` naming it.

    The search settings are checked here, once (a :class:`~evlatcorr.config.SearchConfig`, ``.config``).
    Both modes refuse a batch with a frame that has no events in ``[exposure_start, exposure_end +
    exposure time)`` with a :class:`ValueError` naming the sample: there is nothing to estimate its
    latency from.

    Example:
        >>> corrector = EventLatencyCorrector()
        >>> corrector
        EventLatencyCorrector(
          mode=constant, threshold=0.2, num_bins=500, search_range=None, num_candidates=100
          (constant): ConstantLatencyCorrector(threshold=0.2, num_bins=500, search_range=None, num_candidates=100)
        )
    """

    def __init__(
        self,
        mode: str = "constant",
        threshold: float | str = 0.2,
        num_bins: int = 500,
        search_range: tuple[float, float] | None = None,
        num_candidates: int = 100,
        refine: bool = True,
        epsilon: float = DEFAULT_EPSILON,
        window: int = DEFAULT_WINDOW,
        sigma_us: float = DEFAULT_SIGMA_US,
        score: str = DEFAULT_SCORE,
        ghost_confidence: float | None = DEFAULT_GHOST_CONFIDENCE,
        tiles: bool = True,
        pair_weight: float = DEFAULT_PAIR_WEIGHT,
        curve: str | None = None,
        frame_gamma: float = 1.0,
        **spatial_kwargs: Any,
    ) -> None:
        super().__init__()
        from evlatcorr.gamma import check_frame_gamma

        self.frame_gamma = check_frame_gamma(frame_gamma)
        if mode not in _MODES:
            raise ValueError(f"mode must be one of {_MODES}, got {mode!r}")
        if spatial_kwargs:
            _check_spatial_options(spatial_kwargs)
        if mode == "constant" and (curve is not None or spatial_kwargs):
            given = ", ".join((["curve"] if curve is not None else []) + sorted(spatial_kwargs))
            raise ValueError(f"curve and spatial options need mode='spatial' (given: {given})")
        self.mode, self.threshold = mode, threshold
        self.config = SearchConfig(num_bins=num_bins, search_range=search_range, num_candidates=num_candidates,
                                   refine=refine, score=score, epsilon=epsilon, window=window, sigma_us=sigma_us,
                                   ghost_confidence=ghost_confidence, tiles=tiles, pair_weight=pair_weight)
        self.constant: ConstantLatencyCorrector | None = None
        self.spatial: nn.Module | None = None
        if mode == "constant":
            self.constant = ConstantLatencyCorrector(threshold, self.config)
        else:
            from evlatcorr.spatial import SpatialLatencyCorrector

            if not (threshold == "auto" or (isinstance(threshold, (int, float)) and threshold > 0)):
                raise ValueError(f"threshold must be a positive number or 'auto', got {threshold!r}")
            # "auto": θ is estimated on each batch as constant mode does (forward), and handed to the fit
            self.spatial = SpatialLatencyCorrector(curve=curve, threshold=0.2 if threshold == "auto" else threshold,
                                                   config=self.config, **spatial_kwargs)

    # the settings, read through the config (one source of truth)
    num_bins = property(lambda self: self.config.num_bins)
    search_range = property(lambda self: self.config.search_range)
    num_candidates = property(lambda self: self.config.num_candidates)
    score = property(lambda self: self.config.score)

    def extra_repr(self) -> str:
        gamma = f", frame_gamma={self.frame_gamma}" if self.frame_gamma != 1 else ""
        return (f"mode={self.mode}, threshold={self.threshold}, num_bins={self.num_bins}, "
                f"search_range={self.search_range}, num_candidates={self.num_candidates}{gamma}")

    # opaque to TorchDynamo: the search reads events of data-dependent sizes and runs passes of its own, so tracing
    # it breaks the graph at every step and recompiles (benchmarks/compile.py); torch.compile of a whole pipeline
    # then compiles the network behind it and runs this as it is
    @torch.compiler.disable
    def forward(self, frames: EventFrames) -> EventFrames:
        if not isinstance(frames, EventFrames):
            raise ValueError(f"EventLatencyCorrector takes an EventFrames batch, got {type(frames).__name__}")
        if self.frame_gamma == 1:
            return self._correct(frames)
        from evlatcorr.gamma import display_image, linear_frames

        out = self._correct(linear_frames(frames, self.frame_gamma))
        latent = None if out.latent is None else display_image(out.latent, self.frame_gamma)
        return out.replace(blurry=frames.blurry, blurry_next=frames.blurry_next, sharp=frames.sharp,
                           target_frames=frames.target_frames, latent=latent)

    def _correct(self, frames: EventFrames) -> EventFrames:
        if self.constant is not None:
            return self.constant(frames)
        if self.spatial.model is None and frames.blurry_next is not None and frames.exposure_start_next is not None:
            out = correct_constant_latency(frames, self.threshold, self.config, frames.meta.get("previous_latency"),
                                           frames.meta.get("latency_history"))
            return _sloped_by_pairs(out, frames, self.config)
        if self.threshold != "auto":
            return self.spatial(frames)
        # spatial mode with threshold="auto": θ as constant mode estimates it (one for pairs, else per frame), at
        # the constant search's latency, then the fit with it
        check_search_size(frames.sensor_size)
        check_has_events(frames)
        return self.spatial(frames, threshold=_auto_threshold(frames, self.config, None))


def _sloped_by_pairs(out: EventFrames, frames: EventFrames, config: SearchConfig) -> EventFrames:
    """Spatial mode given pairs, without a trained curve: each frame's constant latency (``out``: the constant
    corrector's, its reader with the pair's agreement) plus how far the curve fitted to its pair's agreement
    (:func:`evlatcorr.pair_curve.fit_pair_curve`) departs from its own single latency at each pixel. A pair that tells
    nothing (blank, no events past the second exposure) keeps the frame's constant latency."""
    from evlatcorr.pair_curve import fit_pair_curve

    theta = _threshold_vector(out.meta["threshold"], frames.batch_size)
    fits = []
    for i, pair in enumerate(frames.split()):  # one fit per pair: a loop over frames, not pixels or events
        try:
            fits.append(fit_pair_curve(pair, float(theta[i])))
        except ValueError:
            fits.append(None)
    return _with_slopes(out, frames, config, fits)


def _with_slopes(out: EventFrames, frames: EventFrames, config: SearchConfig, fits: list) -> EventFrames:
    """``out`` (a constant corrector's) with each frame's latency plus its curve's departure (``fits``: a
    :class:`~evlatcorr.pair_curve.PairCurve` or None per frame), held inside the search range, its events and latent
    following; as it is where no curve has a slope. ``meta["pair_curves"]`` and ``meta["latency_slope_us"]`` say
    which."""
    from evlatcorr.spatial import _latency_bounds, _mid_exposure

    meta = dict(out.meta)
    meta["pair_curves"] = fits
    meta["latency_slope_us"] = torch.tensor([0.0 if f is None else f.slope_us for f in fits], dtype=torch.float64)
    if not any(f is not None and f.slope_us for f in fits):
        return out.with_outputs(meta=meta)
    theta = _threshold_vector(out.meta["threshold"], frames.batch_size)
    with torch.no_grad():  # the map inside the search range, as spatial mode keeps its maps
        departure = torch.cat([torch.zeros_like(out.latency[i:i + 1]) if f is None
                               else f.departure(frames.blurry[i:i + 1]).to(out.latency) for i, f in enumerate(fits)])
        low, high = (bound.to(out.latency).view(-1, 1, 1, 1) for bound in _latency_bounds(frames, config.search_range))
        latency = torch.minimum(torch.maximum(out.latency + departure, low), high)
        corrected = frames.events.shift(latency.double())
        latent = _edi_deblur(frames.blurry, corrected, frames.exposure_start, frames.exposure_end,
                             _mid_exposure(frames), theta, None, config.num_bins, integral="continuous")
    return out.with_outputs(latency=latency.contiguous(), corrected=corrected, latent=latent, meta=meta)


class SlopedLatencyCorrector(nn.Module):
    """A constant corrector's latencies plus one curve's departure over intensity, for every frame: what the command
    line's spatial mode runs on a recording without a trained curve, the curve fitted to the recording's first pairs
    (:func:`evlatcorr.pair_curve.fit_pair_curve`).

    Args:
        corrector: a constant corrector (an :class:`EventLatencyCorrector`, or one wrapped in a
            :class:`~evlatcorr.temporal.StreamingLatencyCorrector`).
        curve: the :class:`~evlatcorr.pair_curve.PairCurve` whose departure from its single latency is added.
        config: the corrector's search settings (its range holds the maps; its bins the latent's EDI).

    Example:
        >>> from evlatcorr.pair_curve import fit_pair_curve
        >>> from evlatcorr.simulate import simulate
        >>> seq = simulate("camera", num_frames=3, height=24, width=32, latency_us=3000.0, seed=0)
        >>> constant = EventLatencyCorrector()
        >>> sloped = SlopedLatencyCorrector(constant, fit_pair_curve(seq.pairs(), 0.2), constant.config)
        >>> out = sloped(seq.frames())
        >>> out.meta["latency_slope_us"].tolist()  # no slope: the constant corrector's output
        [0.0, 0.0, 0.0]
    """

    def __init__(self, corrector: nn.Module, curve: Any, config: SearchConfig) -> None:
        super().__init__()
        from evlatcorr.pair_curve import PairCurve

        if not isinstance(corrector, nn.Module):
            raise ValueError(f"corrector must be a constant corrector module, got {type(corrector).__name__}")
        if not isinstance(curve, PairCurve):
            raise ValueError(f"curve must be a PairCurve (evlatcorr.pair_curve.fit_pair_curve), got "
                             f"{type(curve).__name__}")
        if not isinstance(config, SearchConfig):
            raise ValueError(f"config must be a SearchConfig, got {type(config).__name__}")
        self.corrector, self.curve, self.config = corrector, curve, config

    def extra_repr(self) -> str:
        return f"offset_us={self.curve.offset_us:.0f}, slope_us={self.curve.slope_us:.0f}"

    def forward(self, frames: EventFrames) -> EventFrames:
        out = self.corrector(frames)
        return _with_slopes(out, frames, self.config, [self.curve] * frames.batch_size)


def _warn_if_short(frames: EventFrames, config: SearchConfig) -> None:
    search_range = config.search_range
    high = frames.exposure_time if search_range is None else torch.full_like(frames.exposure_end, search_range[1])
    if config.score == "learned":  # the reader reads its candidates over 0 to the exposure time whatever the range
        high = torch.maximum(high, frames.exposure_time)
    need = frames.exposure_end + high
    ev = frames.events
    last = ev.last_times().to(need)
    short = last < need - (frames.exposure_time / 50)  # allow one coarse bin of slack
    if bool(short.any()):
        i = int(torch.nonzero(short)[0, 0])
        warnings.warn(SampleWarning(
            "events_end", [i],
            f"events of {{which}} end at {float(last[i]):.0f} us but the latency search reads up to "
            f"{float(need[i]):.0f} us (exposure_end + search range): latencies above "
            f"{max(0.0, float(last[i] - frames.exposure_end[i])):.0f} us are not searched (their window would run "
            "past the last event); pass events further past exposure_end to search them",
            "events end before the latency search's reach: the latencies whose window runs past the last event are "
            "not searched"),
            stacklevel=user_stacklevel(),
        )
