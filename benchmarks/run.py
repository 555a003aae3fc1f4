"""The paper's Table 1 on simulated data, as a Lightning test loop.

    python benchmarks/run.py                 # 3 unseen test scenes, 256x336, 20 ms exposure, 4 ms latency
    python benchmarks/run.py --scenes 8      # all 8 test photographs (about 20 minutes on 2 CPU cores)
    python benchmarks/run.py --quick         # CI-sized run (2 small scenes)
    python benchmarks/run.py --latency-model intensity --devices 2 --strategy ddp

Rows: EDI deblurring, EFNet, GEM, EDI interpolation, REFID; inputs "GT input" (ideal events),
"W/o corr." (delayed events), "W/ corr. const." and "W/ corr. spatial"; a "Diff (%)" row per
correction, (corrected - uncorrected) / GT input. Beside it, the latency error of both
corrections against the true latency. Rows whose model is not available (no adapter or no
checkpoint) are reported as n/a with the reason; the others still run.

Data: scenes simulated from the test photographs (never used for training), generated once and
cached as evlatcorr HDF5 files under ``~/.cache/evlatcorr/benchmark/<config>/``, reproducible
by seed. ``--data PATH`` reads our HDF5 sequence files instead, or a recording with sharp frames in
any format ``evlatcorr.io`` reads (HighREV, event_utils HDF5, ...): its events are the "GT input" and
the same events delayed by ``--latency-us`` (or ``--latency-model intensity``) "W/o corr.", the
paper's synthetic protocol on real events; such data has no ground truth between exposures, so
the interpolation rows are n/a.
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import json
import math
import os
import platform
import sys
import time
import warnings
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

# evlatcorr before anything that makes a tensor: it backs large CPU tensors with 2 MB pages
import evlatcorr  # noqa: E402, I001
import lightning as L  # noqa: E402
import torch  # noqa: E402
from evlatcorr import EventLatencyCorrector  # noqa: E402
from evlatcorr.adapters.edi import EDIAdapter  # noqa: E402
from evlatcorr.benchmark import (  # noqa: E402
    CONST,
    SPATIAL,
    BenchmarkModule,
    BenchmarkScene,
    Method,
    SceneDataModule,
    format_table,
)
from evlatcorr.benchmark_data import scenes_from_recording  # noqa: E402
from evlatcorr.io import is_sequence_file, num_sequences, read_sequence, write_sequence  # noqa: E402
from evlatcorr.metrics import load_lpips_network  # noqa: E402
from evlatcorr.simulate import PHOTOGRAPHS_TEST, simulate  # noqa: E402

METHODS = {
    "edi": ("EDI deblurring", "deblur"),
    "efnet": ("EFNet", "deblur"),
    "gem": ("GEM", "deblur"),
    "edi-interp": ("EDI interpolation", "interpolation"),
    "refid": ("REFID", "interpolation"),
}


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, help="our HDF5 sequence file(s) (a file or a folder), or a recording with "
                   "sharp frames in any format evlatcorr.io reads (HighREV folder, event_utils HDF5, ...) into "
                   "which the latency is injected (default: the simulated test set)")
    p.add_argument("--frames-per-scene", type=int, default=4, help="frames taken from each sequence of a --data "
                   "recording")
    p.add_argument("--ckpt", action="append", default=[], metavar="NAME=PATH",
                   help="checkpoint for efnet/gem/refid (official or ours); default: the shipped checkpoints/")
    p.add_argument("--refid-n", type=int, default=1, help="REFID's n (sharp frames in the gap) of a --ckpt refid "
                   "file; its m is read from the weights (shipped: m=4, n=1)")
    p.add_argument("--methods", default=",".join(METHODS), help=f"comma-separated subset of {','.join(METHODS)}")
    p.add_argument("--latency-model", choices=("constant", "intensity"), default="constant")
    p.add_argument("--latency-us", type=float, default=4000.0, help="constant latency of the simulated test set")
    p.add_argument("--scenes", type=int, default=None, help=f"scenes scored: test photographs (1-"
                   f"{len(PHOTOGRAPHS_TEST)}, default 3, which keeps the run under 10 minutes on 2 CPU cores), "
                   "or the first sequences of --data (default all)")
    p.add_argument("--size", type=int, nargs=2, default=(256, 336), metavar=("H", "W"))
    p.add_argument("--num-bins", type=int, default=500)
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--devices", default="1")
    p.add_argument("--strategy", default="auto")
    p.add_argument("--out", type=Path, default=Path("outputs/benchmark"))
    p.add_argument("--quick", action="store_true", help="2 scenes at 64x80, 100 bins: a CI-sized run")
    p.add_argument("--lpips-backbone", type=Path, help="AlexNet features for LPIPS (else torch hub cache / "
                                                        "$EVLATCORR_LPIPS_BACKBONE)")
    p.add_argument("--spatial-steps", type=int, default=30, help="test-time fitting steps of the spatial corrector")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    if args.quick:
        args.scenes, args.size, args.num_bins, args.spatial_steps = 2, (64, 80), 100, 10
    if args.data is None:
        args.scenes = 3 if args.scenes is None else args.scenes
        if not 1 <= args.scenes <= len(PHOTOGRAPHS_TEST):
            p.error(f"--scenes must be between 1 and {len(PHOTOGRAPHS_TEST)} (the test photographs)")
    elif args.scenes is not None and args.scenes < 1:
        p.error("--scenes must be >= 1")
    if args.frames_per_scene < 1:
        p.error("--frames-per-scene must be >= 1")
    unknown = set(args.methods.split(",")) - set(METHODS)
    if unknown:
        p.error(f"unknown methods {sorted(unknown)}; choose from {sorted(METHODS)}")
    return args


def scene_from_sequence(name: str, seq) -> BenchmarkScene:
    return BenchmarkScene(name, seq.frames("ideal"), seq.frames("delayed"), seq.pairs("ideal"),
                          seq.pairs("delayed"), seq.true_latency)


def prepare_data(args: argparse.Namespace) -> list[Any]:
    """The test scenes' sources: simulated once (cached by configuration) or from ``--data``.

    Returns ``(file, index)`` items for our HDF5 sequence files (read when their turn comes) and
    ready :class:`BenchmarkScene` objects for recordings of other formats (their events are the
    "GT input", the same events delayed by the injected latency "W/o corr.").
    """
    if args.data is not None:
        return data_sources(args)
    config = dict(scenes=list(PHOTOGRAPHS_TEST[:args.scenes]), size=list(args.size), latency=args.latency_model,
                  latency_us=args.latency_us, seed=args.seed, exposure_us=20000.0, interval_us=25000.0, v=2)
    key = hashlib.sha1(json.dumps(config, sort_keys=True).encode()).hexdigest()[:10]
    root = Path(os.environ.get("EVLATCORR_CACHE", Path.home() / ".cache" / "evlatcorr")) / "benchmark" / key
    root.mkdir(parents=True, exist_ok=True)
    files = []
    for i, name in enumerate(config["scenes"]):
        path = root / f"{i:02d}_{name}.h5"
        if not path.is_file():
            print(f"simulating test scene {name} ({args.size[1]}x{args.size[0]}) -> {path}", flush=True)
            seq = simulate(name, num_frames=2, height=args.size[0], width=args.size[1], exposure_us=20000.0,
                           frame_interval_us=25000.0, latency=args.latency_model, latency_us=args.latency_us,
                           seed=args.seed + 100 + i)
            write_sequence(path, seq)
        files.append((path, 0))
    return files


def data_sources(args: argparse.Namespace) -> list[Any]:
    """``--data``: a folder of our HDF5 sequence files, one such file, or any recording with sharp frames."""
    path: Path = args.data
    if not path.exists():
        raise SystemExit(f"run.py: error: {path}: no such file or directory")
    candidates = sorted(path.glob("*.h5")) if path.is_dir() else [path]
    sequence_files = [f for f in candidates if is_sequence_file(f)]
    if sequence_files:
        skipped = sorted(set(candidates) - set(sequence_files))
        if skipped:
            print(f"skipping {len(skipped)} .h5 files that hold no simulated sequence: "
                  f"{', '.join(f.name for f in skipped[:5])}", flush=True)
        return [(f, i) for f in sequence_files for i in range(num_sequences(f))][:args.scenes]
    try:
        scenes = list(scenes_from_recording(path, latency=args.latency_model, latency_us=args.latency_us,
                                            frames_per_scene=args.frames_per_scene, max_scenes=args.scenes))
    except (OSError, ValueError) as exc:
        raise SystemExit(f"run.py: error: cannot read {path}: {exc}") from exc
    print(f"{path}: {len(scenes)} scenes of up to {args.frames_per_scene} frames with sharp ground truth; "
          "recorded events as GT input, the same delayed as W/o corr.", flush=True)
    return scenes


def refid_layout_of(path: str, n: int = 1) -> tuple[int, int]:
    """REFID's ``(m, n)`` for a checkpoint: ``m`` from its image head (``2m + 4`` input channels)."""
    from evlatcorr.adapters.checkpoint import load_state_dict_file, resolve_checkpoint

    state = load_state_dict_file(resolve_checkpoint(path, "refid"))
    key = next((k for k in state if k.endswith("head_img.conv2d.weight")), None)
    if key is None:
        raise ValueError(f"{path} is not a REFID checkpoint (no head_img.conv2d.weight)")
    channels = int(state[key].shape[1])
    if channels % 2 or channels < 8:
        raise ValueError(f"{path}: head_img has {channels} input channels; blurry frame interpolation needs 2m + 4")
    return (channels - 4) // 2, n


