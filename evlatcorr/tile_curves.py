"""The learned reader's curves over each tile of a frame as well as over the whole of it, from the same passes.

:func:`~evlatcorr.curve_reader.curve_features` reads five curves over the candidates: three sparsity scores, the
ghost moment and the overshoot, each a reduction over the frame's pixels. Here each is reduced over the whole frame
and over each tile of :data:`~evlatcorr.image_tiles.TILE_GRID` at once (on a CPU inside the compiled passes, which
keep a sum per tile row and column run beside the whole image's), so that a second reader
(:mod:`evlatcorr.tile_reader`) can weigh what the tiles show against the whole frame. A tile's sparsity scores take
the whole frame's brightness floor, its moment the whole frame's high-pass, and its overshoot the tile's own
brightest pixel (the whole frame's values match :func:`~evlatcorr.search_learned.candidate_curves` to float
rounding).
"""

from __future__ import annotations

import math

import kornia
import torch
from torch import Tensor

from evlatcorr import compiled
from evlatcorr.config import SPARSITY_SCORES, SearchConfig
from evlatcorr.curve_reader import curve_features
from evlatcorr.events import Events
from evlatcorr.ghost import HIGH_PASS_SIGMA, _correlation_of_sums, _gaussian_blur, log_grey
from evlatcorr.image_tiles import TILE_GRID, check_grid, tile_counts, tile_edges, tile_pixels, tile_sums
from evlatcorr.overshoot import OVERSHOOT_RANGE, QUANTILE, _upper_quantile, _upper_quantiles, overshoot_stride
from evlatcorr.search_candidates import _CandidateReader, _continuous_reader, _score_chunk, _Window
from evlatcorr.sharpness import _mean_pool, _padded_gradients

__all__ = ["TileCurves", "candidate_tile_curves", "tile_curve_inputs", "tile_gradient_sparsity", "tile_moments",
           "tile_overshoots", "tile_reductions", "tile_sparsity_scores"]

TileCurves = tuple[Tensor, Tensor, Tensor, Tensor]  # whole (F, K), tiles (T, F, K), shares (T,), valid (K,)


def _check_stacks(grey: Tensor, **stacks: Tensor) -> None:
    """``grey`` must be :math:`(1, F, H, W)` and each of ``stacks`` (by name) :math:`(K, F, H, W)`, one ``K``."""
    first = next(iter(stacks.values()))
    if grey.dim() != 4 or grey.shape[0] != 1 or any(v.dim() != 4 or v.shape[1:] != grey.shape[1:]
                                                    or v.shape[0] != first.shape[0] for v in stacks.values()):
        shapes = ", ".join(f"{name} {tuple(v.shape)}" for name, v in stacks.items())
        raise ValueError(f"grey must be (1, F, H, W) and {' and '.join(stacks)} (K, F, H, W) with the same F, H, W, "
                         f"got grey {tuple(grey.shape)}, {shapes}")


def tile_gradient_sparsity(log: Tensor, half: bool, grid: tuple[int, int] = TILE_GRID) -> Tensor:
    """The gradient sparsity ``‖∇I‖₁ / (‖∇I‖₂ · sqrt(n))`` of each image :math:`(K, 1, H, W)` over the whole image
    and over each tile, at full resolution and (``half``) of its 2x2 means: :math:`(2, K, 1 + T)` float64 (row 1
    zero without ``half``). A CPU takes one compiled pass; elsewhere, or for images asking for a gradient, eager
    PyTorch (the same values).

    Raises:
        ValueError: when ``log`` is not :math:`(K, 1, H, W)`, or the grid does not fit it (or its 2x2 means).
    """
    if log.dim() != 4 or log.shape[1] != 1:
        raise ValueError(f"log must be (K, 1, H, W), got {tuple(log.shape)}")
    height, width = log.shape[-2:]
    if (log.device.type == "cpu" and compiled.ENABLED and log.dim() == 4 and log.shape[1] == 1
            and min(height, width) >= 4 and not log.requires_grad):
        from evlatcorr.compiled.gradients import gradient_tile_sparsity

        return torch.from_numpy(gradient_tile_sparsity(log.flatten(0, 1).contiguous(), half, grid))
    out = torch.zeros((2, log.shape[0], 1 + grid[0] * grid[1]), dtype=torch.float64, device=log.device)
    for level, image in enumerate([log, _mean_pool(log, 2)] if half else [log]):
        h, w = image.shape[-2:]
        check_grid(grid, h, w)
        if h * w < 2:  # a single pixel has no gradient
            continue
        gradients = _central_gradients(image)  # (K, 2, H, W) in the image's dtype, summed in float64 (as compiled)
        l1 = _whole_and_tile_sums(gradients.abs(), grid).sum(1)
        l2 = _whole_and_tile_sums(gradients.square() if gradients.requires_grad else gradients.square_(), grid).sum(1)
        counts = torch.cat([torch.tensor([float(h * w)]), tile_counts(h, w, grid)]).to(log.device)
        out[level] = l1 / (l2.sqrt() * (2 * counts).sqrt() + 1e-12)
    return out


