"""The command behind ``python benchmarks/run.py``: the paper's Table 1 on simulated data, as a Lightning test loop.

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
import json
import math
import platform
import time
import warnings
from pathlib import Path
from typing import Any

import lightning as L
import torch

import evlatcorr
import evlatcorr.adapters
from evlatcorr.adapters.edi import EDIAdapter
from evlatcorr.benchmark.figures import Figures
from evlatcorr.benchmark.loop import CONST, SPATIAL, BenchmarkModule, BenchmarkScene, Method, SceneDataModule
from evlatcorr.benchmark.metrics import load_lpips_network
from evlatcorr.benchmark.scenes import prepare_data, scene_from_sequence
from evlatcorr.benchmark.table import format_table
from evlatcorr.cli.common import parse_cpu_or_cuda
from evlatcorr.correction import EventLatencyCorrector
from evlatcorr.gamma import frame_gamma_argument
from evlatcorr.io import read_sequence
from evlatcorr.io.outputs import check_writable_folder
from evlatcorr.lightning.arguments import MIN_FRAME_SIZE, trainer_or_exit
from evlatcorr.simulate import PHOTOGRAPHS_TEST
from evlatcorr.simulation.latency import MAX_LATENCY_US

__all__ = ["METHODS", "parse_args", "build_methods", "main"]

METHODS = {
    "edi": ("EDI deblurring", "deblur"),
    "efnet": ("EFNet", "deblur"),
    "gem": ("GEM", "deblur"),
    "edi-interp": ("EDI interpolation", "interpolation"),
    "refid": ("REFID", "interpolation"),
}


#: the default run, and --quick's (CI-sized); the scenes' default depends on --data (below)
FULL: dict[str, Any] = {"size": (256, 336), "num_bins": 500, "spatial_steps": 30}
QUICK: dict[str, Any] = {"scenes": 2, "size": (64, 80), "num_bins": 100, "spatial_steps": 10}
#: the rows whose weights --ckpt gives
CHECKPOINT_METHODS = ("efnet", "gem", "refid")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """The command line of ``benchmarks/run.py`` (``--quick`` sets a CI-sized configuration)."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, help="our HDF5 sequence file(s) (a file or a folder), or a recording with "
                   "sharp frames in any format evlatcorr.io reads (HighREV folder, event_utils HDF5, ...) into "
                   "which the latency is injected (default: the simulated test set)")
    p.add_argument("--frame-gamma", type=frame_gamma_argument, default=1.0, metavar="G",
                   help="a --data recording whose frames are encoded for display (2.2: PNG or video frames, sRGB): "
                   "EDI and the correctors read them raised to G, linear as they need them, while the networks "
                   "read, and every row is scored on, the frames as the file has them (default 1: linear, as a "
                   "DAVIS's raw frames are)")
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
    p.add_argument("--size", type=int, nargs=2, default=None, metavar=("H", "W"),
                   help=f"simulated test set's size (default: {' '.join(map(str, FULL['size']))})")
    p.add_argument("--num-bins", type=int, default=None, help=f"EDI sub-intervals (default: {FULL['num_bins']})")
    p.add_argument("--device", default="cpu", help="cpu or cuda")
    p.add_argument("--devices", default="1")
    p.add_argument("--strategy", default="auto")
    p.add_argument("--out", type=Path, default=Path("outputs/benchmark"))
    p.add_argument("--quick", action="store_true", help="2 scenes at 64x80, 100 bins, 10 spatial steps: a CI-sized "
                   "run (the options given beside it win)")
    p.add_argument("--lpips-backbone", type=Path, help="AlexNet features for LPIPS (else torch hub cache / "
                                                        "$EVLATCORR_LPIPS_BACKBONE)")
    p.add_argument("--spatial-steps", type=int, default=None,
                   help=f"test-time fitting steps of the spatial corrector (default: {FULL['spatial_steps']})")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    preset = QUICK if args.quick else FULL
    for name, value in preset.items():  # what is given explicitly wins over --quick
        if getattr(args, name) is None:
            setattr(args, name, value)
    if min(args.size) < MIN_FRAME_SIZE or args.num_bins < 2 or args.spatial_steps < 0 or args.refid_n < 0:
        p.error(f"--size must be at least {MIN_FRAME_SIZE} {MIN_FRAME_SIZE}, --num-bins >= 2, --spatial-steps and "
                f"--refid-n >= 0; got {list(args.size)}, {args.num_bins}, {args.spatial_steps} and {args.refid_n}")
    for item in args.ckpt:
        name, _, path = item.partition("=")
        if name not in CHECKPOINT_METHODS or not path:
            p.error(f"--ckpt takes NAME=PATH with NAME one of {', '.join(CHECKPOINT_METHODS)}, got {item!r}")
        if path != "default" and not Path(path).exists():
            p.error(f"--ckpt {item}: no such file")
    if args.lpips_backbone is not None and not args.lpips_backbone.is_file():
        p.error(f"--lpips-backbone {args.lpips_backbone}: no such file")
    if args.data is None:
        args.scenes = 3 if args.scenes is None else args.scenes
        if not 1 <= args.scenes <= len(PHOTOGRAPHS_TEST):
            p.error(f"--scenes must be between 1 and {len(PHOTOGRAPHS_TEST)} (the test photographs)")
    elif args.scenes is not None and args.scenes < 1:
        p.error("--scenes must be >= 1")
    if args.frames_per_scene < 1:
        p.error("--frames-per-scene must be >= 1")
    if args.data is None and args.frame_gamma != 1:
        p.error("--frame-gamma is for --data recordings whose frames are encoded for display; the simulated test set "
                "is linear")
    if args.data is not None and not args.data.exists():
        p.error(f"--data {args.data}: no such file or directory")
    if not 0.0 <= args.latency_us <= MAX_LATENCY_US:  # before any scene is simulated (the simulator refuses it too)
        p.error(f"--latency-us must be between 0 and {MAX_LATENCY_US:.0f} us, got {args.latency_us}")
    try:
        parse_cpu_or_cuda(args.device)
    except ValueError as exc:
        p.error(str(exc))
    unknown = set(args.methods.split(",")) - set(METHODS)
    if unknown:
        p.error(f"unknown methods {sorted(unknown)}; choose from {sorted(METHODS)}")
    try:  # last, once everything else holds: it makes the folder
        check_writable_folder(args.out)
    except ValueError as exc:
        p.error(f"--out: {exc}")
    return args


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
    """The rows' models, and for each one that cannot be loaded the reason (its rows are n/a)."""
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


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and write ``results.md``, ``results.csv``, ``results.json`` and the figures."""
    args = parse_args(argv)
    trainer = _trainer(args)
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
    _test(trainer, module, files, unreadable, stages)
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
    md = _markdown(args, results, files, unreadable, stages, wall, lpips_why if lpips_net is None else None)
    _write(args, md, results, files, unreadable, stages, wall, figures)
    return 0


def _trainer(args: argparse.Namespace) -> L.Trainer:
    """The test loop's Trainer, made first: a setting Lightning refuses (``--devices 0``, an unknown ``--strategy``)
    is one line and exit code 2 before any scene is simulated or model loaded."""
    devices: int | str = int(args.devices) if args.devices.isdigit() else args.devices
    return trainer_or_exit("run.py", lambda: L.Trainer(
        accelerator=args.device if args.device != "cuda" else "gpu", devices=devices, strategy=args.strategy,
        logger=False, enable_model_summary=False, enable_progress_bar=True,
        use_distributed_sampler=False))  # scenes split by rank


def _test(trainer: L.Trainer, module: BenchmarkModule, files: list[Any], unreadable: dict[str, str],
          stages: dict[str, float]) -> None:
    """The Lightning test loop over the scenes; a scene that cannot be read is skipped and noted."""

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

    if trainer.is_global_zero:
        print(f"scoring {len(files)} scenes: {', '.join(m.name for m in module.methods)} x "
              f"{', '.join(module.inputs)} (one progress step per scene)", flush=True)
    start = time.perf_counter()
    trainer.test(module, SceneDataModule(load, len(files)))
    loop = time.perf_counter() - start
    stages.update({f"test loop: {k}": v for k, v in module.stage_seconds.items()})
    stages["test loop: other (reading scenes, Lightning)"] = loop - sum(module.stage_seconds.values())


def _markdown(args: argparse.Namespace, results: dict[str, Any], files: list[Any], unreadable: dict[str, str],
              stages: dict[str, float], wall: float, lpips_why: str | None) -> str:
    """results.md: what was scored, the table, the latency errors, what is n/a and where the time went."""
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
        if args.frame_gamma != 1:
            data += (f"; frames encoded for display, read linear with frame_gamma {args.frame_gamma:g} by EDI and "
                     "the correctors, as in the file by the networks and the metrics")
    else:
        data = f"{args.data}: {read} simulated sequences"
    header = f"{data}; EDI {args.num_bins} bins; LPIPS {'AlexNet' if lpips_why is None else 'n/a: ' + lpips_why}"
    notes = "".join(f"\n- {k}: n/a, {v}" for k, v in results["failures"].items())
    notes += "".join(f"\n- skipped {k}: {v}" for k, v in unreadable.items())
    stage_lines = ["| stage | seconds | share |", "| --- | --- | --- |"] + [
        f"| {k} | {v:.1f} | {100 * v / wall:.0f} % |" for k, v in stages.items()]
    return (f"{header}\n\n{format_table(results)}\n\n{chr(10).join(latency_lines)}\n{notes}\n\n"
            f"wall time {wall:.0f} s (before writing the figures), by stage:\n\n{chr(10).join(stage_lines)}\n")


def _write(args: argparse.Namespace, md: str, results: dict[str, Any], files: list[Any], unreadable: dict[str, str],
           stages: dict[str, float], wall: float, figures: Figures) -> None:
    """results.md, results.csv, the figures and results.json (every figure, the configuration, versions)."""
    args.out.mkdir(parents=True, exist_ok=True)
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
