"""Table 1 on a recording whose frames are encoded for display: what ``run.py --data --frame-gamma`` changes.

Simulated scenes (their events without latency: ``run.py --data`` injects it) are written as HighREV folders twice,
their 8-bit PNGs once linear and once encoded for display (``linear ** (1 / gamma)``, as PNG exports and video
frames are), and ``benchmarks/run.py --data``'s EDI rows score them three ways: the linear frames, the encoded frames
read as they are, and the encoded frames read with ``--frame-gamma``. Each run's files are kept under ``--out``.

    python benchmarks/display_gamma_table1.py                    # 2 scenes at 36x52, gamma 2.2, about 30 s
    python benchmarks/display_gamma_table1.py --size 64 80 --gamma 2.4
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse  # noqa: E402
import json  # noqa: E402
from pathlib import Path  # noqa: E402
from typing import Any  # noqa: E402

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

from evlatcorr.benchmark.table1 import main as table1  # noqa: E402
from evlatcorr.gamma import check_frame_gamma  # noqa: E402
from evlatcorr.simulate import simulate  # noqa: E402

SCENES = ("camera", "rocket")
CORRECTIONS = ("W/ corr. const.", "W/ corr. spatial")
INPUTS = ("GT input", "W/o corr.", *CORRECTIONS)


def write_highrev_split(root: Path, sequences: dict[str, Any], gamma: float = 1.0) -> None:
    """A HighREV split folder from simulated sequences: for each frame one event piece over its exposure and one up
    to the next exposure (the reader drops the second from the exposure), x/y swapped as HighREV stores them, 8-bit
    images encoded as ``linear ** (1 / gamma)`` (1: linear)."""
    for folder in ("blur", "sharp", "event"):
        (root / folder).mkdir(parents=True, exist_ok=True)
    for name, seq in sequences.items():
        events = seq.ideal_events
        for k in range(seq.num_frames):
            stem = f"{name}_{k:05d}"
            for folder, image in (("blur", seq.blurry[k]), ("sharp", seq.sharp[k])):
                array = (image.permute(1, 2, 0).numpy() ** (1 / gamma) * 255).round().astype(np.uint8)
                Image.fromarray(array).save(root / folder / f"{stem}.png")
            start, end = float(seq.exposure_start[k]), float(seq.exposure_end[k])
            stop = float(seq.exposure_start[k + 1]) if k + 1 < seq.num_frames else end + 20000.0
            for j, (lo, hi) in enumerate([(start, end), (end, stop)]):  # the pieces partition time
                piece = events.window(lo, hi)
                np.savez(root / "event" / f"{stem}_{j:02d}.npz", x=piece.y.numpy()[:, None],
                         y=piece.x.numpy()[:, None], timestamp=piece.t.numpy()[:, None],
                         polarity=(piece.p.numpy() > 0).astype(np.uint8)[:, None])


def simulated_scenes(size: tuple[int, int]) -> dict[str, Any]:
    """The scenes written: two frames each, 20 ms exposures 25 ms apart, events without latency."""
    return {name: simulate(name, num_frames=2, height=size[0], width=size[1], exposure_us=20000.0,
                           frame_interval_us=25000.0, latency="none", seed=i) for i, name in enumerate(SCENES)}


def main(argv: list[str] | None = None) -> dict[str, dict[str, Any]]:
    """Run the three ways and print their table; returns each run's ``results.json``, by the run's name."""
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--size", type=int, nargs=2, default=(36, 52), metavar=("H", "W"))
    p.add_argument("--gamma", type=float, default=2.2, help="the display encoding's gamma (default 2.2)")
    p.add_argument("--out", type=Path, default=Path("outputs/display_gamma_table1"))
    args = p.parse_args(argv)
    try:
        gamma = check_frame_gamma(args.gamma)
    except ValueError as err:
        p.error(str(err))
    if min(args.size) < 16:
        p.error(f"--size must be at least 16x16 (the networks' multiple), got {args.size[0]}x{args.size[1]}")
    scenes = simulated_scenes(tuple(args.size))
    linear, encoded = args.out / "linear" / "val", args.out / "encoded" / "val"
    write_highrev_split(linear, scenes)
    write_highrev_split(encoded, scenes, gamma)
    rows = ("--methods", "edi", "--num-bins", "100", "--spatial-steps", "3")
    runs = {"linear frames": [str(linear)], "encoded, read as they are": [str(encoded)],
            f"encoded, --frame-gamma {gamma:g}": [str(encoded), "--frame-gamma", str(gamma)]}
    results = {}
    for k, (name, data) in enumerate(runs.items()):
        out = args.out / f"run{k}"
        table1(["--data", *data, *rows, "--out", str(out)])
        results[name] = json.loads((out / "results.json").read_text())
    print(_markdown(results, args.size, gamma))
    return results


def _markdown(results: dict[str, dict[str, Any]], size: tuple[int, int], gamma: float) -> str:
    lines = [f"{len(SCENES)} scenes at {size[1]}x{size[0]}, 4 ms of latency injected, gamma {gamma:g}: latency error "
             "of the corrections and EDI deblurring PSNR (dB, against the sharp frames as the files hold them)", "",
             "| frames | latency error, constant / spatial | EDI PSNR: " + " / ".join(INPUTS) + " |",
             "| --- | --- | --- |"]
    for name, result in results.items():
        errors = " / ".join(f"{result['latency_error'][c]['mae_us']:.0f}" for c in CORRECTIONS)
        psnr = {r["input"]: r["psnr"] for r in result["table"] if r["method"] == "EDI deblurring"}
        lines.append(f"| {name} | {errors} µs | " + " / ".join(f"{psnr[i]:.2f}" for i in INPUTS) + " |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
