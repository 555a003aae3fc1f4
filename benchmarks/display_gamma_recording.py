"""A real recording's frames encoded for display: how far the constant latency moves, and what ``frame_gamma`` gives.

Every frame with at least ``--min-events`` events in its window is corrected alone by the default constant corrector
three ways: as read (a DAVIS's frames are linear), encoded for display (``linear ** (1 / gamma)``, as a PNG export or a
video frame holds them) and the encoded frames with ``EventLatencyCorrector(frame_gamma=gamma)``. Also the
recording's θ from two-frame consistency (``recording_threshold``) as read and encoded. No ground truth: the figures
say how much the estimate moves, not which is right (EDI's model is linear: the frames as read).

    python benchmarks/display_gamma_recording.py                        # the shared low-light cradle recording
    python benchmarks/display_gamma_recording.py REC.aedat4 --threshold 0.4 --gamma 2.2
"""

from __future__ import annotations

import _setup  # noqa: F401  first: the repository on sys.path and 2 MB CPU pages, before torch loads

# isort: split

import argparse  # noqa: E402
import statistics  # noqa: E402
import warnings  # noqa: E402
from pathlib import Path  # noqa: E402

from evlatcorr import EventLatencyCorrector  # noqa: E402
from evlatcorr.gamma import check_frame_gamma, linear_frames  # noqa: E402
from evlatcorr.io import open_recording  # noqa: E402
from evlatcorr.restore import recording_threshold  # noqa: E402

DEFAULT_RECORDING = _setup.shared_recording("cradle_lowlight.aedat4")


def _summary(latencies: list[float]) -> str:
    return f"median {statistics.median(latencies):.0f} us ({min(latencies):.0f}-{max(latencies):.0f})"


def main(argv: list[str] | None = None) -> dict[str, list[float]]:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("recording", type=Path, nargs="?", default=DEFAULT_RECORDING)
    p.add_argument("--threshold", type=float, default=0.52, help="θ of the recording (default: the cradle's, 0.52)")
    p.add_argument("--gamma", type=float, default=2.2, help="the display encoding's gamma (default 2.2)")
    p.add_argument("--min-events", type=int, default=5000, help="frames with at least this many events (default 5000)")
    p.add_argument("--after-us", type=float, default=20_000.0, help="events read past each exposure (default 20000)")
    args = p.parse_args(argv)
    try:
        gamma = check_frame_gamma(args.gamma)
    except ValueError as err:
        p.error(str(err))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the reader's notes on the last frames' windows
        frames = [f for f in open_recording(args.recording, after_us=args.after_us) if len(f.events) >= args.min_events]
        if not frames:
            p.error(f"{args.recording}: no frame with at least {args.min_events} events")
        encoded = [linear_frames(f, 1 / gamma) for f in frames]
        theta_encoded = recording_threshold(open_recording(args.recording, after_us=args.after_us,
                                                           frame_gamma=1 / gamma))
        plain, given = EventLatencyCorrector(threshold=args.threshold), EventLatencyCorrector(threshold=args.threshold,
                                                                                               frame_gamma=gamma)
        results = {
            "as read": [float(plain(f).latency.mean()) for f in frames],
            "encoded": [float(plain(f).latency.mean()) for f in encoded],
            f"encoded, frame_gamma={gamma:g}": [float(given(f).latency.mean()) for f in encoded],
        }
        if theta_encoded is not None:
            own = EventLatencyCorrector(threshold=float(theta_encoded))
            results[f"encoded, its own θ {float(theta_encoded):.3f}"] = [float(own(f).latency.mean()) for f in encoded]
    print(f"{args.recording.name}: {len(frames)} frames with at least {args.min_events} events, θ {args.threshold}, "
          f"gamma {gamma:g}")
    for name, latencies in results.items():
        print(f"{name}: {_summary(latencies)}")
    return results


if __name__ == "__main__":
    main()
