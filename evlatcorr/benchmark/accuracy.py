"""A seeded accuracy suite for latency estimators on simulated scenes (``benchmarks/accuracy.py``).

Two splits of one-frame cases, each drawn from its own fixed seed:

- ``"dev"``: :data:`~evlatcorr.simulate.PHOTOGRAPHS_TRAIN` photographs and procedural scenes with
  one set of seeds; tune on it.
- ``"dev_wide"``: 120 more cases of the dev split's distribution (its photographs, seeds of their own): tune on
  it with ``"dev"`` where 40 cases cannot tell two estimators apart (their medians move by about 100 µs
  between draws, and one case decides a worst figure).
- ``"test"``: :data:`~evlatcorr.simulate.PHOTOGRAPHS_TEST` photographs and procedural scenes with
  disjoint seeds; report on it.

Each factor (scene, dark background, brightness, motion kind, speed, direction, latency model,
latency, each noise model, threshold) is drawn from its own generator stream, categorical factors
as a shuffled balanced list, so every split covers every procedural kind, motion kind, latency
model and noise model, and dark scenes. A case is a 20 ms exposure of a ``(96, 128)`` sensor
whose events stop 15 ms after the exposure's end.

:func:`evaluate_case` scores an estimator (delayed :class:`~evlatcorr.frames.EventFrames` in, a
latency map :math:`(B, 1, H, W)` µs out): the latency error, and EDI PSNR against the sharp
mid-exposure frame with ideal events, with the delayed events uncorrected and corrected by the
estimated map; the recovery ``(corr − uncorr) / (ideal − uncorr)``; for the photoreceptor model
(``"intensity"``) also the best constant shift's PSNR (an oracle) and the share of its gain the
estimator achieves; and the estimator on the case's ideal events, where 0 is right, with what correcting them by
its answer does to their EDI PSNR.

The cases and their simulation are in :mod:`evlatcorr.benchmark.accuracy_cases`, the summaries and tables in
:mod:`evlatcorr.benchmark.accuracy_report`; this module scores estimators on them and names all three's public parts.

Example:
    >>> cases = make_cases("test")
    >>> len(cases) >= 48, cases[0].split
    (True, 'test')
"""

from __future__ import annotations

import importlib
import importlib.util
import math
import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

from evlatcorr.benchmark import compare
from evlatcorr.benchmark.accuracy_cases import (  # the suite's cases, here too: the suite's one public face
    BEST_SHIFTS_US,
    DEFAULT_SIZE,
    DELAY_TRAIN_SPLIT,
    LATENCY_MODELS,
    MOTION_KINDS,
    SPLITS,
    TRAIN_SPLITS,
    Case,
    at_exposure,
    make_cases,
    simulate_case,
)
from evlatcorr.benchmark.accuracy_report import recovery_text, summarize, to_markdown, warning_kinds, write_results
from evlatcorr.benchmark.compare import NO_GAP_DB, edi_psnr, psnr
from evlatcorr.edi import edi_deblur, event_grid
from evlatcorr.frames import EventFrames
from evlatcorr.simulate import SimulatedSequence

__all__ = [
    "SPLITS",
    "LATENCY_MODELS",
    "MOTION_KINDS",
    "DEFAULT_SIZE",
    "DELAY_TRAIN_SPLIT",
    "TRAIN_SPLITS",
    "Case",
    "at_exposure",
    "make_cases",
    "simulate_case",
    "case_reference",
    "training_target",
    "evaluate_case",
    "corrector_estimator",
    "load_estimator",
    "run_suite",
    "summarize",
    "warning_kinds",
    "to_markdown",
    "write_results",
]

Estimator = Callable[[EventFrames], "Tensor | EventFrames"]  # a latency map, or frames holding one




# --- evaluation ------------------------------------------------------------------------------------------------------
def _gain_ratio(value: float, low: float, high: float) -> float:
    """``(value − low) / (high − low)``, NaN when ``high <= low + NO_GAP_DB``."""
    return compare.recovery(value, low, high, NO_GAP_DB)


def case_reference(case: Case, simulated: tuple[EventFrames, EventFrames, SimulatedSequence] | None = None
                   ) -> dict[str, Any]:
    """What does not depend on the estimator: EDI PSNR with ideal and uncorrected events, true latency stats,
    and the best constant shift: the oracle latency whose EDI is closest to the sharp frame (a scan of
    :data:`BEST_SHIFTS_US` refined to 62.5 µs). For a constant latency it shows how far EDI's own optimum lies from
    the true latency; where latency varies with intensity, how much of the gap any one latency can recover.

    Returns:
        a dict with ``psnr_ideal``, ``psnr_uncorrected``, ``true_latency_us`` (mean), ``true_latency_min_us``,
        ``true_latency_max_us``, ``num_events``, ``best_shift_us`` and ``psnr_best_shift``.
    """
    delayed, ideal, _ = simulated if simulated is not None else simulate_case(case)
    true = delayed.meta["true_latency"]
    ref: dict[str, Any] = dict(
        psnr_ideal=edi_psnr(ideal, case.threshold), psnr_uncorrected=edi_psnr(delayed, case.threshold),
        true_latency_us=float(true.mean()), true_latency_min_us=float(true.min()),
        true_latency_max_us=float(true.max()), num_events=len(delayed.events))
    ref.update(_best_shift(delayed, case.threshold, case.after_us))
    return ref


