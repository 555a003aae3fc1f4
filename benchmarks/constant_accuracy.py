"""Accuracy of the constant-latency corrector on simulated test scenes.

For every test photograph and injected latency: the estimated latency's error, and EDI PSNR
against the sharp mid-exposure frame with ideal events, delayed events, and corrected events.

    python benchmarks/constant_accuracy.py                       # 8 test scenes x {1, 4, 8} ms, 260x346
    python benchmarks/constant_accuracy.py --size 130 173 --latencies 4000
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch
from torchmetrics.functional.image import peak_signal_noise_ratio

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evlatcorr import EventLatencyCorrector, edi_deblur  # noqa: E402
from evlatcorr.simulate import PHOTOGRAPHS_TEST, simulate  # noqa: E402


def psnr(image: torch.Tensor, target: torch.Tensor) -> float:
    return float(peak_signal_noise_ratio(image.clamp(0, 1), target, data_range=1.0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--size", type=int, nargs=2, default=(260, 346), metavar=("H", "W"))
    parser.add_argument("--latencies", type=float, nargs="+", default=(1000.0, 4000.0, 8000.0))
    parser.add_argument("--scenes", nargs="+", default=list(PHOTOGRAPHS_TEST))
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    corrector = EventLatencyCorrector()
    print("| scene | true (us) | estimated (us) | error (us) | EDI PSNR GT | w/o corr. | w/ corr. | gap recovered |")
    print("| --- | --- | --- | --- | --- | --- | --- | --- |")
    errors, recovered = [], []
    for i, name in enumerate(args.scenes):
        for latency in args.latencies:
            seq = simulate(name, num_frames=1, height=args.size[0], width=args.size[1], latency="constant",
                           latency_us=latency, seed=args.seed + i)
            delayed, ideal = seq.frames("delayed"), seq.frames("ideal")
            out = corrector(delayed)
            est = float(out.latency.mean())
            sharp = delayed.sharp
            gt = psnr(edi_deblur(ideal.blurry, ideal.events, ideal.exposure_start, ideal.exposure_end), sharp)
            wo = psnr(edi_deblur(delayed.blurry, delayed.events, delayed.exposure_start, delayed.exposure_end), sharp)
            w = psnr(out.latent, sharp)
            frac = (w - wo) / (gt - wo) if gt > wo else float("nan")
            errors.append(abs(est - latency))
            recovered.append(frac)
            print(f"| {name} | {latency:.0f} | {est:.0f} | {est - latency:+.0f} | {gt:.2f} | {wo:.2f} | {w:.2f} | "
                  f"{100 * frac:.0f}% |", flush=True)
    print(f"\nmean |error| {statistics.mean(errors):.0f} us, median {statistics.median(errors):.0f} us, "
          f"max {max(errors):.0f} us; median PSNR gap recovered {100 * statistics.median(recovered):.0f}%")


if __name__ == "__main__":
    main()
