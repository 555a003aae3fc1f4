"""A learned reader of the search's candidate curves: which candidate is the true latency (``score="learned"``).

Each sparsity score's minimum lies off the true latency on many scenes (step EDI's lag, ghosts of small objects
over a static background, flat dark regions), each score in its own way, and no hand-written rule over the
curves (the median of the three, votes, tie-breaks at the ghost moment's zero) did better on the suite's dev
split. :class:`CurveReader` learns that rule from simulated frames whose latency is known: a small 1-D CNN
over the coarse candidates reads

- the three sparsity scores' curves, each relative to its median and range over the candidates that could be
  scored (so neither a score's level nor its scale matters),
- the ghost moment (:func:`evlatcorr.ghost.ghost_moment`) of each candidate,
- the overshoot (:func:`evlatcorr.overshoot.overshoot`): how far the candidate's latent rises over the exposure
  above the blurry frame's brightest, in log (a wrong window's ghosts overshoot; it points near the truth on many
  scenes where the sharpness scores mislead),
- which candidates could be scored (their window holds events),

and gives a log-probability per candidate. :class:`CurveReaderEnsemble` averages a few readers trained from
different seeds. The search's estimate is the centre of the ensemble's probability over its likeliest candidate
and two neighbours on each side, a latency between candidates.

The shipped weights (``checkpoints/curve-reader.safetensors``, 5 x 3105 parameters) come from
``python benchmarks/train_curve_reader.py``: cases of the accuracy suite's generator
(:data:`evlatcorr.benchmark.accuracy.TRAIN_SPLITS`: the dev split's photographs, seeds disjoint from both dev
and test), the reader trained against each case's
:func:`~evlatcorr.benchmark.accuracy.training_target`: the true latency of a constant one, the best constant
shift under the photoreceptor model.

Example:
    >>> reader = CurveReader()
    >>> curves = torch.zeros(2, NUM_FEATURES, 101)
    >>> valid = torch.ones(2, 101, dtype=torch.bool)
    >>> reader(curves, valid).shape
    torch.Size([2, 101])
"""

from __future__ import annotations

import copy
import functools
import json
import math
from pathlib import Path

import torch
from torch import Tensor, nn

__all__ = ["NUM_FEATURES", "CurveReader", "CurveReaderEnsemble", "FusedCurveReaderEnsemble", "curve_features",
           "probability_centre", "train_curve_reader", "load_curve_reader", "without_overshoot", "WEIGHTS_NAME",
           "CENTRE_HALF_WIDTH"]

# three sparsity curves, the ghost moment, the overshoot, the valid mask
NUM_FEATURES = 6
WEIGHTS_NAME = "curve-reader"
# the training target: a Gaussian around the true latency, µs (about one and a half coarse candidates)
TARGET_SIGMA_US = 300.0
# noise added to the normalised curves while training (they span about 1)
TRAIN_NOISE = 0.02
_MASKED = -1e4
# The estimate is the centre of the probability over the likeliest candidate and this many either side (±400 µs at
# 20 ms). On 159 cases of the dev distribution (the dev split and a second draw, never the test split) it beat
# refining the pick with the sparsity scores at every T / 500: constant latency median error 690 -> 587 µs,
# photoreceptor share 88 -> 92 %, a higher EDI PSNR on 82 cases and a lower on 49.
CENTRE_HALF_WIDTH = 2


