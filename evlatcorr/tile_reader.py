"""The tile reader: a second curve reader that weighs the shipped reader's reads of a frame's tiles against the whole
frame's curves.

The shipped reader (:mod:`evlatcorr.curve_reader`) reads each tile's curves (:mod:`evlatcorr.tile_curves`) as if
it were a frame. Two rows summarise those reads over the candidates: their log-probabilities averaged by each tile's
share of the events' change, and their maximum over the tiles (each clamped at −30, zero where a candidate is not
valid, divided by 10). A second ensemble of the same architecture reads the whole frame's three score rows, ghost
moment and overshoot, those two rows and the mask (:data:`NUM_TILE_FEATURES` rows), trained on the shipped
reader's training frames plus per-pixel delay frames (``benchmarks/train_tile_reader.py``). The estimate's
log-probability is the mean of its log-probability and the whole frame's reader's, both normalised over the valid
candidates: the two read alike where the whole frame is clear, and half of each keeps a tile read from overruling
a clear whole-frame curve (``docs/estimator.md``).
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

from evlatcorr.curve_reader import NUM_FEATURES, CurveReaderEnsemble, load_curve_reader
from evlatcorr.locations import shipped_weights

__all__ = ["NUM_TILE_FEATURES", "TILE_WEIGHTS_NAME", "load_tile_reader", "read_tiles", "tile_inputs",
           "tile_log_probability"]

TILE_WEIGHTS_NAME = "tile-reader"
NUM_TILE_FEATURES = NUM_FEATURES + 2  # the whole frame's five curves, the tiles' two rows, the mask
# the tiles' log-probabilities are clamped here (a tile with flat curves gives some candidates −inf-like values)
_FLOOR = -30.0
# the tiles' rows are divided by this, to the scale of the normalised curves
_SCALE = 10.0


def read_tiles(tiles: Tensor, valid: Tensor, reader: torch.nn.Module | None = None) -> Tensor:
    """The curve reader's log-probabilities of each tile's candidates :math:`(N, T, K)` float32 from
    :func:`~evlatcorr.curve_reader.curve_features` of the tiles :math:`(N, T, F, K)` and the valid candidates
    :math:`(N, K)` (``reader``: the shipped curve reader when None).

    Raises:
        ValueError: when the shapes do not match.
    """
    if tiles.dim() != 4 or valid.shape != (tiles.shape[0], tiles.shape[-1]):
        raise ValueError(f"need tiles (N, T, F, K) and valid (N, K), got {tuple(tiles.shape)} and "
                         f"{tuple(valid.shape)}")
    n, t = tiles.shape[:2]
    reader = load_curve_reader() if reader is None else reader
    parameter = next(reader.parameters())
    with torch.no_grad():
        log_p = reader(tiles.reshape(n * t, *tiles.shape[2:]).to(parameter),
                       valid.repeat_interleave(t, 0).to(parameter.device))
    return log_p.reshape(n, t, -1).float()


def tile_inputs(whole: Tensor, tile_log_p: Tensor, share: Tensor, valid: Tensor) -> Tensor:
    """The tile reader's input :math:`(N, NUM\\_TILE\\_FEATURES, K)` float32.

    Args:
        whole: :func:`~evlatcorr.curve_reader.curve_features` of the whole frames :math:`(N, F, K)`.
        tile_log_p: the curve reader's log-probabilities of each tile's candidates :math:`(N, T, K)`
            (:func:`read_tiles`).
        share: each tile's share of the events' absolute change :math:`(N, T)`.
        valid: :math:`(N, K)` bool.

    Example:
        >>> whole, tiles = torch.zeros(2, NUM_FEATURES, 11), torch.zeros(2, 9, 11)
        >>> tile_inputs(whole, tiles, torch.full((2, 9), 1 / 9), torch.ones(2, 11, dtype=torch.bool)).shape
        torch.Size([2, 8, 11])
    """
    n, t = tile_log_p.shape[:2]
    if (whole.dim() != 3 or whole.shape[1] != NUM_FEATURES or tile_log_p.shape != (n, t, whole.shape[2])
            or share.shape != (n, t) or valid.shape != (n, whole.shape[2]) or n != whole.shape[0]):
        raise ValueError(f"need whole (N, {NUM_FEATURES}, K), tile_log_p (N, T, K), share (N, T) and valid (N, K), "
                         f"got {tuple(whole.shape)}, {tuple(tile_log_p.shape)}, {tuple(share.shape)} and "
                         f"{tuple(valid.shape)}")
    log_p = tile_log_p.float().to(whole.device).clamp_min(_FLOOR) * valid.to(whole.device)[:, None]
    pooled = (share.float().to(whole.device)[:, :, None] * log_p).sum(1, keepdim=True)
    return torch.cat([whole[:, :NUM_FEATURES - 1].float(), pooled / _SCALE, log_p.amax(1, keepdim=True) / _SCALE,
                      whole[:, NUM_FEATURES - 1:].float()], 1)


def tile_log_probability(inputs: Tensor, whole_log_p: Tensor, valid: Tensor,
                         tile_reader: torch.nn.Module | None = None) -> Tensor:
    """The estimate's log-probability :math:`(N, K)` float64: the mean of the tile reader's and the whole frame's
    reader's (``whole_log_p`` :math:`(N, K)`), each normalised over the valid candidates; −inf where not valid.

    Args:
        inputs: :func:`tile_inputs` :math:`(N, NUM\\_TILE\\_FEATURES, K)`.
        whole_log_p: the whole frame's reader's log-probability (any normalisation) :math:`(N, K)`.
        valid: :math:`(N, K)` bool, at least one per frame.
        tile_reader: the tile reader (the shipped one when None).

    Raises:
        ValueError: when the shapes do not match.
    """
    if (inputs.dim() != 3 or inputs.shape[1] != NUM_TILE_FEATURES or whole_log_p.shape != valid.shape
            or valid.shape != (inputs.shape[0], inputs.shape[2])):
        raise ValueError(f"need inputs (N, {NUM_TILE_FEATURES}, K), whole_log_p and valid (N, K), got "
                         f"{tuple(inputs.shape)}, {tuple(whole_log_p.shape)} and {tuple(valid.shape)}")
    tile_reader = load_tile_reader() if tile_reader is None else tile_reader
    parameter = next(tile_reader.parameters())
    with torch.no_grad():
        fused = tile_reader(inputs.to(parameter), valid.to(parameter.device)).double().to(whole_log_p.device)
    valid = valid.to(whole_log_p.device)

    def normalised(log_p: Tensor) -> Tensor:
        return torch.log_softmax(log_p.double().masked_fill(~valid, -math.inf), 1)

    return (0.5 * (normalised(fused) + normalised(whole_log_p))).masked_fill(~valid, -math.inf)


@functools.lru_cache(maxsize=4)
def load_tile_reader(path: str | None = None) -> CurveReaderEnsemble:
    """The shipped tile reader (or the one saved at ``path``), in eval mode.

    Raises:
        FileNotFoundError: when no weights are found (the message says where it looked).
    """
    path = shipped_weights(f"{TILE_WEIGHTS_NAME}.safetensors", path, "tile reader",
                           "run python benchmarks/train_tile_reader.py, or pass tiles=False")
    ensemble = load_curve_reader.__wrapped__(path)
    if next(ensemble.parameters()).shape[1] != NUM_TILE_FEATURES:
        raise ValueError(f"{path} reads {next(ensemble.parameters()).shape[1]} rows, not the tile reader's "
                         f"{NUM_TILE_FEATURES}")
    return ensemble
