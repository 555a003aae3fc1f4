"""Spatially-varying vs constant latency correction on the simulator's intensity-dependent latency.

For each latency model, trains the latency polynomial self-supervised (no ground truth) on the
training photographs, then evaluates on the test photographs (never seen in training): the mean
absolute error of the latency map (µs) and EDI PSNR/SSIM against the sharp mid-exposure frame, for
no correction, constant correction and spatial correction (the trained curve), plus EDI from the
ideal events as the upper bound. Latency: dim pixels up to 10 ms late, bright ones 0.5 ms
(``τ = clip(500 µs / I, 500, 10000)``), 20 ms exposures.

Latency models (``--latency-model``, default both):

- ``intensity_delay``: each event delayed by the true per-pixel map: the map error is exact;
- ``intensity``: a low-pass photoreceptor whose time constant is that map (as v2e / IEBCS); the
  reported true map is the lag of the filter following a ramp, an approximation of the effective delay.

    python benchmarks/spatial.py                                 # 96x128, both models, ~5 min on 2 cores
    python benchmarks/spatial.py --latency-model intensity --test-time-fit --out outputs/spatial

Writes ``results.md`` (tables and settings), ``curve_<model>.pt`` and ``curves.png`` (learned ψ
against the true ``τ(I)``) under ``--out``.
"""

from __future__ import annotations

import _setup  # first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse
import math
import time
import warnings
from pathlib import Path

import lightning as L  # noqa: E402
import torch  # noqa: E402

from evlatcorr import EventLatencyCorrector  # noqa: E402
from evlatcorr.benchmark.compare import edi_latent, image_quality  # noqa: E402
from evlatcorr.lightning import EventFramesDataModule, LatencyCorrectionModule, simulated_training_frames  # noqa: E402
from evlatcorr.simulate import PHOTOGRAPHS_TEST, PHOTOGRAPHS_TRAIN, simulate  # noqa: E402
from evlatcorr.spatial import PolynomialLatency, save_curve  # noqa: E402

LATENCY_RANGE_US = (500.0, 10_000.0)
VARYING_RATIO = 3.0  # a scene "varies strongly in brightness" when its true latency spans more than this ratio


def train_curve(model_name: str, args: argparse.Namespace, size: tuple[int, int]) -> tuple[PolynomialLatency, str]:
    t0 = time.perf_counter()
    L.seed_everything(args.seed, verbose=False)
    frames = simulated_training_frames(PHOTOGRAPHS_TRAIN, size, args.seed, latency=model_name)
    module = LatencyCorrectionModule(order=args.order, lr=args.lr, num_bins=args.train_bins,
                                     constant_epochs=min(2, args.epochs), decay_epochs=max(0, args.epochs - 2),
                                     eta=args.eta)
    trainer = L.Trainer(max_epochs=args.epochs, accelerator="cpu", devices=1, logger=False,
                        enable_checkpointing=False, enable_model_summary=False, enable_progress_bar=False)
    trainer.fit(module, EventFramesDataModule(frames))
    save_curve(module.latency_model, args.out / f"curve_{model_name}.pt", latency_model=model_name)
    coefficients = [round(c, 3) for c in module.latency_model.coefficients.tolist()]
    note = (f"trained on {len(frames)} frames of the {len(PHOTOGRAPHS_TRAIN)} training photographs in "
            f"{time.perf_counter() - t0:.0f} s ({args.epochs} epochs, lr {args.lr}, {args.train_bins} bins); "
            f"coefficients (ms) {coefficients}")
    print(note, flush=True)
    return module.latency_model, note


