"""The benchmark table as markdown: PSNR/SSIM/LPIPS per method and input, and the paper's "Diff (%)" rows."""

from __future__ import annotations

import math
from typing import Any

from evlatcorr.benchmark.loop import CONST, GT, NO_CORR, SPATIAL

__all__ = ["diff_percent", "format_table"]


def diff_percent(gt: float, without: float, corrected: float) -> float:
    """The paper's "Diff (%)": ``(corrected - uncorrected) / GT input * 100``."""
    if gt == 0 or any(math.isnan(v) for v in (gt, without, corrected)):
        return math.nan
    return (corrected - without) / gt * 100.0


def format_table(results: dict[str, Any]) -> str:
    """The table as markdown, with a Diff (%) row per corrected input."""
    rows = results["table"]
    lines = ["| method | input | PSNR ↑ | SSIM ↑ | LPIPS ↓ |", "| --- | --- | --- | --- | --- |"]
    methods = list(dict.fromkeys(r["method"] for r in rows))
    fmt = lambda v, d: "n/a" if math.isnan(v) else f"{v:.{d}f}"  # noqa: E731
    for m in methods:
        by_input = {r["input"]: r for r in rows if r["method"] == m}
        for name, r in by_input.items():
            lines.append(f"| {m} | {name} | {fmt(r['psnr'], 3)} | {fmt(r['ssim'], 3)} | {fmt(r['lpips'], 3)} |")
        for name in (CONST, SPATIAL):
            if name in by_input:
                d = [diff_percent(by_input[GT][k], by_input[NO_CORR][k], by_input[name][k])
                     for k in ("psnr", "ssim", "lpips")]
                label = "Diff (%) const." if name == CONST else "Diff (%) spatial"
                lines.append(f"| {m} | {label} | " + " | ".join(
                    "n/a" if math.isnan(v) else f"{v:+.2f}" for v in d) + " |")
    return "\n".join(lines)
