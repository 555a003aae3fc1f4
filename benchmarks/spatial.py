"""Spatially-varying vs constant latency correction on the simulator's intensity-dependent latency.

Trains the latency polynomial self-supervised (no ground truth) on scenes from the training
photographs, then evaluates on the test photographs (never seen in training): mean absolute
error of the latency map (µs) and EDI PSNR/SSIM against the sharp mid-exposure frame, for no
correction, constant correction and spatial correction (the trained curve).

    python benchmarks/spatial.py                        # 96x128, 20 ms exposure, 0.5-10 ms latency
    python benchmarks/spatial.py --latency-model intensity --out outputs/spatial

``--latency-model intensity_delay`` (default) delays each event by the true per-pixel map, so the
map error is exact; ``intensity`` uses the low-pass photoreceptor (whose map is only an
approximation of the effective delay, see ``evlatcorr.simulate``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from torchmetrics.functional.image import peak_signal_noise_ratio, structural_similarity_index_measure

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evlatcorr import EventLatencyCorrector, edi_deblur  # noqa: E402
from evlatcorr.simulate import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN, simulate  # noqa: E402
from evlatcorr.spatial import save_curve  # noqa: E402
from evlatcorr.training import EventFramesDataModule, LatencyCorrectionModule, simulated_training_frames  # noqa: E402


def quality(latent: torch.Tensor, sharp: torch.Tensor) -> tuple[float, float]:
    latent = latent.clamp(0, 1)
    return (float(peak_signal_noise_ratio(latent, sharp, data_range=1.0)),
            float(structural_similarity_index_measure(latent, sharp, data_range=1.0)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"))
    p.add_argument("--latency-model", choices=("intensity_delay", "intensity"), default="intensity_delay")
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--order", type=int, default=5)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--train-bins", type=int, default=100)
    p.add_argument("--eta", type=float, default=20.0, help="weight of L_mse (paper: 20)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("outputs/spatial"))
    args = p.parse_args()
    warnings.filterwarnings("ignore", module="lightning")
    args.out.mkdir(parents=True, exist_ok=True)
    size = tuple(args.size)

    t0 = time.perf_counter()
    L.seed_everything(args.seed, verbose=False)
    frames = simulated_training_frames(PHOTOGRAPHS_TRAIN, size, args.seed, latency=args.latency_model)
    module = LatencyCorrectionModule(order=args.order, lr=args.lr, num_bins=args.train_bins,
                                     constant_epochs=min(2, args.epochs), decay_epochs=max(0, args.epochs - 2),
                                     eta=args.eta)
    trainer = L.Trainer(max_epochs=args.epochs, accelerator="cpu", devices=1, logger=False,
                        enable_checkpointing=False, enable_model_summary=False, enable_progress_bar=True)
    trainer.fit(module, EventFramesDataModule(frames))
    save_curve(module.latency_model, args.out / "curve.pt")
    coefficients = [round(c, 3) for c in module.latency_model.coefficients.tolist()]
    print(f"trained on {len(frames)} frames of {len(PHOTOGRAPHS_TRAIN)} training photographs "
          f"in {time.perf_counter() - t0:.0f} s; coefficients {coefficients}")

    constant = EventLatencyCorrector()
    spatial = EventLatencyCorrector(mode="spatial", curve=str(args.out / "curve.pt"))
    lines = ["| scene | true latency (us) mean [min, max] | MAE none | MAE const | MAE spatial | PSNR none | "
             "PSNR const | PSNR spatial | SSIM none | SSIM const | SSIM spatial |", "|" + " --- |" * 11]
    wins = []
    for i, name in enumerate(PHOTOGRAPHS_TEST):
        seq = simulate(name, num_frames=1, height=size[0], width=size[1], latency=args.latency_model,
                       seed=1000 + args.seed + i)
        batch, truth = seq.frames("delayed"), seq.true_latency
        none = edi_deblur(batch.blurry, batch.events, batch.exposure_start, batch.exposure_end)
        c, s = constant(batch), spatial(batch)
        mae = [float(truth.abs().mean()), float((c.latency - truth).abs().mean()),
               float((s.latency - truth).abs().mean())]
        q = [quality(x, batch.sharp) for x in (none, c.latent, s.latent)]
        wins.append(mae[2] < mae[1] and q[2][0] > q[1][0] and q[2][1] > q[1][1])
        lines.append(f"| {name} | {float(truth.mean()):.0f} [{float(truth.min()):.0f}, {float(truth.max()):.0f}] | "
                     + " | ".join(f"{v:.0f}" for v in mae) + " | "
                     + " | ".join(f"{x[0]:.2f}" for x in q) + " | " + " | ".join(f"{x[1]:.3f}" for x in q) + " |")
        print(lines[-1], flush=True)
    summary = (f"\nspatial beats constant in latency MAE, PSNR and SSIM on {sum(wins)}/{len(wins)} test scenes "
               f"({args.latency_model}, {size[1]}x{size[0]}, 20 ms exposure, latency 0.5-10 ms); "
               f"median MAE const {statistics.median(float(x.split('|')[4]) for x in lines[2:]):.0f} us")
    table = "\n".join(lines) + summary
    (args.out / "results.md").write_text(table + "\n")
    print(table.splitlines()[0])
    print(summary)
    print(f"wrote {args.out / 'results.md'} ({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
