"""Where the default search spends a device's time: a torch profile of its kernels (a diagnostic, not a timing).

Runs the default constant-latency search on ``speed.py``'s frame (DAVIS346, ~2 M events, true latency 4 ms) a few
times under ``torch.profiler`` and prints, per call, the kernels' summed device time, how many kernels were
launched, how many host-device copies and waits were made (torch's sync debug mode counts the waits), and the
operators that took most device time. With ``--frames B`` the B frames of one simulated recording are searched in one
call (on a GPU they share one pass, ``evlatcorr.search_batched``).

    python benchmarks/profile_search.py --device cuda
    python benchmarks/profile_search.py --device cuda --frames 8 --rows 40

The kernels' time is what a whole-search graph could not go below; the wall time per call less that time is what
launches, waits and Python cost. Times under the profiler are longer than ``speed.py``'s: use those for figures.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse
import time
import warnings

import torch
from torch.profiler import ProfilerActivity, profile

from evlatcorr.search import search_constant_latency
from evlatcorr.simulate import simulate


def frames_of(device: torch.device, num_frames: int, height: int, width: int):
    """``num_frames`` frames of one simulated recording at ``speed.py``'s settings (astronaut, 4 ms latency)."""
    seq = simulate("astronaut", num_frames=num_frames, height=height, width=width, exposure_us=20_000.0,
                   latency="constant", latency_us=4000.0, seed=0)
    frames = seq.frames("delayed").to(device)
    return frames.blurry, frames.events, frames.exposure_start, frames.exposure_end


def count_waits(call) -> int:
    """The host-device waits of one ``call()`` on a GPU, as torch's sync debug mode reports them."""
    torch.cuda.set_sync_debug_mode("warn")
    try:
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            call()
    finally:
        torch.cuda.set_sync_debug_mode("default")
    return sum("synchroniz" in str(w.message) for w in caught)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--frames", type=int, default=1, help="frames per call")
    parser.add_argument("--calls", type=int, default=5, help="profiled calls (after three untimed)")
    parser.add_argument("--rows", type=int, default=30, help="operators listed")
    parser.add_argument("--height", type=int, default=260)
    parser.add_argument("--width", type=int, default=346)
    args = parser.parse_args()
    if args.frames < 1 or args.calls < 1:
        parser.error("--frames and --calls must be positive")
    device = torch.device(args.device)
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
    waits = count_waits(call) if device.type == "cuda" else 0
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
              f"{len(kernels) / args.calls:.0f} kernels and copies ({copies:.0f} copies), {waits} waits")
    key = "self_device_time_total" if device.type == "cuda" else "self_cpu_time_total"
    print(averages.table(sort_by=key, row_limit=args.rows, max_name_column_width=60))


if __name__ == "__main__":
    main()