def probability_centre(log_p: Tensor, candidates: Tensor, num_valid: int,
                       half_width: int = CENTRE_HALF_WIDTH) -> tuple[float, float]:
    """The likeliest candidate and the centre of the probability over it and ``half_width`` neighbours each side.

    Args:
        log_p: log-probabilities (up to a constant) of the candidates :math:`(K,)`.
        candidates: the candidate latencies :math:`(K,)`, sorted.
        num_valid: how many candidates could be scored; they are the first ones (a window past the last event is
            never scored), and ``log_p`` of the others must be far below the valid ones'.
        half_width: neighbours on each side.

    Returns:
        ``(pick, centre)`` in the candidates' unit. As many neighbours on each side (fewer at the edges of the valid
        candidates): a pick at an edge, e.g. no latency, stays there instead of being pulled inwards.

    Example:
        >>> probability_centre(torch.tensor([0.0, 2.0, 2.0, 0.0]), torch.tensor([0.0, 1.0, 2.0, 3.0]), 4, 1)
        (1.0, 1.4049...)
    """
    if log_p.shape != candidates.shape or log_p.dim() != 1 or not 1 <= num_valid <= len(log_p):
        raise ValueError(f"log_p and candidates must both be (K,) with 1 <= num_valid <= K, got {tuple(log_p.shape)}, "
                         f"{tuple(candidates.shape)} and {num_valid}")
    log_p, candidates = log_p.double(), candidates.double()
    k = int(torch.argmax(log_p))
    half = max(0, min(half_width, k, num_valid - 1 - k))
    near = slice(k - half, k + half + 1)
    return float(candidates[k]), float((torch.softmax(log_p[near], 0) * candidates[near]).sum())


def curve_features(scores: Tensor, moment: Tensor, valid: Tensor, overshoot: Tensor) -> Tensor:
    """The reader's input :math:`(NUM\\_FEATURES, K)` float32 from one frame's candidate curves (or
    :math:`(N, NUM\\_FEATURES, K)` from N frames' at once).

    Args:
        scores: the sparsity scores :math:`(3, K)` of the candidates (any value where ``valid`` is False), or
            :math:`(N, 3, K)`.
        moment: the ghost moment of each candidate :math:`(K,)` (0 where not valid), or :math:`(N, K)`.
        valid: :math:`(K,)` bool: the candidate's window holds events; or :math:`(N, K)`.
        overshoot: :func:`evlatcorr.overshoot.overshoot` of each candidate :math:`(K,)` (any value where not valid),
            or :math:`(N, K)`.

    Returns:
        each score relative to its median over the valid candidates and divided by its range there (0 where
        not valid, or everywhere when fewer than two are valid), the moment, the overshoot (0 where not valid) and
        ``valid`` as 0/1.
    """
    if (scores.dim() not in (2, 3) or moment.shape != scores.shape[:-2] + scores.shape[-1:]
            or valid.shape != moment.shape or overshoot.shape != moment.shape):
        raise ValueError(f"scores must be (M, K) with moment, valid and overshoot (K,), or (N, M, K) with them (N, K), "
                         f"got {tuple(scores.shape)}, {tuple(moment.shape)}, {tuple(valid.shape)} and "
                         f"{tuple(overshoot.shape)}")
    # every curve at once and on the curves' device (no per-curve host sync); the same values as each curve's
    # median and range over its valid candidates
    scores, moment = scores.double(), moment.double().to(scores.device)
    overshoot = overshoot.double().to(scores.device)
    valid = valid.to(scores.device)
    along = valid.unsqueeze(-2)  # (..., 1, K): the same candidates for each score
    masked = scores.masked_fill(~along, math.nan)
    median = masked.nanmedian(dim=-1, keepdim=True).values
    spread = (scores.masked_fill(~along, -math.inf).amax(-1, keepdim=True)
              - scores.masked_fill(~along, math.inf).amin(-1, keepdim=True))
    usable = along & (valid.sum(-1, keepdim=True) >= 2).unsqueeze(-1)
    rows = torch.where(usable, (scores - median) / spread.clamp_min(1e-12), 0.0)
    cues = [torch.where(valid, cue, 0.0).unsqueeze(-2) for cue in (moment, overshoot)]
    return torch.cat([rows, *cues, valid.double().unsqueeze(-2)], -2).float()


def without_overshoot(curves: Tensor) -> Tensor:
    """:func:`curve_features` :math:`(..., NUM\\_FEATURES, K)` without the overshoot's row: what a reader trained
    without it reads (``benchmarks/train_curve_reader.py --without-overshoot``, to measure what the cue adds).

    Raises:
        ValueError: when ``curves`` do not have :data:`NUM_FEATURES` rows.

    Example:
        >>> without_overshoot(torch.zeros(2, NUM_FEATURES, 7)).shape
        torch.Size([2, 5, 7])
    """
    if curves.dim() < 2 or curves.shape[-2] != NUM_FEATURES:
        raise ValueError(f"curves must be (..., {NUM_FEATURES}, K), got {tuple(curves.shape)}")
    overshoot_row = NUM_FEATURES - 2  # the rows: three scores, the ghost moment, the overshoot, the mask
    return torch.cat([curves[..., :overshoot_row, :], curves[..., overshoot_row + 1:, :]], -2)


