"""The accuracy suite's summaries (:mod:`evlatcorr.benchmark.accuracy`): figures per estimator, split and latency
model; the spatial mode against the constant one; markdown tables; results written as markdown, CSV and JSON."""

from __future__ import annotations

import csv
import json
import math
import re
import statistics
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from evlatcorr.benchmark.accuracy_cases import LATENCY_MODELS, SPLITS
from evlatcorr.benchmark.accuracy_compare import bootstrap_interval, comparison_markdown, paired_comparison

__all__ = ["summarize", "warning_kinds", "to_markdown", "write_results"]



def _finite(values: Iterable[float]) -> list[float]:
    return [v for v in values if v is not None and not math.isnan(v)]


def _median(values: Iterable[float]) -> float:
    v = _finite(values)
    return statistics.median(v) if v else math.nan


def _group_stats(rows: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    const = [r for r in rows if r["latency_model"] == "constant"]
    gap = [r for r in rows if r["latency_model"] in ("constant", "intensity_delay")]
    photo = [r for r in rows if r["latency_model"] == "intensity"]
    errors = _finite(r["latency_abs_error_us"] for r in const)
    # where the latency changes EDI's image (as recovery counts them): elsewhere no estimate is right or wrong for it
    errors_with_gap = _finite(r["latency_abs_error_us"] for r in const if not r["no_gap"])
    # how far EDI's own PSNR optimum lies from the truth: the floor of a latency error that still buys image quality
    oracle = [abs(r["best_shift_us"] - r["true_latency_us"]) for r in const]
    recovery = _finite(r["recovery"] for r in gap)
    ideal = _finite(r.get("ideal_estimate_us", math.nan) for r in rows)
    ideal_change = sorted(_finite(r.get("ideal_psnr_change_db", math.nan) for r in rows))
    photo_share = [r["best_shift_share"] for r in photo]
    return {
        "cases": len(rows),
        "median_abs_error_us": _median(errors), "worst_abs_error_us": max(errors, default=math.nan),
        "worst_abs_error_with_gap_us": max(errors_with_gap, default=math.nan),
        "median_best_shift_error_us": _median(oracle),
        "median_map_error_us": _median(r["latency_abs_error_us"] for r in rows if r["latency_model"] != "constant"),
        "median_recovery": _median(recovery), "worst_recovery": min(recovery, default=math.nan),
        "no_gap": sum(bool(r["no_gap"]) for r in gap),
        "median_best_shift_share": _median(r["best_shift_share"] for r in photo),
        "median_delay_best_shift_share": _median(r["best_shift_share"] for r in rows
                                                 if r["latency_model"] == "intensity_delay"),
        "median_const_best_shift_share": _median(r["best_shift_share"] for r in const),
        "median_time_s": _median(r["time_s"] for r in rows),
        "failed": sum(bool(r.get("error")) for r in rows),
        "median_ideal_estimate_us": _median(abs(v) for v in ideal),
        "worst_ideal_estimate_us": max((abs(v) for v in ideal), default=math.nan),
        "ideal_within_150us": sum(abs(v) <= 150.0 for v in ideal), "ideal_cases": len(ideal),
        "mean_ideal_psnr_change_db": statistics.fmean(ideal_change) if ideal_change else math.nan,
        "p10_ideal_psnr_change_db": ideal_change[len(ideal_change) // 10] if ideal_change else math.nan,
        "worst_ideal_psnr_change_db": ideal_change[0] if ideal_change else math.nan,
        "ideal_losing_half_db": sum(v < -0.5 for v in ideal_change),
        # how far one case more or less could move the headline medians: their bootstrap 95 % intervals
        "median_abs_error_interval_us": _median_interval(errors),
        "median_recovery_interval": _median_interval(recovery),
        "median_best_shift_share_interval": _median_interval(photo_share),
    }


def _median_interval(values: Iterable[float]) -> tuple[float, float]:
    return bootstrap_interval(_finite(values), statistic="median")


def warning_kinds(results: Sequence[Mapping[str, Any]]) -> list[tuple[int, str]]:
    """The kinds of warning the estimates raised, most common first: ``(estimates that raised it, an example)``.

    Messages that differ only in their numbers (a sample's times, a latency) are one kind, so the warning every case
    raises by design (the suite's streams stop 15 ms after the exposure) is one line, not one per case.

    Example:
        >>> rows = [{"warnings": ["events end at 49967 us"]}, {"warnings": ["events end at 50012 us", "no minimum"]}]
        >>> warning_kinds(rows)
        [(2, 'events end at 49967 us'), (1, 'no minimum')]

    Raises:
        ValueError: when a row has no list of messages under ``"warnings"``.
    """
    kinds: dict[str, list[Any]] = {}
    for k, row in enumerate(results):
        if not isinstance(row.get("warnings"), (list, tuple)):
            raise ValueError(f"row {k} has no list of messages under 'warnings'")
        for kind, message in {re.sub(r"-?\d[\d.,e+-]*", "#", w): w for w in sorted(row["warnings"])}.items():
            kinds.setdefault(kind, [0, message])[0] += 1
    return sorted(map(tuple, kinds.values()), key=lambda item: (-item[0], item[1]))


def summarize(results: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Aggregates per estimator, split and latency model (and over all models).

    Returns:
        ``{"groups": [{"estimator", "split", "latency_model", "cases", "median_abs_error_us", "worst_abs_error_us",
        "worst_abs_error_with_gap_us" (over the cases with a gap, where the latency changes EDI's image),
        "median_best_shift_error_us" (|oracle shift − true|), "median_const_best_shift_share" (constant cases),
        "median_map_error_us" (map cases), "median_recovery", "worst_recovery" (constant and intensity_delay cases with
        a gap), "no_gap", "median_best_shift_share" (intensity), "median_delay_best_shift_share" (intensity_delay),
        "median_time_s", "failed" (cases whose estimator raised; left out of the other figures),
        "median_ideal_estimate_us", "worst_ideal_estimate_us", "ideal_within_150us", "ideal_cases" (the estimates on
        ideal events, whose right answer is 0), "mean_ideal_psnr_change_db", "p10_ideal_psnr_change_db",
        "worst_ideal_psnr_change_db", "ideal_losing_half_db" (the EDI PSNR change of the ideal events corrected by that
        estimate, and the cases where it loses more than 0.5 dB), "median_abs_error_interval_us",
        "median_recovery_interval", "median_best_shift_share_interval" (the medians' bootstrap 95 % intervals, ``(low,
        high)``, NaN from fewer than two cases)}, ...], "spatial_vs_constant": [...], "spread_bands":
        [...], "paired": [[...], ...]}``;
        the second lists, for map cases evaluated by both ``"constant"`` and ``"spatial"``, their
        map errors and whether spatial's is lower; the third, the constant-latency cases in three bands of the
        learned reader's spread (``latency_spread_us``) with their errors; the fourth, each estimator after the first
        against the first, case by case (:func:`~evlatcorr.benchmark.accuracy_compare.paired_comparison`).
    """
    groups = []
    keys = sorted({(r["estimator"], r["split"]) for r in results}, key=lambda k: (k[0], SPLITS.index(k[1])))
    for estimator, split in keys:
        rows = [r for r in results if r["estimator"] == estimator and r["split"] == split]
        for model in (*LATENCY_MODELS, "all"):
            sub = rows if model == "all" else [r for r in rows if r["latency_model"] == model]
            if sub:
                groups.append({"estimator": estimator, "split": split, "latency_model": model, **_group_stats(sub)})
    by_case: dict[str, dict[str, Mapping[str, Any]]] = {}
    for r in results:
        by_case.setdefault(r["name"], {})[r["estimator"]] = r
    comparison = []
    for name, rows in by_case.items():
        if "constant" in rows and "spatial" in rows and rows["constant"]["latency_model"] != "constant":
            c, s = rows["constant"]["latency_abs_error_us"], rows["spatial"]["latency_abs_error_us"]
            comparison.append({"name": name, "split": rows["constant"]["split"],
                               "latency_model": rows["constant"]["latency_model"], "map_error_constant_us": c,
                               "map_error_spatial_us": s, "spatial_better": s < c,
                               "psnr_constant": rows["constant"]["psnr_corrected"],
                               "psnr_spatial": rows["spatial"]["psnr_corrected"]})
    return {"groups": groups, "spatial_vs_constant": comparison, "spread_bands": _spread_bands(results, keys),
            "paired": _paired(results)}


def _paired(results: Sequence[Mapping[str, Any]]) -> list[list[dict[str, Any]]]:
    """Each estimator after the first (in the rows' order) against the first, where they share scored cases."""
    estimators = list(dict.fromkeys(r["estimator"] for r in results))
    paired = []
    for other in estimators[1:]:
        try:
            paired.append(paired_comparison(results, estimators[0], other))
        except ValueError:  # no case both scored: nothing to compare
            continue
    return paired


def _spread_bands(results: Sequence[Mapping[str, Any]], keys: Sequence[tuple[str, str]]) -> list[dict[str, Any]]:
    """Per estimator and split, the constant-latency cases with a spread (:func:`_spread`) in three bands of as many
    cases, from the least to the most spread: does the spread tell a good estimate from a bad one?"""
    bands = []
    for estimator, split in keys:
        rows = sorted((r for r in results if r["estimator"] == estimator and r["split"] == split
                       and r["latency_model"] == "constant" and not math.isnan(r.get("latency_spread_us", math.nan))),
                      key=lambda r: r["latency_spread_us"])
        if len(rows) < 3:
            continue
        for band in range(3):
            part = rows[band * len(rows) // 3:(band + 1) * len(rows) // 3]
            errors = [r["latency_abs_error_us"] for r in part]
            bands.append({"estimator": estimator, "split": split, "band": band + 1, "cases": len(part),
                          "spread_low_us": part[0]["latency_spread_us"],
                          "spread_high_us": part[-1]["latency_spread_us"],
                          "median_abs_error_us": _median(errors), "worst_abs_error_us": max(errors),
                          "over_2ms": sum(e > 2000.0 for e in errors)})
    return bands


def recovery_text(v: float) -> str:
    """A recovery as a percentage, or "no gap" where the case has none to recover (NaN)."""
    return "no gap" if v is None or math.isnan(v) else f"{100 * v:.0f}%"


def _share(v: float) -> str:
    """A summary's ratio: "–" when no case has one."""
    return "–" if v is None or math.isnan(v) else f"{100 * v:.0f}%"


def _num(v: float, digits: int = 0) -> str:
    return "–" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def _interval_lines(groups: Sequence[Mapping[str, Any]]) -> list[str]:
    """The headline medians with their bootstrap 95 % intervals, per estimator, split and latency model."""
    rows = []
    for g in groups:
        figures = {"constant": [("median abs error", g["median_abs_error_us"], g["median_abs_error_interval_us"],
                                 "us"), ("median recovery", g["median_recovery"], g["median_recovery_interval"], "%")],
                   "intensity_delay": [("median recovery", g["median_recovery"], g["median_recovery_interval"], "%")],
                   "intensity": [("median share of the best shift", g["median_best_shift_share"],
                                  g["median_best_shift_share_interval"], "%")]}.get(g["latency_model"], [])
        for name, value, (low, high), unit in figures:
            if value is None or math.isnan(value) or math.isnan(low):  # no interval from fewer than two cases
                continue
            text = (f"{_num(value)} µs ({_num(low)} to {_num(high)})" if unit == "us" else
                    f"{_share(value)} ({_share(low)} to {_share(high)})")
            rows.append(f"| {g['estimator']} | {g['split']} | {g['latency_model']} | {g['cases']} | {name} | {text} |")
    if not rows:
        return []
    return ["", "## How sure the medians are", "",
            "Bootstrap 95 % intervals (the cases resampled, seeded): how far the same estimator's median could "
            "move on another draw of as many cases.", "",
            "| estimator | split | latency model | cases | figure | median (95 % interval) |", "|" + " --- |" * 6,
            *rows]


def to_markdown(results: Sequence[Mapping[str, Any]], summary: Mapping[str, Any] | None = None) -> str:
    """Markdown tables: the summary per estimator / split / latency model, then one row per case and estimator."""
    summary = summary if summary is not None else summarize(results)
    lines = ["## Summary", "",
             "| estimator | split | latency model | cases | median abs error µs | worst abs error µs | "
             "worst abs error with a gap µs | median abs error of EDI's best shift µs | median map error µs | "
             "median recovery | worst recovery | no gap | median share of best shift | median time s | failed |",
             "|" + " --- |" * 15]
    for g in summary["groups"]:
        share = {"intensity": g["median_best_shift_share"], "intensity_delay": g["median_delay_best_shift_share"]
                 }.get(g["latency_model"], g["median_const_best_shift_share"])
        lines.append(f"| {g['estimator']} | {g['split']} | {g['latency_model']} | {g['cases']} | "
                     f"{_num(g['median_abs_error_us'])} | {_num(g['worst_abs_error_us'])} | "
                     f"{_num(g['worst_abs_error_with_gap_us'])} | {_num(g['median_best_shift_error_us'])} | "
                     f"{_num(g['median_map_error_us'])} | "
                     f"{_share(g['median_recovery'])} | "
                     f"{_share(g['worst_recovery'])} | {g['no_gap']} | "
                     f"{_share(share)} | "
                     f"{_num(g['median_time_s'], 2)} | {g['failed']} |")
    lines += _interval_lines(summary["groups"])
    comparison = summary.get("spatial_vs_constant") or []
    if comparison:
        wins = sum(c["spatial_better"] for c in comparison)
        lines += ["", f"## Spatial vs constant on map cases: spatial has the lower map error on {wins}/"
                  f"{len(comparison)}", "",
                  "| case | latency model | map error constant µs | map error spatial µs | spatial better | "
                  "PSNR constant | PSNR spatial |", "|" + " --- |" * 7]
        for c in comparison:
            lines.append(f"| {c['name']} | {c['latency_model']} | {_num(c['map_error_constant_us'])} | "
                         f"{_num(c['map_error_spatial_us'])} | {'yes' if c['spatial_better'] else 'no'} | "
                         f"{_num(c['psnr_constant'], 2)} | {_num(c['psnr_spatial'], 2)} |")
    ideal = [g for g in summary["groups"] if g["latency_model"] == "all" and g.get("ideal_cases")]
    if ideal:
        lines += ["", "## Ideal events (no latency): the estimate should be 0", "",
                  "EDI PSNR change: the ideal events corrected by the estimate against the ideal events as they are "
                  "(what correcting costs where there is no latency, e.g. in daylight).", "",
                  "| estimator | split | cases | median abs estimate µs | worst µs | within 150 µs | "
                  "EDI PSNR change mean / p10 / worst dB | losing > 0.5 dB |",
                  "|" + " --- |" * 8]
        for g in ideal:
            lines.append(f"| {g['estimator']} | {g['split']} | {g['ideal_cases']} | "
                         f"{_num(g['median_ideal_estimate_us'])} | {_num(g['worst_ideal_estimate_us'])} | "
                         f"{g['ideal_within_150us']} | {_num(g['mean_ideal_psnr_change_db'], 2)} / "
                         f"{_num(g['p10_ideal_psnr_change_db'], 2)} / {_num(g['worst_ideal_psnr_change_db'], 2)} | "
                         f"{g['ideal_losing_half_db']} |")
    if summary.get("spread_bands"):
        lines += ["", "## The learned reader's spread against the error (constant latency)", "",
                  "`meta[\"latency_spread_us\"]`: the standard deviation of the reader's probability over the "
                  "candidates; the cases in three bands of as many cases each.", "",
                  "| estimator | split | band | cases | spread µs | median abs error µs | worst abs error µs | "
                  "error > 2 ms |", "|" + " --- |" * 8]
        for b in summary["spread_bands"]:
            lines.append(f"| {b['estimator']} | {b['split']} | {b['band']} | {b['cases']} | "
                         f"{_num(b['spread_low_us'])}-{_num(b['spread_high_us'])} | {_num(b['median_abs_error_us'])} | "
                         f"{_num(b['worst_abs_error_us'])} | {b['over_2ms']} |")
    for groups in summary.get("paired") or []:
        lines += ["", comparison_markdown(groups).rstrip("\n")]
    lines += ["", "## Cases", "",
              "Error: estimate − true for constant latency, mean |map − true| for the intensity models. "
              "Recovery: (corr − uncorr) / (ideal − uncorr) of EDI PSNR (dB) against the sharp frame. "
              "Best shift: the oracle constant latency whose EDI is closest to the sharp frame (0 to where the "
              "events stop, to a 240th of that: 0-15 ms to 62.5 µs at the suite's 20 ms exposures); "
              "its error against the true constant latency is how far EDI's own optimum lies from the truth.", "",
              "| estimator | case | noise | true µs | est µs | error µs | PSNR ideal | uncorr | corr | recovery | "
              "best shift µs / PSNR | share of best | time s |",
              "|" + " --- |" * 13]
    for r in results:
        best = "" if math.isnan(r["psnr_best_shift"]) else f"{r['best_shift_us']:.0f} / {r['psnr_best_shift']:.2f}"
        share = "" if math.isnan(r["psnr_best_shift"]) or r.get("error") else recovery_text(r["best_shift_share"])
        estimate = (f"{r['est_latency_us']:.0f} | {r['latency_error_us']:+.0f}" if not r.get("error")
                    else f"failed: {r['error']} | –")
        lines.append(f"| {r['estimator']} | {r['name']} | {r['noise_models'] or '–'} | {r['true_latency_us']:.0f} | "
                     f"{estimate} | {r['psnr_ideal']:.2f} | "
                     f"{r['psnr_uncorrected']:.2f} | {_num(r['psnr_corrected'], 2)} | "
                     f"{'–' if r.get('error') else recovery_text(r['recovery'])} | {best} | "
                     f"{share} | "
                     f"{r['time_s']:.2f} |")
    return "\n".join(lines) + "\n"


def _json_safe(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, Mapping):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(v) for v in value]
    return value


def write_results(results: Sequence[Mapping[str, Any]], out_dir: str | Path, summary: Mapping[str, Any] | None = None,
                  header: str = "") -> dict[str, Path]:
    """Write ``results.md`` (``header``, then :func:`to_markdown`), ``results.csv``, ``results.json`` and, where some
    case has an estimate, ``results.png`` (:func:`~evlatcorr.benchmark.accuracy_figure.plot_results`) to ``out_dir``.

    Returns:
        the paths written, by extension.
    """
    from evlatcorr.benchmark.accuracy_figure import plot_results

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary = summary if summary is not None else summarize(results)
    paths = {"md": out / "results.md", "csv": out / "results.csv", "json": out / "results.json"}
    paths["md"].write_text(header + to_markdown(results, summary))
    columns: list[str] = []
    for r in results:
        columns += [k for k in r if k not in columns]
    with paths["csv"].open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=columns)
        writer.writeheader()
        for r in results:
            writer.writerow({k: " | ".join(v) if isinstance(v, list) else v for k, v in r.items()})
    paths["json"].write_text(json.dumps(_json_safe({"results": list(results), "summary": summary}), indent=1))
    if any(not r.get("error") and isinstance(r.get("est_latency_us"), float) and math.isfinite(r["est_latency_us"])
           for r in results):
        paths["png"] = plot_results(results, out / "results.png")
    return paths
