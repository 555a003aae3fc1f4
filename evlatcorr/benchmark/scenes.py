"""The benchmark's test scenes: simulated from the test photographs once and cached, or read from ``--data``."""

from __future__ import annotations

import argparse
import hashlib
import json
import os
from pathlib import Path
from typing import Any

from evlatcorr.benchmark.loop import BenchmarkScene
from evlatcorr.benchmark.recording import scenes_from_recording
from evlatcorr.io import is_sequence_file, num_sequences, write_sequence
from evlatcorr.simulate import PHOTOGRAPHS_TEST, simulate

__all__ = ["scene_from_sequence", "prepare_data", "data_sources"]


def scene_from_sequence(name: str, seq) -> BenchmarkScene:
    """A :class:`BenchmarkScene` of a simulated (or stored) sequence: its ideal and delayed frames and pairs.

    The pairs' events start one exposure time before the first exposure (REFID's voxel grid starts before
    it, as a camera's stream has events there), the same for both inputs.
    """
    lead = float((seq.exposure_end - seq.exposure_start).max())
    return BenchmarkScene(name, seq.frames("ideal"), seq.frames("delayed"), seq.pairs("ideal", before_us=lead),
                          seq.pairs("delayed", before_us=lead), seq.true_latency, events_before_us=lead)


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
        if args.frame_gamma != 1:
            raise SystemExit(f"run.py: error: --frame-gamma {args.frame_gamma:g}: {path} holds our HDF5 sequences, "
                             "whose frames are linear; the option is for recordings whose frames are encoded for "
                             "display")
        skipped = sorted(set(candidates) - set(sequence_files))
        if skipped:
            print(f"skipping {len(skipped)} .h5 files that hold no simulated sequence: "
                  f"{', '.join(f.name for f in skipped[:5])}", flush=True)
        return [(f, i) for f in sequence_files for i in range(num_sequences(f))][:args.scenes]
    try:
        scenes = list(scenes_from_recording(path, latency=args.latency_model, latency_us=args.latency_us,
                                            frames_per_scene=args.frames_per_scene, max_scenes=args.scenes,
                                            frame_gamma=args.frame_gamma))
    except (OSError, ValueError) as exc:
        raise SystemExit(f"run.py: error: cannot read {path}: {exc}") from exc
    print(f"{path}: {len(scenes)} scenes of up to {args.frames_per_scene} frames with sharp ground truth; "
          "recorded events as GT input, the same delayed as W/o corr.", flush=True)
    return scenes
