"""An ``--estimator`` for ``benchmarks/accuracy.py``: the learned curve reader run on image tiles as well as on the
whole frame, its log-probabilities fused.

A small object moving over a static textured background barely changes a whole-image sharpness score, so the
whole frame's curves can miss what one tile of it shows clearly. This estimator reads the shipped curve reader's
inputs (the three sparsity curves, the ghost moment and the overshoot over the coarse candidates) on the whole
frame and on each tile of a 2x2 and a 3x3 grid, and sums the log-probabilities: the whole frame's with weight 1,
each grid's tiles with weights that add up to 1 per grid, in proportion to the events in each tile (a tile with no
motion has flat curves that the reader, reading them relative to their own range, would answer at random). The
estimate is the centre of the summed probability, as the search takes it for one frame. This form (tiles cropped,
log-probabilities summed by hand-set weights) was measured on the tuning cases and not shipped; its learned
successor, which reads the tiles from the search's own passes, is the default (:mod:`evlatcorr.tile_reader`,
``docs/estimator.md``):

    python benchmarks/accuracy.py --split tuning --mode none \\
        --estimator benchmarks/estimators/tiles.py:estimate_whole --estimator benchmarks/estimators/tiles.py:estimate

``estimate_whole`` is the same read on the whole frame only: the reader's estimate of the search with
``tiles=False``, without its fallbacks (a frame whose windows hold no events is refused here), the fair baseline for
the tiles.
``estimate_map_2x2`` and ``estimate_map_3x3`` give each tile its own latency instead (its log-probability plus the
whole frame's), interpolated bilinearly between the tiles' centres: a per-pixel map for latencies that vary with
intensity, also measured and not shipped.
"""

from __future__ import annotations

import math

import kornia
import torch
import torch.nn.functional as F
from torch import Tensor

from evlatcorr import search_candidates, search_learned
from evlatcorr.config import SPARSITY_SCORES, SearchConfig
from evlatcorr.curve_reader import curve_features, probability_centre
from evlatcorr.frames import EventFrames
from evlatcorr.ghost import inverse_ratio_moment
from evlatcorr.overshoot import MAX_PIXELS, overshoot, overshoot_stride

GRIDS = ((2, 2), (3, 3))  # tiles per (rows, columns)


