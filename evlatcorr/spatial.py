"""Spatially-varying latency: a polynomial of intensity trained through the differentiable EDI.

``ψ(L) = scale · Σ_{i=0..K} a_i f(L)^i`` per pixel (paper Eq. 15), with ``L`` the blurry frame's
luminance (the mean intensity over the exposure, ``B / 2Δτ`` for a frame normalised to [0, 1]) and

    f(L) = log((L + ε) / (1 + ε)) / log(ε / (1 + ε))          (ε = 0.01)

a fixed map that is monotone decreasing (black → 1, white → 0 exactly) and keeps every power
``f^i`` in [0, 1], so the coefficients are of the same order and Adam steps are well conditioned
(a raw intensity basis would crowd the dim pixels, where latency changes fastest, near 0).
The log follows the photoreceptor: latency grows like 1 / intensity, i.e. fast in log intensity
at the dark end. ``scale`` (1000 µs) makes the coefficients milliseconds. They start at zero (the
no-latency assumption).

The objective (Eq. 19-21). The paper does not say in which unit its weights (α=1, β=1, η=20,
ζ=0.1) apply; we measure latencies as fractions of the frame's exposure time, which makes every
term dimensionless and the same weights work for any exposure. (With latencies in ms, η=20 ties
the map to ``l_const`` so tightly that it cannot vary: on ``benchmarks/spatial.py`` spatial
correction then beats constant correction on 5/8 test scenes instead of 7/8.)

- ``L_ETF``: the ETF of the EDI latent image from the linear (Eq. 16-18) event integral with the
  latency map clipped to ``[0, l_max]``, divided by the ETF at the frame's ``l_const`` (so 1 means
  "as sharp as the constant correction"), with ``g`` centred on ``l_const``;
- ``L_bound``: mean of ``relu(−l) + relu(l − l_max)`` (the clipping cuts the gradient there, this
  term brings the map back);
- ``L_mse``: mean of ``(l − l_const)²``;
- ``L_dev``: mean of ``relu(dψ/dL)`` over the frame's pixels (ψ must decrease with intensity).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import kornia
import torch
from torch import Tensor, nn

from evlatcorr.blank_frames import BLANK_KINDS, blank_kinds
from evlatcorr.checks import FEW_EVENTS, check_has_events, check_search_size, check_threshold, resolve_memory_budget
from evlatcorr.config import SearchConfig
from evlatcorr.edi import _check_grid, _edi_deblur
from evlatcorr.etf import DEFAULT_EPSILON, DEFAULT_SIGMA_US, DEFAULT_WINDOW, etf_loss
from evlatcorr.event_grid import EventGrid, _event_grid, _event_grid_bytes
from evlatcorr.frames import EventFrames
from evlatcorr.latency_table import LatencyTable
from evlatcorr.sample_warnings import user_stacklevel
from evlatcorr.search import _search_constant_latency, fallback_warning, few_events_warning

__all__ = ["PolynomialLatency", "LossWeights", "spatial_objective", "fit_spatial_latency",
           "SpatialLatencyCorrector", "save_curve", "load_curve"]


class PolynomialLatency(nn.Module):
    """Per-pixel latency ``ψ(L) = scale · Σ a_i f(L)^i`` from the blurry frame's intensity.

    Args:
        order: polynomial order ``K`` (≥ 0; the paper uses 5).
        eps: ε of ``f(L) = log((L + ε) / (1 + ε)) / log(ε / (1 + ε))``.
        scale_us: µs per unit of the polynomial (coefficients in ms by default).

    Example:
        >>> psi = PolynomialLatency()
        >>> psi(torch.rand(2, 3, 8, 8)).shape  # zero at initialisation
        torch.Size([2, 1, 8, 8])
    """

    def __init__(self, order: int = 5, eps: float = 0.01, scale_us: float = 1000.0) -> None:
        super().__init__()
        if order < 0:
            raise ValueError(f"order K must be >= 0, got {order}")
        if not 0 < eps < 1:
            raise ValueError(f"eps must be in (0, 1), got {eps}")
        self.order, self.eps, self.scale_us = order, eps, scale_us
        self.coefficients = nn.Parameter(torch.zeros(order + 1))

    def extra_repr(self) -> str:
        return f"order={self.order}, eps={self.eps}, scale_us={self.scale_us}"

    @staticmethod
    def intensity(blurry: Tensor) -> Tensor:
        """Luminance ``L`` :math:`(B, 1, H, W)` of a blurry frame in [0, 1]."""
        return kornia.color.rgb_to_grayscale(blurry) if blurry.shape[1] == 3 else blurry

    def _log_range(self) -> float:
        return math.log(self.eps / (1 + self.eps))  # negative: f decreases

    def transform(self, intensity: Tensor) -> Tensor:
        """``f(L)`` in [0, 1]: 1 for black, 0 for white, decreasing in between."""
        return torch.log((intensity.clamp(0, 1) + self.eps) / (1 + self.eps)) / self._log_range()

    def powers(self, f: Tensor) -> Tensor:
        return torch.stack([f**i for i in range(self.order + 1)], dim=-1)

    def curve(self, intensity: Tensor) -> Tensor:
        """ψ at given intensities (any shape), µs."""
        return self.scale_us * (self.powers(self.transform(intensity)) * self.coefficients.to(intensity)).sum(-1)

    def slope(self, intensity: Tensor) -> Tensor:
        """dψ/dL at given intensities, µs per unit intensity (Eq. 20's inner term)."""
        f = self.transform(intensity)
        df_dl = 1.0 / ((intensity.clamp(0, 1) + self.eps) * self._log_range())
        i = torch.arange(1, self.order + 1, device=f.device, dtype=f.dtype)
        dpsi_df = (i * self.coefficients[1:].to(f) * f[..., None] ** (i - 1)).sum(-1) if self.order else 0 * f
        return self.scale_us * df_dl * dpsi_df

    def forward(self, blurry: Tensor) -> Tensor:
        return self.curve(self.intensity(blurry))


@dataclass
class LossWeights:
    """α, β, η, ζ of Eq. (21)."""

    etf: float = 1.0
    bound: float = 1.0
    mse: float = 20.0
    dev: float = 0.1


def spatial_objective(
    model: PolynomialLatency,
    frames: EventFrames,
    l_const: Tensor,
    l_max: Tensor,
    etf_const: Tensor,
    threshold: float = 0.2,
    num_bins: int = 100,
    weights: LossWeights | None = None,
    epsilon: float = DEFAULT_EPSILON,
    window: int = DEFAULT_WINDOW,
    sigma_us: float = DEFAULT_SIGMA_US,
    grid: EventGrid | None = None,
    table: LatencyTable | None = None,
) -> dict[str, Tensor]:
    """The terms of Eq. (19)-(21) and their weighted sum ``"total"`` for one batch.

    Args:
        model: the latency polynomial.
        frames: the batch (events reaching ``exposure_end + l_max``).
        l_const: the frames' constant latencies :math:`(B,)` µs.
        l_max: upper bound of the latency :math:`(B,)` µs.
        etf_const: ETF at ``l_const`` :math:`(B,)`, the normaliser of ``L_ETF``.
        grid: the batch's linear :func:`~evlatcorr.event_grid.event_grid` for ``num_bins`` over latencies
            ``[0, l_max]``, when it is read more than once (test-time fitting); built here when None.
        table: a :class:`~evlatcorr.latency_table.LatencyTable` of the batch over ``[0, l_max]``: the EDI
            is read from it (exact step integral, linear in the latency between its entries) instead of
            the linear integral; for test-time fitting, where it is built once and read at every step.
    """
    theta = check_threshold(threshold, frames.batch_size)
    _check_grid_spans(grid, frames, 0.0, l_max, num_bins)  # the map is clipped into [0, l_max]
    config = SearchConfig(num_bins=num_bins, epsilon=epsilon, window=window, sigma_us=sigma_us)
    return _spatial_objective(model, frames, l_const, l_max, etf_const, theta, config, weights, grid, table)


def _spatial_objective(model: PolynomialLatency, frames: EventFrames, l_const: Tensor, l_max: Tensor,
                       etf_const: Tensor, theta: Tensor, config: SearchConfig, weights: LossWeights | None,
                       grid: EventGrid | None, table: LatencyTable | None) -> dict[str, Tensor]:
    """:func:`spatial_objective` of checked inputs: a positive threshold :math:`(B,)`, a grid spanning
    ``[0, l_max]``; ``config`` gives the EDI bins and the ETF settings."""
    w = weights or LossWeights()
    latency = model(frames.blurry)  # (B, 1, H, W) µs
    b = latency.shape[0]
    l_max_map = l_max.to(latency).view(b, 1, 1, 1)
    clipped = torch.minimum(latency.clamp_min(0.0), l_max_map)
    if table is not None:
        latent = frames.blurry * torch.exp(-table.read(clipped)).to(frames.blurry.dtype)
    else:
        latent = _edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                             _mid_exposure(frames), theta, clipped, config.num_bins, integral="linear", grid=grid)
    mean_latency = clipped.mean(dim=(1, 2, 3))
    etf = etf_loss(latent, mean_latency, l_const.to(latency), config.epsilon, config.window, config.sigma_us)
    # latencies as fractions of each frame's exposure time: dimensionless, so the paper's weights hold
    unit = frames.exposure_time.to(latency).view(b, 1, 1, 1)
    terms = {
        "etf": (etf / etf_const.to(etf)).mean(),
        "bound": ((torch.relu(-latency) + torch.relu(latency - l_max_map)) / unit).mean(),
        "mse": (((latency - l_const.to(latency).view(b, 1, 1, 1)) / unit) ** 2).mean(),
        "dev": torch.relu(model.slope(model.intensity(frames.blurry)) / unit).mean(),
    }
    terms["total"] = w.etf * terms["etf"] + w.bound * terms["bound"] + w.mse * terms["mse"] + w.dev * terms["dev"]
    return terms


