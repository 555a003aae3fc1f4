"""``torch.compile`` of a whole pipeline, ``nn.Sequential(EventLatencyCorrector(), network)``: what it costs.

The corrector is opaque to TorchDynamo (``torch.compiler.disable`` on its ``forward``): its search reads the events
with data-dependent shapes and runs its own compiled passes, so tracing it only breaks the graph again and again and
recompiles. The adapters' event representations are opaque for the same reason. A compiled pipeline therefore
compiles the network and runs the corrector and the events' representation as they are. This script times
the pipeline eager, compiled with the corrector traced (the same corrector with the plain ``forward``) and compiled as
shipped, in one run: the first call (the compile, with Inductor's caches off, as on a first run) and the median of
the calls after it, and checks that the outputs agree with the eager pipeline.

    python benchmarks/compile.py                         # EFNet, 64x96, 2 frames, 5 calls each (about 4 minutes)
    python benchmarks/compile.py --skip-traced           # without the traced corrector's slow compile
    python benchmarks/compile.py --model gem --size 96 128
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import os  # noqa: E402

# every compile from scratch, as a user's first run: Inductor's caches on disk would let one row reuse another's
# compiled network (and a previous run's)
os.environ.setdefault("TORCHINDUCTOR_FORCE_DISABLE_CACHES", "1")

import argparse  # noqa: E402
import logging  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
import warnings  # noqa: E402
from collections.abc import Callable  # noqa: E402

import torch  # noqa: E402
from torch import nn  # noqa: E402

from evlatcorr import EventFrames, EventLatencyCorrector  # noqa: E402
from evlatcorr.adapters import EFNetAdapter, GEMAdapter  # noqa: E402
from evlatcorr.simulate import simulate  # noqa: E402

#: the networks measured behind the corrector (random weights: the time does not depend on them)
NETWORKS = {"efnet": EFNetAdapter, "gem": GEMAdapter}


class TracedCorrector(EventLatencyCorrector):
    """The corrector with the plain ``forward``, which TorchDynamo traces (for the comparison only)."""

    forward = EventLatencyCorrector.forward.__wrapped__


def time_calls(pipeline: Callable[[EventFrames], EventFrames], frames: EventFrames,
               calls: int) -> tuple[float, float, EventFrames]:
    """The first call's seconds, the median of ``calls`` more, and the last output."""
    start = time.perf_counter()
    out = pipeline(frames)
    first = time.perf_counter() - start
    seconds = []
    for _ in range(calls):
        start = time.perf_counter()
        out = pipeline(frames)
        seconds.append(time.perf_counter() - start)
    return first, statistics.median(seconds), out


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", choices=sorted(NETWORKS), default="efnet",
                   help="the network behind the corrector (default: efnet)")
    p.add_argument("--size", type=int, nargs=2, default=(64, 96), metavar=("H", "W"))
    p.add_argument("--frames", type=int, default=2, help="frames per call (default: 2)")
    p.add_argument("--calls", type=int, default=5, help="timed calls after the first (default: 5)")
    p.add_argument("--skip-traced", action="store_true", help="leave out the pipeline with the corrector traced")
    args = p.parse_args(argv)
    if args.frames < 1 or args.calls < 1 or min(args.size) < 18:
        p.error("--frames and --calls must be >= 1 and --size at least 18 18")
    warnings.simplefilter("ignore")  # graph breaks and recompiles are what is measured, not printed
    logging.getLogger("torch._dynamo").setLevel(logging.ERROR)
    logging.getLogger("torch._inductor").setLevel(logging.ERROR)
    height, width = args.size
    frames = simulate("camera", num_frames=args.frames, height=height, width=width, latency_us=3000.0,
                      seed=0).frames("delayed")
    network = NETWORKS[args.model]().eval()
    rows = [("eager", nn.Sequential(EventLatencyCorrector(threshold=0.2), network))]
    if not args.skip_traced:
        rows.append(("torch.compile, the corrector traced",
                     torch.compile(nn.Sequential(TracedCorrector(threshold=0.2), network))))
    rows.append(("torch.compile, the corrector opaque (shipped)",
                 torch.compile(nn.Sequential(EventLatencyCorrector(threshold=0.2), network))))
    print(f"{args.model}, {args.frames} frames of {height}x{width} per call, {torch.get_num_threads()} threads; "
          f"median of {args.calls} calls after the first")
    print("| pipeline | first call (s) | each call after (ms) | max. difference to eager |")
    print("| --- | --- | --- | --- |")
    reference = None
    with torch.no_grad():
        for name, pipeline in rows:
            torch.compiler.reset()
            first, median, out = time_calls(pipeline, frames, args.calls)
            reference = out.output if reference is None else reference
            difference = float((out.output - reference).abs().max())
            print(f"| {name} | {first:.1f} | {median * 1e3:.0f} | {difference:.1e} |", flush=True)


if __name__ == "__main__":
    main()
