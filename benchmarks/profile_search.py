"""Where the default search spends a device's time: a torch profile of its kernels (a diagnostic, not a timing).

Runs the default constant-latency search on ``speed.py``'s frame (DAVIS346, ~2 M events, true latency 4 ms) a few
times under ``torch.profiler`` and prints, per call, the kernels' summed device time, how many kernels were
launched, how many host-device copies and waits were made (torch's sync debug mode counts the waits), and the
operators that took most device time. With ``--frames B`` the B frames of one simulated recording are searched in one
call (on a GPU they share one pass, ``evlatcorr.search_batched``).

    python benchmarks/profile_search.py --device cuda
    python benchmarks/profile_search.py --device cuda --frames 8 --rows 40
    python benchmarks/profile_search.py --device cuda --by-line   # which lines of evlatcorr launch and wait
    python benchmarks/profile_search.py --reductions              # the tiles' kernels, counted without a GPU

The kernels' time is what a whole-search graph could not go below; the wall time per call less that time is what
launches, waits and Python cost. Times under the profiler are longer than ``speed.py``'s: use those for figures.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse
import collections
import time
import traceback
import warnings

import torch
from torch.profiler import ProfilerActivity, profile
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from evlatcorr.cli.common import parse_cpu_or_cuda
from evlatcorr.search import search_constant_latency
from evlatcorr.simulate import simulate


def frames_of(device: torch.device, num_frames: int, height: int, width: int):
    """``num_frames`` frames of one simulated recording at ``speed.py``'s settings (astronaut, 4 ms latency)."""
    seq = simulate("astronaut", num_frames=num_frames, height=height, width=width, exposure_us=20_000.0,
                   latency="constant", latency_us=4000.0, seed=0)
    frames = seq.frames("delayed").to(device)
    return frames.blurry, frames.events, frames.exposure_start, frames.exposure_end


_OUTSIDE = "(outside evlatcorr)"


def _caller_line() -> str:
    """The innermost frame of the running Python stack inside the package, as "evlatcorr/file.py(line): function"."""
    for frame in reversed(traceback.extract_stack()):
        if "evlatcorr/" in frame.filename and "benchmarks/" not in frame.filename:
            return f"evlatcorr/{frame.filename.split('evlatcorr/', 1)[1]}({frame.lineno}): {frame.name}"
    return _OUTSIDE


def waits_of(call) -> collections.Counter:
    """The host-device waits of one ``call()`` on a GPU, as torch's sync debug mode reports them, counted by the
    package's line that asked for each."""
    lines: collections.Counter = collections.Counter()
    show = warnings.showwarning

    def record(message, category, *args, **kwargs):
        if "synchroniz" in str(message):
            lines[_caller_line()] += 1

    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always")
            warnings.showwarning = record
            call()
    finally:
        warnings.showwarning = show
        torch.cuda.set_sync_debug_mode("default")
    return lines


class _OperatorsByLine(TorchDispatchMode):
    """Counts every torch operator dispatched inside it, and those that take a tensor off the host (each a kernel
    launch or a copy), by the package's line that called it (any device, any torch version: it reads Python's own
    stack, not the profiler's)."""

    def __init__(self) -> None:
        super().__init__()
        self.count: collections.Counter = collections.Counter()
        self.on_device: collections.Counter = collections.Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        line = _caller_line()
        self.count[line] += 1
        if any(isinstance(t, torch.Tensor) and t.device.type != "cpu" for t in tree_leaves((args, kwargs))):
            self.on_device[line] += 1
        return func(*args, **(kwargs or {}))


def operators_by_line(call, calls: int) -> list[tuple[str, float, float]]:
    """(line, torch operators per call, those on a device per call) of ``calls`` calls of ``call()``, by the
    package's line behind them, most device operators (then operators) first."""
    with _OperatorsByLine() as counting:
        for _ in range(calls):
            call()
    lines = sorted(counting.count, key=lambda line: (-counting.on_device[line], -counting.count[line]))
    return [(line, counting.count[line] / calls, counting.on_device[line] / calls) for line in lines]