def constant_reference(frames: EventFrames, threshold: float, num_bins: int, search_range: tuple[float, float] | None,
                       num_candidates: int, epsilon: float, window: int, sigma_us: float,
                       grid: EventGrid | None = None, table: LatencyTable | None = None) -> tuple[Tensor, Tensor]:
    """``l_const`` per frame and the ETF of its latent image (read from ``table`` when given, else the linear
    integral)."""
    config = SearchConfig(num_bins=num_bins, search_range=search_range, num_candidates=num_candidates,
                          epsilon=epsilon, window=window, sigma_us=sigma_us)
    theta = check_threshold(threshold, frames.batch_size)
    low, high = _latency_bounds(frames, config.search_range)
    _check_grid_spans(grid, frames, low, high, num_bins)  # l_const lies in [low, high]
    return _constant_reference(frames, theta, config, grid, table)


def _constant_reference(frames: EventFrames, theta: Tensor, config: SearchConfig, grid: EventGrid | None,
                        table: LatencyTable | None, l_const: Tensor | None = None) -> tuple[Tensor, Tensor]:
    """:func:`constant_reference` of checked inputs (a positive threshold :math:`(B,)`); ``l_const`` :math:`(B,)`,
    where the caller has searched already, is taken as it is."""
    num_bins, epsilon, window, sigma_us = config.num_bins, config.epsilon, config.window, config.sigma_us
    if l_const is None:
        l_const = _search_constant_latency(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                                           theta, config).latency
    l_const = l_const.to(frames.device)
    with torch.no_grad():
        if table is not None:
            latent = frames.blurry * torch.exp(-table.read(l_const.to(frames.blurry).view(-1, 1, 1, 1)))
        else:
            latent = _edi_deblur(frames.blurry, frames.events, frames.exposure_start, frames.exposure_end,
                                 _mid_exposure(frames), theta, l_const, num_bins, integral="linear", grid=grid)
        etf = etf_loss(latent, l_const.float(), l_const.float(), epsilon, window, sigma_us)
    return l_const, etf


