"""The ``evlatcorr`` command's arguments: one sub-command each for correct, deblur, interpolate, simulate and info."""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from evlatcorr.gamma import frame_gamma_argument
from evlatcorr.restore import INTERPOLATION_MODELS, MODELS
from evlatcorr.temporal import DEFAULT_FUSED_FRAMES

__all__ = ["build_parser"]


_EXPOSURE_HELP = ("exposure, us, for files that only stamp frame times (event_utils HDF5 whose images carry a "
                  "timestamp alone, ROS1 bags without the driver's exposure topic); other recordings keep their own")


def _float_or_nan(text: str) -> float:
    """``text`` as a float; NaN where it is not a number (refused as such by the caller's check)."""
    try:
        return float(text)
    except ValueError:
        return math.nan


def _finite_us(text: str) -> float:
    """A finite number of µs (argparse's ``float`` takes ``nan`` and ``inf``)."""
    value = _float_or_nan(text)
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number of us, got {text!r}")
    return value


def _positive_us(text: str) -> float:
    """A positive, finite number of µs (an exposure)."""
    value = _finite_us(text)
    if value <= 0:
        raise argparse.ArgumentTypeError(f"must be a positive number of us, got {text!r}")
    return value


def _num_bins(text: str) -> int:
    """EDI's sub-intervals of an exposure: a whole number >= 2, refused before any reading."""
    try:
        value = int(text)
    except ValueError:
        value = 0
    if value < 2:
        raise argparse.ArgumentTypeError(f"must be a whole number >= 2, got {text!r}")
    return value


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="evlatcorr",
        description="Event-camera latency correction for event-guided deblurring and frame interpolation.",
        epilog="Formats read: AEDAT4 (DAVIS), ROS1 bags (rpg_dvs_ros), evlatcorr HDF5, event_utils HDF5, GEM npz "
               "pairs, HighREV video folders. Times are microseconds.",
    )
    sub = p.add_subparsers(dest="command", required=True, metavar="COMMAND")

    c = sub.add_parser("correct", help="estimate latency per frame and write corrected events + a CSV report",
                       description="Estimate the latency of every frame, remove it from the events and write them "
                                   "(event_utils input stays event_utils, anything else becomes evlatcorr HDF5), "
                                   "with a per-frame CSV report and a figure of the latencies next to OUT.")
    c.add_argument("input", type=Path, help="recording to correct")
    c.add_argument("output", type=Path, help="corrected recording to write (.h5)")
    c.add_argument("--report", type=Path, help="per-frame CSV report (default: OUT with the suffix .csv)")
    c.add_argument("--figure", type=Path, help="every frame's latency and events drawn over time, a PNG (default: "
                                               "the report with the suffix .png)")
    c.add_argument("--no-figure", action="store_true", help="write no figure")
    c.add_argument("--mode", choices=("constant", "spatial"), default="constant",
                   help="one latency per frame (default), or a per-pixel map from a polynomial of intensity (without "
                        "--curve: constant mode's latencies plus a slope over intensity fitted to the first pairs' "
                        "agreement)")
    c.add_argument("--curve", type=Path, help="trained latency curve checkpoint (mode spatial)")
    _fuse_frames_option(c, "constant mode (and spatial mode without --curve)",
                        "N frames either side too (a recording's latency changes slowly",
                        "the report")
    c.add_argument("--no-pairs", action="store_true",
                   help="fuse the reader's evidence alone: without each pair of consecutive frames' agreement (with "
                        "--fuse-frames in constant mode; the report's pair_latency_us is where a pair agrees best); "
                        "in spatial mode without --curve, fit the paper's polynomial to each frame's sharpness "
                        "instead of adding the recording's slope over intensity, fitted to its first pairs, to "
                        "constant mode's latencies")
    _common_options(c)

    d = sub.add_parser("deblur", help="deblur every frame with EDI or a network; PNGs, a side-by-side GIF, a CSV",
                       description="Deblur every frame with --model and write into OUTDIR: PNGs per frame (blurry, "
                                   "the model's output with the stamped events and, with --correct, with the "
                                   "corrected events), side_by_side.gif (blurry | uncorrected | corrected) and "
                                   "frames.csv (latency, threshold, confidence, the learned reader's spread, "
                                   "events, time per frame) and, with --correct, latency.png (every frame's latency "
                                   "drawn over time). OUTDIR is "
                                   "written under a temporary name and appears only when every frame is done.")
    d.add_argument("input", type=Path, help="recording to deblur")
    d.add_argument("outdir", type=Path, help="folder to write")
    _restore_options(d, MODELS)

    i = sub.add_parser("interpolate", help="frames between exposures with EDI or REFID; PNGs, a GIF, a CSV",
                       description="Interpolate --num frames evenly between each pair of consecutive exposures "
                                   "and write them into OUTDIR as PNGs (with the stamped and, with --correct, the "
                                   "corrected events), side_by_side.gif, frames.csv (one row per pair) and, with "
                                   "--correct, latency.png.")
    i.add_argument("input", type=Path, help="recording to interpolate")
    i.add_argument("outdir", type=Path, help="folder to write")
    i.add_argument("--num", type=int, default=1, help="frames between two exposures (default: 1)")
    _restore_options(i, INTERPOLATION_MODELS)

    s = sub.add_parser("simulate", help="write a simulated recording with known latency (evlatcorr HDF5)",
                       description="Simulate a camera moving over a photograph: blurry and sharp frames, ideal "
                                   "events and events stamped late by a known latency, written as evlatcorr HDF5 "
                                   "(the input of every other command).")
    s.add_argument("output", type=Path, help="file to write (.h5)")
    s.add_argument("--image", default="astronaut", help="scikit-image photograph (default: astronaut)")
    s.add_argument("--frames", type=int, default=4, help="blurry frames (default: 4)")
    s.add_argument("--size", type=int, nargs=2, default=(260, 346), metavar=("H", "W"),
                   help="sensor size (default: 260 346, a DAVIS346)")
    s.add_argument("--exposure-us", type=_positive_us, default=20000.0, help="exposure, us (default: 20000)")
    s.add_argument("--interval-us", type=float, default=25000.0,
                   help="time between exposure starts, us (default: 25000)")
    s.add_argument("--latency-model", choices=("none", "constant", "intensity"), default="constant",
                   help="none (ideal events), constant (every event --latency-us late; the default) or intensity "
                        "(a photoreceptor low-pass whose lag grows as the pixel dims)")
    s.add_argument("--latency-us", type=float, default=4000.0, help="the constant latency, us (default: 4000)")
    s.add_argument("--seed", type=int, default=0, help="seed of the motion (default: 0)")

    n = sub.add_parser("info", help="summarise a recording",
                       description="Summarise a recording: format, sensor size, frames and exposures, events, their "
                                   "time span and how many fall inside each exposure. Reads the events once and "
                                   "no images.")
    n.add_argument("input", type=Path, help="recording to summarise")
    n.add_argument("--exposure-us", type=_positive_us,
                   help=_EXPOSURE_HELP)
    _topic_options(n)
    return p


