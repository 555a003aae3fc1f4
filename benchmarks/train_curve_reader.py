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
    python benchmarks/train_curve_reader.py --cache curves.pt --layers 5 --channels 24 --out /tmp/wide.safetensors

``--ideal-frames N`` also trains on the ideal events (no latency, target 0) of N of the constant-latency training
cases, evenly spread over them; ``--before-us B`` keeps B µs of events before each exposure and reads the curves from
−B (read them with ``benchmarks/estimators/reader.py:estimate_before``). Both measured and not shipped
(``docs/estimator.md``). ``--layers`` and ``--channels`` set each reader's depth (its receptive field) and width:
readers that see the whole curve were measured and not shipped either. ``--leave-out`` trains without the frames of
some photographs, to see how the reader does on photographs it never saw (``docs/estimator.md``):

    python benchmarks/train_curve_reader.py --cache c.pt --leave-out coins grass page retina cell --out A.safetensors

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
from evlatcorr.simulate import PHOTOGRAPHS_TRAIN

ROOT = Path(__file__).resolve().parents[1]


def _cached(cache: Path | None, before_us: float, read) -> dict:
    """The curves saved at ``cache`` (refused if they were read with other candidates), else ``read()``'s, saved
    there."""
    if cache is not None and cache.exists():
        data = torch.load(cache)
        if data.get("before_us", 0.0) != before_us:
            raise SystemExit(f"{cache} holds curves read from {data.get('before_us', 0.0)} us before the exposure, "
                             f"not {before_us}: pass another --cache")
        return data
    data = read()
    if cache is not None:
        torch.save(data, cache)
    return data


def _read_curves(cases: list, which: str, before_us: float, target) -> dict:
    """The candidate curves of each case's ``which`` (``"delayed"`` or ``"ideal"``) frame and its ``target(case,
    frame)``."""
    curves, valid, targets = [], [], []
    latencies = None
    for case in tqdm(cases, desc=f"{which} frames", unit="case"):
        delayed, ideal, _ = simulate_case(case, before_us=before_us)
        frame = delayed if which == "delayed" else ideal
        latencies, x, v = candidate_curves(frame.blurry, frame.events, float(frame.exposure_start[0]),
                                           float(frame.exposure_end[0]), case.threshold, before_us)
        curves.append(x)
        valid.append(v)
        targets.append(target(case, frame))
    data = {"latencies": latencies, "curves": torch.stack(curves), "valid": torch.stack(valid),
            "targets": torch.tensor(targets, dtype=torch.float64),
            "names": [c.name if which == "delayed" else f"{c.name}-ideal" for c in cases]}
    if before_us:
        data["before_us"] = before_us
    return data


def extract(cache: Path | None, before_us: float = 0.0) -> dict:
    """Every training case's candidate curves and true latency (read from ``cache`` when it exists); with
    ``before_us``, the frames keep that long of events before the exposure and the candidates reach below 0."""
    cases = [c for split in TRAIN_SPLITS for c in make_cases(split)]
    return _cached(cache, before_us, lambda: _read_curves(cases, "delayed", before_us, training_target))


