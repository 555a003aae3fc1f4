"""Settings of the constant-latency search and its sharpness score, validated once where they are made.

A :class:`SearchConfig` travels as one object from :class:`~evlatcorr.correction.EventLatencyCorrector`
through :func:`~evlatcorr.correction.correct_constant_latency` to the search, instead of a bundle of
positional numbers that every layer re-checks.

Example:
    >>> from evlatcorr.config import SearchConfig
    >>> config = SearchConfig(num_candidates=50, search_range=(0, 8000))
    >>> config.search_range, config.num_candidates, config.score
    ((0.0, 8000.0), 50, 'learned')
    >>> SearchConfig(num_bins=1)
    Traceback (most recent call last):
    ...
    ValueError: num_bins must be >= 2, got 1
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

from evlatcorr.checks import check_search_range

__all__ = ["SearchConfig", "SCORES", "DEFAULT_SCORE", "SPARSITY_SCORES", "DEFAULT_PAIR_WEIGHT", "DEFAULT_EPSILON",
           "DEFAULT_WINDOW", "DEFAULT_SIGMA_US"]

# the paper's ETF settings (evlatcorr.etf reads them from here: the search's settings live in this bottom layer):
# edge thickness's gradient amplifier ε, local contrast's window (pixels), the temporal prior's width (µs)
DEFAULT_EPSILON = 20.0
DEFAULT_WINDOW = 7
DEFAULT_SIGMA_US = 1000.0

# sparsity scores: (c of log(I / mean(I) + c), image scales). c sets how much relatively dark pixels count:
# 0.25 found the constant latency best on the dev split, 1.0 follows the bright pixels when latency varies
# with intensity; the coarse scale sees the low-contrast blur remnants of under-correction better.
SPARSITY_SCORES = {"sparsity": (0.25, (1,)), "sparsity_bright": (1.0, (1,)), "sparsity_multiscale": (0.25, (1, 2))}
# "consensus": the median of the three sparsity scores' estimates (one failing score is outvoted)
# "learned" (default): a small network reads the three sparsity curves and the ghost moment and picks the
# candidate (evlatcorr.curve_reader); better than "consensus" on both the dev and the test split of the suite
SCORES = ("etf", *SPARSITY_SCORES, "consensus", "learned")
DEFAULT_SCORE = "learned"
# the ghost cue decides only the frames with no sharpness minimum (which would otherwise get no shift): up to
# 0.01 it also fixed the dev split's constant-latency misses, but under the photoreceptor model it lowered the
# share of the best shift's gain on 5 of the 8 frames it decided in a 99-case draw of the dev distribution
DEFAULT_GHOST_CONFIDENCE = 0.0
# a pair's agreement: log-odds per unit of log disagreement (evlatcorr.pair_evidence.pair_log_odds). On the tuning
# cases' 6-frame sequences fused ±2 (benchmarks/sequence_accuracy.py --pair-weights 3 10 30 100) 10 took the
# constant-latency median error from 546 / 341 to 395 / 269 µs (dev / dev_wide) and the ideal events' from 700 / 686
# µs to 0; 30 and 100 were closer on constant latency and cost dev_wide's per-pixel delay cases 0.3-0.4 dB
# (docs/estimator.md)
DEFAULT_PAIR_WEIGHT = 10.0


@dataclass(frozen=True)
class SearchConfig:
    """How the constant latency is searched and scored.

    Attributes:
        num_bins: sub-intervals ``n`` of the exposure (paper: 500): the refinement step is ``T / n``.
        search_range: ``(low, high)`` µs, finite, ``high > low``; None: 0 to each frame's exposure time. With
            ``score="learned"`` a range inside that one bounds the answer while the reader still reads its
            candidates over 0 to the exposure time, as it was trained (a range beyond it is read as given, with a
            warning).
        num_candidates: coarse candidates over the range (at least 2).
        refine: search every sub-interval around the best candidate (``score="learned"``: take the centre of
            the reader's probability around its pick instead of the pick itself).
        score: one of :data:`SCORES` (see :func:`~evlatcorr.search.search_constant_latency`).
        epsilon: ETF edge amplifier ε.
        window: ETF local-contrast window.
        sigma_us: σ of the temporal prior towards the previous frame's latency, µs.
        ghost_confidence: frames whose confidence is at most this take their latency from the ghost-moment
            cue (:mod:`evlatcorr.ghost`) where its curve crosses zero once. 0 (default): only frames with no
            score minimum at all and no previous latency, which would otherwise get no shift; 0.01: also
            nearly flat curves (better for a constant latency, worse where it varies with intensity); None:
            never. Continuous method only.
        tiles: ``score="learned"``: also read the curves of the frame's 3x3 tiles and weigh them against the
            whole frame's with the tile reader (:mod:`evlatcorr.tile_reader`); False: the whole frame's alone.
            Frames under 18x18 pixels are read whole (:func:`~evlatcorr.image_tiles.tiles_fit`).
        pair_weight: ``score="learned"``, frames given with the next one (``blurry_next`` set, their events past
            the next exposure, as interpolation and REFID read them): the weight of the two frames' agreement
            (:func:`~evlatcorr.pair_evidence.pair_log_odds`) added to the frame's reader evidence; 0: the frame
            alone.
    """

    num_bins: int = 500
    search_range: tuple[float, float] | None = None
    num_candidates: int = 100
    refine: bool = True
    score: str = DEFAULT_SCORE
    epsilon: float = DEFAULT_EPSILON
    window: int = DEFAULT_WINDOW
    sigma_us: float = DEFAULT_SIGMA_US
    ghost_confidence: float | None = DEFAULT_GHOST_CONFIDENCE
    tiles: bool = True
    pair_weight: float = DEFAULT_PAIR_WEIGHT

    def __post_init__(self) -> None:
        if not isinstance(self.num_bins, int) or self.num_bins < 2:
            raise ValueError(f"num_bins must be >= 2, got {self.num_bins}")
        if not isinstance(self.num_candidates, int) or self.num_candidates < 2:
            raise ValueError(f"num_candidates must be >= 2, got {self.num_candidates}")
        if self.score not in SCORES:
            raise ValueError(f"score must be one of {SCORES}, got {self.score!r}")
        if not self.sigma_us > 0:
            raise ValueError(f"sigma_us must be positive, got {self.sigma_us}")
        if self.ghost_confidence is not None and not 0 <= self.ghost_confidence <= 1:
            raise ValueError(f"ghost_confidence must be in [0, 1] or None, got {self.ghost_confidence}")
        if isinstance(self.pair_weight, bool) or not (isinstance(self.pair_weight, (int, float))
                                                      and math.isfinite(self.pair_weight) and self.pair_weight >= 0):
            raise ValueError(f"pair_weight must be a finite number >= 0, got {self.pair_weight!r}")
        # frozen: normalise the range through object.__setattr__ (floats, or None)
        object.__setattr__(self, "search_range", check_search_range(self.search_range))

    def replace(self, **changes: object) -> SearchConfig:
        """A copy with some settings changed (validated again)."""
        return dataclasses.replace(self, **changes)