def _central_gradients(image: Tensor) -> Tensor:
    """The x and y differences of :func:`evlatcorr.sharpness._padded_gradients` (zero along a side of one pixel) of
    :math:`(K, 1, H, W)` as one :math:`(K, 2, H, W)` tensor, written in place without padded copies unless the image
    asks for a gradient."""
    if image.requires_grad:
        gradients = list(_padded_gradients(image))
        if len(gradients) < 2:  # a side of one pixel
            zero = torch.zeros_like(image)
            gradients = [zero, *gradients] if image.shape[-1] == 1 else [*gradients, zero]
        return torch.cat(gradients, 1)
    out = image.new_empty((image.shape[0], 2, *image.shape[-2:]))
    for axis, target in ((-1, out[:, :1]), (-2, out[:, 1:])):
        size = image.shape[axis]
        if size == 1:
            target.zero_()
            continue
        # (at, ahead, behind, length): central differences inside, one-sided at the first and last pixel
        for at, ahead, behind, length in ((1, 2, 0, size - 2), (0, 1, 0, 1), (size - 1, size - 1, size - 2, 1)):
            torch.sub(image.narrow(axis, ahead, length), image.narrow(axis, behind, length),
                      out=target.narrow(axis, at, length))
    return out


def _whole_and_tile_sums(values: Tensor, grid: tuple[int, int]) -> Tensor:
    """The sum of each image :math:`(..., H, W)` and of each of its tiles, in float64: :math:`(..., 1 + T)`."""
    tiles = tile_sums(values, grid, torch.float64)
    return torch.cat([tiles.sum(-1, keepdim=True), tiles], -1)


def tile_sparsity_scores(grey: Tensor, inverse: Tensor, grid: tuple[int, int] = TILE_GRID) -> Tensor:
    """The three sparsity scores (:data:`~evlatcorr.config.SPARSITY_SCORES`) of the latents ``grey · inverse``
    over each whole frame and each of its tiles: ``grey`` :math:`(1, F, H, W)`, ``inverse`` :math:`(K, F, H, W)`
    (frame ``f``'s candidates in channel ``f``) → :math:`(3, K, F, 1 + T)` float64. Each log latent takes its
    frame's mean as its floor, as :func:`evlatcorr.search_candidates._latent_scores` does.

    Raises:
        ValueError: when the shapes do not match, or the grid does not fit the frames.
    """
    _check_stacks(grey, inverse=inverse)
    k, frames, height, width = inverse.shape
    mean = torch.einsum("kfhw,fhw->kf", inverse, grey[0].to(inverse)).div_(height * width).clamp_min_(1e-12)
    scales: dict[float, set[int]] = {}
    for floor, factors in SPARSITY_SCORES.values():
        scales.setdefault(floor, set()).update(factors)
    terms = {}
    for floor, factors in scales.items():
        log = torch.addcmul(floor * mean[:, :, None, None], inverse, grey).log_().reshape(k * frames, 1, height, width)
        both = tile_gradient_sparsity(log, 2 in factors, grid).view(2, k, frames, -1)
        del log  # before the next floor's is made
        terms.update({(floor, factor): both[factor - 1] for factor in factors})
    return torch.stack([sum(terms[floor, factor] for factor in factors)
                        for floor, factors in SPARSITY_SCORES.values()])