def fit_spatial_latency(
    frames: EventFrames,
    model: PolynomialLatency | None = None,
    steps: int = 100,
    lr: float = 0.05,
    threshold: float = 0.2,
    num_bins: int = 100,
    search_range: tuple[float, float] | None = None,
    num_candidates: int = 100,
    weights: LossWeights | None = None,
    epsilon: float = DEFAULT_EPSILON,
    window: int = DEFAULT_WINDOW,
    sigma_us: float = DEFAULT_SIGMA_US,
    progress: bool = False,
    start_from_constant: bool = False,
    objective_edi: str = "table",
) -> tuple[PolynomialLatency, list[float]]:
    """Test-time optimisation: fit ψ on the given batch by Adam (a bounded number of steps).

    With ``start_from_constant`` the polynomial starts at the batch's mean ``l_const`` instead of
    zero (the paper's zero start is for training over a dataset; a few test-time steps from zero
    cannot travel milliseconds).

    ``objective_edi="table"`` (default): every pixel's EDI is tabulated once at ``num_bins + 1`` latencies
    over ``[0, l_max]`` (:class:`~evlatcorr.latency_table.LatencyTable`, exact in continuous time) and each
    step reads it by linear interpolation: a step costs a few gathers per pixel. ``"linear"``: each step
    reads the linear integral (Eq. 16-18) from an event grid built once; when that grid would exceed
    :data:`evlatcorr.checks.MEMORY_BUDGET_BYTES`, each step builds (in strips of rows) the grid its EDI
    reads, which is slower and moves the loss slightly.

    Returns:
        the fitted model and the total loss per step.

    Raises:
        ValueError: when a frame has no events in ``[exposure_start, exposure_end + exposure time)``
            (as :func:`~evlatcorr.correction.correct_constant_latency`), or for a bad argument.
    """
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    if objective_edi not in ("table", "linear"):
        raise ValueError(f"objective_edi must be 'table' or 'linear', got {objective_edi!r}")
    config = SearchConfig(num_bins=num_bins, search_range=search_range, num_candidates=num_candidates,
                          epsilon=epsilon, window=window, sigma_us=sigma_us)
    theta = check_threshold(threshold, frames.batch_size)
    check_search_size(frames.sensor_size)
    check_has_events(frames)
    return _fit_spatial_latency(frames, model, steps, lr, theta, config, weights, progress, start_from_constant,
                                objective_edi)