class _Operators(TorchDispatchMode):
    """Counts the torch operators dispatched inside it that are not views (each a kernel on a GPU)."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += not func.is_view
        return func(*args, **(kwargs or {}))


def reduction_operators(frames: int, height: int, width: int, candidates: int = 101) -> dict[str, int]:
    """The torch operators (views left out) of one pass's reductions of ``candidates`` latents per frame, as a GPU
    takes them (all candidates in one chunk, the GPU's branches), counted on meta tensors: shapes, no data, no
    device. The whole frame's (its sparsity scores, ghost moments and overshoots) and the same with the 3x3 tiles."""
    from evlatcorr.config import SearchConfig
    from evlatcorr.ghost import stacked_inverse_ratio_moment
    from evlatcorr.overshoot import overshoot, overshoot_stride
    from evlatcorr.search_batched import _chunk_scores
    from evlatcorr.tile_curves import tile_moments, tile_overshoots, tile_sparsity_scores

    meta = torch.device("meta")
    grey = torch.empty(1, frames, height, width, device=meta)
    inverse, change = (torch.empty(candidates, frames, height, width, device=meta) for _ in range(2))
    stride = overshoot_stride(height, width)
    peak = torch.empty(candidates, frames, -(-height // stride), -(-width // stride), device=meta)
    passes = {"whole frame": lambda: (_chunk_scores(grey, inverse, SearchConfig()),
                                      stacked_inverse_ratio_moment(grey, inverse, change),
                                      overshoot(grey, inverse, peak)),
              "whole frame and tiles": lambda: (tile_sparsity_scores(grey, inverse),
                                                tile_moments(grey, inverse, change),
                                                tile_overshoots(grey, inverse, peak))}
    counts = {}
    for name, call in passes.items():
        call()  # cached matrices made
        with _Operators() as counting:
            call()
        counts[name] = counting.count
    return counts


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--frames", type=int, default=1, help="frames per call")
    parser.add_argument("--calls", type=int, default=5, help="profiled calls (after three untimed)")
    parser.add_argument("--rows", type=int, default=30, help="operators listed")
    parser.add_argument("--height", type=int, default=260)
    parser.add_argument("--width", type=int, default=346)
    parser.add_argument("--by-line", action="store_true",
                        help="also count the operators, and on a GPU the waits, by the package's line behind them")
    parser.add_argument("--reductions", action="store_true",
                        help="only count the kernels of one pass's reductions, the whole frame's and with its tiles, "
                             "as a GPU takes them (on meta tensors: no GPU needed)")
    args = parser.parse_args()
    if args.frames < 1 or args.calls < 1:
        parser.error("--frames and --calls must be positive")
    if args.reductions:
        counts = reduction_operators(args.frames, args.height, args.width)
        print(f"torch operators (views left out) of one pass's reductions, {args.frames} frame(s) of "
              f"{args.height}x{args.width}, 101 candidates, as a GPU takes them (counted on meta tensors):")
        for name, count in counts.items():
            print(f"  {name}: {count}")
        return
    try:
        device = parse_cpu_or_cuda(args.device)
    except ValueError as exc:
        parser.error(str(exc))
    blurry, events, start, end = frames_of(device, args.frames, args.height, args.width)

    def call():
        return search_constant_latency(blurry, events, start, end)

    def wait():
        if device.type == "cuda":
            torch.cuda.synchronize()

    for _ in range(3):
        call()
    wait()
    t0 = time.perf_counter()
    for _ in range(args.calls):
        call()
    wait()
    wall = (time.perf_counter() - t0) / args.calls
    waits = waits_of(call) if device.type == "cuda" else collections.Counter()
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    with profile(activities=activities) as prof:
        for _ in range(args.calls):
            call()
        wait()
    averages = prof.key_averages()
    kernels = [e for e in prof.events() if e.device_type.name == "CUDA"]
    device_us = sum(e.device_time for e in kernels) / args.calls
    copies = sum(1 for e in kernels if "Memcpy" in e.name) / args.calls
    print(f"[{device.type}] default search, {args.frames} frame(s) per call, {len(events)} events, "
          f"{args.height}x{args.width}: wall {wall * 1000:.2f} ms per call (mean of {args.calls}, unprofiled)")
    if device.type == "cuda":
        print(f"[cuda] per call: device time of kernels and copies {device_us / 1000:.2f} ms, "
              f"{len(kernels) / args.calls:.0f} kernels and copies ({copies:.0f} copies), {waits.total()} waits")
    key = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(averages.table(sort_by=key, row_limit=args.rows, max_name_column_width=60))
    if args.by_line:
        print(f"[{device.type}] torch operators per call by the line that called them (top {args.rows}; "
              "'off host': those that take a tensor on a device, each a kernel or a copy):")
        for line, n, on_device in operators_by_line(call, args.calls)[:args.rows]:
            print(f"  {n:6.1f} ops  {on_device:6.1f} off host  {line}")
        if device.type == "cuda":
            print("[cuda] waits per call by the line that asked for them:")
            for line, n in waits.most_common():
                print(f"  {n:4d}  {line}")


if __name__ == "__main__":
    main()
