"""The ``evlatcorr`` command line: correct, deblur, simulate and inspect event recordings.

Exit codes: 0 success, 2 bad input (unreadable or unsupported file, bad option), 1 other errors.
"""

from __future__ import annotations

import argparse
import csv
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

__all__ = ["main"]

EXIT_OK, EXIT_ERROR, EXIT_BAD_INPUT = 0, 1, 2


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="evlatcorr",
        description="Event-camera latency correction for event-guided deblurring and frame interpolation.",
        epilog="Formats read: AEDAT4 (DAVIS), evlatcorr HDF5, event_utils HDF5, GEM npz pairs, HighREV video folders. "
               "Times are microseconds.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    c = sub.add_parser("correct", help="estimate latency per frame and write corrected events + a CSV report",
                       description="Estimate the latency of every frame, remove it from the events and write them "
                                   "(event_utils input stays event_utils, anything else becomes evlatcorr HDF5), "
                                   "with a per-frame CSV report next to OUT.")
    c.add_argument("input", type=Path, help="recording to correct")
    c.add_argument("output", type=Path, help="corrected recording to write (.h5)")
    c.add_argument("--mode", choices=("constant", "spatial"), default="constant")
    c.add_argument("--curve", type=Path, help="trained latency curve checkpoint (mode spatial)")
    _common(c)

    d = sub.add_parser("deblur", help="write EDI deblurred frames as PNG",
                       description="Deblur every frame with EDI and write PNGs (blurry and EDI) into OUTDIR.")
    d.add_argument("input", type=Path)
    d.add_argument("outdir", type=Path)
    d.add_argument("--correct", action="store_true", help="correct the latency first (constant per frame)")
    _common(d)

    s = sub.add_parser("simulate", help="write a simulated recording with known latency (evlatcorr HDF5)")
    s.add_argument("output", type=Path)
    s.add_argument("--image", default="astronaut", help="scikit-image photograph (default: astronaut)")
    s.add_argument("--frames", type=int, default=4)
    s.add_argument("--size", type=int, nargs=2, default=(260, 346), metavar=("H", "W"))
    s.add_argument("--exposure-us", type=float, default=20000.0)
    s.add_argument("--interval-us", type=float, default=25000.0, help="time between exposure starts")
    s.add_argument("--latency-model", choices=("none", "constant", "intensity"), default="constant")
    s.add_argument("--latency-us", type=float, default=4000.0, help="constant latency")
    s.add_argument("--seed", type=int, default=0)

    i = sub.add_parser("info", help="summarise a recording")
    i.add_argument("input", type=Path)
    i.add_argument("--exposure-us", type=float, help="exposure for files that only stamp frame times")
    return p


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--threshold", default="0.2", help="contrast threshold, or 'auto' (default: 0.2)")
    p.add_argument("--num-bins", type=int, default=500, help="EDI sub-intervals per exposure (default: 500)")
    p.add_argument("--search-us", type=float, nargs=2, metavar=("LOW", "HIGH"),
                   help="latency search range in us (default: 0 to the exposure time)")
    p.add_argument("--exposure-us", type=float, help="exposure for files that only stamp frame times")