def _fit_spatial_latency(frames: EventFrames, model: PolynomialLatency | None, steps: int, lr: float,
                         theta: Tensor, config: SearchConfig, weights: LossWeights | None, progress: bool,
                         start_from_constant: bool, objective_edi: str,
                         l_const: Tensor | None = None) -> tuple[PolynomialLatency, list[float]]:
    """:func:`fit_spatial_latency` of checked inputs (a positive threshold :math:`(B,)`); ``config`` holds the
    fit's EDI bins (``num_bins``), the latency range and the constant search's settings; ``l_const`` :math:`(B,)`,
    the frames' constant latencies where the caller has searched them already."""
    num_bins, search_range = config.num_bins, config.search_range
    model = model if model is not None else PolynomialLatency()
    model = model.to(frames.device)
    l_max = frames.exposure_time if search_range is None else torch.full_like(frames.exposure_time, search_range[1])
    # every step reads the same events at other latencies in [0, l_max] (and l_const): integrate them once
    l_min = 0.0 if search_range is None else min(0.0, search_range[0])
    grid = table = None  # no grid over the memory budget: every step's EDI builds (in strips) the grid it reads
    if objective_edi == "table":
        table = LatencyTable.build(frames.events, frames.exposure_start, frames.exposure_end, theta, l_min,
                                   float(l_max.max()), num_bins + 1)
    else:
        grid = _linear_grid_within_budget(frames, l_min, l_max, num_bins)
    l_const, etf_const = _constant_reference(frames, theta, config, grid, table, l_const)
    if start_from_constant:
        with torch.no_grad():  # ψ ≡ mean l_const: the fit only has to learn the variation around it
            model.coefficients.zero_()
            model.coefficients[0] = float(l_const.mean()) / model.scale_us
    optimiser = torch.optim.Adam(model.parameters(), lr=lr)
    history = []
    iterator: Any = range(steps)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc="fit latency curve", unit="step")
    for _ in iterator:
        optimiser.zero_grad()
        terms = _spatial_objective(model, frames, l_const, l_max, etf_const, theta, config, weights, grid, table)
        terms["total"].backward()
        optimiser.step()
        history.append(float(terms["total"].detach()))
    return model, history


def _mid_exposure(frames: EventFrames) -> Tensor:
    """The EDI's default reference time (mid-exposure) per frame :math:`(B,)`, µs."""
    return (frames.exposure_start + frames.exposure_end) / 2


def _latency_bounds(frames: EventFrames, search_range: tuple[float, float] | None) -> tuple[Tensor, Tensor]:
    """The range the constant latency is searched in, per frame :math:`(B,)` float64 µs."""
    if search_range is None:
        return torch.zeros_like(frames.exposure_time), frames.exposure_time
    low, high = search_range
    return torch.full_like(frames.exposure_time, low), torch.full_like(frames.exposure_time, high)