def tile_features(frames: EventFrames, grids: tuple[tuple[int, int], ...] = GRIDS
                  ) -> tuple[Tensor, Tensor, Tensor, list[tuple[Tensor, Tensor]]]:
    """The reader's inputs (:func:`~evlatcorr.curve_reader.curve_features`) of the first frame's coarse candidates on
    the whole frame and per tile: what :func:`tile_log_probabilities` reads, and what a second reader fusing the
    tiles would (``docs/estimator.md``, "a learned fusion of the tiles").

    Raises:
        ValueError: for more than one frame, a frame without events or with fewer than three candidates to score,
            a grid whose tiles are under 3x3 pixels, or a frame larger than the suite's (the overshoot's sample).

    Returns:
        the candidates :math:`(K,)` µs, which are valid :math:`(K,)`, the whole frame's inputs :math:`(F, K)` and
        per grid ``(the tiles' inputs (T, F, K), each tile's share of the events' absolute change over the
        candidates (T,))``.
    """
    height, width = frames.sensor_size
    if frames.batch_size != 1:
        raise ValueError(f"the tiles read one frame, got {frames.batch_size}")
    for rows, cols in grids:
        whole_tiles = isinstance(rows, int) and isinstance(cols, int)
        if not (whole_tiles and 1 <= rows <= height // 3 and 1 <= cols <= width // 3):
            raise ValueError(f"a grid must be whole numbers of tiles, each at least 3x3 pixels of the {height}x{width} "
                             f"frame, got {(rows, cols)}")
    if overshoot_stride(height, width) != 1:  # the whole frame's overshoot reads a sample of its pixels, not tiles
        raise ValueError(f"the tiles read frames of at most {MAX_PIXELS} pixels (the suite's 96x128), got "
                         f"{height}x{width}")
    events = frames.events.sample(0)
    if not len(events):
        raise ValueError("the frame has no events")
    blurry = frames.blurry[:1]
    grey = kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry
    start, end = float(frames.exposure_start[0]), float(frames.exposure_end[0])
    span = search_candidates._Window(start, end, 0.0, end - start, float(events.t.max()) - end)
    config = SearchConfig(score="learned")
    reader = search_candidates._continuous_reader(grey, events, span, float(frames.meta["threshold"]), config, None)
    kept = reader.coarse[reader.coarse <= reader.top]
    if len(kept) < 3:
        raise ValueError("fewer than three candidates' windows hold events")
    num = len(reader.coarse)
    valid = torch.arange(num) < len(kept)
    inverse, change, peak = reader.inverse_ratio(kept), reader.log_change(kept), reader.log_peak(kept)
    latency = reader.to_us(kept).float()

    def read(region: tuple[slice, slice]) -> Tensor:
        part = (..., *region)
        scores = torch.full((len(SPARSITY_SCORES), num), math.inf, dtype=torch.float64)
        scores[:, :len(kept)] = search_candidates._latent_scores(grey[part], inverse[part], latency, None,
                                                      tuple(SPARSITY_SCORES), config).double()
        moment = torch.zeros(num, dtype=torch.float64)
        moment[:len(kept)] = inverse_ratio_moment(grey[part], inverse[part], change[part]).double()
        over = torch.zeros(num, dtype=torch.float64)
        over[:len(kept)] = overshoot(grey[part], inverse[part], peak[part])
        return curve_features(scores, moment, valid, over)

    whole = read((slice(None), slice(None)))
    tiled = []
    for rows, cols in grids:
        r, c = [round(i * height / rows) for i in range(rows + 1)], [round(j * width / cols) for j in range(cols + 1)]
        regions = [(slice(r[i], r[i + 1]), slice(c[j], c[j + 1])) for i in range(rows) for j in range(cols)]
        activity = torch.stack([change[(..., *region)].abs().sum().double() for region in regions])
        tiled.append((torch.stack([read(region) for region in regions]), activity / activity.sum().clamp_min(1e-12)))
    return reader.to_us(reader.coarse).double(), valid, whole, tiled


def tile_log_probabilities(frames: EventFrames, grids: tuple[tuple[int, int], ...] = GRIDS
                           ) -> tuple[Tensor, Tensor, Tensor, list[tuple[Tensor, Tensor]]]:
    """The reader's log-probabilities of the first frame's coarse candidates on the whole frame and per tile.

    Raises:
        ValueError: as :func:`tile_features`.

    Returns:
        the candidates :math:`(K,)` µs, which are valid :math:`(K,)`, the whole frame's log-probability
        :math:`(K,)` (−inf where not valid) and per grid ``(log-probabilities (T, K), each tile's share of the
        events' absolute change over the candidates (T,))``.
    """
    candidates, valid, whole, tiled = tile_features(frames, grids)

    def read(features: Tensor) -> Tensor:
        log_p = search_learned._read_curves(features[None], valid[None])[0]
        return torch.full_like(log_p, -math.inf).masked_scatter_(valid, torch.log_softmax(log_p[valid], 0))

    return candidates, valid, read(whole), [(torch.stack([read(f) for f in tiles]), share) for tiles, share in tiled]


def fused_latency(frames: EventFrames, grids: tuple[tuple[int, int], ...] = GRIDS) -> float:
    """The centre of the whole frame's and the tiles' summed log-probabilities, µs."""
    candidates, valid, whole, tiled = tile_log_probabilities(frames, grids)
    total = whole.clone()
    for log_p, share in tiled:
        total[valid] += (share[:, None] * log_p[:, valid]).sum(0)
    _, centre = probability_centre(total.masked_fill(~valid, -1e30), candidates, int(valid.sum()))
    return centre


def _as_map(frames: EventFrames, latency: float) -> Tensor:
    return torch.full_like(frames.blurry[:1, :1], latency)


def estimate(frames: EventFrames) -> Tensor:
    """The tiles' fused latency as a map (1, 1, H, W) µs (the first frame; the case's threshold)."""
    return _as_map(frames, fused_latency(frames))


def estimate_whole(frames: EventFrames) -> Tensor:
    """The same read on the whole frame only, as a map (1, 1, H, W) µs."""
    return _as_map(frames, fused_latency(frames, ()))


def tile_latency_map(frames: EventFrames, grid: tuple[int, int]) -> Tensor:
    """Each tile's centre of its own and the whole frame's summed log-probabilities, bilinear between the tiles'
    centres: a map (1, 1, H, W) µs."""
    candidates, valid, whole, tiled = tile_log_probabilities(frames, (grid,))
    centres = []
    for log_p in tiled[0][0]:
        total = log_p.clone()
        total[valid] += whole[valid]
        centres.append(probability_centre(total.masked_fill(~valid, -1e30), candidates, int(valid.sum()))[1])
    coarse = torch.tensor(centres, dtype=torch.float32).view(1, 1, *grid)
    return F.interpolate(coarse, size=frames.blurry.shape[-2:], mode="bilinear", align_corners=False).to(frames.blurry)


def estimate_map_2x2(frames: EventFrames) -> Tensor:
    """:func:`tile_latency_map` of a 2x2 grid."""
    return tile_latency_map(frames, (2, 2))


def estimate_map_3x3(frames: EventFrames) -> Tensor:
    """:func:`tile_latency_map` of a 3x3 grid."""
    return tile_latency_map(frames, (3, 3))