def tile_moments(grey: Tensor, inverse: Tensor, log_change: Tensor, grid: tuple[int, int] = TILE_GRID) -> Tensor:
    """:func:`~evlatcorr.ghost.inverse_ratio_moment` over each whole frame and each of its tiles (the correlation of
    the high-passed log latent with the high-passed event change over the tile's pixels): ``grey``
    :math:`(1, F, H, W)`, ``inverse`` and ``log_change`` :math:`(K, F, H, W)` → :math:`(K, F, 1 + T)` float64.

    Raises:
        ValueError: when the shapes do not match, or the grid does not fit the frames.
    """
    _check_stacks(grey, inverse=inverse, log_change=log_change)
    k, frames, height, width = inverse.shape
    flat = (k * frames, 1, height, width)
    a = torch.log(inverse).add_(log_grey(grey, inverse.dtype)).view(flat)
    b = log_change.to(a.dtype).reshape(flat)
    if a.device.type == "cpu" and compiled.ENABLED and min(height, width) > 3 and not a.requires_grad:
        from evlatcorr.compiled.high_pass import TAPS, high_pass_tile_correlation

        taps = kornia.filters.get_gaussian_kernel1d(TAPS, HIGH_PASS_SIGMA, dtype=torch.float64)[0].numpy()
        out = high_pass_tile_correlation(a[:, 0].contiguous(), b[:, 0].contiguous(), taps, grid)
        return torch.from_numpy(out).view(k, frames, -1)
    check_grid(grid, height, width)
    n = torch.cat([torch.tensor([float(height * width)]), tile_counts(height, width, grid)]).to(a.device)
    pair = torch.cat([a, b])  # both high-passed by one blur, their sums, then those of a·(a, b) and b·b
    del a, b
    low = _gaussian_blur(pair, HIGH_PASS_SIGMA)
    pair = (pair - low if pair.requires_grad else pair.sub_(low)).view(2, k * frames, height, width)
    del low
    (sum_a, sum_b), (sum_aa, sum_ab) = _whole_and_tile_sums(pair, grid), _whole_and_tile_sums(pair * pair[0], grid)
    sum_bb = _whole_and_tile_sums(pair[1].square(), grid)
    return _correlation_of_sums(sum_a, sum_b, sum_ab, sum_aa, sum_bb, n).view(k, frames, -1)