def _check_grid_spans(grid: EventGrid | None, frames: EventFrames, low: Tensor | float, high: Tensor,
                      num_bins: int) -> None:
    """A grid passed in must serve every latency in ``[low, high]`` (checked at both ends)."""
    for latency in (low, high):
        _check_grid(grid, frames.events, frames.exposure_start, frames.exposure_end, _mid_exposure(frames), latency,
                    num_bins, frames.blurry.dtype)


def _linear_grid_within_budget(frames: EventFrames, l_min: float, l_max: Tensor, num_bins: int) -> EventGrid | None:
    """The linear event grid over latencies ``[l_min, l_max]``, or None when it is over the memory budget."""
    events, b = frames.events, frames.batch_size
    args = (events, frames.exposure_start.to(events.device), frames.exposure_end.to(events.device),
            _mid_exposure(frames).to(events.device),
            torch.full((b,), l_min, dtype=torch.float64, device=events.device),
            l_max.to(events.device, torch.float64), num_bins, "linear", frames.blurry.dtype)
    if _event_grid_bytes(*args) > resolve_memory_budget():
        return None
    return _event_grid(*args, None)


def save_curve(model: PolynomialLatency, path: str | Path, **extra: Any) -> None:
    """Save the coefficients and f's settings (a small torch file)."""
    torch.save({"coefficients": model.coefficients.detach().cpu(), "order": model.order, "eps": model.eps,
                "scale_us": model.scale_us, "f": "log((L+eps)/(1+eps))/log(eps/(1+eps))", "format": "evlatcorr-curve",
                **extra}, path)


