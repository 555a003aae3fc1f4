"""Demo: simulate a scene with a known latency, correct it, and compare EDI with and without correction.

    python benchmarks/demo.py                       # 4 ms latency, 20 ms exposure, DAVIS346-sized frame
    python benchmarks/demo.py --latency-us 8000 --image coffee --size 130 173
"""

from __future__ import annotations

import _setup  # first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse
import time

from evlatcorr import EventLatencyCorrector  # noqa: E402
from evlatcorr.benchmark.compare import edi_psnr, psnr, recovery  # noqa: E402
from evlatcorr.simulate import simulate  # noqa: E402


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--image", default="astronaut", help="scikit-image photograph name")
    parser.add_argument("--latency-us", type=float, default=4000.0)
    parser.add_argument("--exposure-us", type=float, default=20000.0)
    parser.add_argument("--size", type=int, nargs=2, default=(260, 346), metavar=("H", "W"))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    if min(args.size) < _setup.MIN_SCENE_SIZE:
        parser.error(f"--size must be at least {_setup.MIN_SCENE_SIZE} {_setup.MIN_SCENE_SIZE}, got {list(args.size)}")

    t0 = time.perf_counter()
    try:
        seq = simulate(args.image, num_frames=1, height=args.size[0], width=args.size[1],
                       exposure_us=args.exposure_us, latency="constant", latency_us=args.latency_us, seed=args.seed)
    except ValueError as exc:  # a bad --image, --size, --latency-us or --exposure-us: the simulator says which
        parser.error(str(exc))
    delayed, ideal = seq.frames("delayed"), seq.frames("ideal")
    print(f"simulated '{args.image}' {args.size[1]}x{args.size[0]}: exposure {args.exposure_us / 1000:.0f} ms, "
          f"true latency {args.latency_us:.0f} us, {len(delayed.events)} events ({time.perf_counter() - t0:.1f} s)")

    t0 = time.perf_counter()
    out = EventLatencyCorrector()(delayed)
    estimated = float(out.latency[0].mean())
    print(f"estimated latency {estimated:.0f} us (error {estimated - args.latency_us:+.0f} us, "
          f"{time.perf_counter() - t0:.2f} s)")

    sharp = delayed.sharp
    ideal_db, uncorrected_db, corrected_db = edi_psnr(ideal), edi_psnr(delayed), psnr(out.latent, sharp)
    print(f"{'EDI PSNR (dB) vs sharp mid-exposure frame':44s}")
    print(f"  {'blurry input':40s} {psnr(delayed.blurry, sharp):6.2f}")
    print(f"  {'ideal events (GT input)':40s} {ideal_db:6.2f}")
    print(f"  {'delayed events, without correction':40s} {uncorrected_db:6.2f}")
    print(f"  {'delayed events, with correction':40s} {corrected_db:6.2f}")
    print(f"  recovery of the ideal events' gain: {100 * recovery(corrected_db, uncorrected_db, ideal_db):.0f} %")


if __name__ == "__main__":
    main()
