"""A recording's contrast threshold θ as the command line estimates it, against the truth, over the accuracy suite.

Each case of the suite (:mod:`evlatcorr.benchmark.accuracy`) becomes a short recording (``--frames`` frames, 20 ms
exposures 25 ms apart) with a θ drawn for it over 0.1-0.6, written as a file; its θ is estimated as ``evlatcorr
correct`` does (:func:`evlatcorr.restore.recording_threshold`) and compared with the truth
(:mod:`evlatcorr.benchmark.threshold`). Tune on ``dev`` / ``dev_wide``, report ``test``.

    python benchmarks/threshold.py --split test              # 48 recordings, about 5 minutes on 2 cores
    python benchmarks/threshold.py --split dev --num 10      # a quick look

Writes ``results.md``, ``results.csv``, ``results.json`` and ``results.png`` (the estimated against the true θ)
under ``--out``.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

_setup.passive_openmp()

import argparse  # noqa: E402
import csv  # noqa: E402
import json  # noqa: E402
import math  # noqa: E402
import shlex  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr.benchmark.accuracy import make_cases  # noqa: E402
from evlatcorr.benchmark.threshold import CLOSE, MATTERS_DB, evaluate_threshold, summarize_thresholds  # noqa: E402
from evlatcorr.consistency import THRESHOLD_BOUNDS as BOUNDS  # noqa: E402

MODELS = {"constant": "constant latency", "intensity": "photoreceptor low-pass", "intensity_delay": "per-pixel delay"}


def with_interval(value: float, interval: tuple[float, float] | None) -> str:
    """A share and its 95 % interval, e.g. ``6 % (3-12 %)``; the share alone where there is no interval."""
    if interval is None or not all(math.isfinite(v) for v in interval):
        return f"{value:.0%}"
    return f"{value:.0%} ({interval[0] * 100:.0f}-{interval[1]:.0%})"


def to_markdown(rows: list[dict], summaries: dict[str, dict], command: str, seconds: float) -> str:
    lines = [f"`{command}` ({seconds / 60:.1f} min)", "",
             "| cases | estimated | θ error: median (95 % interval) / p90 / worst | within "
             + " / ".join(f"{c:.0%}" for c in CLOSE)
             + " | estimate / true: lowest / median / highest | EDI PSNR lost to it: median / p90 / worst | "
             "share of EDI's gain kept: median (interval) / p10 / worst | constant latency: median error with the "
             "true / estimated θ |", "| --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name, s in summaries.items():
        if not s.get("estimated"):
            lines.append(f"| {name} ({s['cases']}) | 0 | | | | | | |")
            continue
        latency = (f"{s['median_latency_error_true_theta_us']:.0f} / {s['median_latency_error_estimated_theta_us']:.0f}"
                   f" µs ({s['constant_cases']})" if "constant_cases" in s else "")
        lines.append(
            f"| {name} ({s['cases']}) | {s['estimated']} | "
            f"{with_interval(s['median_relative_error'], s.get('median_relative_error_interval'))} / "
            f"{s['p90_relative_error']:.0%} / {s['worst_relative_error']:.0%} | "
            + " / ".join(f"{s[f'within_{c:.0%}']:.0%}" for c in CLOSE)
            + f" | {s['lowest_ratio']:.2f} / {s['median_ratio']:.2f} / {s['highest_ratio']:.2f} | "
            f"{s.get('median_psnr_loss_db', math.nan):.2f} / {s.get('p90_psnr_loss_db', math.nan):.2f} / "
            f"{s.get('worst_psnr_loss_db', math.nan):.2f} dB | "
            + (f"{with_interval(s['median_gain_kept'], s.get('median_gain_kept_interval'))} / "
               f"{s['p10_gain_kept']:.0%} / {s['worst_gain_kept']:.0%}" if "median_gain_kept" in s else "")
            + f" | {latency} |")
    lines += ["", "The intervals: a seeded bootstrap over the recordings (`evlatcorr.benchmark.accuracy_compare."
              "bootstrap_interval`).", "",
              f"θ matters where EDI with the true θ beats the blurry frame by more than {MATTERS_DB} dB (where "
              "events are few, any θ gives about the same image and its error says nothing).", "",
              "| case | latency model | true θ | estimate | ratio | EDI PSNR: blurry / the true θ / estimated θ | "
              "gain kept | constant latency: error with the true / estimated θ | time s |",
              "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for r in rows:
        latency = (f"{r['latency_error_true_theta_us']:.0f} / {r['latency_error_estimated_theta_us']:.0f} µs"
                   if math.isfinite(r["latency_error_true_theta_us"]) else "")
        psnr = (f"{r['psnr_blurry']:.2f} / {r['psnr_true_theta']:.2f} / {r['psnr_estimated_theta']:.2f}"
                if math.isfinite(r["psnr_true_theta"]) else "")
        kept = f"{r['gain_kept']:.0%}" if math.isfinite(r["gain_kept"]) else "θ does not matter"
        lines.append(f"| {r['case']} | {MODELS.get(r['latency_model'], r['latency_model'])} | {r['threshold']:.3f} | "
                     f"{r['estimate']:.3f} | {r['ratio']:.2f} | {psnr} | {kept} | {latency} | {r['seconds']:.1f} |")
    return "\n".join(lines) + "\n"


def plot(rows: list[dict], path: Path) -> None:
    """The estimated against the true θ (log axes), with the diagonal and a ±15 % band."""
    from matplotlib.figure import Figure
    from matplotlib.ticker import FixedLocator, FormatStrFormatter, NullFormatter

    done = [r for r in rows if math.isfinite(r["estimate"])]
    fig = Figure(figsize=(5, 4.5))
    ax = fig.subplots()
    grid = [0.08, 0.8]
    ax.fill_between(grid, [g * (1 - CLOSE[0]) for g in grid], [g * (1 + CLOSE[0]) for g in grid], color="0.9",
                    label=f"±{CLOSE[0]:.0%}")
    ax.plot(grid, grid, color="0.5", lw=0.8)
    ax.axhline(BOUNDS[0], color="C3", lw=0.6, ls=":", label=f"the search's bounds ({BOUNDS[0]:g}, {BOUNDS[1]:g})")
    ax.axhline(BOUNDS[1], color="C3", lw=0.6, ls=":")
    for k, (model, label) in enumerate(MODELS.items()):
        for matters in (True, False):
            mine = [r for r in done if r["latency_model"] == model and r["matters"] == matters]
            ax.scatter([r["threshold"] for r in mine], [r["estimate"] for r in mine], s=14,
                       **({"color": f"C{k}", "label": label} if matters else
                          {"facecolors": "none", "edgecolors": f"C{k}"}))
    ax.scatter([], [], s=14, facecolors="none", edgecolors="0.4", label="θ does not matter (hollow)")
    low = min([grid[0], *(0.9 * r["estimate"] for r in done)])
    high = max([grid[1], *(1.1 * r["estimate"] for r in done)])
    ax.set(xscale="log", yscale="log", xlim=grid, ylim=(low, high), xlabel="true θ",
           ylabel="estimated θ (evlatcorr.restore.recording_threshold)")
    for axis, (lo, hi) in ((ax.xaxis, grid), (ax.yaxis, (low, high))):  # plain numbers, not powers of ten
        axis.set_major_locator(FixedLocator([t for t in (0.05, 0.1, 0.2, 0.3, 0.4, 0.6, 1.0, 1.5) if lo <= t <= hi]))
        axis.set_major_formatter(FormatStrFormatter("%g"))
        axis.set_minor_formatter(NullFormatter())
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "test", ("test", "dev", "dev_wide", "tuning"), num_help="first N cases of each split")
    p.add_argument("--frames", type=int, default=6, help="frames per recording (default: 6)")
    _setup.add_exposure_option(p)
    p.add_argument("--out", type=Path, default=Path("outputs/threshold"))
    args = p.parse_args(argv)
    if args.frames < 2:
        p.error(f"--frames must be at least 2 (θ is estimated from pairs of frames), got {args.frames}")
    _setup.check_case_options(p, args)
    splits = {"tuning": ("dev", "dev_wide")}.get(args.split, (args.split,))
    cases = [c for s in splits for c in make_cases(s, args.num, tuple(args.size))]
    cases = _setup.cases_at_exposure(p, cases, args.exposure_us)
    _setup.check_out_folder(p, args.out)
    t0 = time.perf_counter()
    rows, unsimulated = _setup.each_simulated(cases, lambda case: evaluate_threshold(case, args.frames), "recordings")
    seconds = time.perf_counter() - t0
    matters = [r for r in rows if r["matters"]]
    summaries = {"all": summarize_thresholds(rows), "where θ matters": summarize_thresholds(matters)}
    for model, label in MODELS.items():
        summaries[f"where θ matters: {label}"] = summarize_thresholds([r for r in matters
                                                                       if r["latency_model"] == model])
    command = shlex.join(["python", "benchmarks/threshold.py", *(sys.argv[1:] if argv is None else argv)])
    table = to_markdown(rows, summaries, command, seconds) + unsimulated
    (args.out / "results.md").write_text(table)
    (args.out / "results.json").write_text(json.dumps({"command": command, "summary": summaries, "rows": rows},
                                                      indent=1))
    with open(args.out / "results.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    plot(rows, args.out / "results.png")
    print(table.split("\n\n| case |")[0])
    print(f"wrote {args.out}/results.md, results.csv, results.json, results.png")


if __name__ == "__main__":
    main()
