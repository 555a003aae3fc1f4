"""Real data, no ground truth: latency correction on a low-light DAVIS346 recording, seen and measured.

    python benchmarks/real_data.py                                   # the shared cradle recording
    python benchmarks/real_data.py RECORDING.aedat4 --frames 2 10 --out docs --threshold 0.4

For every frame: the constant latency, and the two-frame disagreement (:mod:`evlatcorr.consistency`)
with the stamped and with the corrected events: how much this frame's and the next frame's EDI
reconstructions differ at the middle of the gap between their exposures. Nothing in it is what
the latency search minimises (the sharpness of one frame), and it needs no ground truth: with the
right latency both frames read the events of their own exposures and agree.

Writes ``<out>/real_data_latency.csv`` (one row per frame), ``<out>/real_data.md`` (the summary)
and ``<out>/real_data.png``: for each frame in ``--frames``, crops around the moving object of the
blurry frame, EDI with the stamped events, EDI with the corrected events, and EFNet and GEM (the
shipped weights) with the corrected events, plus each frame's score against the candidate latency.
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse
import csv
import math
import statistics
import time
import warnings
from pathlib import Path

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import torch  # noqa: E402

from evlatcorr import EventLatencyCorrector, edi_deblur  # noqa: E402
from evlatcorr.consistency import pair_disagreement  # noqa: E402
from evlatcorr.io import open_recording  # noqa: E402
from evlatcorr.pair_evidence import pair_log_odds  # noqa: E402
from evlatcorr.restore import build_model, has_events, pair_frames, pair_reach_us, recording_threshold  # noqa: E402
from evlatcorr.temporal import frame_evidence, fuse_latencies  # noqa: E402

DEFAULT = _setup.shared_recording("cradle_lowlight.aedat4")
MOVING_EVENTS = 5000  # a frame "moves" when its exposure holds at least this many events


def busiest_crop(events, size: tuple[int, int], crop: int = 96) -> tuple[slice, slice]:
    """The ``crop`` x ``crop`` window with the most events (the moving object)."""
    height, width = size
    crop = min(crop, height, width)
    counts = torch.zeros(height, width).index_put_((events.y, events.x), torch.ones(len(events)), accumulate=True)
    smooth = torch.nn.functional.avg_pool2d(counts[None, None], crop, stride=4)[0, 0]
    k = int(torch.argmax(smooth))
    y0, x0 = (k // smooth.shape[1]) * 4, (k % smooth.shape[1]) * 4
    return slice(y0, y0 + crop), slice(x0, x0 + crop)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("recording", type=Path, nargs="?", default=DEFAULT)
    parser.add_argument("--frames", type=int, nargs="+", default=[2, 3, 10], help="frames to show")
    parser.add_argument("--threshold", type=float, help="contrast threshold (default: estimated, two-frame "
                                                        "consistency)")
    parser.add_argument("--out", type=Path, default=Path("docs"))
    args = parser.parse_args()
    if args.threshold is not None and not (math.isfinite(args.threshold) and args.threshold > 0):
        parser.error(f"--threshold must be a positive number, got {args.threshold}")
    if not args.recording.exists():
        parser.error(f"{args.recording}: no such file")
    if not args.frames or min(args.frames) < 0:
        parser.error(f"--frames takes frame numbers >= 0, got {args.frames}")
    torch.set_num_threads(max(1, torch.get_num_threads()))

    rec = open_recording(args.recording)
    shown = [i for i in args.frames if i < len(rec)]
    if not shown:
        parser.error(f"--frames {args.frames}: the recording has {len(rec)} frames (0-{len(rec) - 1})")
    args.frames = shown
    _setup.check_out_folder(parser, args.out)
    t0 = time.perf_counter()
    theta = args.threshold if args.threshold is not None else recording_threshold(rec)
    print(f"contrast threshold {theta:.3f} ({'given' if args.threshold else 'estimated'}, "
          f"{time.perf_counter() - t0:.0f} s)", flush=True)
    corrector = EventLatencyCorrector(threshold=theta)
    networks = {name: build_model(name) for name in ("efnet", "gem")}
    rec.after_us = pair_reach_us(rec)
    rows, shown, evidence = [], [], {}
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the last frame's window runs past the end of the file
        for batch, pair in pair_frames(rec):
            i = batch.meta["frame"]
            moving = len(batch.events.window(batch.exposure_start, batch.exposure_end))
            row = {"frame": i, "events_in_exposure": moving, "threshold": round(theta, 4)}
            if not has_events(batch):
                rows.append(row)
                continue
            out = corrector(batch)
            latency = float(out.latency.mean())
            row["latency_us"] = round(latency, 1)
            evidence[i] = (*frame_evidence(out)[0], pair)
            if pair is not None:
                stamped = float(pair_disagreement(pair, theta, 0.0))
                corrected = float(pair_disagreement(pair, theta, latency))
                row.update(disagreement_stamped=round(stamped, 5), disagreement_corrected=round(corrected, 5))
            rows.append(row)
            print(row, flush=True)
            if i in args.frames:
                plain = edi_deblur(batch.blurry, batch.events, batch.exposure_start, batch.exposure_end, theta)
                with torch.no_grad():
                    restored = {name: net(out).output for name, net in networks.items()}
                shown.append((i, batch, plain, out, latency, restored))

    add_fused(rows, evidence, theta)
    with open(args.out / "real_data_latency.csv", "w", newline="") as fh:
        fields = ["frame", "events_in_exposure", "threshold", "latency_us", "disagreement_stamped",
                  "disagreement_corrected", "fused_latency_us", "disagreement_fused", "paired_latency_us",
                  "disagreement_paired"]
        w = csv.DictWriter(fh, fieldnames=fields)
        w.writeheader()
        w.writerows(rows)
    summary = summarize(rows, args.recording.name, theta)
    (args.out / "real_data.md").write_text(_page_header(args) + summary)
    print(summary)
    plot(shown, args, theta)
    print(f"wrote {args.out / 'real_data.png'}, {args.out / 'real_data.md'} and {args.out / 'real_data_latency.csv'}")


def add_fused(rows: list[dict], evidence: dict, theta: float) -> None:
    """Each estimated frame's latency fused with 2 frames either side (:func:`evlatcorr.temporal.fuse_latencies`):
    from the reader's evidence alone (``fused_latency_us``), and with each pair of consecutive frames' agreement too
    (``paired_latency_us``, :func:`evlatcorr.pair_evidence.pair_log_odds`, as ``evlatcorr correct`` does by
    default); and the frame's pair's disagreement with each."""
    frames = sorted(evidence)
    if not frames:
        return
    own = torch.tensor([evidence[i][0] for i in frames], dtype=torch.float64)
    candidates, log_p = [evidence[i][1] for i in frames], [evidence[i][2] for i in frames]
    pairs = [None if evidence[i][3] is None or evidence[i][2] is None else
             pair_log_odds(evidence[i][3], theta, evidence[i][1]) for i in frames]
    estimates = {"fused": fuse_latencies(own, candidates, log_p),
                 "paired": fuse_latencies(own, candidates, log_p, pair_log_odds=pairs)}
    by_frame = {r["frame"]: r for r in rows}
    for name, fused in estimates.items():
        for i, latency in zip(frames, fused.tolist()):
            row, pair = by_frame[i], evidence[i][3]
            row[f"{name}_latency_us"] = round(latency, 1)
            if pair is not None:
                row[f"disagreement_{name}"] = round(float(pair_disagreement(pair, theta, latency)), 5)


def _page_header(args: argparse.Namespace) -> str:
    """What ``real_data.md`` holds, and the command that wrote it."""
    command = ("python benchmarks/real_data.py" + ("" if args.recording == DEFAULT else f" {args.recording}")
               + ("" if args.threshold is None else f" --threshold {args.threshold:g}"))
    return (f"# Latency correction on a real recording: {args.recording.name}\n\n"
            f"Written by `{command}`. A real recording has no sharp frame to score "
            "against: each pair of consecutive frames is scored by how much their EDI reconstructions disagree at the "
            "middle of the gap between the two exposures (`evlatcorr.consistency.pair_disagreement`: the mean "
            "absolute difference of their log intensities; lower is more consistent), with the events as stamped and "
            "corrected by the frame's latency. `real_data_latency.csv` beside it has every frame's figures.\n\n")


def summarize(rows: list[dict], name: str, theta: float) -> str:
    """Median two-frame disagreement over the moving frames' pairs, stamped vs corrected."""
    paired = [r for r in rows if "disagreement_corrected" in r and r["events_in_exposure"] >= MOVING_EVENTS]
    if not paired:
        return f"{name}: no moving frame pair\n"
    stamped = [r["disagreement_stamped"] for r in paired]
    corrected = [r["disagreement_corrected"] for r in paired]
    better = sum(c < s for s, c in zip(stamped, corrected))
    latencies = [r["latency_us"] for r in paired]
    table = (f"| {name} (θ = {theta:.3f}) | pairs | latency µs, median (min-max) | two-frame disagreement, stamped "
             f"| corrected | pairs where correction lowers it |\n| --- | --- | --- | --- | --- | --- |\n"
             f"| moving frames (≥ {MOVING_EVENTS} events in the exposure), each frame alone | {len(paired)} | "
             f"{statistics.median(latencies):.0f} ({min(latencies):.0f}-{max(latencies):.0f}) | "
             f"{statistics.median(stamped):.4f} | {statistics.median(corrected):.4f} | {better} of {len(paired)} |\n")
    for name, what in (("fused", "the same, latency fused with 2 frames either side"),
                       ("paired", "the same, fused with each pair's agreement too (`evlatcorr correct`'s default)")):
        fused = [r for r in paired if f"disagreement_{name}" in r]
        if len(fused) != len(paired):
            continue
        lat = [r[f"{name}_latency_us"] for r in fused]
        dis = [r[f"disagreement_{name}"] for r in fused]
        table += (f"| {what} | {len(fused)} | {statistics.median(lat):.0f} ({min(lat):.0f}-{max(lat):.0f}) | "
                  f"{statistics.median(stamped):.4f} | {statistics.median(dis):.4f} | "
                  f"{sum(d < s for s, d in zip(stamped, dis))} of {len(fused)} |\n")
    return table