def _threshold(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise ValueError(f"--threshold must be a number or 'auto', got {text!r}") from None
    if value <= 0:
        raise ValueError(f"--threshold must be positive, got {value}")
    return value


def _open(args: argparse.Namespace, after_us: float | None = None):
    from evlatcorr.io import EventUtilsRecording, open_recording

    rec = open_recording(args.input, after_us=after_us)
    if isinstance(rec, EventUtilsRecording) and getattr(args, "exposure_us", None) is not None:
        rec.exposure_us = args.exposure_us
    return rec


def _corrector(args: argparse.Namespace, mode: str = "constant", curve: Path | None = None):
    from evlatcorr import EventLatencyCorrector

    kwargs = {}
    if curve is not None:
        kwargs["curve"] = str(curve)
    return EventLatencyCorrector(mode=mode, threshold=_threshold(args.threshold), num_bins=args.num_bins,
                                 search_range=tuple(args.search_us) if args.search_us else None, **kwargs)


def _progress(iterable, total: int | None, desc: str):
    from tqdm import tqdm

    return tqdm(iterable, total=total, desc=desc, unit="frame", file=sys.stderr, disable=not sys.stderr.isatty())


def cmd_correct(args: argparse.Namespace) -> int:
    import h5py

    from evlatcorr.io import EventUtilsRecording, EventWriter, write_event_utils
    from evlatcorr.io.h5 import _write_header, atomic_path

    corrector = _corrector(args, args.mode, args.curve)
    high = args.search_us[1] if args.search_us else None
    rec = _open(args, after_us=high)
    device = torch.device(args.device)
    rows, latencies, starts, ends, images = [], [], [], [], []
    for batch in _progress(rec, len(rec), "correct"):
        out = corrector(batch.to(device))
        lat_map = out.latency[0, 0].cpu()
        cand, etf = out.meta.get("etf_curve", (None, None))
        rows.append({
            "frame": batch.meta["frame"], "exposure_start_us": f"{float(batch.exposure_start):.1f}",
            "exposure_end_us": f"{float(batch.exposure_end):.1f}", "latency_us": f"{float(lat_map.mean()):.1f}",
            "latency_min_us": f"{float(lat_map.min()):.1f}", "latency_max_us": f"{float(lat_map.max()):.1f}",
            "score": f"{float(etf[torch.isfinite(etf)].min()):.5f}" if etf is not None and bool(
                torch.isfinite(etf).any()) else "",
            "confidence": f"{float(out.meta['latency_confidence'][0]):.3f}" if "latency_confidence" in out.meta
            else "",
            "fallback": int(bool(out.meta["latency_fallback"][0])) if "latency_fallback" in out.meta else "",
            "events_in_window": len(batch.events),
        })
        latencies.append(lat_map)
        starts.append(float(batch.exposure_start))
        ends.append(float(batch.exposure_end))
        images.append(batch.blurry[0].cpu().numpy())
    if not rows:
        raise ValueError(f"{args.input}: no frames")
    corrected = _corrected_stream(rec, np.array(starts), latencies)
    report = args.output.with_suffix(".csv")
    if isinstance(rec, EventUtilsRecording):
        from evlatcorr.events import Events

        chunks = list(corrected)
        cat = np.concatenate(chunks) if chunks else np.zeros(0)
        ev = Events.from_numpy(cat, sensor_size=rec.sensor_size) if len(cat) else None
        if ev is None:
            raise ValueError(f"{args.input}: no events")
        write_event_utils(args.output, ev, like=rec)
    else:
        with atomic_path(args.output) as tmp, h5py.File(tmp, "w") as f:
            _write_header(f, rec.sensor_size, source=str(args.input), corrected_mode=args.mode)
            writer = EventWriter(f, "events")
            for chunk in corrected:
                writer.append(chunk["x"], chunk["y"], chunk["t"], chunk["p"])
            f.create_dataset("frames/blurry", data=np.stack(images), compression="lzf",
                             chunks=(1, *images[0].shape))
            f["frames/exposure_start"] = np.array(starts)
            f["frames/exposure_end"] = np.array(ends)
            f["frames/estimated_latency"] = np.array([float(m.mean()) for m in latencies], dtype=np.float32)
    with atomic_path(report) as tmp:
        with open(tmp, "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    print(f"wrote {args.output} and {report} ({len(rows)} frames, median latency "
          f"{np.median([float(r['latency_us']) for r in rows]):.0f} us)")
    return EXIT_OK


def _corrected_stream(rec, starts: np.ndarray, latencies: list[torch.Tensor]):
    """Corrected events in time order, chunk by chunk.

    Each event takes the latency of the frame whose interval ``[start_i, start_{i+1})`` holds its
    stamp (at its pixel). Shifted events are held back until no later chunk can precede them.
    """
    maps = torch.stack(latencies).numpy()  # (F, H, W)
    hold_back = float(maps.max()) - float(min(0.0, maps.min())) + 1.0
    width = rec.sensor_size[1]
    pending: list[np.ndarray] = []
    for chunk in rec.iter_event_chunks():
        if not len(chunk):
            continue
        frame = np.clip(np.searchsorted(starts, chunk["t"], side="right") - 1, 0, len(starts) - 1)
        shifted = chunk.copy()
        shifted["t"] = chunk["t"] - maps.reshape(len(starts), -1)[frame, chunk["y"].astype(np.int64) * width
                                                                  + chunk["x"].astype(np.int64)]
        pending.append(shifted)
        merged = np.concatenate(pending)
        merged = merged[np.argsort(merged["t"], kind="stable")]
        safe = float(chunk["t"][-1]) - hold_back
        cut = int(np.searchsorted(merged["t"], safe, side="left"))
        if cut:
            yield merged[:cut]
        pending = [merged[cut:]]
    if pending and len(pending[0]):
        yield pending[0]


def cmd_deblur(args: argparse.Namespace) -> int:
    from PIL import Image

    from evlatcorr import edi_deblur

    rec = _open(args, after_us=args.search_us[1] if args.search_us else None)
    corrector = _corrector(args) if args.correct else None
    args.outdir.mkdir(parents=True, exist_ok=True)
    device = torch.device(args.device)
    count = 0

    def save(t: torch.Tensor, path: Path) -> None:
        a = (t.clamp(0, 1).cpu().numpy() * 255 + 0.5).astype(np.uint8)
        Image.fromarray(a[0] if a.shape[0] == 1 else a.transpose(1, 2, 0)).save(path)

    for batch in _progress(rec, len(rec), "deblur"):
        batch = batch.to(device)
        i = batch.meta["frame"]
        if corrector is not None:
            out = corrector(batch)
            latent = out.latent
        else:
            latent = edi_deblur(batch.blurry, batch.events, batch.exposure_start, batch.exposure_end,
                                _threshold(args.threshold), None, args.num_bins)
        save(batch.blurry[0], args.outdir / f"frame_{i:05d}_blurry.png")
        save(latent[0], args.outdir / f"frame_{i:05d}_edi{'_corrected' if args.correct else ''}.png")
        count += 1
    print(f"wrote {count} frames to {args.outdir}")
    return EXIT_OK


def cmd_simulate(args: argparse.Namespace) -> int:
    from evlatcorr.io import write_sequence
    from evlatcorr.simulate import simulate

    seq = simulate(args.image, num_frames=args.frames, height=args.size[0], width=args.size[1],
                   exposure_us=args.exposure_us, frame_interval_us=args.interval_us, latency=args.latency_model,
                   latency_us=args.latency_us, seed=args.seed)
    write_sequence(args.output, seq)
    print(f"wrote {args.output}: {args.frames} frames {args.size[1]}x{args.size[0]}, "
          f"{len(seq.delayed_events)} events, latency {args.latency_model} "
          f"({float(seq.true_latency.mean()):.0f} us mean)")
    return EXIT_OK


def cmd_info(args: argparse.Namespace) -> int:
    rec = _open(args)
    for key, value in rec.info().items():
        print(f"{key:40s} {value}")
    return EXIT_OK


def main(argv: Sequence[str] | None = None) -> int:
    from evlatcorr.io import RecordingError

    args = _parser().parse_args(argv)
    command = {"correct": cmd_correct, "deblur": cmd_deblur, "simulate": cmd_simulate, "info": cmd_info}
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("default")
            return command[args.command](args)
    except (RecordingError, ValueError, FileNotFoundError) as exc:
        print(f"evlatcorr {args.command}: error: {exc}", file=sys.stderr)
        return EXIT_BAD_INPUT


if __name__ == "__main__":
    sys.exit(main())
