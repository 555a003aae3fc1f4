"""``score="learned"`` in the constant-latency search: the curves the curve reader reads, and its pick.

Over one frame's coarse candidates (:mod:`evlatcorr.search_candidates`) the three sparsity scores, the ghost moment
(:mod:`evlatcorr.ghost`) and the overshoot (:mod:`evlatcorr.overshoot`) make the reader's input
(:func:`~evlatcorr.curve_reader.curve_features`); the shipped reader (:mod:`evlatcorr.curve_reader`) gives each
candidate a probability, and the estimate is the centre of that probability around the likeliest candidate.
:func:`candidate_curves` gives what the reader was trained on. With ``SearchConfig.tiles`` (the default) the same
curves are also read over the frame's tiles (:mod:`evlatcorr.tile_curves`) and the tile reader
(:mod:`evlatcorr.tile_reader`) weighs them against the whole frame's.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import warnings

import kornia
import torch
from torch import Tensor

from evlatcorr.checks import check_image
from evlatcorr.config import SPARSITY_SCORES, SearchConfig
from evlatcorr.events import Events
from evlatcorr.ghost import ghost_root, inverse_ratio_moment
from evlatcorr.overshoot import overshoot
from evlatcorr.sample_warnings import user_stacklevel
from evlatcorr.search_candidates import _CandidateReader, _continuous_reader, _score_candidates, _score_chunk, _Window

__all__ = ["candidate_curves"]

def _curve_inputs(reader: _CandidateReader, grey: Tensor, coarse: Tensor, coarse_scores: Tensor
                  ) -> tuple[Tensor, Tensor, Tensor]:
    """:func:`~evlatcorr.curve_reader.curve_features` of one frame's coarse candidates on the frame's device, which
    are valid (on the scores' device, the host), and their ghost moments :math:`(K,)` (0 past the last event)."""
    from evlatcorr.curve_reader import curve_features

    valid = torch.isfinite(coarse_scores[0])
    kept = coarse[coarse <= reader.top]  # the valid candidates: a prefix of the sorted coarse ones
    moment = torch.zeros(len(coarse), dtype=torch.float64, device=grey.device)
    moment[:len(kept)] = _candidate_moments(reader, grey, kept)
    over = torch.zeros(len(coarse), dtype=torch.float64, device=grey.device)
    if len(kept):
        over[:len(kept)] = overshoot(grey, reader.inverse_ratio(kept), reader.log_peak(kept))
    # the features are made where the moments are: on a GPU the moments are not waited for, and the reader runs
    # there too (on a many-core host its few tiny convolutions cost milliseconds of thread wake-ups)
    return curve_features(coarse_scores.to(grey.device), moment, valid.to(grey.device), over), valid, moment


def _learned_log_p(reader: _CandidateReader, grey: Tensor, coarse: Tensor, coarse_scores: Tensor
                   ) -> tuple[Tensor, Tensor]:
    """The shipped curve reader's log-odds of one frame's coarse candidates :math:`(K,)` float64 on the host, and
    their ghost moments :math:`(K,)` on the frame's device (0 past the last event)."""
    curves, valid, moment = _curve_inputs(reader, grey, coarse, coarse_scores)
    return _read_curves(curves[None], valid[None])[0], moment


def _tiled_log_p(reader: _CandidateReader, grey: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """The coarse candidates' sparsity scores :math:`(3, K)` on the host (inf where not valid), the estimate's
    log-probability :math:`(K,)` float64 on the host (the whole frame's reader and the tile reader together,
    :func:`evlatcorr.tile_reader.tile_log_probability`) and the whole frame's ghost moments :math:`(K,)` on the
    frame's device: what :func:`_learned_log_p` gives, with the frame's tiles read too (``SearchConfig.tiles``)."""
    from evlatcorr.curve_reader import curve_features
    from evlatcorr.tile_curves import tile_reductions
    from evlatcorr.tile_reader import tile_inputs, tile_log_probability

    scores, moment, over, share, valid = tile_reductions(reader, grey)
    curves = curve_features(scores, moment, valid.expand(len(scores), -1), over)
    log_p = _read_curves(curves, valid.expand(len(scores), -1))  # (1 + T, K) on the host: the whole frame, tiles
    valid = valid.cpu()
    inputs = tile_inputs(curves[:1].cpu(), log_p[None, 1:], share[None].cpu(), valid[None])
    fused = tile_log_probability(inputs, log_p[:1], valid[None], _tile_reader())[0]
    return scores[0].cpu(), fused, moment[0]


@functools.lru_cache(maxsize=1)
def _tile_reader() -> torch.nn.Module:
    """The shipped tile reader on the host, its members fused (:func:`_curve_reader_on`): it reads the host's
    log-probabilities of the tiles."""
    from evlatcorr.curve_reader import FusedCurveReaderEnsemble
    from evlatcorr.tile_reader import load_tile_reader

    return FusedCurveReaderEnsemble(load_tile_reader()).eval()


def _read_curves(curves: Tensor, valid: Tensor) -> Tensor:
    """The shipped curve reader's log-odds :math:`(N, K)` float64 on the host of :math:`(N, F, K)` curves (on the
    device they were made on) and their valid candidates :math:`(N, K)`: the one wait for the device."""
    ensemble = _curve_reader_on(curves.device)
    with torch.no_grad():
        log_p = ensemble(curves.to(next(ensemble.parameters()).dtype), valid.to(curves.device))
    return log_p.double().cpu()


def _candidate_moments(reader: _CandidateReader, grey: Tensor, kept: Tensor) -> Tensor:
    """:func:`~evlatcorr.ghost.ghost_moment` of candidates whose windows hold events, float64 :math:`(K,)` on the
    frame's device: in float32, a few candidates at a time on a CPU (their images stay in cache)."""
    moment = torch.zeros(len(kept), dtype=torch.float64, device=grey.device)
    if len(kept):
        inverse, change = reader.inverse_ratio(kept), reader.log_change(kept)
        chunk = _score_chunk(grey)
        for k0 in range(0, len(kept), chunk):
            k1 = min(k0 + chunk, len(kept))
            moment[k0:k1] = inverse_ratio_moment(grey, inverse[k0:k1], change[k0:k1])
    return moment


@functools.lru_cache(maxsize=4)
def _curve_reader_on(device: torch.device) -> torch.nn.Module:
    """The shipped curve reader on ``device``, its members fused into grouped convolutions (a fifth of the calls,
    each a fixed cost far above the arithmetic of one frame's curves): float32 on a CPU, as trained; float64
    elsewhere, where a GPU's convolutions may otherwise round through TF32 and pick another candidate than a CPU on
    near ties. The search reads its curves on the frame's device."""
    from evlatcorr.curve_reader import FusedCurveReaderEnsemble, load_curve_reader

    fused = FusedCurveReaderEnsemble(load_curve_reader()).eval()
    return fused if device.type == "cpu" else fused.to(device, torch.float64)


def _learned_pick(reader: _CandidateReader, coarse: Tensor, log_p: Tensor, valid: Tensor,
                  prior: tuple[Tensor, float, float] | None = None, allowed: Tensor | None = None
                  ) -> tuple[float, float, float, Tensor, float | None]:
    """The coarse candidate :mod:`evlatcorr.curve_reader`'s shipped ensemble finds likeliest (its log-odds
    ``log_p`` :math:`(K,)` on the host, :func:`_learned_log_p`; ``valid``: the scored candidates) and the centre of
    its probability over that candidate's neighbours (both in reader units), the standard deviation of its
    probability over all candidates (µs), and the reader's log-probability of each candidate without the prior
    :math:`(K,)` (normalised over the scored candidates, −inf elsewhere); and, where ``allowed`` keeps more than half
    of that probability out, the likeliest candidate outside it in µs (the latency a user's range holds the estimate
    away from), else None.

    The centre is the probability-weighted mean of the likeliest candidate and
    :data:`~evlatcorr.curve_reader.CENTRE_HALF_WIDTH` valid
    candidates either side (fewer at the edges, as many on both sides): a latency between candidates, the
    sub-candidate estimate of ``refine=True``.

    ``prior``: ``(candidates in µs, previous latency, σ)``: the temporal prior of the sparsity scores,
    ``exp((l − l')² / 4σ²)`` on a score, enters as ``−(l − l')² / 4σ²`` on the reader's log-probability.
    ``allowed``: :math:`(K,)` bool on the host, the candidates that may answer for the user's ``search_range``
    where it is narrower than the candidates' (:func:`_answer_block`; the caller checks that one of them is
    valid): the probability, and its standard deviation, are restricted to them.
    """
    from evlatcorr.curve_reader import probability_centre

    valid = valid.cpu()
    outside = None
    if allowed is not None:
        unbounded = torch.softmax(log_p.masked_fill(~valid, -math.inf), 0)
        if float(unbounded[~allowed].sum()) > 0.5:  # the frame's own evidence says the latency lies outside the range
            outside = float(reader.to_us(coarse.cpu().double()[int(torch.argmax(unbounded * ~allowed))]))
        valid = valid & allowed
        log_p = log_p.masked_fill(~valid, -math.inf)
    # what the frame alone says, for fusing frames (evlatcorr.temporal): normalised over the scored candidates
    own = torch.full_like(log_p, -math.inf)
    own[valid] = torch.log_softmax(log_p[valid], 0)
    if prior is not None:
        latencies, previous, sigma = prior
        log_p = log_p - (latencies.double() - previous) ** 2 / (4 * sigma**2)
    candidates = coarse.cpu().double()
    if allowed is None:  # the valid candidates are the first ones
        pick, centre = probability_centre(log_p, candidates, int(valid.sum()))
    else:  # a run of them
        first, last = (int(i) for i in torch.nonzero(valid).flatten()[[0, -1]])
        pick, centre = probability_centre(log_p[first:last + 1], candidates[first:last + 1], last + 1 - first)
    probability, latencies = torch.softmax(log_p, 0), reader.to_us(candidates).double()
    mean = (probability * latencies).sum()
    spread = float((probability * (latencies - mean) ** 2).sum().sqrt())
    return pick, centre, spread, own, outside


def _answer_block(latencies: Tensor, low: float, high: float) -> Tensor:
    """Which of the sorted candidate latencies :math:`(K,)` µs may answer for the range ``[low, high]``: those inside
    it, and the nearest one outside each end (a range narrower than the candidates' spacing still has two)."""
    below, above = latencies <= low, latencies >= high
    first = int(torch.nonzero(below).flatten()[-1]) if bool(below.any()) else 0
    last = int(torch.nonzero(above).flatten()[0]) if bool(above.any()) else len(latencies) - 1
    block = torch.zeros(len(latencies), dtype=torch.bool)
    block[first:last + 1] = True
    return block


def _reader_windows(windows: list[_Window]) -> list[_Window]:
    """The windows the learned reader reads where the user gave a ``search_range``: its candidates over 0 to the
    exposure time, the range it was trained on (it reads the candidates as fractions of their range), and the
    user's range kept as the bounds of the answer. A range beyond 0 to the exposure time is read as given, with a
    warning: the reader was never trained on such curves."""
    out = []
    for span in windows:
        exposure = span.end - span.start
        if span.low >= 0.0 and span.high <= exposure * (1 + 1e-9):
            out.append(dataclasses.replace(span, low=0.0, high=exposure, answer=(span.low, span.high)))
        else:
            out.append(span)
    wide = [span for span in out if span.answer is None]
    if wide:
        warnings.warn(f"search_range {wide[0].low:.0f}-{wide[0].high:.0f} us reaches beyond 0 to the exposure time "
                      f"({wide[0].end - wide[0].start:.0f} us), the range the learned reader was trained on: it reads "
                      "that range's curves as if they spanned the exposure time, and its estimates there are "
                      "untested", stacklevel=user_stacklevel())
    return out


def candidate_curves(blurry: Tensor, events: Events, exposure_start: float, exposure_end: float,
                     threshold: float, before_us: float = 0.0) -> tuple[Tensor, Tensor, Tensor]:
    """What the curve reader reads for one frame at the default settings (the whole frame's curves; the tiles':
    :func:`evlatcorr.tile_curves.candidate_tile_curves`): the coarse candidates
    :math:`(K,)` µs, their :func:`~evlatcorr.curve_reader.curve_features` :math:`(F, K)` and which are valid
    :math:`(K,)` (what :func:`evlatcorr.curve_reader.train_curve_reader` is trained on).

    Args:
        blurry: :math:`(1, C, H, W)` in [0, 1].
        events: the frame's events (``batch_size == 1``), reaching past ``exposure_end``.
        exposure_start, exposure_end: µs.
        threshold: contrast threshold θ.
        before_us: also candidates below 0, down to ``−before_us`` and spaced as the others (windows that start
            before the exposure: the events must start that early); for measuring readers of such curves
            (``benchmarks/train_curve_reader.py --before-us``), not what the search reads.
    """
    check_image(blurry, "blurry")
    if blurry.shape[0] != 1 or events.batch_size != 1:
        raise ValueError(f"candidate_curves takes one frame, got {blurry.shape[0]} images and {events.batch_size} "
                         "event samples")
    exposure = exposure_end - exposure_start
    if not (math.isfinite(before_us) and 0.0 <= before_us <= exposure):
        raise ValueError(f"before_us must be between 0 and the exposure time {exposure} us, got {before_us}")
    # the default's spacing over the exposure, and as many more candidates below 0 at that spacing
    spacings = SearchConfig.num_candidates
    config = SearchConfig(score="learned", num_candidates=round(spacings * (exposure + before_us) / exposure))
    grey = kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry
    last = float(events.t.max()) if len(events) else -math.inf
    span = _Window(exposure_start, exposure_end, -before_us, exposure, last - exposure_end)
    reader = _continuous_reader(grey, events, span, float(threshold), config, None)
    coarse_scores = torch.stack(_score_candidates(reader, grey, tuple(SPARSITY_SCORES), config, None,
                                                  [reader.coarse] * len(SPARSITY_SCORES)))
    curves, valid, _ = _curve_inputs(reader, grey, reader.coarse, coarse_scores)
    return reader.coarse.cpu(), curves.cpu(), valid.cpu()


def _ghost_latency(reader: _CandidateReader, grey: Tensor, coarse: Tensor, moment: Tensor | None = None
                   ) -> float | None:
    """:func:`~evlatcorr.ghost.ghost_root` over the coarse candidates whose windows hold events, µs (``moment``:
    the coarse candidates' moments when already made, :func:`_learned_log_p`)."""
    kept = coarse[coarse <= reader.top]
    if len(kept) < 3:
        return None
    moment = _candidate_moments(reader, grey, kept) if moment is None else moment[:len(kept)]
    return ghost_root(reader.to_us(kept).cpu(), moment.cpu())