def extract_ideal(num: int, cache: Path | None, before_us: float = 0.0) -> dict:
    """The candidate curves of the ideal events of ``num`` constant-latency training cases, evenly spread over
    them, with a target of 0 (read from ``cache`` when it exists)."""
    constant = [c for split in TRAIN_SPLITS for c in make_cases(split) if c.latency_model == "constant"]
    if not 0 < num <= len(constant):
        raise SystemExit(f"--ideal-frames must be in 1..{len(constant)}, got {num}")
    picked = [constant[k * len(constant) // num] for k in range(num)]
    return _cached(cache, before_us, lambda: _read_curves(picked, "ideal", before_us, lambda case, frame: 0.0))


def leave_out(data: dict, photographs: list[str]) -> dict:
    """``data`` (:func:`extract`'s, one row per training case in order) without the frames of ``photographs``."""
    unknown = sorted(set(photographs) - set(PHOTOGRAPHS_TRAIN))
    if unknown:
        raise SystemExit(f"--leave-out takes training photographs {PHOTOGRAPHS_TRAIN}, got {unknown}")
    cases = [c for split in TRAIN_SPLITS for c in make_cases(split)]
    if [c.name for c in cases] != list(data["names"]):
        raise SystemExit("the cached curves are not the training cases': pass another --cache")
    keep = torch.tensor([c.procedural or c.scene not in photographs for c in cases])
    return {key: data[key][keep] for key in ("curves", "valid", "targets")} | {
        "latencies": data["latencies"], "names": [n for n, k in zip(data["names"], keep.tolist()) if k]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--out", type=Path, default=ROOT / "checkpoints" / f"{WEIGHTS_NAME}.safetensors")
    parser.add_argument("--cache", type=Path, default=None, help="save (or reuse) the extracted curves here")
    parser.add_argument("--members", type=int, default=5)
    parser.add_argument("--epochs", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--channels", type=int, default=16, help="each reader's channels")
    parser.add_argument("--layers", type=int, default=3,
                        help="each reader's dilated convolutions (receptive field 1 + 4 (2^layers - 1) candidates)")
    parser.add_argument("--ideal-frames", type=int, default=0,
                        help="also train on the ideal events (target 0) of this many constant-latency training cases")
    parser.add_argument("--before-us", type=float, default=0.0,
                        help="frames keep this long of events before the exposure, and the curves reach down to "
                             "minus it (measured, not shipped: benchmarks/estimators/reader.py:estimate_before)")
    parser.add_argument("--without-overshoot", action="store_true",
                        help="train on the other inputs only (what the overshoot adds; measure with "
                             "benchmarks/estimators/reader.py)")
    parser.add_argument("--leave-out", nargs="+", default=[], metavar="PHOTOGRAPH",
                        help="train without these training photographs' frames (how the reader does on photographs "
                             "it never saw)")
    args = parser.parse_args()
    if min(args.members, args.epochs, args.channels, args.layers) < 1 or args.ideal_frames < 0:
        parser.error("--members, --epochs, --channels and --layers must be >= 1 and --ideal-frames >= 0")
    t0 = time.perf_counter()
    data = extract(args.cache, args.before_us)
    if args.leave_out:
        data = leave_out(data, args.leave_out)
    if args.ideal_frames:
        name = f"{args.cache.stem}-ideal{args.ideal_frames}.pt" if args.cache is not None else None
        ideal_cache = args.cache.with_name(name) if name is not None else None
        ideal = extract_ideal(args.ideal_frames, ideal_cache, args.before_us)
        data = {key: torch.cat([data[key], ideal[key]]) for key in ("curves", "valid", "targets")} | {
            "latencies": data["latencies"]}
    print(f"{len(data['targets'])} training frames in {time.perf_counter() - t0:.0f} s", flush=True)
    curves = without_overshoot(data["curves"]) if args.without_overshoot else data["curves"]
    ensemble = train_curve_reader(curves, data["valid"], data["latencies"], data["targets"],
                                  members=args.members, epochs=args.epochs, seed=args.seed, channels=args.channels,
                                  layers=args.layers)
    provenance = {"cases": list(TRAIN_SPLITS), "frames": len(data["targets"]),
                  "targets": "true latency (constant cases), best constant shift (photoreceptor cases)",
                  "members": args.members,
                  "epochs": args.epochs, "seed": args.seed, "channels": args.channels, "layers": args.layers,
                  "without_overshoot": args.without_overshoot,
                  "command": "python benchmarks/train_curve_reader.py"}
    if args.ideal_frames:
        provenance["ideal_frames"] = args.ideal_frames
    if args.before_us:
        provenance["before_us"] = args.before_us
    if args.leave_out:
        provenance["left_out"] = args.leave_out
    args.out.parent.mkdir(parents=True, exist_ok=True)
    save_curve_reader(ensemble, args.out, provenance)
    print(f"wrote {args.out} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