def _best_shift(delayed: EventFrames, threshold: float, reach_us: float = BEST_SHIFTS_US[-1]) -> dict[str, float]:
    """The oracle: the constant latency whose EDI is closest to the sharp frame in PSNR.

    A scan of :data:`BEST_SHIFTS_US` (scaled to end at ``reach_us``, where the events stop: a case at another
    exposure), then two halvings of the step around the best (±125, ±62.5 µs at the suite's 20 ms).
    """
    shifts = [s * reach_us / BEST_SHIFTS_US[-1] for s in BEST_SHIFTS_US]
    grid = event_grid(delayed.events, delayed.exposure_start, delayed.exposure_end, 500, (0.0, shifts[-1]))

    def psnr_at(shift: float) -> float:
        return psnr(edi_deblur(delayed.blurry, delayed.events, delayed.exposure_start, delayed.exposure_end,
                                threshold=threshold, latency=shift, grid=grid), delayed.sharp)

    best = max((psnr_at(shift), shift) for shift in shifts)
    step = shifts[1] - shifts[0]
    for _ in range(2):
        step /= 2
        around = [s for s in (best[1] - step, best[1] + step) if shifts[0] <= s <= shifts[-1]]
        best = max([best, *((psnr_at(s), s) for s in around)])
    return {"psnr_best_shift": best[0], "best_shift_us": best[1]}


def training_target(case: Case, delayed: EventFrames, *, delay_best_shift: bool = False) -> float:
    """What the learned curve reader is trained to pick for a training case, µs: the true latency of a constant
    one, the best constant shift (:func:`case_reference`'s oracle) under the photoreceptor model, where no one
    latency is true; with ``delay_best_shift``, the best constant shift under the per-pixel delay model too (the
    tile reader's delay frames, :mod:`evlatcorr.tile_reader`).

    Raises:
        ValueError: for the ``"intensity_delay"`` model without ``delay_best_shift`` (the curve reader is not
            trained on its frames).
    """
    if case.latency_model == "constant":
        return case.latency_us
    if case.latency_model == "intensity" or (case.latency_model == "intensity_delay" and delay_best_shift):
        return _best_shift(delayed, case.threshold, case.after_us)["best_shift_us"]
    raise ValueError(f"no training target for the {case.latency_model!r} latency model")


def _as_map(latency: Any, frames: EventFrames) -> Tensor:
    b, (h, w) = frames.batch_size, frames.sensor_size
    if isinstance(latency, EventFrames):
        latency = latency.latency
    if not isinstance(latency, Tensor):
        try:
            latency = torch.as_tensor(latency, dtype=torch.float64)
        except (TypeError, ValueError):
            raise ValueError(f"the estimator must return a latency map (B, 1, H, W) in µs, got "
                             f"{type(latency).__name__}") from None
    latency = latency.detach().to(frames.device, torch.float64)
    if latency.dim() in (0, 1) and latency.numel() in (1, b):
        latency = latency.reshape(-1, 1, 1, 1).expand(b, 1, h, w)
    if tuple(latency.shape) != (b, 1, h, w):
        raise ValueError(f"the estimator must return a latency map of shape {(b, 1, h, w)} in µs, got "
                         f"{tuple(latency.shape)}")
    if not bool(torch.isfinite(latency).all()):
        raise ValueError("the estimator returned NaN or infinite latencies")
    return latency