def load_curve(path: str | Path) -> PolynomialLatency:
    """Load a curve saved by :func:`save_curve` or a Lightning checkpoint of ``LatencyCorrectionModule``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such latency curve checkpoint")
    data = torch.load(path, map_location="cpu", weights_only=False)
    if "state_dict" in data:  # Lightning checkpoint
        hp = data.get("hyper_parameters", {})
        state = {k.split("latency_model.", 1)[1]: v for k, v in data["state_dict"].items()
                 if k.startswith("latency_model.")}
        model = PolynomialLatency(hp.get("order", 5), hp.get("eps", 0.01), hp.get("scale_us", 1000.0))
        model.load_state_dict(state, strict=True)
        return model
    if data.get("format") != "evlatcorr-curve":
        raise ValueError(f"{path}: not an evlatcorr latency curve")
    model = PolynomialLatency(data["order"], data["eps"], data["scale_us"])
    with torch.no_grad():
        model.coefficients.copy_(data["coefficients"])
    return model


class SpatialLatencyCorrector(nn.Module):
    """Per-pixel latency correction (what ``EventLatencyCorrector(mode="spatial")`` runs).

    With ``curve``, the trained polynomial gives the map directly; without, a polynomial is fitted
    on the batch it is given (``steps`` Adam steps of the self-supervised objective). Like the
    constant mode, a batch with a frame that has no events in ``[exposure_start, exposure_end +
    exposure time)`` is refused with a :class:`ValueError` naming the sample. A blank frame (black or saturated
    nearly everywhere, or flat: :mod:`evlatcorr.blank_frames`), or one whose constant search finds no latency (its
    ``l_const`` would anchor the fit), takes no part in the fit and gets the search range's low end, with a warning;
    a trained ``curve`` reads a flat frame's intensities as any other's. ``meta["latency_source"]`` says per frame
    what set its map (``"curve"``, ``"fit"``, ``"clipped"``, ``"flat"`` or ``"fallback"``),
    ``meta["latency_fallback"]`` :math:`(B,)` which frames got the fallback.

    Args:
        curve: path of a saved curve or Lightning checkpoint, or None.
        threshold: contrast threshold θ (``forward(frames, threshold=...)`` overrides it for one call: a θ estimated
            on those frames, as ``EventLatencyCorrector(mode="spatial", threshold="auto")`` does).
        config: the search settings (:class:`~evlatcorr.config.SearchConfig`): the output latent's EDI bins
            (``num_bins``), the latency range, and how the fit's constant starting point ``l_const`` is searched
            and scored; default ``SearchConfig()``.
        steps: test-time optimisation steps when no curve is given.
        lr: Adam learning rate of the test-time optimisation.
        train_bins: EDI sub-intervals used while fitting (the output latent uses ``num_bins``).
        order: polynomial order for test-time fitting.
        weights: loss weights of the test-time fit (default α=1, β=1, η=20, ζ=0.1).
        progress: show a progress bar while fitting; default: when ``steps >= 100``.

    Example:
        >>> corrector = SpatialLatencyCorrector(steps=50)
        >>> corrector
        SpatialLatencyCorrector(curve=fit per batch, steps=50)
    """

    def __init__(self, curve: str | Path | None = None, threshold: float | str = 0.2,
                 config: SearchConfig | None = None, steps: int = 30, lr: float = 0.05, train_bins: int = 100,
                 order: int = 5, weights: LossWeights | None = None, progress: bool | None = None) -> None:
        super().__init__()
        if isinstance(threshold, str):
            raise ValueError("mode='spatial' needs a numeric threshold")
        if not threshold > 0:
            raise ValueError(f"threshold must be positive, got {threshold}")
        if steps < 1 or train_bins < 2:
            raise ValueError(f"steps must be >= 1 and train_bins >= 2, got {steps} and {train_bins}")
        if order < 0:
            raise ValueError(f"order K must be >= 0, got {order}")
        if config is not None and not isinstance(config, SearchConfig):
            raise ValueError(f"config must be a SearchConfig, got {type(config).__name__}")
        self.model = load_curve(curve) if curve is not None else None
        self.threshold, self.config = float(threshold), config or SearchConfig()
        self.steps, self.lr, self.train_bins, self.order, self.weights = steps, lr, train_bins, order, weights
        self.progress = steps >= 100 if progress is None else progress

    def extra_repr(self) -> str:
        return f"curve={'trained' if self.model is not None else 'fit per batch'}, steps={self.steps}"

    def forward(self, frames: EventFrames, threshold: float | Tensor | None = None) -> EventFrames:
        check_search_size(frames.sensor_size)
        counts = check_has_events(frames)  # as the constant mode: no latency without events
        # the frames were checked when made, the settings in __init__: the work below checks nothing again
        if threshold is None:
            theta = torch.full((frames.batch_size,), self.threshold, dtype=torch.float64)
        else:
            theta = check_threshold(threshold, frames.batch_size).detach().to("cpu", torch.float64)
        fell_back = [False] * frames.batch_size
        if self.model is not None:  # the curve reads intensities: only a black or saturated frame has none to read
            blank = [kind if kind == "clipped" else None for kind in _blank_frames(frames, ("clipped",))]
            model = self.model.to(frames.device)
        else:
            blank = _blank_frames(frames)
            model, fell_back = self._fit(frames, theta, blank)
        skipped = [c is not None or f for c, f in zip(blank, fell_back)]
        if self.model is None:  # a trained curve reads the frame's intensities; a fit reads its events
            _warn_if_few_events(counts, skipped)
        with torch.no_grad():  # the map inside the search range, as a constant estimate is
            low, high = (bound.to(frames.blurry).view(-1, 1, 1, 1)
                         for bound in _latency_bounds(frames, self.config.search_range))
            latency = torch.minimum(torch.maximum(model(frames.blurry), low), high)
            if any(skipped):  # as the constant search: no shift beyond the range's low end
                skip = torch.tensor(skipped, device=latency.device).view(-1, 1, 1, 1)
                latency = torch.where(skip, low.expand_as(latency), latency)
            corrected = frames.events.shift(latency.double())
            latent = _edi_deblur(frames.blurry, corrected, frames.exposure_start, frames.exposure_end,
                                 _mid_exposure(frames), theta, None, self.config.num_bins)
        meta = dict(frames.meta)
        meta["threshold"] = self.threshold if threshold is None else threshold
        meta["latency_curve"] = model.coefficients.detach().cpu()
        meta["latency_fallback"] = torch.tensor(skipped, dtype=torch.bool, device=frames.device)
        meta["events_in_window"] = counts
        meta["latency_source"] = [c or ("fallback" if f else "fit" if self.model is None else "curve")
                                  for c, f in zip(blank, fell_back)]
        return frames.with_outputs(latency=latency.float().contiguous(), corrected=corrected, latent=latent, meta=meta)

    def _fit(self, frames: EventFrames, theta: Tensor, blank: list[str | None]) -> tuple[PolynomialLatency, list[bool]]:
        """The polynomial fitted on the frames that are not ``blank`` and whose constant search finds a latency,
        and which frames it did not (the fit anchors each frame's map at that latency, so a frame with none would
        be pulled to the fallback's no shift: it is left out, and warned of, as in constant mode)."""
        fell_back = [False] * frames.batch_size
        kept = [i for i, kind in enumerate(blank) if kind is None]
        if not kept:  # nothing to fit: every map is the fallback
            return PolynomialLatency(self.order).to(frames.device), fell_back
        config = self.config.replace(num_bins=self.train_bins)
        if frames.blurry.requires_grad:  # the fit trains the polynomial alone: the caller's .grad stays untouched
            frames = frames.replace(blurry=frames.blurry.detach())
        fitted = _select(frames, kept)
        with torch.no_grad():
            reference = _search_constant_latency(fitted.blurry, fitted.events, fitted.exposure_start,
                                                 fitted.exposure_end, theta[:len(kept)], config)
        none_found = reference.fallback.tolist()
        for i, fell in zip(kept, none_found):
            fell_back[i] = fell
        if any(none_found):
            which = [i for i, fell in enumerate(fell_back) if fell]
            warnings.warn(fallback_warning("fallback", which, _LEFT_OUT), stacklevel=user_stacklevel())
            found = [j for j, fell in enumerate(none_found) if not fell]
            if not found:
                return PolynomialLatency(self.order).to(frames.device), fell_back
            fitted = _select(fitted, found)
            l_const = reference.latency[found]
        else:
            l_const = reference.latency
        # fitting needs autograd even when called under no_grad or inference mode (e.g. a test loop)
        with torch.inference_mode(False), torch.enable_grad():
            if any(t.is_inference() for t in (fitted.blurry, fitted.events.t)):
                fitted = _clone_frames(fitted)
            model, _ = _fit_spatial_latency(fitted, PolynomialLatency(self.order), self.steps, self.lr,
                                            theta[:fitted.batch_size], config, self.weights, self.progress, True,
                                            "table", l_const.clone())
        return model, fell_back


def _warn_if_few_events(counts: Tensor, skipped: list[bool]) -> None:
    """Name the fitted frames when they hold under :data:`~evlatcorr.checks.FEW_EVENTS` events in their windows
    together, as constant mode names a frame: one polynomial is fitted to all their events, and so few cannot tell
    a latency (a skipped frame was named already)."""
    fitted = [i for i, skip in enumerate(skipped) if not skip]
    total = sum(int(counts[i]) for i in fitted)
    if fitted and total < FEW_EVENTS:
        warnings.warn(few_events_warning(fitted, str(total), "the map fitted to them", together=len(fitted) > 1),
                      stacklevel=user_stacklevel())


def _select(frames: EventFrames, which: list[int]) -> EventFrames:
    """The frames of a batch at the indices ``which``, in order (the batch itself where it is all of them)."""
    if len(which) == frames.batch_size:
        return frames
    parts = frames.split()
    return EventFrames.cat([parts[i] for i in which])


#: what a frame left out of the spatial fit gets (the outcome of :func:`evlatcorr.search.fallback_warning`)
_LEFT_OUT = "left out of the fit, {its} latency is the low end of the search range"


def _blank_frames(frames: EventFrames, kinds: tuple[str, ...] = BLANK_KINDS) -> list[str | None]:
    """Each frame's kind of blank among ``kinds`` (:func:`evlatcorr.blank_frames.blank_kinds`), else None: such
    frames take no part in the fit and keep the fallback latency, with a warning, as the constant search does."""
    blank = [kind if kind in kinds else None for kind in blank_kinds(frames.blurry)]
    for kind in kinds:
        which = [i for i, k in enumerate(blank) if k == kind]
        if which:
            warnings.warn(fallback_warning(kind, which, _LEFT_OUT), stacklevel=user_stacklevel())
    return blank


def _clone_frames(frames: EventFrames) -> EventFrames:
    """Normal (non-inference) copies of the tensors the fit saves for backward."""
    from evlatcorr.events import Events

    ev = frames.events
    events = Events.from_canonical(ev.x.clone(), ev.y.clone(), ev.t.clone(), ev.p.clone(), ev.batch.clone(),
                                   ev.sensor_size, ev.batch_size)
    return frames.replace(blurry=frames.blurry.clone(), events=events,
                          exposure_start=frames.exposure_start.clone(), exposure_end=frames.exposure_end.clone())
