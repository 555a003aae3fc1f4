"""Two estimators on the same accuracy-suite cases, case by case: is a change better, or within the noise?

The suite's headline figures are medians over a dozen to a few dozen cases per latency model, and one case can move
them (a photoreceptor share of 87 against 90 % is one case of twelve). A paired comparison says more: for each latency
model, the mean EDI PSNR change over the cases both estimators scored, with a seeded bootstrap 95 % interval, and how
many cases gain or lose more than 0.5 dB. An interval that holds 0 is a change within what these cases can tell.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.benchmark.accuracy_cases import LATENCY_MODELS

__all__ = ["bootstrap_interval", "paired_comparison", "comparison_markdown", "load_results", "compare_runs"]

#: a case gains or loses when its EDI PSNR moves by more than this, dB
CLEAR_CHANGE_DB = 0.5


def bootstrap_interval(values: Sequence[float], level: float = 0.95, resamples: int = 4000, seed: int = 0,
                       statistic: str = "mean") -> tuple[float, float]:
    """The percentile bootstrap interval of the mean (or ``statistic="median"``) of ``values``: the cases drawn with
    replacement, seeded. NaN values are left out.

    Returns ``(nan, nan)`` for fewer than two values.

    Example:
        >>> low, high = bootstrap_interval([0.1, 0.3, 0.2, 0.4, 0.0, 0.2])
        >>> low < 0.2 < high
        True
    """
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    if isinstance(resamples, bool) or not isinstance(resamples, int) or resamples < 1:
        raise ValueError(f"resamples must be a whole number >= 1, got {resamples!r}")
    if statistic not in ("mean", "median"):
        raise ValueError(f"statistic must be 'mean' or 'median', got {statistic!r}")
    data = np.asarray([v for v in values if v is not None and math.isfinite(v)], dtype=np.float64)
    if data.size < 2:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    samples = data[rng.integers(0, data.size, size=(resamples, data.size))]
    values_of = samples.mean(axis=1) if statistic == "mean" else np.median(samples, axis=1)
    tail = (1.0 - level) / 2
    return float(np.quantile(values_of, tail)), float(np.quantile(values_of, 1.0 - tail))


def _scored(row: Mapping[str, Any]) -> bool:
    return not row.get("error") and row.get("psnr_corrected") is not None and math.isfinite(row["psnr_corrected"])


def paired_comparison(results: Sequence[Mapping[str, Any]], baseline: str, other: str,
                      seed: int = 0) -> list[dict[str, Any]]:
    """``other`` against ``baseline`` on the cases (by split and name) that both scored, per latency model and over
    all of them.

    Args:
        results: the suite's rows (:func:`evlatcorr.benchmark.accuracy.run_suite`, or ``results.json``'s
            ``"results"``), holding both estimators' rows.
        baseline: the estimator compared against (its ``"estimator"`` name).
        other: the estimator compared.
        seed: the bootstrap's seed.

    Returns:
        one dict per latency model with cases (then ``"all"``): ``baseline``, ``other``, ``latency_model``,
        ``cases``, ``mean_psnr_change_db`` (other − baseline, EDI PSNR with the corrected events) and its bootstrap
        95 % interval ``psnr_change_low_db`` / ``psnr_change_high_db``, ``gaining`` / ``losing`` (cases moving more
        than 0.5 dB), ``median_abs_error_us`` of each (``baseline_…``, ``other_…``: the estimate's error, or the map
        error for the intensity models) and, where the rows have them, ``mean_ideal_psnr_change_db`` of each (what
        correcting ideal events by the estimate costs).

    Raises:
        ValueError: when an estimator has no rows, or the two share no scored case.

    Example:
        >>> rows = [{"estimator": e, "split": "dev", "name": f"dev-{i}", "latency_model": "constant",
        ...          "psnr_corrected": 30.0 + i + (0.5 if e == "b" else 0.0), "latency_abs_error_us": 100.0}
        ...         for e in ("a", "b") for i in range(4)]
        >>> [round(g["mean_psnr_change_db"], 2) for g in paired_comparison(rows, "a", "b")]
        [0.5, 0.5]
    """
    by_estimator: dict[str, dict[tuple[str, str], Mapping[str, Any]]] = {baseline: {}, other: {}}
    for row in results:
        if row["estimator"] in by_estimator:
            by_estimator[row["estimator"]][(row["split"], row["name"])] = row
    for name, rows in by_estimator.items():
        if not rows:
            raise ValueError(f"no rows of estimator {name!r}; the results hold "
                             f"{sorted({r['estimator'] for r in results})}")
    pairs = [(row, by_estimator[other][key]) for key, row in by_estimator[baseline].items()
             if key in by_estimator[other] and _scored(row) and _scored(by_estimator[other][key])]
    if not pairs:
        raise ValueError(f"{baseline!r} and {other!r} share no case that both scored")
    groups = []
    for model in (*LATENCY_MODELS, "all"):
        sub = pairs if model == "all" else [(a, b) for a, b in pairs if a["latency_model"] == model]
        if sub:
            groups.append({"baseline": baseline, "other": other, "latency_model": model, **_paired_stats(sub, seed)})
    return groups


def _paired_stats(pairs: Sequence[tuple[Mapping[str, Any], Mapping[str, Any]]], seed: int) -> dict[str, Any]:
    change = [b["psnr_corrected"] - a["psnr_corrected"] for a, b in pairs]
    low, high = bootstrap_interval(change, seed=seed)

    def median(values: list[float]) -> float:
        finite = [v for v in values if v is not None and math.isfinite(v)]
        return float(np.median(finite)) if finite else math.nan

    def mean(values: list[float]) -> float:
        finite = [v for v in values if v is not None and math.isfinite(v)]
        return float(np.mean(finite)) if finite else math.nan

    return {
        "cases": len(pairs), "mean_psnr_change_db": float(np.mean(change)),
        "psnr_change_low_db": low, "psnr_change_high_db": high,
        "gaining": sum(c > CLEAR_CHANGE_DB for c in change), "losing": sum(c < -CLEAR_CHANGE_DB for c in change),
        "baseline_median_abs_error_us": median([a["latency_abs_error_us"] for a, _ in pairs]),
        "other_median_abs_error_us": median([b["latency_abs_error_us"] for _, b in pairs]),
        "baseline_mean_ideal_psnr_change_db": mean([a.get("ideal_psnr_change_db", math.nan) for a, _ in pairs]),
        "other_mean_ideal_psnr_change_db": mean([b.get("ideal_psnr_change_db", math.nan) for _, b in pairs]),
    }


def comparison_markdown(groups: Sequence[Mapping[str, Any]]) -> str:
    """:func:`paired_comparison`'s groups as a markdown table (one row per latency model)."""
    if not groups:
        return ""

    def num(v: float, digits: int) -> str:
        return "–" if v is None or math.isnan(v) else f"{v:+.{digits}f}" if digits else f"{v:.0f}"

    first = groups[0]
    lines = [f"## {first['other']} against {first['baseline']}, case by case", "",
             "EDI PSNR with the corrected events, other − baseline, over the cases both scored: the mean with a "
             "bootstrap 95 % interval (cases resampled; an interval that holds 0 is within what these cases tell), "
             f"and the cases moving more than {CLEAR_CHANGE_DB} dB. Errors: the constant latency's, or the map's.", "",
             "| latency model | cases | mean PSNR change dB (95 % interval) | gaining / losing > 0.5 dB | "
             "median abs error µs, baseline → other | ideal events: mean PSNR change dB, baseline → other |",
             "|" + " --- |" * 6]
    for g in groups:
        lines.append(f"| {g['latency_model']} | {g['cases']} | {num(g['mean_psnr_change_db'], 3)} "
                     f"({num(g['psnr_change_low_db'], 3)} to {num(g['psnr_change_high_db'], 3)}) | "
                     f"{g['gaining']} / {g['losing']} | {num(g['baseline_median_abs_error_us'], 0)} → "
                     f"{num(g['other_median_abs_error_us'], 0)} | {num(g['baseline_mean_ideal_psnr_change_db'], 2)} → "
                     f"{num(g['other_mean_ideal_psnr_change_db'], 2)} |")
    return "\n".join(lines) + "\n"


