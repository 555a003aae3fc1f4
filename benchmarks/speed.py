"""Speed of the one-pass constant-latency search against a naive per-candidate loop.

The one-pass search reads every candidate's window from the exact continuous-time integral
(``evlatcorr/continuous.py``); the previous method, a binned prefix-sum table (``method="binned"``), is
timed in the same run (``continuous/binned speed-up``). The naive loop is what one would write first:
for every candidate latency, shift the events, re-bin them, re-run EDI and score the latent image (one
sparsity score). Both find the argmin over the same candidates; this script checks they agree, and
prints the median time of each over repeats, their ratio (``ratio: <number>`` per device) and, for the
one-pass search, frames per second.

    python benchmarks/speed.py                  # DAVIS346 frame, 500 bins, 20 ms, ~2 M events, 100 candidates
    python benchmarks/speed.py --repeats 3 --naive-repeats 1 --height 130 --width 173
    python benchmarks/speed.py --part adapters --device cuda   # corrector vs EFNet/GEM/REFID forward
    python benchmarks/speed.py --part memory --events 3000000  # peak memory of one constant correction
    python benchmarks/speed.py --part batch                    # 4 frames in one call against one frame
    python benchmarks/speed.py --part spatial                  # the spatial test-time fit, new and previous
    python benchmarks/speed.py --part against --against cfd57f4  # this checkout's default search against a revision's
    python benchmarks/speed.py --part stages                   # where the default search's time goes
    python benchmarks/speed.py --part stream                   # the streaming corrector against the corrector alone
    python benchmarks/speed.py --part recording                # the corrector on a real recording's frames

``--part adapters`` times, at the benchmark's resolution (256x336, 20 ms exposure), the constant
corrector (``EventLatencyCorrector()``: search, shift, EDI latent) against each adapter's forward pass
(event representation + network, eval mode, no grad) on the same frame, and prints the corrector's
cost as a percentage of each (``corrector/EFNet: <p> %``), each timed after three untimed calls (the
steady state of a stream of frames). Weights do not change the time; the shipped ones are used when present.

``--part against --against REV`` times the default search (``search_constant_latency`` at its defaults) of this
checkout and of the git revision ``REV`` on the same frame, each in fresh processes taken in turn for
``--rounds`` rounds (the machine's slow drifts hit both alike), and prints each one's median over every call and
their ratio (``speed-up against REV: <x>``): the "old and new in one run" of a speed claim. Both run under this
checkout's memory settings (2 MB pages, freed memory kept; ``EVLATCORR_KEEP_FREED_MEMORY=0`` leaves glibc's
default for both). With ``--score NAME`` both search with that score (e.g. ``consensus``, the default of ``cfd57f4``):
the same work on both sides, where the defaults compare different amounts of it.

``--part recording`` times the corrector (``EventLatencyCorrector``, the recording's θ given) on every frame of a
recording (``--recording``, default the shared low-light DAVIS346 one), each after its untimed first call, with a
CPU's compiled passes (the default, ``evlatcorr.compiled``) and, in the same run, in eager PyTorch
(``evlatcorr.compiled.ENABLED = False``), with the median over frames of each frame's median of ``--repeats`` calls,
and checks that both give the same latencies (a GPU, which has no compiled passes, is timed once); then the time to
estimate the recording's θ (what ``threshold="auto"`` and the command line do once per recording), once, and each
pair of consecutive frames' agreement (``pair_log_odds``, what ``evlatcorr correct`` and the corrector given pairs add).

``--part stages`` says where the default search's time goes; on a CPU it does so twice in one run, with the compiled
passes (the default) and in eager PyTorch (``eager/compiled: <x>``).

``--part memory`` runs one constant correction (``EventLatencyCorrector()``, the defaults) on a
DAVIS346 frame (260x346) with ``--events`` events spread over its exposure and search window, in a
fresh process, and prints its peak resident memory (``peak RSS: <MB>``, from ``getrusage``) and,
on a GPU, ``torch.cuda.max_memory_allocated``.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse
import functools
import itertools
import json
import resource
import statistics
import subprocess
import sys
import tarfile
import tempfile
import time
import warnings
from pathlib import Path

import torch  # noqa: E402

from evlatcorr import EventLatencyCorrector, Events  # noqa: E402
from evlatcorr.cli.common import parse_cpu_or_cuda  # noqa: E402
from evlatcorr.edi import edi_deblur  # noqa: E402
from evlatcorr.search import DEFAULT_SCORE, SCORES, search_constant_latency, sharpness_score  # noqa: E402

# the naive loop re-runs EDI and one score per candidate; the default scores three ways and reads their curves,
# so the one-pass/naive ratio is measured with one score and the default is timed on its own
RATIO_SCORE = "sparsity"
# calls before timing in --part adapters: the first few calls of a process pay page faults on fresh memory
# (the corrector's first calls ran 1.5x slower here); a stream of frames runs in the steady state
WARM_UP = 3
from evlatcorr.simulate import simulate  # noqa: E402

# the shared low-light DAVIS346 recording (a Newton's cradle, 20 ms exposures), where this checkout sits beside it
RECORDING = next((p for p in (Path(__file__).resolve().parents[2] / "shared", Path("/work/shared"))
                  if (p / "data").is_dir()), Path("../shared")) / "data" / "davis346" / "cradle_lowlight.aedat4"


def make_frame(height: int, width: int, exposure_us: float, latency_us: float, device: torch.device, seed: int = 0):
    """A simulated DAVIS-like frame (astronaut photograph, ~1 px/ms motion) with a known constant latency."""
    seq = simulate("astronaut", num_frames=1, height=height, width=width, exposure_us=exposure_us,
                   latency="constant", latency_us=latency_us, seed=seed)
    frames = seq.frames("delayed").to(device)
    return frames.blurry, frames.events, frames.exposure_start, frames.exposure_end


def naive_search(blurry, events, start, end, candidates, threshold, num_bins):
    scores = []
    for lat in candidates.tolist():
        latent = edi_deblur(blurry, events.shift(lat), start, end, threshold, None, num_bins)
        scores.append(sharpness_score(latent, torch.tensor([lat], dtype=torch.float32), None, RATIO_SCORE,
                                      20.0, 7, 1000.0))
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
    parser.add_argument("--height", type=int, default=260)
    parser.add_argument("--width", type=int, default=346)
    parser.add_argument("--bins", type=int, default=500)
    parser.add_argument("--exposure-us", type=float, default=20_000.0)
    parser.add_argument("--candidates", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=5, help="repeats of the one-pass search")
    parser.add_argument("--naive-repeats", type=int, default=3, help="repeats of the naive loop")
    parser.add_argument("--device", action="append", help="cpu and/or cuda (default: cpu, and cuda if present)")
    parser.add_argument("--part", choices=("search", "batch", "spatial", "adapters", "memory", "against", "stages",
                                           "stream", "recording", "all"),
                        default="all", help="what to time; 'against' and 'recording' are not part of 'all'")
    parser.add_argument("--recording", type=Path, default=RECORDING, help="--part recording's recording")
    parser.add_argument("--threshold", type=float, default=0.52,
                        help="--part recording's contrast threshold (default: the shared recording's, 0.52)")
    parser.add_argument("--against", metavar="REV", help="git revision whose default search --part against times")
    parser.add_argument("--rounds", type=int, default=3, help="alternating rounds of --part against")
    parser.add_argument("--score", default="default", choices=("default", *SCORES),
                        help="--part against: the score both revisions search with (default: each one's default)")
    parser.add_argument("--events", type=int, default=3_000_000, help="events of --part memory")
    parser.add_argument("--memory-child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--batch-sizes", type=int, nargs="+", default=[4], metavar="B",
                        help="frames per call of --part batch (each against one frame)")
    parser.add_argument("--memory-budget", type=float, default=None, metavar="BYTES",
                        help="memory budget of --part batch's searches (default: the library's, 2 GiB)")
    parser.add_argument("--adapter-size", type=int, nargs=2, default=(256, 336), metavar=("H", "W"),
                        help="frame size of --part adapters (the benchmark's)")
    args = parser.parse_args()
    if min(args.batch_sizes) < 1:
        parser.error("--batch-sizes must be positive")
    counts = {"--repeats": args.repeats, "--naive-repeats": args.naive_repeats, "--rounds": args.rounds,
              "--candidates": args.candidates, "--events": args.events}
    problems = [f"{flag} must be >= 1, got {value}" for flag, value in counts.items() if value < 1]
    problems += ["--bins must be >= 2"] * (args.bins < 2)
    problems += ["sizes must be >= 16 pixels"] * (min(args.height, args.width, *args.adapter_size) < 16)
    problems += ["--exposure-us must be > 0"] * (not args.exposure_us > 0)
    if problems:
        parser.error("; ".join(problems))
    devices = args.device or (["cpu"] + (["cuda"] if torch.cuda.is_available() else []))
    for name in devices:
        try:
            parse_cpu_or_cuda(name)
        except ValueError as exc:
            parser.error(str(exc))
    if args.memory_child:
        memory_child(torch.device(devices[0]), args)
        return
    if args.part == "against":
        if not args.against:
            parser.error("--part against needs --against REV (a git revision of this repository)")
        bench_against(args)
        return
    if args.part == "recording":
        for name in devices:
            bench_recording(torch.device(name), args)
        return

    print(f"frame {args.width}x{args.height}, {args.bins} bins, exposure {args.exposure_us / 1000:.0f} ms, "
          f"{args.candidates} candidates, true latency 4000 us; torch {torch.__version__}, "
          f"{torch.get_num_threads()} CPU threads")
    for name in devices:
        if args.part in ("search", "all"):
            bench_device(torch.device(name), args)
        if args.part in ("adapters", "all"):
            bench_adapters(torch.device(name), args)
        if args.part in ("memory", "all"):
            bench_memory(name, args)
        if args.part in ("batch", "all"):
            bench_batch(torch.device(name), args)
        if args.part in ("spatial", "all"):
            bench_spatial(torch.device(name), args)
        if args.part in ("stages", "all"):
            bench_stages(torch.device(name), args)
        if args.part in ("stream", "all"):
            bench_stream(torch.device(name), args)


# one process's timing of the default search at a source tree (argv: tree, frame file, repeats, this checkout's
# evlatcorr/pages.py); it inherits THP_MEM_ALLOC_ENABLE from this script and applies this checkout's
# keep_freed_memory (read from its file, so the tree's own package is the one imported): both trees run under the
# memory settings our entry points ask for
_AGAINST_CHILD = """
import importlib.util, json, sys, time
tree, frame_file, repeats, pages_file, score = sys.argv[1], sys.argv[2], int(sys.argv[3]), sys.argv[4], sys.argv[5]
spec = importlib.util.spec_from_file_location("_memory_settings", pages_file)
settings = importlib.util.module_from_spec(spec)
spec.loader.exec_module(settings)
settings.keep_freed_memory()
sys.path.insert(0, tree)
import evlatcorr
import torch
from evlatcorr.events import Events
from evlatcorr.search import search_constant_latency
assert evlatcorr.__file__.startswith(tree), evlatcorr.__file__
d = torch.load(frame_file)
events = Events(d["x"], d["y"], d["t"], d["p"], sensor_size=tuple(d["size"]))
kwargs = {} if score == "default" else {"score": score}
def call():
    return search_constant_latency(d["blurry"], events, d["start"], d["end"], 0.2, d["bins"], None, d["candidates"],
                                   **kwargs)