class CurveReader(nn.Module):
    """Log-odds :math:`(B, K)` of each candidate being the true latency, from :func:`curve_features` :math:`(B, F, K)`.

    ``layers`` 5-tap convolutions, the i-th dilated by 2^i (the shipped 3: a receptive field of 29 candidates), of
    ``channels`` channels each, and a 1x1 output; candidates that could not be scored get a large negative logit.
    """

    def __init__(self, num_features: int = NUM_FEATURES, channels: int = 16, layers: int = 3) -> None:
        super().__init__()
        if layers < 1 or channels < 1:
            raise ValueError(f"a curve reader needs at least one layer and one channel, got {layers} and {channels}")
        convs: list[nn.Module] = []
        for i in range(layers):
            convs += [nn.Conv1d(num_features if i == 0 else channels, channels, 5, padding=2 * 2**i, dilation=2**i),
                      nn.ReLU()]
        self.net = nn.Sequential(*convs, nn.Conv1d(channels, 1, 1))

    def forward(self, curves: Tensor, valid: Tensor) -> Tensor:
        return self.net(curves)[:, 0].masked_fill(~valid, _MASKED)


class CurveReaderEnsemble(nn.Module):
    """The mean log-probability :math:`(B, K)` of several :class:`CurveReader`."""

    def __init__(self, members: int = 5, num_features: int = NUM_FEATURES, channels: int = 16, layers: int = 3) -> None:
        super().__init__()
        self.members = nn.ModuleList(CurveReader(num_features, channels, layers) for _ in range(members))

    def forward(self, curves: Tensor, valid: Tensor) -> Tensor:
        return torch.stack([torch.log_softmax(m(curves, valid), 1) for m in self.members]).mean(0)


class FusedCurveReaderEnsemble(nn.Module):
    """:class:`CurveReaderEnsemble` as four grouped convolutions (one per layer, every member in its own group)
    instead of four per member: the same function (to float rounding), a fifth of the calls, each of which has
    a fixed cost that dwarfs the arithmetic on one frame's 101 candidates.

    Example:
        >>> ensemble = CurveReaderEnsemble(3).double()
        >>> fused = FusedCurveReaderEnsemble(ensemble)
        >>> curves, valid = torch.randn(2, NUM_FEATURES, 40, dtype=torch.float64), torch.rand(2, 40) > 0.2
        >>> torch.allclose(fused(curves, valid), ensemble(curves, valid))
        True
    """

    def __init__(self, ensemble: CurveReaderEnsemble) -> None:
        if not isinstance(ensemble, CurveReaderEnsemble):
            raise ValueError(f"FusedCurveReaderEnsemble takes a CurveReaderEnsemble, got {type(ensemble).__name__}")
        super().__init__()
        self.num_members = len(ensemble.members)
        # the members' layers in their order (activations as they are), each convolution fused across members
        layers: list[nn.Module] = []
        for i, layer in enumerate(ensemble.members[0].net):
            if not isinstance(layer, nn.Conv1d):
                layers.append(copy.deepcopy(layer))
                continue
            convs = [member.net[i] for member in ensemble.members]
            # the first convolution reads the shared input (one group); the others each member's own channels
            first = not any(isinstance(m, nn.Conv1d) for m in layers)
            fused = nn.Conv1d(layer.in_channels * (1 if first else self.num_members),
                              layer.out_channels * self.num_members, layer.kernel_size, padding=layer.padding,
                              dilation=layer.dilation, groups=1 if first else self.num_members)
            with torch.no_grad():
                fused.weight.copy_(torch.cat([c.weight for c in convs]))
                fused.bias.copy_(torch.cat([c.bias for c in convs]))
            layers.append(fused.to(layer.weight.device, layer.weight.dtype))
        self.net = nn.Sequential(*layers)

    def forward(self, curves: Tensor, valid: Tensor) -> Tensor:
        logits = self.net(curves).masked_fill(~valid[:, None], _MASKED)  # (B, members, K)
        return torch.log_softmax(logits, 2).mean(1)


