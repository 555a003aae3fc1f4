"""Where dim pixels lag: a latency per brightness band from two frames' agreement, against one for the pair.

Each per-pixel delay case of the accuracy suite (dim pixels later) is simulated as two frames with a camera's gap
between them (1.25 exposures). The two frames' disagreement between their exposures is read pixel by pixel
(:func:`evlatcorr.pair_evidence.pair_disagreement_maps`, the shipped ramps) over candidates every 250 µs up to the
events' reach. One latency for the pair: the lowest mean disagreement over all pixels. A latency per band: the first
frame's pixels split into ``--bands`` bands of equal size by their blurry brightness, and each band's latency the
best of ``w · L_band + L_pair``, where ``L = −log(d / min d)`` of the band's and of the whole pair's mean
disagreement (``w`` from ``--weights``; ``inf``: the band's own minimum alone). The map (each pixel its band's
latency) is scored against the true map (mean absolute error) and by the first frame's EDI PSNR against ideal
events (recovery), beside the one latency.

    python benchmarks/pair_bands.py --split tuning              # dev + dev_wide: 40 per-pixel delay cases, ~6 min
    python benchmarks/pair_bands.py --split dev --bands 8 --weights 0.3 inf

Writes ``results.md`` and ``results.csv`` under ``--out``.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse  # noqa: E402
import math  # noqa: E402
import statistics  # noqa: E402
from pathlib import Path  # noqa: E402

import torch  # noqa: E402

from evlatcorr.benchmark.accuracy_cases import simulate_case  # noqa: E402
from evlatcorr.benchmark.compare import edi_psnr, recovery  # noqa: E402
from evlatcorr.pair_evidence import pair_disagreement_maps  # noqa: E402

CANDIDATE_STEP_US = 250.0
FRAME_GAP = 1.25  # the frame interval in exposure times, as benchmarks/pair_consistency.py's


def band_rows(case, bands: int, weights: list[float]) -> dict:
    """One per-pixel delay case: the pair's one latency and each weight's band map, their map errors and EDI
    recoveries (NaN without a PSNR gap)."""
    delayed, ideal, seq = simulate_case(case, 2, frame_interval_us=FRAME_GAP * case.exposure_us)
    pair = seq.pairs("delayed", after_us=case.after_us).split()[0]
    first, first_ideal = delayed.split()[0], ideal.split()[0]
    truth = first.meta["true_latency"][0, 0].double()
    reach = float(pair.events.t.max() - pair.exposure_end_next[0])  # a window never runs past the last event
    candidates = torch.arange(0.0, max(reach, 0.0) + 1.0, CANDIDATE_STEP_US, dtype=torch.float64)
    maps = pair_disagreement_maps(pair, case.threshold, candidates).double()
    whole = maps.mean((1, 2))
    brightness = pair.blurry[0].mean(0).double()
    edges = torch.quantile(brightness.flatten(), torch.linspace(0, 1, bands + 1, dtype=torch.float64)[1:-1])
    band_of = torch.bucketize(brightness, edges)
    theta = case.threshold
    ideal_db, stamped_db = edi_psnr(first_ideal, theta), edi_psnr(first, theta)
    one = float(candidates[whole.argmin()])
    one_db = edi_psnr(first, theta, latency=torch.tensor([one]))
    row = {"case": case.name, "pair_latency_us": one, "pair_map_error_us": float((truth - one).abs().mean()),
           "pair_recovery": recovery(one_db, stamped_db, ideal_db)}
    pair_log_odds = -torch.log(whole / whole.min())
    for weight in weights:
        latency = torch.full_like(brightness, one)
        for k in range(bands):
            inside = band_of == k
            if not bool(inside.any()):
                continue
            band = maps[:, inside].mean(1)
            own = -torch.log(band / band.min())
            score = own if math.isinf(weight) else weight * own + pair_log_odds
            latency[inside] = float(candidates[score.argmax()])
        band_db = edi_psnr(first, theta, latency=latency[None, None].float())
        row[f"w{weight:g}_map_error_us"] = float((truth - latency).abs().mean())
        row[f"w{weight:g}_recovery"] = recovery(band_db, stamped_db, ideal_db)
        row[f"w{weight:g}_psnr_change_db"] = band_db - one_db
    return row


def to_markdown(rows: list[dict], weights: list[float], bands: int) -> str:
    gap = [r for r in rows if not math.isnan(r["pair_recovery"])]

    def tenth(values: list[float]) -> float:
        return sorted(values)[len(values) // 10] if values else math.nan

    lines = [f"{len(rows)} per-pixel delay cases ({len(gap)} with a PSNR gap), {bands} brightness bands", "",
             "| latency | map error: median | bands' map error below the pair's | recovery: median / p10 | EDI PSNR "
             "against the pair's one latency: mean / worst / best | cases losing > 0.5 dB |",
             "| --- | --- | --- | --- | --- | --- |"]
    one = [r["pair_recovery"] for r in gap]
    lines.append(f"| the pair's one latency | {statistics.median(r['pair_map_error_us'] for r in rows):.0f} µs | | "
                 f"{statistics.median(one):.0%} / {tenth(one):.0%} | | |" if gap else "| the pair's one latency | |")
    for weight in weights:
        key = f"w{weight:g}"
        changes = [r[f"{key}_psnr_change_db"] for r in rows]
        better = sum(r[f"{key}_map_error_us"] < r["pair_map_error_us"] for r in rows)
        rec = [r[f"{key}_recovery"] for r in gap]
        lines.append(f"| a latency per band, weight {weight:g} | "
                     f"{statistics.median(r[f'{key}_map_error_us'] for r in rows):.0f} µs | {better} of {len(rows)} | "
                     + (f"{statistics.median(rec):.0%} / {tenth(rec):.0%}" if rec else "") + " | "
                     f"{statistics.mean(changes):+.2f} / {min(changes):+.2f} / {max(changes):+.2f} dB | "
                     f"{sum(c < -0.5 for c in changes)} |")
    return "\n".join(lines) + "\n"


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    _setup.add_case_options(p, "tuning", ("tuning", "dev", "dev_wide", "test"),
                            num_help="first N cases of each split (before keeping the per-pixel delay ones)")
    p.add_argument("--bands", type=int, default=4, help="brightness bands of equal size (default: 4)")
    p.add_argument("--weights", type=float, nargs="+", default=[0.3, 1.0, math.inf], metavar="W",
                   help="each band's own evidence against the pair's (inf: the band alone; default: 0.3 1 inf)")
    p.add_argument("--out", type=Path, default=Path("outputs/pair_bands"))
    args = p.parse_args(argv)
    _setup.check_case_options(p, args)
    if args.bands < 1:
        p.error(f"--bands must be at least 1, got {args.bands}")
    if not all(w > 0 for w in args.weights):
        p.error(f"--weights must be positive (inf: the band alone), got {args.weights}")
    rows, note = _setup.evaluate_split(p, args, lambda case: case.latency_model == "intensity_delay",
                                       lambda case: band_rows(case, args.bands, args.weights), "per-pixel delay case")
    _setup.write_results(args.out, "A latency per brightness band from two frames' agreement",
                         to_markdown(rows, args.weights, args.bands) + note, rows)


if __name__ == "__main__":
    main()