for _ in range(3):
    call()
times = []
for _ in range(repeats):
    t0 = time.perf_counter()
    out = call()
    times.append(time.perf_counter() - t0)
print(json.dumps({"times": times, "latency": float(out.latency[0])}))
"""


def bench_against(args: argparse.Namespace) -> None:
    """The default search of this checkout and of git revision ``args.against`` on one frame (CPU), in fresh
    processes taken in turn (``--score``: both search with that score instead of their defaults)."""
    what = "default search" if args.score == "default" else f"search with score={args.score!r}"
    root = Path(__file__).resolve().parents[1]
    with tempfile.TemporaryDirectory() as tmp:
        tree = Path(tmp) / "revision"
        tree.mkdir()
        archive = Path(tmp) / "revision.tar"
        try:
            subprocess.run(["git", "-C", str(root), "archive", "--format=tar", "-o", str(archive), args.against],
                           capture_output=True, text=True, check=True)
        except (OSError, subprocess.CalledProcessError) as exc:
            detail = getattr(exc, "stderr", "") or str(exc)
            sys.exit(f"speed.py: cannot read revision {args.against!r} from the git repository at {root}: "
                     f"{detail.strip()}")
        with tarfile.open(archive) as tar:
            tar.extractall(tree, **({"filter": "data"} if hasattr(tarfile, "data_filter") else {}))
        blurry, ev, start, end = make_frame(args.height, args.width, args.exposure_us, 4000.0, torch.device("cpu"))
        frame = Path(tmp) / "frame.pt"
        torch.save({"blurry": blurry, "x": ev.x, "y": ev.y, "t": ev.t, "p": ev.p, "size": ev.sensor_size,
                    "start": start, "end": end, "bins": args.bins, "candidates": args.candidates}, frame)
        labels = {"this checkout": root, args.against: tree}
        times: dict[str, list[float]] = {label: [] for label in labels}
        latency: dict[str, float] = {}
        print(f"[cpu] {what}, this checkout against {args.against}: {len(ev)} events, {args.rounds} rounds "
              f"of {args.repeats} calls each (after 3 untimed), fresh processes in turn", flush=True)
        for k in range(args.rounds):
            for label, path in labels.items():
                run = subprocess.run([sys.executable, "-c", _AGAINST_CHILD, str(path), str(frame), str(args.repeats),
                                      str(root / "evlatcorr" / "pages.py"), args.score], capture_output=True, text=True)
                if run.returncode != 0:
                    sys.exit(f"speed.py: the search of {label} failed:\n{run.stderr.strip()[-2000:]}")
                out = json.loads(run.stdout.strip().splitlines()[-1])
                times[label] += out["times"]
                latency[label] = out["latency"]
                print(f"[cpu] round {k + 1}, {label}: median {statistics.median(out['times']) * 1000:.1f} ms",
                      flush=True)
    new, old = (statistics.median(times[label]) for label in labels)
    print(f"[cpu] {what}: this checkout {new * 1000:.1f} ms, {args.against} {old * 1000:.1f} ms (medians of "
          f"{len(times[args.against])} calls; estimates {latency['this checkout']:.0f} and "
          f"{latency[args.against]:.0f} us)")
    print(f"[cpu] speed-up against {args.against}: {old / new:.2f}x")


def bench_stages(device: torch.device, args: argparse.Namespace) -> None:
    """Where the default search's time goes on the speed frame: each stage's share of every call, medians over
    ``--repeats`` calls (after three untimed), the stages timed by wrapping the functions that do them."""
    import evlatcorr.compiled as compiled_passes
    import evlatcorr.continuous as continuous
    import evlatcorr.search_candidates as search_candidates
    import evlatcorr.search_learned as search_learned
    import evlatcorr.tile_curves as tile_curves

    blurry, ev, start, end = make_frame(args.height, args.width, args.exposure_us, 4000.0, device)
    stages = {"prepare the events (sort by pixel, levels)": (continuous.ContinuousIntegral, "__init__"),
              "read the candidates' windows": (continuous.ContinuousIntegral, "inverse_ratio"),
              "sharpness scores": (search_candidates, "_latent_scores"),
              "ghost moments": (search_learned, "inverse_ratio_moment"),
              "overshoots": (search_learned, "overshoot"),
              "sharpness scores, whole frame and tiles": (tile_curves, "tile_sparsity_scores"),
              "ghost moments, whole frame and tiles": (tile_curves, "tile_moments"),
              "overshoots, whole frame and tiles": (tile_curves, "tile_overshoots"),
              "the estimate's latent (its window read once more)": (continuous.ContinuousIntegral, "log_ratio")}
    spent: dict[str, float] = {}

    def wrapped(label, fn):
        def run(*a, **k):
            seconds, out = timed(lambda: fn(*a, **k), device)
            spent[label] = spent.get(label, 0.0) + seconds
            return out
        return run

    originals = {label: getattr(owner, name) for label, (owner, name) in stages.items()}
    enabled = compiled_passes.ENABLED
    # on a CPU the compiled passes (the default) and eager PyTorch's way they replaced, in the same run
    ways = {"compiled": True, "eager": False} if device.type == "cpu" else {"": enabled}
    totals = {}
    try:
        for label, (owner, name) in stages.items():
            setattr(owner, name, wrapped(label, originals[label]))
        # the default reads the frame's tiles too (SearchConfig.tiles); the whole frame alone beside it
        for (way, on), tiles in itertools.product(ways.items(), (True, False)):
            compiled_passes.ENABLED = on
            per_call: dict[str, list[float]] = {label: [] for label in [*stages, "other", "total"]}
            search = functools.partial(search_constant_latency, blurry, ev, start, end, num_bins=args.bins,
                                       num_candidates=args.candidates, tiles=tiles)
            for k in range(WARM_UP + args.repeats):
                spent.clear()
                total, _ = timed(search, device)
                if k >= WARM_UP:
                    for label in stages:
                        per_call[label].append(spent.get(label, 0.0))
                    per_call["other"].append(total - sum(spent.values()))
                    per_call["total"].append(total)
            reads = "the whole frame and its tiles" if tiles else "the whole frame alone (tiles=False)"
            print(f"[{device.type}] default search ({DEFAULT_SCORE}) by stage{', ' + way if way else ''}, {reads}, "
                  f"{len(ev)} events, median of {args.repeats}:")
            for label, values in per_call.items():
                if any(values):
                    print(f"[{device.type}]   {label}: {statistics.median(values) * 1000:.1f} ms")
            totals[way, tiles] = statistics.median(per_call["total"])
            if not tiles:
                print(f"[{device.type}] tiles/whole frame alone{', ' + way if way else ''}: "
                      f"{totals[way, True] / totals[way, False]:.2f}x")
    finally:
        compiled_passes.ENABLED = enabled
        for label, (owner, name) in stages.items():
            setattr(owner, name, originals[label])
    if len(ways) == 2:
        print(f"[{device.type}] eager/compiled: {totals['eager', True] / totals['compiled', True]:.2f}x")


def bench_recording(device: torch.device, args: argparse.Namespace) -> None:
    """The corrector on every frame of a real recording, on a CPU with the compiled passes and in eager PyTorch in the
    same run (see the module's docstring)."""
    import evlatcorr.compiled as compiled_passes
    from evlatcorr.io import open_recording

    if not args.recording.is_file():
        raise SystemExit(f"--recording {args.recording}: no such file")
    enabled = compiled_passes.ENABLED
    corrector = EventLatencyCorrector(threshold=args.threshold)
    warnings.simplefilter("ignore")  # the recording's own warnings (its last frame's events end early), said elsewhere
    frames = [frame.to(device) for frame in open_recording(args.recording) if len(frame.events)]

    def per_frame(on: bool) -> tuple[list[float], list[float]]:
        compiled_passes.ENABLED = on
        times, latencies = [], []
        for frame in frames:
            latencies.append(float(corrector(frame).latency.mean()))  # untimed: the first call of each frame
            times.append(statistics.median(timed(lambda f=frame: corrector(f), device)[0]
                                           for _ in range(args.repeats)))
        return times, latencies

    cpu = device.type == "cpu"  # the compiled passes are a CPU's: a GPU runs eager PyTorch either way
    try:
        compiled, compiled_latency = per_frame(True)
        if cpu:
            eager, eager_latency = per_frame(False)
    finally:
        compiled_passes.ENABLED = enabled
    events = statistics.median(len(frame.events) for frame in frames)
    print(f"[{device.type}] {args.recording.name}: {len(frames)} frames {frames[0].sensor_size[1]}x"
          f"{frames[0].sensor_size[0]}, median {events:.0f} events per window, θ = {args.threshold}; median over "
          f"frames of each frame's median of {args.repeats} calls")
    if not cpu:
        print(f"[{device.type}] corrector: {statistics.median(compiled) * 1000:.1f} ms per frame")
    else:
        print(f"[{device.type}] corrector, compiled passes: {statistics.median(compiled) * 1000:.1f} ms per frame; "
              f"eager: {statistics.median(eager) * 1000:.1f} ms; speed-up "
              f"{statistics.median(eager) / statistics.median(compiled):.2f}x")
        gap = max(abs(a - b) for a, b in zip(compiled_latency, eager_latency))
        print(f"[{device.type}] largest latency difference between the two: {gap:.4f} us")
    bench_pairs(device, args, corrector, frames, statistics.median(compiled))
    from evlatcorr.restore import recording_threshold

    seconds, theta = timed(lambda: recording_threshold(open_recording(args.recording), device=device), device)
    print(f"[{device.type}] the recording's θ (threshold='auto': two-frame consistency of its first frames): "
          f"{theta if theta is None else round(theta, 3)}, found in {seconds:.1f} s (once)")


def bench_pairs(device: torch.device, args: argparse.Namespace, corrector, frames: list, per_frame: float) -> None:
    """Each pair of the recording's consecutive frames' agreement over the first frame's candidates
    (:func:`evlatcorr.pair_evidence.pair_log_odds`: what ``evlatcorr correct`` adds per frame, and the corrector per
    pair given pairs), the median over pairs of each pair's median of ``--repeats`` calls, against ``per_frame``
    (the corrector's time per frame, s)."""
    from evlatcorr.io import open_recording
    from evlatcorr.pair_evidence import pair_log_odds
    from evlatcorr.restore import pair_frames, pair_reach_us

    rec = open_recording(args.recording)
    rec.after_us = pair_reach_us(rec)
    pairs = [pair.to(device) for _, pair in pair_frames(rec) if pair is not None and len(pair.events)]
    if not pairs:
        print(f"[{device.type}] {args.recording.name}: no pair of consecutive frames")
        return
    candidates = corrector(frames[0]).meta["etf_curve"][0][0]  # the frames' candidates (one exposure time)
    times = []
    for pair in pairs:
        pair_log_odds(pair, args.threshold, candidates)  # untimed first call
        times.append(statistics.median(timed(lambda p=pair: pair_log_odds(p, args.threshold, candidates), device)[0]
                                       for _ in range(args.repeats)))
    each = statistics.median(times)
    print(f"[{device.type}] each pair's agreement (pair_log_odds, {len(pairs)} pairs, {len(candidates)} candidates): "
          f"{each * 1000:.1f} ms per pair, {each / per_frame:.2f}x the corrector's time per frame")


def bench_batch(device: torch.device, args: argparse.Namespace) -> None:
    """The default search on B frames of one recording in one call (``--batch-sizes``) against one frame: a batch
    must cost at most B times one frame. On a GPU the frames share one pass over their events
    (:mod:`evlatcorr.search_batched`) as far as ``--memory-budget`` allows; on a CPU they are searched one by one."""
    sizes = sorted(set(args.batch_sizes))
    seq = simulate("astronaut", num_frames=max(sizes), height=args.height, width=args.width,
                   exposure_us=args.exposure_us, frame_interval_us=args.exposure_us * 1.25, latency="constant",
                   latency_us=4000.0, seed=0)
    frames = seq.frames("delayed").to(device)

    def first(f, n):
        ev, end = f.events, f.events.sample_bounds()[n]
        events = Events.from_canonical(ev.x[:end], ev.y[:end], ev.t[:end], ev.p[:end], ev.batch[:end],
                                       ev.sensor_size, n)
        return f.replace(blurry=f.blurry[:n], events=events, sharp=None, meta={},
                         exposure_start=f.exposure_start[:n], exposure_end=f.exposure_end[:n])

    def search(f):
        return search_constant_latency(f.blurry, f.events, f.exposure_start, f.exposure_end, 0.2, args.bins, None,
                                       args.candidates, memory_budget=args.memory_budget)

    one = first(frames, 1)
    for _ in range(WARM_UP):
        search(one)
    t_one = statistics.median(timed(lambda: search(one), device)[0] for _ in range(args.repeats))
    budget = ("the default memory budget" if args.memory_budget is None
              else f"a {args.memory_budget / 2**30:.0f} GiB budget")
    print(f"[{device.type}] default search, one frame ({len(one.events)} events): {t_one * 1000:.1f} ms "
          f"({1 / t_one:.0f} frames/s); {budget}, median of {args.repeats}")
    for size in sizes:
        if size == 1:
            continue
        batch = first(frames, size)
        for _ in range(WARM_UP):
            search(batch)
        t_batch = statistics.median(timed(lambda b=batch: search(b), device)[0] for _ in range(args.repeats))
        print(f"[{device.type}] {size} frames in one call ({len(batch.events)} events): {t_batch * 1000:.1f} ms = "
              f"{t_batch / t_one:.2f} x one frame, {size / t_batch:.0f} frames/s")


def bench_stream(device: torch.device, args: argparse.Namespace, num_frames: int = 8) -> None:
    """The streaming corrector (each frame fused with the 2 before it, its latent read at the fused latency) against
    the corrector alone, frame by frame over one simulated recording at the adapters' size: medians over the frames
    of ``--repeats`` passes."""
    from evlatcorr.temporal import StreamingLatencyCorrector

    height, width = args.adapter_size
    seq = simulate("astronaut", num_frames=num_frames, height=height, width=width, exposure_us=20_000.0,
                   frame_interval_us=25_000.0, latency="constant", latency_us=4000.0, seed=0)
    frames = seq.frames("delayed").to(device).split()
    corrector = EventLatencyCorrector(num_bins=args.bins, num_candidates=args.candidates).to(device)
    stream = StreamingLatencyCorrector(corrector)
    alone, streamed = [], []
    with torch.no_grad():
        for frame in frames[:WARM_UP]:
            corrector(frame)
            stream(frame)
        for _ in range(args.repeats):
            stream.reset()
            for frame in frames:
                alone.append(timed(lambda f=frame: corrector(f), device)[0])
                streamed.append(timed(lambda f=frame: stream(f), device)[0])
    t_alone, t_stream = statistics.median(alone), statistics.median(streamed)
    print(f"[{device.type}] stream of {num_frames} frames at {width}x{height}: corrector alone "
          f"{t_alone * 1000:.1f} ms, streaming (fused with 2 frames before) {t_stream * 1000:.1f} ms per frame; "
          f"stream/alone: {t_stream / t_alone:.2f}")


def bench_spatial(device: torch.device, args: argparse.Namespace) -> None:
    """The spatial test-time fit on one frame: the default (a latency table read at each of 30 steps) against
    the previous objective (the linear integral re-read at each of 60 steps), in one run."""
    from evlatcorr.spatial import PolynomialLatency, fit_spatial_latency

    seq = simulate("astronaut", num_frames=1, height=args.height, width=args.width, exposure_us=args.exposure_us,
                   latency="constant", latency_us=4000.0, seed=0)
    frames = seq.frames("delayed").to(device)
    runs = {"table, 30 steps (default)": dict(steps=30, objective_edi="table"),
            "linear integral, 60 steps (previous)": dict(steps=60, objective_edi="linear")}
    for label, kw in runs.items():
        times = [timed(lambda kw=kw: fit_spatial_latency(frames, PolynomialLatency(), num_bins=100,
                                                         start_from_constant=True, **kw), device)[0]
                 for _ in range(args.repeats)]
        print(f"[{device.type}] spatial fit, {label}: median {statistics.median(times):.2f} s per frame "
              f"({len(frames.events)} events, median of {args.repeats})", flush=True)


def bench_memory(device: str, args: argparse.Namespace) -> None:
    """One constant correction in a fresh process (so nothing else raised its peak)."""
    command = [sys.executable, __file__, "--memory-child", "--device", device, "--events", str(args.events),
               "--height", str(args.height), "--width", str(args.width), "--bins", str(args.bins),
               "--exposure-us", str(args.exposure_us), "--candidates", str(args.candidates)]
    out = subprocess.run(command, capture_output=True, text=True, check=True).stdout
    print(out.strip())


def memory_child(device: torch.device, args: argparse.Namespace) -> None:
    from evlatcorr.events import Events
    from evlatcorr.frames import EventFrames

    g = torch.Generator().manual_seed(0)
    h, w, n, exposure = args.height, args.width, args.events, args.exposure_us
    blurry = torch.rand(1, 1, h, w, generator=g)
    t = torch.sort(torch.rand(n, generator=g, dtype=torch.float64) * 2 * exposure).values
    events = Events(torch.randint(0, w, (n,), generator=g), torch.randint(0, h, (n,), generator=g), t,
                    torch.randint(0, 2, (n,), generator=g), sensor_size=(h, w))
    frames = EventFrames(blurry, events, torch.tensor([0.0]), torch.tensor([exposure])).to(device)
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    corrector = EventLatencyCorrector(num_bins=args.bins, num_candidates=args.candidates)
    t0 = time.perf_counter()
    with torch.no_grad():
        corrector(frames)
    elapsed = time.perf_counter() - t0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    gpu = (f"; torch.cuda.max_memory_allocated: {torch.cuda.max_memory_allocated() / 2**20:.0f} MB"
           if device.type == "cuda" else "")
    print(f"[{device.type}] one constant correction, {w}x{h}, {n} events, {args.bins} bins, {args.candidates} "
          f"candidates: {elapsed:.2f} s; peak RSS: {peak:.0f} MB (before the correction: {before:.0f} MB){gpu}")


def _adapters() -> dict[str, torch.nn.Module]:
    from evlatcorr.adapters import EFNetAdapter, GEMAdapter, REFIDAdapter

    def make(cls, **kw):
        try:
            return cls(checkpoint="default", **kw)
        except FileNotFoundError:
            return cls(**kw)

    return {"EFNet": make(EFNetAdapter), "GEM": make(GEMAdapter), "REFID 4+1": make(REFIDAdapter, m=4, n=1)}


def bench_adapters(device: torch.device, args: argparse.Namespace) -> None:
    height, width = args.adapter_size
    seq = simulate("astronaut", num_frames=2, height=height, width=width, exposure_us=20_000.0,
                   frame_interval_us=25_000.0, latency="constant", latency_us=4000.0, seed=0)
    frames, pairs = seq.frames("delayed").to(device), seq.pairs("delayed").to(device)
    frame = frames.replace(blurry=frames.blurry[:1], events=frames.events.sample(0),
                           exposure_start=frames.exposure_start[:1], exposure_end=frames.exposure_end[:1],
                           sharp=None, meta={})
    corrector = EventLatencyCorrector(num_bins=args.bins, num_candidates=args.candidates).to(device)
    print(f"[{device.type}] adapters at {width}x{height}, one frame ({len(frame.events)} events), "
          f"median of {args.repeats}")
    with torch.no_grad():
        for _ in range(WARM_UP):
            corrector(frame)
        t_corr = statistics.median(timed(lambda: corrector(frame), device)[0] for _ in range(args.repeats))
        print(f"[{device.type}] constant corrector: {t_corr * 1000:.1f} ms")
        for name, adapter in _adapters().items():
            adapter = adapter.to(device).eval()
            batch = pairs if name.startswith("REFID") else frame
            for _ in range(WARM_UP):
                adapter(batch)
            t = statistics.median(timed(lambda a=adapter, b=batch: a(b), device)[0] for _ in range(args.repeats))
            print(f"[{device.type}] {name} forward: {t * 1000:.1f} ms; corrector/{name}: {100 * t_corr / t:.1f} %")


def bench_device(device: torch.device, args: argparse.Namespace) -> None:
    blurry, ev, start, end = make_frame(args.height, args.width, args.exposure_us, 4000.0, device)
    print(f"[{device.type}] {len(ev)} events in the frame's window")

    def one_pass(refine: bool = False, score: str = RATIO_SCORE, method: str = "continuous"):
        return search_constant_latency(blurry, ev, start, end, 0.2, args.bins, None, args.candidates, refine=refine,
                                       score=score, method=method)

    one_pass()  # warm-up (allocator, kernels)
    fast = [timed(one_pass, device) for _ in range(args.repeats)]
    result = fast[-1][1]
    # the one-pass search never scores windows past the last event: the naive loop gets the same candidates
    candidates = result.candidates[0][torch.isfinite(result.etf[0].cpu())].to(device)
    slow = [timed(lambda: naive_search(blurry, ev, start, end, candidates, 0.2, args.bins), device)
            for _ in range(args.naive_repeats)]
    refined = [timed(lambda: one_pass(True), device) for _ in range(args.repeats)]
    fast_latency, slow_latency = float(result.latency[0]), float(slow[-1][1])
    t_fast = statistics.median(t for t, _ in fast)
    t_slow = statistics.median(t for t, _ in slow)
    t_refined = statistics.median(t for t, _ in refined)
    print(f"[{device.type}] one-pass search: median {t_fast * 1000:.1f} ms over {args.repeats} "
          f"({1 / t_fast:.1f} frames/s); with sub-candidate refinement {t_refined * 1000:.1f} ms "
          f"(estimate {float(refined[-1][1].latency[0]):.0f} us)")
    print(f"[{device.type}] naive loop:      median {t_slow * 1000:.1f} ms over {args.naive_repeats}")
    default = [timed(lambda: one_pass(True, DEFAULT_SCORE), device) for _ in range(args.repeats)]
    t_default = statistics.median(t for t, _ in default)
    print(f"[{device.type}] default search ({DEFAULT_SCORE}, its defaults): median {t_default * 1000:.1f} ms (estimate "
          f"{float(default[-1][1].latency[0]):.0f} us)")
    if DEFAULT_SCORE != "consensus":  # the previous default, in this run: what the learned reader costs
        consensus = [timed(lambda: one_pass(True, "consensus"), device) for _ in range(args.repeats)]
        t_consensus = statistics.median(t for t, _ in consensus)
        print(f"[{device.type}] consensus score, refined: median {t_consensus * 1000:.1f} ms (estimate "
              f"{float(consensus[-1][1].latency[0]):.0f} us); {DEFAULT_SCORE}/consensus: "
              f"{t_default / t_consensus:.2f}x")
    # the previous method (binned prefix-sum table, trapezoidal rule), the same calls, in this run
    binned = [timed(lambda: one_pass(True, DEFAULT_SCORE, "binned"), device) for _ in range(args.repeats)]
    t_binned = statistics.median(t for t, _ in binned)
    print(f"[{device.type}] binned table (previous method), default search: median {t_binned * 1000:.1f} ms "
          f"(estimate {float(binned[-1][1].latency[0]):.0f} us); continuous/binned speed-up: "
          f"{t_binned / t_default:.2f}x")
    print(f"[{device.type}] same argmin: {abs(fast_latency - slow_latency) < 1e-6} "
          f"({fast_latency:.1f} us vs {slow_latency:.1f} us)")
    print(f"[{device.type}] ratio: {t_slow / t_fast:.1f}")


if __name__ == "__main__":
    main()