def train_curve_reader(curves: Tensor, valid: Tensor, latencies: Tensor, targets: Tensor, members: int = 5,
                       epochs: int = 300, seed: int = 0, channels: int = 16, layers: int = 3) -> CurveReaderEnsemble:
    """Fit an ensemble to frames of known latency (full-batch Adam; seconds on a CPU for a thousand frames).

    Args:
        curves: :func:`curve_features` of each frame :math:`(N, F, K)` (the readers take ``F`` inputs).
        valid: :math:`(N, K)` bool.
        latencies: the candidates :math:`(K,)` µs (the same for every frame).
        targets: each frame's target latency :math:`(N,)` µs (its true one, or its best constant shift).
        members: readers in the ensemble, each from its own seed ``seed + i``.
        epochs: full-batch steps per reader.
        channels: each reader's channels (see :class:`CurveReader`).
        layers: each reader's dilated convolutions (see :class:`CurveReader`).

    Returns:
        the ensemble, in eval mode.
    """
    if curves.dim() != 3 or valid.shape != (curves.shape[0], curves.shape[2]) or targets.shape != curves.shape[:1]:
        raise ValueError(f"need curves (N, F, K), valid (N, K) and targets (N,), got {tuple(curves.shape)}, "
                         f"{tuple(valid.shape)} and {tuple(targets.shape)}")
    target = torch.exp(-0.5 * ((latencies.float()[None] - targets.float()[:, None]) / TARGET_SIGMA_US) ** 2) * valid
    target = target / target.sum(1, keepdim=True).clamp_min(1e-12)
    ensemble = CurveReaderEnsemble(members, curves.shape[1], channels, layers)
    generator = torch.Generator().manual_seed(seed)
    for i, reader in enumerate(ensemble.members):
        torch.manual_seed(seed + i)  # the layers' initialisation
        reader.load_state_dict(CurveReader(curves.shape[1], channels, layers).state_dict())
        optimiser = torch.optim.Adam(reader.parameters(), lr=3e-3, weight_decay=1e-3)
        for _ in range(epochs):
            noisy = curves + TRAIN_NOISE * torch.randn(curves.shape, generator=generator) * valid[:, None]
            noisy[:, -1] = curves[:, -1]  # the mask stays exact
            loss = -(target * torch.log_softmax(reader(noisy, valid), 1)).sum(1).mean()
            optimiser.zero_grad()
            loss.backward()
            optimiser.step()
    return ensemble.eval()


@functools.lru_cache(maxsize=4)
def load_curve_reader(path: str | None = None) -> CurveReaderEnsemble:
    """The shipped ensemble (or the one saved at ``path``, a ``.safetensors`` file), in eval mode.

    Raises:
        FileNotFoundError: when no weights are found (the message says where it looked).
    """
    from safetensors.torch import load_file

    from evlatcorr.locations import shipped_weights

    path = shipped_weights(f"{WEIGHTS_NAME}.safetensors", path, "curve reader",
                           "run python benchmarks/train_curve_reader.py, or use another score")
    state = load_file(path)
    members = len({key.split(".")[1] for key in state})
    # its inputs, channels and layers, as trained (a convolution's weight and bias at every other index of net)
    convs = len({key.split(".")[3] for key in state if key.startswith("members.0.net.")})
    first = state["members.0.net.0.weight"]
    ensemble = CurveReaderEnsemble(members, first.shape[1], first.shape[0], convs - 1)
    ensemble.load_state_dict(state, strict=True)
    return ensemble.eval()


def save_curve_reader(ensemble: CurveReaderEnsemble, path: str | Path, provenance: dict | None = None) -> None:
    """Write the ensemble as safetensors (and ``provenance`` as JSON beside it)."""
    from safetensors.torch import save_file

    path = Path(path)
    save_file({k: v.contiguous() for k, v in ensemble.state_dict().items()}, str(path))
    if provenance is not None:
        path.with_suffix(".json").write_text(json.dumps(provenance, indent=2) + "\n")