def evaluate_case(case: Case, estimate: Estimator, *,
                  simulated: tuple[EventFrames, EventFrames, SimulatedSequence] | None = None,
                  reference: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """Score one estimator on one case.

    Args:
        case: the case.
        estimate: takes the delayed :class:`EventFrames` (one frame; ``meta["threshold"]`` holds the
            case's true threshold) and returns its latency map :math:`(B, 1, H, W)` µs (a scalar,
            a :math:`(B,)` vector or an :class:`EventFrames` with ``latency`` are accepted too), e.g.
            ``lambda f: EventLatencyCorrector(threshold=case.threshold)(f).latency``.
        simulated: ``simulate_case(case)``, to reuse it across estimators.
        reference: ``case_reference(case, simulated)``, to reuse it across estimators.

    Returns:
        the case's fields, :func:`case_reference`'s values and ``est_latency_us`` (mean of the map),
        ``latency_error_us`` (constant: estimate − true; maps: mean |map − true| over pixels),
        ``latency_abs_error_us``, ``latency_bias_us`` (mean estimate − mean truth), ``psnr_corrected``,
        ``recovery`` (NaN when there is no gap), ``no_gap``, ``best_shift_share`` (the share of the best
        constant shift's PSNR gain), ``latency_spread_us`` (the learned reader's,
        when ``estimate`` returns the corrector's frames; else NaN), ``ideal_estimate_us`` (the estimator's
        latency on the case's ideal events, where 0 is right), ``ideal_psnr_change_db`` (their EDI PSNR corrected by
        it, minus as they are), ``time_s`` (the estimate's wall time) and
        ``warnings`` (messages raised by it) and ``error`` (empty; when the estimator raised, its exception as
        ``"Type: message"``, with NaN estimates and scores: one case's failure does not stop a suite).
    """
    simulated = simulated if simulated is not None else simulate_case(case)
    delayed = simulated[0]
    ref = dict(reference) if reference is not None else case_reference(case, simulated)
    frames = delayed.replace(meta={**delayed.meta, "threshold": case.threshold})
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        try:
            raw, error = estimate(frames), ""
        except Exception as exc:  # noqa: BLE001 - one case's failure is recorded, the suite goes on
            raw, error = None, f"{type(exc).__name__}: {exc}"
        elapsed = time.perf_counter() - t0
    scores = dict.fromkeys(_ESTIMATE_COLUMNS, math.nan) if error else _estimate_columns(case, delayed, ref, raw)
    return {
        **_case_columns(case), **ref, **scores, **_ideal_columns(case, estimate, simulated[1], ref["psnr_ideal"]),
        "no_gap": not ref["psnr_ideal"] > ref["psnr_uncorrected"] + NO_GAP_DB, "time_s": elapsed,
        "warnings": sorted({str(w.message) for w in caught}), "error": error,
    }


def _ideal_columns(case: Case, estimate: Estimator, ideal: EventFrames, psnr_ideal: float) -> dict[str, float]:
    """The estimator on the case's ideal events (no latency: 0 is right): ``ideal_estimate_us``, its mean latency,
    and ``ideal_psnr_change_db``, the EDI PSNR of the ideal events corrected by it minus that of the ideal events
    as they are (what correcting costs, or gains, where there is no latency to correct); NaN if it raises."""
    # the ideal events' own latency is 0 (their meta carries the case's, for the delayed events)
    true = torch.zeros_like(ideal.meta["true_latency"])
    frames = ideal.replace(meta={**ideal.meta, "threshold": case.threshold, "true_latency": true})
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the main estimate's warnings are the case's
        try:
            latency = _as_map(estimate(frames), ideal)
        except Exception:  # noqa: BLE001 - reported as NaN; the main estimate's failure is the case's error
            return {"ideal_estimate_us": math.nan, "ideal_psnr_change_db": math.nan}
        change = edi_psnr(ideal, case.threshold, latency.float()) - psnr_ideal
    return {"ideal_estimate_us": float(latency.mean()), "ideal_psnr_change_db": change}


_ESTIMATE_COLUMNS = ("est_latency_us", "est_latency_min_us", "est_latency_max_us", "latency_error_us",
                     "latency_abs_error_us", "latency_bias_us", "psnr_corrected", "recovery", "best_shift_share",
                     "latency_spread_us")


def _estimate_columns(case: Case, delayed: EventFrames, ref: Mapping[str, Any], raw: Any) -> dict[str, float]:
    """The :data:`_ESTIMATE_COLUMNS` of an estimator's answer ``raw``."""
    latency = _as_map(raw, delayed)
    true = delayed.meta["true_latency"].to(torch.float64)
    if case.latency_model == "constant":
        error = float(latency.mean() - true.mean())
        abs_error = abs(error)
    else:
        error = abs_error = float((latency - true).abs().mean())
    psnr_corrected = edi_psnr(delayed, case.threshold, latency.float())
    return {
        "est_latency_us": float(latency.mean()), "est_latency_min_us": float(latency.min()),
        "est_latency_max_us": float(latency.max()), "latency_error_us": error, "latency_abs_error_us": abs_error,
        "latency_bias_us": float(latency.mean() - true.mean()), "psnr_corrected": psnr_corrected,
        "recovery": _gain_ratio(psnr_corrected, ref["psnr_uncorrected"], ref["psnr_ideal"]),
        "best_shift_share": _gain_ratio(psnr_corrected, ref["psnr_uncorrected"], ref["psnr_best_shift"]),
        "latency_spread_us": _spread(raw),
    }


def _spread(raw: Any) -> float:
    """The learned reader's ``meta["latency_spread_us"]`` of an estimator's answer (NaN where it has none)."""
    spread = raw.meta.get("latency_spread_us") if isinstance(raw, EventFrames) else None
    return math.nan if spread is None else float(spread.double().mean())


def _case_columns(case: Case) -> dict[str, Any]:
    d = case.to_dict()
    d["objects"] = " ".join(s if k is None else f"proc-{s}:{k}" for s, k in case.objects)
    d["latency_range_us"] = f"{case.latency_range_us[0]:.0f}-{case.latency_range_us[1]:.0f}"
    d["size"] = f"{case.size[0]}x{case.size[1]}"
    d.update(dark=case.dark, dark_regions=case.dark_regions, noise_models=" ".join(case.noise_models))
    return d


# --- estimators ------------------------------------------------------------------------------------------------------
def corrector_estimator(mode: str = "constant", threshold: float | str = 0.2, **kwargs: Any) -> Estimator:
    """``EventLatencyCorrector(mode, threshold, **kwargs)`` as an estimator (returns its output frames: the suite
    reads their latency map and ``meta["latency_spread_us"]``).

    Example:
        >>> estimate = corrector_estimator("constant", threshold=0.25)
    """
    from evlatcorr.correction import EventLatencyCorrector

    corrector = EventLatencyCorrector(mode=mode, threshold=threshold, **kwargs)

    def estimate(frames: EventFrames) -> EventFrames:
        return corrector(frames)

    return estimate


def load_estimator(spec: str) -> Estimator:
    """Load ``"module:function"`` or ``"path/to/file.py:function"``: a callable ``f(frames) -> latency map``.

    Example:
        >>> load_estimator("evlatcorr.benchmark.accuracy:corrector_estimator")  # doctest: +ELLIPSIS
        <function corrector_estimator at ...>
    """
    if not isinstance(spec, str) or spec.count(":") < 1:
        raise ValueError(f"estimator must be 'module:function' or 'file.py:function', got {spec!r}")
    module_name, _, attr = spec.rpartition(":")
    if module_name.endswith(".py"):
        path = Path(module_name)
        if not path.is_file():
            raise ValueError(f"estimator file {path} does not exist")
        module_spec = importlib.util.spec_from_file_location(path.stem, path)
        if module_spec is None or module_spec.loader is None:
            raise ValueError(f"cannot load {path} as a Python module")
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
    else:
        module = importlib.import_module(module_name)
    fn = getattr(module, attr, None)
    if not callable(fn):
        raise ValueError(f"{spec}: {attr!r} is not a callable of {module_name}")
    return fn


def run_suite(cases: Sequence[Case], estimators: Mapping[str, Callable[[Case], Estimator]],
              progress: Callable[[str], None] | None = print, before_us: float = 0.0) -> list[dict[str, Any]]:
    """Simulate each case once and evaluate every estimator on it.

    Args:
        cases: the cases.
        estimators: name → factory ``case -> estimator`` (e.g. to pass the case's threshold).
        progress: called with one line per case and estimator; None for silence.
        before_us: the frames also keep this long of events before the exposure (:func:`simulate_case`).

    Returns:
        one :func:`evaluate_case` dict per case and estimator, with ``estimator``, ``sim_time_s``
        and ``reference_time_s`` added.
    """
    results = []
    for k, case in enumerate(cases):
        t0 = time.perf_counter()
        simulated = simulate_case(case, before_us=before_us)
        t1 = time.perf_counter()
        reference = case_reference(case, simulated)
        t2 = time.perf_counter()
        for name, factory in estimators.items():
            row = evaluate_case(case, factory(case), simulated=simulated, reference=reference)
            row.update(estimator=name, sim_time_s=t1 - t0, reference_time_s=t2 - t1)
            results.append(row)
            if progress is not None and row["error"]:
                progress(f"[{k + 1}/{len(cases)}] {name:>8} {case.name}: the estimator failed ({row['error']})")
            elif progress is not None:
                progress(f"[{k + 1}/{len(cases)}] {name:>8} {case.name}: true {row['true_latency_us']:.0f} est "
                         f"{row['est_latency_us']:.0f} err {row['latency_error_us']:+.0f} us, PSNR ideal "
                         f"{row['psnr_ideal']:.2f} uncorr {row['psnr_uncorrected']:.2f} corr "
                         f"{row['psnr_corrected']:.2f}, recovery {recovery_text(row['recovery'])}; "
                         f"sim {t1 - t0:.1f} s, ref {t2 - t1:.1f} s, estimate {row['time_s']:.1f} s")
    return results