def evaluate(model_name: str, args: argparse.Namespace, size: tuple[int, int]) -> tuple[list[str], PolynomialLatency]:
    psi, note = train_curve(model_name, args, size)
    methods = {"const": EventLatencyCorrector(),
               "spatial": EventLatencyCorrector(mode="spatial", curve=str(args.out / f"curve_{model_name}.pt"))}
    if args.test_time_fit:
        methods["fit"] = EventLatencyCorrector(mode="spatial", steps=args.fit_steps, progress=False)
    names = ["none", *methods]
    header = ("| scene | true latency µs: mean [min, max] | " + " | ".join(f"MAE {m}" for m in names) + " | "
              + " | ".join(f"PSNR {m}" for m in names) + " | PSNR ideal | " + " | ".join(f"SSIM {m}" for m in names)
              + " | SSIM ideal |")
    keys = [k.strip() for k in header.split("|")[3:-1]]
    lines = [header, "|" + " --- |" * (header.count("|") - 1)]
    totals: dict[str, list[float]] = {}
    wins, varying = [], []
    t0 = time.perf_counter()
    for i, scene in enumerate(PHOTOGRAPHS_TEST):
        seq = simulate(scene, num_frames=1, height=size[0], width=size[1], latency=model_name,
                       latency_range_us=LATENCY_RANGE_US, seed=1000 + args.seed + i)
        batch, truth = seq.frames("delayed"), seq.true_latency
        ideal = seq.frames("ideal")
        none = edi_latent(batch)
        outputs = {m: corrector(batch) for m, corrector in methods.items()}
        mae = [float(truth.abs().mean())] + [float((o.latency - truth).abs().mean()) for o in outputs.values()]
        q = [image_quality(x, batch.sharp) for x in (none, *(o.latent for o in outputs.values()))]
        q_ideal = image_quality(edi_latent(ideal), batch.sharp)
        c, s = names.index("const"), names.index("spatial")
        wins.append(mae[s] < mae[c] and q[s][0] > q[c][0] and q[s][1] > q[c][1])
        varying.append(float(truth.max() / truth.min()) > VARYING_RATIO)
        row = [*mae, *(x[0] for x in q), q_ideal[0], *(x[1] for x in q), q_ideal[1]]
        for key, value in zip(keys, row):
            totals.setdefault(key, []).append(value)
        lines.append(f"| {scene}{'' if varying[-1] else ' (uniform)'} | {float(truth.mean()):.0f} "
                     f"[{float(truth.min()):.0f}, {float(truth.max()):.0f}] | "
                     + " | ".join(_fmt(k, v) for k, v in zip(keys, row)) + " |")
        print(lines[-1], flush=True)
    lines.append("| **mean** | | " + " | ".join(_fmt(k, sum(v) / len(v)) for k, v in totals.items()) + " |")
    strong = [w for w, v in zip(wins, varying) if v]
    summary = [
        f"- {note}",
        f"- spatial beats constant in latency MAE, PSNR and SSIM on {sum(wins)}/{len(wins)} test scenes, "
        f"{sum(strong)}/{len(strong)} of those whose true latency spans more than {VARYING_RATIO:g}x "
        f"(the others are marked uniform); evaluation {time.perf_counter() - t0:.0f} s",
    ]
    if args.test_time_fit:
        summary.append(f"- fit: `EventLatencyCorrector(mode='spatial')` without a curve: {args.fit_steps} Adam steps "
                       "of the same objective on the frame itself, starting from its l_const")
    return [f"### latency model `{model_name}`", "", *lines, "", *summary, ""], psi


def _fmt(key: str, value: float) -> str:
    return f"{value:.0f}" if key.startswith("MAE") else f"{value:.2f}" if key.startswith("PSNR") else f"{value:.3f}"


def plot_curves(curves: dict[str, PolynomialLatency], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    grid = torch.linspace(0.02, 1.0, 200)
    fig, ax = plt.subplots(figsize=(5, 3.5))
    ax.plot(grid, (LATENCY_RANGE_US[0] / grid).clamp(*LATENCY_RANGE_US) / 1000, "k--", label="true τ(I)")
    with torch.no_grad():
        for name, psi in curves.items():
            ax.plot(grid, psi.curve(grid) / 1000, label=f"learned ψ ({name})")
    ax.set_xlabel("blurry-frame intensity")
    ax.set_ylabel("latency (ms)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(96, 128), metavar=("H", "W"))
    p.add_argument("--latency-model", choices=("intensity_delay", "intensity", "both"), default="both")
    p.add_argument("--epochs", type=int, default=5)
    p.add_argument("--order", type=int, default=5)
    p.add_argument("--lr", type=float, default=0.05)
    p.add_argument("--train-bins", type=int, default=100)
    p.add_argument("--eta", type=float, default=20.0, help="weight of L_mse (paper: 20)")
    p.add_argument("--test-time-fit", action="store_true", help="also fit a curve on each test frame (slower)")
    p.add_argument("--fit-steps", type=int, default=60)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("outputs/spatial"))
    args = p.parse_args()
    floor = _setup.MIN_SCENE_SIZE
    if min(args.size) < floor or args.epochs < 1 or args.order < 0 or args.train_bins < 2 or args.fit_steps < 1:
        p.error(f"--size must be at least {floor} {floor}, --epochs and --fit-steps >= 1, --order >= 0 and "
                "--train-bins >= 2")
    if not (math.isfinite(args.lr) and args.lr > 0 and math.isfinite(args.eta) and args.eta >= 0):
        p.error(f"--lr must be a positive number and --eta >= 0, got {args.lr} and {args.eta}")
    warnings.filterwarnings("ignore", module="lightning")
    warnings.filterwarnings("ignore", message=".*does not have many workers.*")
    args.out.mkdir(parents=True, exist_ok=True)
    size = tuple(args.size)
    t0 = time.perf_counter()
    models = ("intensity_delay", "intensity") if args.latency_model == "both" else (args.latency_model,)
    report = ["# Spatially-varying latency correction (simulated)", "",
              f"{size[1]}x{size[0]} pixels, 20 ms exposure, latency τ = clip(500 µs / I, 0.5, 10 ms); "
              f"trained on {', '.join(PHOTOGRAPHS_TRAIN)}; tested on {', '.join(PHOTOGRAPHS_TEST)}. "
              "EDI latent at mid-exposure with 500 bins against the sharp frame; 'ideal' = EDI from the events "
              "without latency. MAE in µs.", ""]
    curves = {}
    for name in models:
        lines, curves[name] = evaluate(name, args, size)
        report.extend(lines)
    plot_curves(curves, args.out / "curves.png")
    report.append(f"Total {time.perf_counter() - t0:.0f} s on this machine (CPU).")
    text = "\n".join(report) + "\n"
    (args.out / "results.md").write_text(text)
    print(text)
    print(f"wrote {args.out / 'results.md'}, {args.out / 'curves.png'}")


if __name__ == "__main__":
    main()