def build_methods(args: argparse.Namespace) -> tuple[list[Method], dict[str, str]]:
    ckpts = dict(item.split("=", 1) for item in args.ckpt if "=" in item)
    methods, missing = [], {}
    for key in args.methods.split(","):
        title, task = METHODS[key]
        if key == "edi":
            methods.append(Method(title, EDIAdapter(num_bins=args.num_bins), task))
            continue
        if key == "edi-interp":
            methods.append(Method(title, EDIAdapter("interpolation", num_bins=args.num_bins), task))
            continue
        source = ckpts.get(key, "default")
        try:
            if key == "efnet":
                adapter = evlatcorr.adapters.EFNetAdapter(checkpoint=source)
            elif key == "gem":
                adapter = evlatcorr.adapters.GEMAdapter(checkpoint=source)
            else:
                m, n = (4, 1) if source == "default" else refid_layout_of(source, args.refid_n)
                # "default": the shipped refid-4-1 weights (4 sharp frames per 20 ms exposure, 1 in the 5 ms gap)
                adapter = evlatcorr.adapters.REFIDAdapter(checkpoint=source, m=m, n=n)
            methods.append(Method(title, adapter.eval(), task))
        except (FileNotFoundError, ValueError, KeyError, RuntimeError) as exc:
            what = "no shipped checkpoint" if source == "default" else f"checkpoint {source} not loaded"
            missing[title] = f"{what} ({exc})"
    return methods, missing


