"""HighREV (Sun et al., CVPR 2023; NTIRE 2025 event deblurring): blur/sharp PNGs and NPZ event chunks.

Two layouts are read (the path is the folder holding ``blur/``):

- *split folder* (NTIRE 2025 / EFNet release)::

      <split>/blur/<seq>_<k>.png           blurry frames (RGB)
      <split>/sharp/<seq>_<k>.png          optional sharp frame at mid-exposure
      <split>/event/<seq>_<k>_<j>.npz      the events of frame k in pieces j = 00, 01, ...

  The pieces cut the frame's events at its sharp sub-frames; the last piece lies after the
  exposure ("out of the exposure time" in the dataset's loader), so the exposure is made of all
  pieces but the last (``drop_last=True``). Each sequence ``<seq>`` is an independent segment.

- *video folder* (REFID release)::

      <split>/<video>/blur/*.png           blurry frames, in name order
      <split>/<video>/gt/*.png             sharp sub-frames (optional)
      <split>/<video>/event/*.npz          one piece per sharp sub-frame interval
                                           (or <split>_event/<video>/*.npz)

  Blurry frame ``k`` averages ``m`` sharp sub-frames and ``n`` are skipped before the next one
  (REFID's 11+1 by default). Taking piece ``j`` as the events between sub-frames ``j`` and
  ``j+1`` (REFID's loaders add one or two pieces around it as context), the exposure is pieces
  ``k(m+n) .. k(m+n)+m-2`` (the ``m-1`` intervals between its sub-frames), and its sharp frame
  the middle sub-frame ``k(m+n) + m//2``.

NPZ keys: ``x``, ``y``, ``timestamp``, ``polarity`` (1-D or ``(N, 1)`` columns). Conventions
converted once:

- **x and y are swapped** in the files with respect to the images (the dataset loaders swap
  them back; ``swap_xy=True`` does the same);
- HighREV stores **no exposure times**: a frame's exposure is taken as the span of the events of
  its exposure pieces (first to last event), which is the span of its sharp sub-frames up to the
  gap to the nearest event;
- timestamps are taken as microseconds (``time_unit`` = ``"s"``, ``"ms"`` or ``"ns"`` to convert);
- polarity 0/1 (or ±1) → ±1; images 8-bit RGB → [0, 1]; sensor size = the blurry PNG's ``(H, W)``.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.io.base import Recording
from evlatcorr.io.conversions import sorted_by_time, structured_events, time_scale, to_microseconds, to_unit_image
from evlatcorr.io.npz_access import open_npz
from evlatcorr.io.records import FrameInfo, RecordingError, SegmentEnd

__all__ = ["HighREVRecording", "is_highrev"]


def _event_dir(video: Path) -> Path | None:
    if (video / "event").is_dir():
        return video / "event"
    split = video.parent
    beside = split.parent / f"{split.name}_event" / video.name
    return beside if beside.is_dir() else None


def _natural(path: Path) -> list[Any]:
    return [int(s) if s.isdigit() else s for s in re.split(r"(\d+)", path.stem)]


def is_highrev(path: str | Path) -> bool:
    """Whether ``path`` is a folder with ``blur/`` PNGs and HighREV event NPZs."""
    path = Path(path)
    return path.is_dir() and (path / "blur").is_dir() and _event_dir(path) is not None


def _load_png(path: Path, where: str) -> np.ndarray:
    from PIL import Image

    try:
        with Image.open(path) as im:
            a = np.asarray(im.convert("RGB") if im.mode not in ("L", "I;16", "RGB") else im)
    except OSError as exc:
        raise RecordingError(f"{where}: cannot read {path} ({exc})") from exc
    return to_unit_image(a, where)


class HighREVRecording(Recording):
    """Reader of HighREV folders (see the module docstring for both layouts and the conventions).

    Args:
        path: the folder holding ``blur/`` (a split folder or a video folder).
        before_us: events to include before exposure start (µs).
        after_us: events to include after exposure end (µs); ``None``: the exposure time.
        sequence: split folders only: read one sequence (``<seq>`` name) instead of all of them.
        m: video folders: sharp sub-frames per blurry frame.
        n: video folders: sub-frames skipped between blurry frames.
        drop_last: split folders: the last event piece of a frame lies after its exposure.
        event_dir: the event folder, when it is not found by the layout rules.
        swap_xy: swap the files' ``x`` and ``y`` (True for HighREV).
        time_unit: unit of ``timestamp``: ``"us"`` (default), ``"ms"``, ``"s"`` or ``"ns"``.

    Example:
        >>> rec = HighREVRecording("HighREV/val")  # doctest: +SKIP
        >>> rec.segment_names[:2], rec.num_frames  # doctest: +SKIP
    """

    format_name = "highrev"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 sequence: str | None = None, m: int = 11, n: int = 1, drop_last: bool = True,
                 event_dir: str | Path | None = None, swap_xy: bool = True, time_unit: str = "us") -> None:
        super().__init__(path, before_us, after_us)
        if m < 2 or n < 0:
            raise ValueError(f"need m >= 2 sharp sub-frames per blurry frame and n >= 0, got m={m}, n={n}")
        self.scale = time_scale(time_unit)
        self.m, self.n, self.drop_last, self.swap_xy = m, n, drop_last, swap_xy
        blur = sorted((self.path / "blur").glob("*.png")) if (self.path / "blur").is_dir() else []
        if not blur:
            raise RecordingError(f"{self.path}: no blur/*.png frames (pass the folder that holds blur/)")
        found = Path(event_dir) if event_dir is not None else _event_dir(self.path)
        if found is None or not found.is_dir():
            raise RecordingError(f"{self.path}: no event folder (looked for {self.path / 'event'} and "
                                 f"{self.path.parent.parent / (self.path.parent.name + '_event') / self.path.name})")
        self.event_dir = found
        event_files = sorted(self.event_dir.glob("*.npz"))
        if not event_files:
            raise RecordingError(f"{self.event_dir}: no event .npz files")
        names = {f.name for f in event_files}
        self.layout = "split" if any(n.startswith(blur[0].stem + "_") for n in names) else "video"
        # per segment: list of (blur png, sharp png or None, exposure pieces, all pieces in order)
        self._plan: list[list[tuple[Path, Path | None, list[Path]]]] = []
        self._pieces: list[list[Path]] = []
        if self.layout == "split":
            self._plan_split(blur, event_files, sequence)
        else:
            if sequence is not None:
                raise ValueError("sequence= applies to split folders (blur/<seq>_<k>.png); this is a video folder")
            self._plan_video(blur, event_files)
        self.sensor_size = tuple(_load_png(self._plan[0][0][0], f"{self.path}: frame 0").shape[1:])
        self._spans: dict[Path, tuple[float, float] | None] = {}

    def _plan_split(self, blur: list[Path], event_files: list[Path], sequence: str | None) -> None:
        by_stem: dict[str, list[Path]] = {}
        for f in event_files:
            stem = f.stem.rsplit("_", 1)[0]
            by_stem.setdefault(stem, []).append(f)
        sequences: dict[str, list[Path]] = {}
        for b in blur:
            seq = b.stem.rsplit("_", 1)[0] if "_" in b.stem else b.stem
            sequences.setdefault(seq, []).append(b)
        if sequence is not None:
            if sequence not in sequences:
                raise RecordingError(f"{self.path}: no sequence {sequence!r}; there are {sorted(sequences)[:10]}"
                                     f"{' ...' if len(sequences) > 10 else ''}")
            sequences = {sequence: sequences[sequence]}
        index = 0
        for frames in sequences.values():
            plan, pieces = [], []
            for b in sorted(frames, key=_natural):
                files = sorted(by_stem.get(b.stem, []))
                if not files:
                    raise RecordingError(f"{self.path}: frame {index} ({b.name}) has no event files "
                                         f"{self.event_dir / (b.stem + '_*.npz')}")
                exposure = files[:-1] if self.drop_last and len(files) > 1 else files
                sharp = self.path / "sharp" / b.name
                plan.append((b, sharp if sharp.is_file() else None, exposure))
                pieces.extend(files)
                index += 1
            self._plan.append(plan)
            self._pieces.append(pieces)
        self.segment_names = list(sequences) if len(sequences) > 1 else []

    def _plan_video(self, blur: list[Path], event_files: list[Path]) -> None:
        gt = sorted((self.path / "gt").glob("*.png")) if (self.path / "gt").is_dir() else []
        plan, step = [], self.m + self.n
        for k, b in enumerate(blur):
            first = k * step
            exposure = event_files[first:first + self.m - 1]
            if len(exposure) < self.m - 1:
                raise RecordingError(f"{self.path}: frame {k} ({b.name}) needs event files {first}..."
                                     f"{first + self.m - 2} (m={self.m}, n={self.n}), but {self.event_dir} has "
                                     f"only {len(event_files)}")
            mid = first + self.m // 2
            plan.append((b, gt[mid] if mid < len(gt) else None, exposure))
        self._plan, self._pieces = [plan], [event_files]

    # events -------------------------------------------------------------------------------
    def _load(self, file: Path) -> np.ndarray:
        with open_npz(file, ("x", "y", "timestamp", "polarity"), "a HighREV event file") as z:
            x, y = (z["y"], z["x"]) if self.swap_xy else (z["x"], z["y"])
            ev = sorted_by_time(structured_events(x, y, to_microseconds(z["timestamp"], self.scale), z["polarity"],
                                                  where=str(file)))
        self._spans[file] = (float(ev["t"][0]), float(ev["t"][-1])) if len(ev) else None
        return ev

    def _span(self, file: Path) -> tuple[float, float] | None:
        if file not in self._spans:
            self._load(file)
        return self._spans[file]

    def _check_chunk(self, chunk: np.ndarray, newest: float, segment: int) -> None:
        try:
            super()._check_chunk(chunk, newest, segment)
        except RecordingError as exc:
            if "outside the sensor" in str(exc):
                raise RecordingError(f"{exc} (x and y are swapped in HighREV files: check swap_xy="
                                     f"{self.swap_xy})") from None
            raise

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        for seg, pieces in enumerate(self._pieces):
            if seg:
                yield SegmentEnd()
            for file in pieces:
                chunk = self._load(file)
                if len(chunk):
                    yield chunk

    # frames -------------------------------------------------------------------------------
    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        times, index = [], 0
        for seg, plan in enumerate(self._plan):
            for blur, _, exposure in plan:
                spans = [s for s in (self._span(f) for f in exposure) if s is not None]
                if not spans:
                    raise RecordingError(f"{self.path}: frame {index} ({blur.name}) has no events in its exposure "
                                         f"pieces {[f.name for f in exposure][:3]}...: its exposure (taken from "
                                         "the event timestamps) is unknown")
                start, end = min(s[0] for s in spans), max(s[1] for s in spans)
                times.append((start, max(end, np.nextafter(start, np.inf)), seg))
                index += 1
        return times

    def frames(self) -> Iterator[FrameInfo]:
        times = self.frame_times()
        index = 0
        for seg, plan in enumerate(self._plan):
            for blur, sharp, _ in plan:
                where = f"{self.path}: frame {index} ({blur.name})"
                image = _load_png(blur, where)
                if image.shape[1:] != self.sensor_size:
                    raise RecordingError(f"{where} is {image.shape[1:]}, expected {self.sensor_size}")
                sharp_img = _load_png(sharp, where + " sharp") if sharp is not None else None
                meta = {"image": blur.name}
                if self.segment_names:
                    meta["sequence"] = self.segment_names[seg]
                yield FrameInfo(index, times[index][0], times[index][1], image, sharp=sharp_img, segment=seg,
                                meta=meta)
                index += 1
