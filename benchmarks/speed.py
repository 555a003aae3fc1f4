"""Speed of the one-pass constant-latency search against a naive per-candidate loop.

The naive loop is what one would write first: for every candidate latency, shift the events,
re-bin them, re-run EDI and score the latent image with the ETF. The one-pass search bins the
events once and reads every candidate from one prefix-sum table (see ``evlatcorr/search.py``).
Both find the argmin over the same candidates; this script checks they agree, and prints the
median time of each over repeats, their ratio (``ratio: <number>`` per device) and, for the
one-pass search, frames per second.

    python benchmarks/speed.py                  # DAVIS346 frame, 500 bins, 20 ms, ~1 M events, 100 candidates
    python benchmarks/speed.py --events 200000 --repeats 3 --naive-repeats 1
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from evlatcorr import Events  # noqa: E402
from evlatcorr.edi import edi_deblur  # noqa: E402
from evlatcorr.etf import etf_loss  # noqa: E402
from evlatcorr.search import search_constant_latency  # noqa: E402


def make_frame(num_events: int, height: int, width: int, exposure_us: float, latency_us: float,
               device: torch.device, seed: int = 0):
    """A blurry frame of a moving bar pattern and its events, ~num_events over 2 exposures, latency added."""
    g = torch.Generator().manual_seed(seed)
    span = 2 * exposure_us
    # events from vertical edges moving right at constant speed (+ uniform noise events, 10%)
    n_edge = int(num_events * 0.9)
    t = torch.rand(n_edge, generator=g, dtype=torch.float64) * span
    y = torch.randint(0, height, (n_edge,), generator=g)
    phase = torch.randint(0, 8, (n_edge,), generator=g)
    x = ((phase * (width // 8)) + (t / exposure_us * 20).long()) % width
    p = (phase % 2) * 2 - 1
    n_noise = num_events - n_edge
    t = torch.cat([t, torch.rand(n_noise, generator=g, dtype=torch.float64) * span]) + latency_us
    x = torch.cat([x, torch.randint(0, width, (n_noise,), generator=g)])
    y = torch.cat([y, torch.randint(0, height, (n_noise,), generator=g)])
    p = torch.cat([p, torch.randint(0, 2, (n_noise,), generator=g) * 2 - 1])
    ev = Events(x, y, t, p, sensor_size=(height, width), sort=True).to(device)
    blurry = (torch.rand(1, 1, height, width, generator=g) * 0.6 + 0.2).to(device)
    return blurry, ev


def naive_search(blurry, events, start, end, candidates, threshold, num_bins):
    scores = []
    for lat in candidates.tolist():
        latent = edi_deblur(blurry, events.shift(lat), start, end, threshold, None, num_bins)
        scores.append(etf_loss(latent))
    scores = torch.cat(scores)
    return candidates[int(torch.argmin(scores))]


def timed(fn, device: torch.device) -> tuple[float, object]:
    if device.type == "cuda":
        torch.cuda.synchronize()
    t0 = time.perf_counter()
    out = fn()
    if device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - t0, out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--events", type=int, default=1_000_000)
    parser.add_argument("--height", type=int, default=260)
    parser.add_argument("--width", type=int, default=346)
    parser.add_argument("--bins", type=int, default=500)
    parser.add_argument("--exposure-us", type=float, default=20_000.0)
    parser.add_argument("--candidates", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the one-pass search")
    parser.add_argument("--naive-repeats", type=int, default=3, help="repeats of the naive loop")
    parser.add_argument("--device", action="append", help="cpu and/or cuda (default: cpu, and cuda if present)")
    args = parser.parse_args()
    devices = args.device or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))

    print(f"frame {args.width}x{args.height}, {args.bins} bins, exposure {args.exposure_us / 1000:.0f} ms, "
          f"{args.events} events, {args.candidates} candidates; torch {torch.__version__}, "
          f"{torch.get_num_threads()} CPU threads")
    for name in devices:
        device = torch.device(name)
        blurry, ev = make_frame(args.events, args.height, args.width, args.exposure_us, 4000.0, device)
        start = torch.zeros(1, dtype=torch.float64, device=device)
        end = start + args.exposure_us

        def one_pass():
            return search_constant_latency(blurry, ev, start, end, 0.2, args.bins, None, args.candidates,
                                           refine=False).latency

        one_pass()  # warm-up (allocator, kernels)
        fast = [timed(one_pass, device) for _ in range(args.repeats)]
        fast_latency = float(fast[-1][1][0])
        candidates = search_constant_latency(blurry, ev, start, end, 0.2, args.bins, None, args.candidates,
                                             refine=False).candidates[0].to(device)
        slow = [timed(lambda: naive_search(blurry, ev, start, end, candidates, 0.2, args.bins), device)
                for _ in range(args.naive_repeats)]
        slow_latency = float(slow[-1][1])
        t_fast = statistics.median(t for t, _ in fast)
        t_slow = statistics.median(t for t, _ in slow)
        refined = [timed(lambda: search_constant_latency(blurry, ev, start, end, 0.2, args.bins, None,
                                                         args.candidates).latency, device)[0]
                   for _ in range(args.repeats)]
        print(f"[{name}] one-pass search: median {t_fast * 1000:.1f} ms over {args.repeats} "
              f"({1 / t_fast:.1f} frames/s); with sub-candidate refinement {statistics.median(refined) * 1000:.1f} ms")
        print(f"[{name}] naive loop:      median {t_slow * 1000:.1f} ms over {args.naive_repeats}")
        print(f"[{name}] same argmin: {abs(fast_latency - slow_latency) < 1e-6} "
              f"({fast_latency:.1f} us vs {slow_latency:.1f} us)")
        print(f"[{name}] ratio: {t_slow / t_fast:.1f}")


if __name__ == "__main__":
    main()