class Figures:
    """Collects the first scene's outputs for the figures."""

    def __init__(self) -> None:
        self.first: tuple[BenchmarkScene, dict[str, Any]] | None = None

    def __call__(self, scene: BenchmarkScene, outputs: dict[str, Any]) -> None:
        if self.first is None:
            self.first = (scene.to("cpu"), {k: _cpu(v) for k, v in outputs.items()})

    @staticmethod
    def _write_crops(out: Path, scene: BenchmarkScene, outputs: dict[str, Any]) -> str:
        """restored.png: a row per method (its blurry input and ground truth, then the result of each
        input), cropped to the first frame's most textured 96x128 window, where latency shows."""
        import matplotlib.pyplot as plt

        restored, targets = outputs["restored"], outputs["target"]
        top, left = sharpest_window(scene.frames_ideal.sharp[0], 96, 128)
        crop = (slice(None), slice(top, top + 96), slice(left, left + 128))
        methods = list(dict.fromkeys(method for method, _ in restored))
        inputs = list(dict.fromkeys(name for _, name in restored))
        cols = 2 + len(inputs)
        fig, axes = plt.subplots(len(methods), cols, figsize=(2.4 * cols, 2.1 * len(methods)), squeeze=False)
        for ax in axes.flat:
            ax.axis("off")
        for row, method in zip(axes, methods):
            panels = [("blurry input", scene.frames_ideal.blurry[0]), ("ground truth", targets[method][0])]
            panels += [(name, restored[(method, name)][0]) for name in inputs if (method, name) in restored]
            for ax, (title, image) in zip(row, panels):
                ax.imshow(image[crop].permute(1, 2, 0).clamp(0, 1).numpy(), interpolation="nearest")
                ax.set_title(f"{method}\n{title}", fontsize=8)
        fig.suptitle(f"{scene.name}, frame 0 (interpolation: the first gap's frame), 96x128 crop at "
                     f"y={top}, x={left}", fontsize=9)
        fig.tight_layout()
        fig.savefig(out / "restored.png", dpi=90)
        plt.close(fig)
        return "restored.png"

    def write(self, out: Path) -> list[str]:
        if self.first is None:
            return []
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        scene, outputs = self.first
        written = []
        meta = outputs.get("meta", {}).get(CONST)
        if meta is not None and "etf_curve" in meta:
            cand, etf = meta["etf_curve"]
            fig, ax = plt.subplots(figsize=(5, 3.5))
            ax.plot(cand[0].numpy() / 1000, etf[0].numpy())
            ax.axvline(float(scene.true_latency[0].mean()) / 1000, color="g", ls="-", label="true")
            ax.axvline(float(outputs["latency"][CONST][0].mean()) / 1000, color="r", ls="--", label="estimated")
            ax.set_xlabel("candidate latency (ms)")
            ax.set_ylabel(f"{meta.get('score', 'etf')} score (lower = sharper)")
            ax.set_title(f"{scene.name}, frame 0")
            ax.legend()
            fig.tight_layout()
            fig.savefig(out / "etf_vs_latency.png", dpi=100)
            plt.close(fig)
            written.append("etf_vs_latency.png")
        if outputs["restored"]:
            written.append(self._write_crops(out, scene, outputs))
        maps = [("true", scene.true_latency[0, 0])] + [(k, v[0, 0]) for k, v in outputs["latency"].items()]
        fig, axes = plt.subplots(1, len(maps), figsize=(3.4 * len(maps), 2.8), squeeze=False)
        vmax = max(float(m.max()) for _, m in maps) / 1000
        for ax, (title, m) in zip(axes[0], maps):
            im = ax.imshow(m.numpy() / 1000, vmin=0, vmax=vmax, cmap="viridis")
            ax.set_title(f"{title} (ms)", fontsize=9)
            ax.axis("off")
        fig.colorbar(im, ax=list(axes[0]), shrink=0.8)
        fig.savefig(out / "latency_maps.png", dpi=90)
        plt.close(fig)
        written.append("latency_maps.png")
        return written