def _topic_options(p: argparse.ArgumentParser) -> None:
    """A ROS bag's topics, for bags with several of a kind (stereo, or raw and colour images)."""
    p.add_argument("--events-topic", help="ROS bags: the dvs_msgs/EventArray topic (default: the only one)")
    p.add_argument("--image-topic", help="ROS bags: the sensor_msgs/Image topic (default: the only one, or the "
                                         "one beside the events)")


def _restore_options(p: argparse.ArgumentParser, models: tuple[str, ...]) -> None:
    p.add_argument("--model", choices=models, default="edi", help="restoration model (default: edi)")
    p.add_argument("--ckpt", type=Path, help="network weights (default: the shipped ones)")
    p.add_argument("--correct", nargs="?", const="constant", default="none", choices=("none", "constant", "spatial"),
                   help="latency correction (default: none; --correct alone: constant)")
    p.add_argument("--curve", type=Path, help="trained latency curve checkpoint (--correct spatial)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty OUTDIR")
    p.add_argument("--max-frames", type=int, help="only the first N frames (default: all); interpolate and REFID: "
                   "the N pairs they start, each with the frame after it")
    _fuse_frames_option(p, "--correct constant", "the N frames before it too (frame by frame, as a stream",
                        "frames.csv")
    p.add_argument("--no-pairs", action="store_true",
                   help="--correct constant reads each frame with the next one and adds their agreement to the "
                        "frame's evidence (a model of single frames still reads the frame alone), and --correct "
                        "spatial without --curve adds to those latencies a slope over intensity fitted to the first "
                        "pairs; this leaves both out (spatial: the sharpness fit) "
                        "(faster: the pair costs about as much as the frame's own search, and deblurring reads each "
                        "frame's events up to the next exposure)")
    _common_options(p)


def _fuse_frames_option(p: argparse.ArgumentParser, applies: str, which: str, report: str) -> None:
    """``--fuse-frames N``: ``correct`` fuses frames either side, ``deblur`` / ``interpolate`` the ones before."""
    p.add_argument("--fuse-frames", type=int, default=DEFAULT_FUSED_FRAMES, metavar="N",
                   help=f"{applies}: each frame's latency from the learned reader's evidence of {which}; default "
                        f"{DEFAULT_FUSED_FRAMES}, 0: each frame alone), 0 where that evidence keeps no latency likely; "
                        f"{report} keeps each frame's own estimate as frame_latency_us")


def _common_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--device", default="cpu", help="cpu or cuda (default: cpu)")
    p.add_argument("--threshold", default="auto",
                   help="contrast threshold θ, or 'auto' (default): one θ for the recording, the one that makes "
                        "consecutive frames' EDI reconstructions agree best (per frame when it has one frame)")
    p.add_argument("--num-bins", type=_num_bins, default=500, help="EDI sub-intervals per exposure (default: 500)")
    p.add_argument("--search-us", type=_finite_us, nargs=2, metavar=("LOW", "HIGH"),
                   help="the range the latency lies in, us: bounds the estimate, while the learned reader still "
                        "reads 0 to the exposure time as trained (default: 0 to the exposure time)")
    p.add_argument("--exposure-us", type=_positive_us,
                   help=_EXPOSURE_HELP)
    p.add_argument("--frame-gamma", type=frame_gamma_argument, default=1.0, metavar="G",
                   help="raise the frames to G as they are read: EDI needs linear intensity, as a DAVIS's raw "
                        "frames are (default 1: kept as they are); 2.2 for frames encoded for display (PNG or "
                        "video frames, sRGB); a network still reads them, and PNGs are written, as the file has them")
    _topic_options(p)