def load_results(path: str | Path) -> list[dict[str, Any]]:
    """The rows of an accuracy run: its ``results.json``, or the folder that holds it.

    Raises:
        ValueError: when the file is missing or holds no suite rows.
    """
    path = Path(path)
    file = path / "results.json" if path.is_dir() else path
    try:
        data = json.loads(file.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ValueError(f"{file}: cannot read an accuracy run's results ({exc})") from exc
    rows = data.get("results") if isinstance(data, dict) else None
    if not isinstance(rows, list) or not all(isinstance(r, dict) and "estimator" in r for r in rows):
        raise ValueError(f"{file} holds no accuracy-suite rows (benchmarks/accuracy.py writes them)")
    return [{k: math.nan if v is None else v for k, v in r.items()} for r in rows]


def compare_runs(base: Sequence[Mapping[str, Any]], other: Sequence[Mapping[str, Any]], base_estimator: str,
                 other_estimator: str, labels: tuple[str, str] = ("base", "other"),
                 seed: int = 0) -> list[dict[str, Any]]:
    """:func:`paired_comparison` of one estimator of one run against one of another run (the same estimator at two
    commits, say), by case; ``labels`` name the two in the groups.

    Example:
        >>> row = {"split": "dev", "name": "dev-0", "latency_model": "constant", "latency_abs_error_us": 100.0}
        >>> a = [{**row, "estimator": "constant", "psnr_corrected": 30.0}]
        >>> b = [{**row, "estimator": "constant", "psnr_corrected": 30.25}]
        >>> compare_runs(a, b, "constant", "constant")[0]["mean_psnr_change_db"]
        0.25
    """
    if labels[0] == labels[1]:
        raise ValueError(f"the two runs need two labels, got {labels}")
    rows = [{**r, "estimator": labels[0]} for r in base if r["estimator"] == base_estimator]
    rows += [{**r, "estimator": labels[1]} for r in other if r["estimator"] == other_estimator]
    return paired_comparison(rows, labels[0], labels[1], seed)
