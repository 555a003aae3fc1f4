"""Train the tile reader (:mod:`evlatcorr.tile_reader`) and write its weights.

Simulates the curve reader's training cases (:data:`evlatcorr.benchmark.accuracy.TRAIN_SPLITS`, 2000 frames) and
the 300 per-pixel delay cases of :data:`~evlatcorr.benchmark.accuracy.DELAY_TRAIN_SPLIT`, reads each frame's curves
over the whole frame and its 3x3 tiles (:func:`evlatcorr.tile_curves.candidate_tile_curves`), has the shipped curve
reader read the tiles (:func:`evlatcorr.tile_reader.tile_inputs`), and fits an ensemble of 5 readers to each frame's
target (:func:`evlatcorr.benchmark.accuracy.training_target`: the true latency, or the best constant shift under
the photoreceptor and per-pixel delay models), the delay frames counted three times. The best-shift scans of the
500 photoreceptor and delay frames are most of the time (about 10 minutes per 300 frames on 2 CPU cores); with
``--targets-from`` taking the targets of caches written before (``benchmarks/train_curve_reader.py --cache``, or this
script's ``--cache``), reading the frames took 6 minutes with ``--workers 2``, and training 2 minutes.

    python benchmarks/train_tile_reader.py                        # writes checkpoints/tile-reader.*
    python benchmarks/train_tile_reader.py --cache tiles.pt --workers 2 --out /tmp/tiles.safetensors
    python benchmarks/train_tile_reader.py --targets-from curves.pt --cache tiles.pt

Then ``python benchmarks/accuracy.py --split tuning`` measures it (the default search reads it).
"""

import _setup  # noqa: F401  (the repository on sys.path, 2 MB pages)

# isort: split
import argparse
import multiprocessing
import time
from pathlib import Path

import torch
from tqdm import tqdm

from evlatcorr.benchmark.accuracy import DELAY_TRAIN_SPLIT, TRAIN_SPLITS, make_cases, simulate_case, training_target
from evlatcorr.curve_reader import save_curve_reader, train_curve_reader
from evlatcorr.tile_curves import candidate_tile_curves
from evlatcorr.tile_reader import TILE_WEIGHTS_NAME, read_tiles, tile_inputs

ROOT = Path(__file__).resolve().parents[1]
DELAY_WEIGHT = 3  # each per-pixel delay frame counted this many times (docs/estimator.md)


def _read_case(job: tuple) -> tuple | None:
    """One case's tile curves and target (None where its frame holds fewer than three candidates with events)."""
    case, known = job
    torch.set_num_threads(1)
    delayed, _, _ = simulate_case(case)
    latencies, (whole, tiles, share, valid) = candidate_tile_curves(
        delayed.blurry, delayed.events, float(delayed.exposure_start[0]), float(delayed.exposure_end[0]),
        case.threshold)
    if int(valid.sum()) < 3:
        return None
    target = known if known is not None else training_target(case, delayed, delay_best_shift=True)
    return case.name, latencies, whole, tiles, share, valid, target


def extract(cache: Path | None, known: dict[str, float], workers: int) -> dict:
    """Every training case's tile curves and target (read from ``cache`` when it exists, saved there otherwise)."""
    if cache is not None and cache.exists():
        return torch.load(cache)
    cases = [c for split in (*TRAIN_SPLITS, DELAY_TRAIN_SPLIT) for c in make_cases(split)]
    jobs = [(case, known.get(case.name)) for case in cases]
    if workers > 1:
        with multiprocessing.get_context("spawn").Pool(workers) as pool:
            rows = list(tqdm(pool.imap(_read_case, jobs, chunksize=4), total=len(jobs), desc="frames", unit="case"))
    else:
        rows = [_read_case(job) for job in tqdm(jobs, desc="frames", unit="case")]
    rows = [row for row in rows if row is not None]
    names, latencies, whole, tiles, share, valid, targets = zip(*rows)
    data = {"names": list(names), "latencies": latencies[0], "whole": torch.stack(whole),
            "tiles": torch.stack(tiles), "share": torch.stack(share), "valid": torch.stack(valid),
            "targets": torch.tensor(targets, dtype=torch.float64)}
    if cache is not None:
        torch.save(data, cache)
    return data


def known_targets(paths: list[Path]) -> dict[str, float]:
    """The targets by case name in caches written before (``names`` and ``targets`` entries)."""
    known: dict[str, float] = {}
    for path in paths:
        data = torch.load(path)
        known.update(zip(data["names"], data["targets"].tolist()))
    return known


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "checkpoints" / f"{TILE_WEIGHTS_NAME}.safetensors")
    parser.add_argument("--cache", type=Path, default=None, help="save (or reuse) the extracted curves here")
    parser.add_argument("--targets-from", type=Path, nargs="+", default=[], metavar="CACHE",
                        help="take the targets of the cases these caches hold instead of scanning for them")
    parser.add_argument("--workers", type=int, default=1, help="processes simulating and reading the frames")
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if min(args.workers, args.members, args.epochs) < 1:
        parser.error(f"--workers, --members and --epochs must be >= 1, got {args.workers}, {args.members} and "
                     f"{args.epochs}")
    t0 = time.perf_counter()
    data = extract(args.cache, known_targets(args.targets_from), args.workers)
    print(f"{len(data['targets'])} training frames in {time.perf_counter() - t0:.0f} s", flush=True)
    inputs = tile_inputs(data["whole"], read_tiles(data["tiles"], data["valid"]), data["share"], data["valid"])
    delay = torch.tensor([name.startswith(f"{DELAY_TRAIN_SPLIT}-") for name in data["names"]])
    order = torch.cat([torch.arange(len(delay))] + [torch.nonzero(delay).flatten()] * (DELAY_WEIGHT - 1))
    ensemble = train_curve_reader(inputs[order], data["valid"][order], data["latencies"], data["targets"][order],
                                  members=args.members, epochs=args.epochs, seed=args.seed)
    provenance = {"cases": [*TRAIN_SPLITS, DELAY_TRAIN_SPLIT], "frames": len(data["targets"]),
                  "delay_frames_weight": DELAY_WEIGHT,
                  "targets": "true latency (constant cases), best constant shift (photoreceptor and per-pixel delay "
                             "cases)",
                  "inputs": "the whole frame's curves, the curve reader's tile reads (share-weighted sum, maximum)",
                  "members": args.members, "epochs": args.epochs, "seed": args.seed,
                  "command": "python benchmarks/train_tile_reader.py"}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_curve_reader(ensemble, args.out, provenance)
    print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
