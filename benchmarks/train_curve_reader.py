"""Train the learned curve reader (``score="learned"``, :mod:`evlatcorr.curve_reader`) and write its weights.

Simulates the accuracy suite's training cases (:data:`evlatcorr.benchmark.accuracy.TRAIN_SPLITS`: 1800
constant-latency and 200 photoreceptor-lag frames of the dev split's photographs and procedural scenes, seeds
disjoint from dev and test), reads each frame's candidate curves as the search does
(:func:`evlatcorr.search.candidate_curves`), and fits an ensemble of 5 readers to each frame's target
(:func:`evlatcorr.benchmark.accuracy.training_target`: the true latency, or under the photoreceptor model the
best constant shift). About 15 minutes on 2 CPU cores: 14 minutes simulating and reading the frames (most of it
the photoreceptor frames' best-shift scans), then about a minute of training.

    python benchmarks/train_curve_reader.py                                  # writes checkpoints/curve-reader.*
    python benchmarks/train_curve_reader.py --cache curves.pt --out /tmp/reader.safetensors
    python benchmarks/train_curve_reader.py --cache curves.pt --without-overshoot --out /tmp/reader5.safetensors
    python benchmarks/train_curve_reader.py --cache curves.pt --ideal-frames 300 --out /tmp/ideal300.safetensors

``--ideal-frames N`` also trains on the ideal events (no latency, target 0) of N of the constant-latency training
cases, evenly spread over them: measured and not shipped (``docs/estimator.md``: the reader then answers 0 wherever
it is unsure, delayed frames included).

Then ``python benchmarks/accuracy.py --split dev --score learned`` measures it.
"""

import _setup  # noqa: F401  (the repository on sys.path, 2 MB pages)

# isort: split
import argparse
import time
from pathlib import Path

import torch
from tqdm import tqdm

from evlatcorr.benchmark.accuracy import TRAIN_SPLITS, make_cases, simulate_case, training_target
from evlatcorr.curve_reader import WEIGHTS_NAME, save_curve_reader, train_curve_reader, without_overshoot
from evlatcorr.search import candidate_curves

ROOT = Path(__file__).resolve().parents[1]


def extract(cache: Path | None) -> dict:
    """Every training case's candidate curves and true latency (read from ``cache`` when it exists)."""
    if cache is not None and cache.exists():
        return torch.load(cache)
    cases = [c for split in TRAIN_SPLITS for c in make_cases(split)]
    curves, valid, targets = [], [], []
    latencies = None
    for case in tqdm(cases, desc="training cases", unit="case"):
        delayed, _, _ = simulate_case(case)
        latencies, x, v = candidate_curves(delayed.blurry, delayed.events, float(delayed.exposure_start[0]),
                                           float(delayed.exposure_end[0]), case.threshold)
        curves.append(x)
        valid.append(v)
        targets.append(training_target(case, delayed))
    data = {"latencies": latencies, "curves": torch.stack(curves), "valid": torch.stack(valid),
            "targets": torch.tensor(targets, dtype=torch.float64), "names": [c.name for c in cases]}
    if cache is not None:
        torch.save(data, cache)
    return data


def extract_ideal(num: int, cache: Path | None) -> dict:
    """The candidate curves of the ideal events of ``num`` constant-latency training cases, evenly spread over
    them, with a target of 0 (read from ``cache`` when it exists)."""
    if cache is not None and cache.exists():
        return torch.load(cache)
    constant = [c for split in TRAIN_SPLITS for c in make_cases(split) if c.latency_model == "constant"]
    if not 0 < num <= len(constant):
        raise SystemExit(f"--ideal-frames must be in 1..{len(constant)}, got {num}")
    picked = [constant[k * len(constant) // num] for k in range(num)]
    curves, valid = [], []
    latencies = None
    for case in tqdm(picked, desc="ideal events", unit="case"):
        _, ideal, _ = simulate_case(case)
        latencies, x, v = candidate_curves(ideal.blurry, ideal.events, float(ideal.exposure_start[0]),
                                           float(ideal.exposure_end[0]), case.threshold)
        curves.append(x)
        valid.append(v)
    data = {"latencies": latencies, "curves": torch.stack(curves), "valid": torch.stack(valid),
            "targets": torch.zeros(num, dtype=torch.float64), "names": [f"{c.name}-ideal" for c in picked]}
    if cache is not None:
        torch.save(data, cache)
    return data


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "checkpoints" / f"{WEIGHTS_NAME}.safetensors")
    parser.add_argument("--cache", type=Path, default=None, help="save (or reuse) the extracted curves here")
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--ideal-frames", type=int, default=0,
                        help="also train on the ideal events (target 0) of this many constant-latency training cases")
    parser.add_argument("--without-overshoot", action="store_true",
                        help="train on the other inputs only (what the overshoot adds; measure with "
                             "benchmarks/estimators/reader.py)")
    args = parser.parse_args()
    t0 = time.perf_counter()
    data = extract(args.cache)
    if args.ideal_frames:
        name = f"{args.cache.stem}-ideal{args.ideal_frames}.pt" if args.cache is not None else None
        ideal_cache = args.cache.with_name(name) if name is not None else None
        ideal = extract_ideal(args.ideal_frames, ideal_cache)
        data = {key: torch.cat([data[key], ideal[key]]) for key in ("curves", "valid", "targets")} | {
            "latencies": data["latencies"]}
    print(f"{len(data['targets'])} training frames in {time.perf_counter() - t0:.0f} s", flush=True)
    curves = without_overshoot(data["curves"]) if args.without_overshoot else data["curves"]
    ensemble = train_curve_reader(curves, data["valid"], data["latencies"], data["targets"],
                                  members=args.members, epochs=args.epochs, seed=args.seed)
    provenance = {"cases": list(TRAIN_SPLITS), "frames": len(data["targets"]),
                  "targets": "true latency (constant cases), best constant shift (photoreceptor cases)",
                  "members": args.members,
                  "epochs": args.epochs, "seed": args.seed, "without_overshoot": args.without_overshoot,
                  "command": "python benchmarks/train_curve_reader.py"}
    if args.ideal_frames:
        provenance["ideal_frames"] = args.ideal_frames
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_curve_reader(ensemble, args.out, provenance)
    print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