def tile_overshoots(grey: Tensor, inverse: Tensor, log_peak: Tensor, grid: tuple[int, int] = TILE_GRID) -> Tensor:
    """:func:`~evlatcorr.overshoot.overshoot` over each whole frame and each tile of its sampled pixels (each tile
    against its own brightest pixel): ``grey`` :math:`(1, F, H, W)`, ``inverse`` :math:`(K, F, H, W)`, ``log_peak``
    as :func:`~evlatcorr.overshoot.overshoot` takes it → :math:`(K, F, 1 + T)` float64, clamped to
    :data:`~evlatcorr.overshoot.OVERSHOOT_RANGE`.

    Raises:
        ValueError: when the shapes do not match, or the grid does not fit the sampled pixels.
    """
    _check_stacks(grey, inverse=inverse)
    stride = overshoot_stride(*grey.shape[-2:])
    sampled = (*inverse.shape[:2], -(-grey.shape[-2] // stride), -(-grey.shape[-1] // stride))
    if log_peak.shape != sampled:
        raise ValueError(f"log_peak must be {sampled} (every {stride}th row and column), got {tuple(log_peak.shape)}")
    grey, inverse = grey[..., ::stride, ::stride], inverse[..., ::stride, ::stride]
    log_frame = log_grey(grey, inverse.dtype)  # (1, F, h, w)
    top = torch.log(inverse).add_(log_frame).add_(log_peak)  # (K, F, h, w)
    height, width = top.shape[-2:]
    check_grid(grid, height, width)
    whole = _upper_quantile(top.flatten(2), QUANTILE) - log_frame.flatten(2).amax(2)
    tiles = _tile_upper_quantiles(top, grid) - _tile_upper_quantiles(log_frame, grid, 1.0)
    return torch.cat([whole[..., None], tiles], 2).double().clamp_(*OVERSHOOT_RANGE)


def _tile_upper_quantiles(values: Tensor, grid: tuple[int, int], q: float = QUANTILE, gather: bool | None = None
                          ) -> Tensor:
    """The upper quantile ``q`` of each tile of the images :math:`(..., H, W)` → :math:`(..., T)`. A CPU takes the
    tiles one by one (slices are free there, gathers are not); elsewhere (or with ``gather``) every tile's pixels
    come in one gather, padded with ``-inf``, for one partial sort: a few kernels instead of dozens. The same values
    either way."""
    height, width = values.shape[-2:]
    if not (gather if gather is not None else values.device.type != "cpu"):
        rows, cols = tile_edges(height, grid[0]), tile_edges(width, grid[1])
        return torch.stack([_upper_quantile(values[..., r0:r1, c0:c1].flatten(-2), q) for r0, r1 in zip(rows, rows[1:])
                            for c0, c1 in zip(cols, cols[1:])], -1)
    pixels = tile_pixels(height, width, grid, values.device)  # (T, N), padded with one past the last pixel
    padded = torch.nn.functional.pad(values.flatten(-2), (0, 1), value=-math.inf)[..., pixels]  # (..., T, N)
    return _upper_quantiles(padded, tile_counts(height, width, grid).long().tolist(), q)


def tile_reductions(reader: _CandidateReader, grey: Tensor, grid: tuple[int, int] = TILE_GRID
                    ) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """One frame's coarse candidates' sparsity scores :math:`(1 + T, 3, K)` (inf where not valid), ghost moments and
    overshoots :math:`(1 + T, K)` (0 where not valid), over the whole frame (row 0) and each tile, each tile's share
    of the events' absolute change over the candidates :math:`(T,)`, and which candidates are valid :math:`(K,)`
    (their windows hold events, a prefix), float64 on the frame's device; ``grey`` :math:`(1, 1, H, W)`."""
    coarse = reader.coarse
    kept = coarse[coarse <= reader.top]  # a prefix of the sorted candidates
    tiles = grid[0] * grid[1]
    num, regions = len(coarse), 1 + tiles
    scores = torch.full((regions, len(SPARSITY_SCORES), num), math.inf, dtype=torch.float64, device=grey.device)
    moment = torch.zeros((regions, num), dtype=torch.float64, device=grey.device)
    over = torch.zeros_like(moment)
    activity = torch.zeros(tiles, dtype=torch.float64, device=grey.device)
    if len(kept):
        inverse, change = reader.inverse_ratio(kept), reader.log_change(kept)
        chunk = _score_chunk(grey)
        for k0 in range(0, len(kept), chunk):  # a few candidates at a time: their images stay in cache
            k1 = min(k0 + chunk, len(kept))
            scores[:, :, k0:k1] = tile_sparsity_scores(grey, inverse[k0:k1], grid)[:, :, 0].permute(2, 0, 1)
            moment[:, k0:k1] = tile_moments(grey, inverse[k0:k1], change[k0:k1], grid)[:, 0].T
            activity += tile_sums(change[k0:k1, 0].abs().sum(0).double(), grid)
        over[:, :len(kept)] = tile_overshoots(grey, inverse, reader.log_peak(kept), grid)[:, 0].T
    valid = torch.arange(num, device=grey.device) < len(kept)
    return scores, moment, over, activity / activity.sum().clamp_min(1e-12), valid


def tile_curve_inputs(reader: _CandidateReader, grey: Tensor, grid: tuple[int, int] = TILE_GRID) -> TileCurves:
    """:func:`~evlatcorr.curve_reader.curve_features` of one frame's coarse candidates over the whole frame
    :math:`(F, K)` and over each tile :math:`(T, F, K)`, each tile's share of the events' absolute change over the
    candidates :math:`(T,)` and which candidates are valid :math:`(K,)` (their windows hold events), on the frame's
    device; ``grey`` :math:`(1, 1, H, W)`."""
    scores, moment, over, share, valid = tile_reductions(reader, grey, grid)
    curves = curve_features(scores, moment, valid.expand(len(scores), -1), over)
    return curves[0], curves[1:], share, valid


def candidate_tile_curves(blurry: Tensor, events: Events, exposure_start: float, exposure_end: float,
                          threshold: float, grid: tuple[int, int] = TILE_GRID) -> tuple[Tensor, TileCurves]:
    """What the tile reader reads for one frame at the default settings, on the host: the coarse candidates
    :math:`(K,)` µs and :func:`tile_curve_inputs` (what :mod:`evlatcorr.tile_reader` is trained on).

    Args:
        blurry: :math:`(1, C, H, W)` in [0, 1].
        events: the frame's events (``batch_size == 1``), reaching past ``exposure_end``.
        exposure_start, exposure_end: µs.
        threshold: contrast threshold θ.
        grid: ``(rows, columns)`` of tiles.

    Raises:
        ValueError: for more than one frame, or a grid whose tiles are under 3x3 pixels.
    """
    if blurry.shape[0] != 1 or events.batch_size != 1:
        raise ValueError(f"candidate_tile_curves takes one frame, got {blurry.shape[0]} images and "
                         f"{events.batch_size} event samples")
    height, width = blurry.shape[-2:]
    if not (isinstance(grid[0], int) and isinstance(grid[1], int) and 1 <= grid[0] <= height // 6
            and 1 <= grid[1] <= width // 6):
        raise ValueError(f"grid must be whole numbers of tiles, each at least 6x6 pixels of the {height}x{width} "
                         f"frame (3x3 at half resolution), got {grid}")
    grey = kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry
    last = float(events.t.max()) if len(events) else -math.inf
    span = _Window(exposure_start, exposure_end, 0.0, exposure_end - exposure_start, last - exposure_end)
    reader = _continuous_reader(grey, events, span, float(threshold), SearchConfig(score="learned"), None)
    whole, tiles, share, valid = tile_curve_inputs(reader, grey, grid)
    return reader.to_us(reader.coarse).cpu(), (whole.cpu(), tiles.cpu(), share.cpu(), valid.cpu())