def sharpest_window(image: torch.Tensor, height: int, width: int) -> tuple[int, int]:
    """Top-left corner of the ``height x width`` window of ``image`` (C, H, W) with the most gradient
    energy: where latency errors show."""
    gray = image.mean(0)
    energy = (gray[1:, :-1] - gray[:-1, :-1]) ** 2 + (gray[:-1, 1:] - gray[:-1, :-1]) ** 2
    h, w = min(height, energy.shape[0]), min(width, energy.shape[1])
    sums = torch.nn.functional.avg_pool2d(energy[None, None], (h, w), stride=8)[0, 0]
    index = int(sums.flatten().argmax())
    return (index // sums.shape[1]) * 8, (index % sums.shape[1]) * 8


def _cpu(value: Any) -> Any:
    if isinstance(value, torch.Tensor):
        return value.detach().cpu()
    if isinstance(value, dict):
        return {k: _cpu(v) for k, v in value.items()}
    if isinstance(value, tuple):
        return tuple(_cpu(v) for v in value)
    return value


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    t0 = time.perf_counter()
    warnings.filterwarnings("ignore", module="lightning")
    stages: dict[str, float] = {}
    files = prepare_data(args)
    stages["scenes (simulate, or read the cache)"] = time.perf_counter() - t0
    t1 = time.perf_counter()
    methods, missing = build_methods(args)
    for title, why in missing.items():
        print(f"{title}: {why}; its rows are n/a", flush=True)
    lpips_net, lpips_why = load_lpips_network(args.lpips_backbone)
    stages["models and LPIPS (load)"] = time.perf_counter() - t1
    if lpips_net is None:
        print(f"LPIPS: n/a ({lpips_why})", flush=True)
    correctors = {CONST: EventLatencyCorrector(num_bins=args.num_bins),
                  SPATIAL: EventLatencyCorrector(mode="spatial", num_bins=args.num_bins, steps=args.spatial_steps)}
    figures = Figures()
    module = BenchmarkModule(methods, correctors, lpips_net, on_scene=figures)

    unreadable: dict[str, str] = {}

    def load(i: int) -> BenchmarkScene | None:
        if isinstance(files[i], BenchmarkScene):
            return files[i]
        path, index = files[i]
        try:
            return scene_from_sequence(path.stem if index == 0 else f"{path.stem}_{index}", read_sequence(path, index))
        except (OSError, ValueError, KeyError) as exc:  # one bad file costs its scene, not the run
            print(f"\nskipping {path} (sequence {index}): cannot read it: {exc}", flush=True)
            unreadable[f"{path}:{index}"] = str(exc)
            return None

    devices: int | str = int(args.devices) if args.devices.isdigit() else args.devices
    trainer = L.Trainer(accelerator=args.device if args.device != "cuda" else "gpu", devices=devices,
                        strategy=args.strategy, logger=False, enable_model_summary=False,
                        enable_progress_bar=True, use_distributed_sampler=False)  # scenes split by rank
    if trainer.is_global_zero:
        print(f"scoring {len(files)} scenes: {', '.join(m.name for m in methods)} x {', '.join(module.inputs)} "
              "(one progress step per scene)", flush=True)
    t2 = time.perf_counter()
    trainer.test(module, SceneDataModule(load, len(files)))
    loop = time.perf_counter() - t2
    stages.update({f"test loop: {k}": v for k, v in module.stage_seconds.items()})
    stages["test loop: other (reading scenes, Lightning)"] = loop - sum(module.stage_seconds.values())
    results = module.results()  # on every rank: computing the metrics syncs them across processes
    if not trainer.is_global_zero:
        return 0
    if len(unreadable) == len(files):
        raise SystemExit(f"run.py: error: none of the {len(files)} scenes could be read")
    for title, why in missing.items():
        for name in module.inputs:
            results["table"].append({"method": title, "input": name, "psnr": math.nan, "ssim": math.nan,
                                     "lpips": math.nan})
        results["failures"][title] = why
    order = [METHODS[k][0] for k in args.methods.split(",")]
    results["table"].sort(key=lambda r: (order.index(r["method"]), module.inputs.index(r["input"])))
    wall = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    table = format_table(results)
    latency_lines = ["| correction | latency MAE (us) | latency max error (us) |", "| --- | --- | --- |"]
    for name, err in results["latency_error"].items():
        latency_lines.append(f"| {name} | {err['mae_us']:.0f} | {err['max_us']:.0f} |")
    truth = (f"{args.latency_us:.0f} us constant" if args.latency_model == "constant" else "intensity-dependent")
    read = len(files) - len(unreadable)
    if args.data is None:
        data = f"Simulated test set: {read} scenes ({args.size[1]}x{args.size[0]}), 20 ms exposure, latency {truth}"
    elif isinstance(files[0], BenchmarkScene):
        h, w = files[0].frames_ideal.sensor_size
        data = (f"{args.data}: {read} sequences ({w}x{h} centre crop, up to {args.frames_per_scene} frames each), "
                f"latency {truth} injected into the recorded events")
    else:
        data = f"{args.data}: {read} simulated sequences"
    header = f"{data}; EDI {args.num_bins} bins; LPIPS {'AlexNet' if lpips_net is not None else 'n/a: ' + lpips_why}"
    notes = "".join(f"\n- {k}: n/a, {v}" for k, v in results["failures"].items())
    notes += "".join(f"\n- skipped {k}: {v}" for k, v in unreadable.items())
    stage_lines = ["| stage | seconds | share |", "| --- | --- | --- |"] + [
        f"| {k} | {v:.1f} | {100 * v / wall:.0f} % |" for k, v in stages.items()]
    md = (f"{header}\n\n{table}\n\n{chr(10).join(latency_lines)}\n{notes}\n\n"
          f"wall time {wall:.0f} s (before writing the figures), by stage:\n\n{chr(10).join(stage_lines)}\n")
    (args.out / "results.md").write_text(md)
    with open(args.out / "results.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=["method", "input", "psnr", "ssim", "lpips"])
        w.writeheader()
        w.writerows(results["table"])
    figures_written = figures.write(args.out)
    (args.out / "results.json").write_text(json.dumps({
        **results, "config": {k: str(v) if isinstance(v, Path) else v for k, v in vars(args).items()},
        "data": [f.name if isinstance(f, BenchmarkScene) else f"{f[0]}:{f[1]}" for f in files],
        "unreadable": unreadable, "seed": args.seed, "wall_time_s": wall, "stage_seconds": stages,
        "figures": figures_written,
        "versions": {"evlatcorr": evlatcorr.__version__, "torch": torch.__version__, "lightning": L.__version__,
                     "python": platform.python_version()},
    }, indent=2, default=lambda v: None if isinstance(v, float) and math.isnan(v) else str(v)))
    print(md)
    print(f"wrote {args.out}/results.md, results.csv, results.json and {', '.join(figures_written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