def plot(shown: list, args: argparse.Namespace, theta: float) -> None:
    columns = 6
    fig, axes = plt.subplots(len(shown), columns, figsize=(3.0 * columns, 3.2 * len(shown)), squeeze=False)
    for row, (i, batch, plain, out, latency, restored) in zip(axes, shown):
        ys, xs = busiest_crop(batch.events.window(batch.exposure_start, batch.exposure_end), batch.sensor_size)
        gain = 1.0 / max(float(batch.blurry[0, 0, ys, xs].quantile(0.99)), 1e-3)  # display only: the scene is dark
        panels = [(batch.blurry, f"frame {i}: blurry"), (plain, "EDI, stamped events"),
                  (out.latent, f"EDI, corrected by {latency / 1000:.2f} ms"),
                  (restored["efnet"], "EFNet, corrected events"), (restored["gem"], "GEM, corrected events")]
        for ax, (img, title) in zip(row[:5], panels):
            ax.imshow((img[0].mean(0)[ys, xs] * gain).clamp(0, 1).numpy(), cmap="gray", vmin=0, vmax=1)
            ax.set_title(title, fontsize=9)
            ax.axis("off")
        cand, curve = out.meta["etf_curve"]
        row[5].plot(cand[0].numpy() / 1000, curve[0].numpy())
        row[5].axvline(latency / 1000, color="r", ls="--", label="estimate")
        row[5].set_xlabel("candidate latency (ms)")
        row[5].set_ylabel(f"{out.meta.get('score', 'etf')} score (lower = sharper)", fontsize=8)
        row[5].legend(fontsize=8)
    fig.suptitle(f"{args.recording.name}: constant latency correction per frame (θ = {theta:.2f}; crops around "
                 "the moving ball, brightened for display)")
    fig.tight_layout()
    fig.savefig(args.out / "real_data.png", dpi=80)


if __name__ == "__main__":
    main()
