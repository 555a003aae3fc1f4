"""AEDAT4 recordings from DAVIS cameras (iniVation), decoded by the ``aedat`` package.

Conventions of the file and how they are converted (once, here):

- timestamps are absolute Unix-epoch microseconds (uint64): kept as µs (float64 in our events,
  exact below 2**53 µs, i.e. for any date before the year 2255);
- polarity is the bool field ``on`` (True = ON, brightness increase): converted to ±1;
- the sensor size comes from the event stream's header, width × height: we use ``(H, W)``;
- every APS frame carries ``exposure_begin_t`` / ``exposure_end_t`` (µs): the exposure window.
  Its ``t`` field is *not* used, because cameras disagree on it (exposure start in some files,
  mid-exposure in others); ``begin_t`` / ``end_t`` are the readout window, not the exposure.
  A frame whose exposure timestamps are missing (0) is refused with a message naming it;
- frames: 8-bit grey (``L``) gives one channel, colour ``RGB``/``RGBA`` three (alpha dropped),
  16-bit pixels are divided by 65535. Frames smaller than the sensor (a region of interest with an
  offset) are refused: events and frames must be pixel-aligned.

The decoder is a streaming packet iterator: frames and event packets come interleaved, and a
frame's packet may come before or after the events of its exposure. :class:`AedatRecording` reads
the file once, keeping the events that a waiting frame needs plus ``max_frame_delay_us`` of past
events while no frame waits (a frame packet written later than that after its window start is
reported with a clear error).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.io.base import Recording
from evlatcorr.io.conversions import structured_events, to_unit_image
from evlatcorr.io.records import FrameInfo, RecordingError, SegmentEnd, starts_with
from evlatcorr.sample_warnings import user_stacklevel

__all__ = ["AedatRecording", "is_aedat4"]

MAGIC = b"#!AER-DAT4.0"
# the header after the magic and its line end: its size (little-endian uint32), then an IOHeader flatbuffer, whose
# file identifier follows its root offset
_HEADER_START = len(MAGIC) + 2
_HEADER_ID = b"IOHE"
# what the aedat decoder says where the file ends inside a packet (Rust's unexpected end of file)
_END_OF_FILE = "failed to fill whole buffer"


def is_aedat4(path: str | Path) -> bool:
    """Whether ``path`` is a file starting with the AEDAT 4.0 magic ``#!AER-DAT4.0``."""
    return starts_with(path, MAGIC)


class AedatRecording(Recording):
    """A DAVIS AEDAT4 file, streamed packet by packet (memory bounded by one frame's window).

    Args:
        path: the ``.aedat4`` file.
        before_us: events to include before exposure start (µs).
        after_us: events to include after exposure end (µs); ``None``: the exposure time.
        max_frame_delay_us: how far (µs) behind the newest event a frame packet may come in the file
            and still find all the events of its window.

    Example:
        >>> rec = AedatRecording("cradle_lowlight.aedat4", after_us=20_000)  # doctest: +SKIP
        >>> rec.sensor_size, rec.num_frames  # doctest: +SKIP
        ((260, 346), 13)
        >>> for batch in rec:  # one EventFrames per frame  # doctest: +SKIP
        ...     print(float(batch.exposure_time), len(batch.events))
    """

    format_name = "aedat4"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 max_frame_delay_us: float = 1_000_000.0) -> None:
        super().__init__(path, before_us, after_us)
        if not self.path.is_file() or not is_aedat4(self.path):
            raise RecordingError(f"{self.path}: not an AEDAT4 file (it does not start with '#!AER-DAT4.0')")
        if not max_frame_delay_us >= 0:
            raise ValueError(f"max_frame_delay_us must be >= 0, got {max_frame_delay_us}")
        self._frame_delay_us = float(max_frame_delay_us)
        streams = self._decoder().id_to_stream()
        events = [s for s in streams.values() if s.get("type") == "events"]
        if not events:
            raise RecordingError(f"{self.path}: no event stream in this AEDAT4 file")
        if len(events) > 1:
            raise RecordingError(f"{self.path}: {len(events)} event streams (stereo?); only one is supported")
        self.sensor_size = (int(events[0]["height"]), int(events[0]["width"]))
        if not any(s.get("type") == "frame" for s in streams.values()):
            raise RecordingError(f"{self.path}: no frame stream: latency correction needs APS frames with "
                                 "exposure timestamps")

    def _decoder(self) -> Any:
        import aedat

        _check_header(self.path)  # a garbled header panics in the decoder's Rust code, which prints a trace first
        try:
            return aedat.Decoder(str(self.path))
        except BaseException as exc:  # the Rust decoder raises plain exceptions for corrupt headers, or panics
            if not _decoder_failed(exc):
                raise
            raise RecordingError(f"{self.path}: cannot decode the AEDAT4 header ({exc})") from exc

    def _numbered_packets(self) -> Iterator[tuple[dict[str, Any], int | None]]:
        """Packets with the index of the frame they carry (``None`` for packets without a frame)."""
        index = 0
        for packet in self._packets():
            if packet.get("frame") is None:
                yield packet, None
            else:
                yield packet, index
                index += 1

    def _packets(self) -> Iterator[dict[str, Any]]:
        decoder = self._decoder()
        index = 0
        while True:
            try:
                packet = next(decoder)
            except StopIteration:
                return
            except BaseException as exc:
                if not _decoder_failed(exc):
                    raise
                if str(exc) == _END_OF_FILE and index:  # the file stops inside a packet: a recording cut off (a
                    # crash, a full disk) keeps everything before it, which is read, and says so
                    warnings.warn(f"{self.path}: the file ends inside the packet after packet {index} (truncated: a "
                                  f"recording cut off, or a corrupt packet size); the {index} packets before it are "
                                  "read", stacklevel=user_stacklevel())
                    return
                if str(exc) == _END_OF_FILE:
                    raise RecordingError(f"{self.path}: the file ends inside its first packet (truncated): nothing to "
                                         "read") from exc
                raise RecordingError(f"{self.path}: corrupt file after packet {index} ({exc})") from exc
            index += 1
            yield packet

    # conversion -------------------------------------------------------------------------------
    def _exposure(self, frame: dict[str, Any], index: int) -> tuple[float, float]:
        begin, end = int(frame.get("exposure_begin_t", 0)), int(frame.get("exposure_end_t", 0))
        if begin <= 0 or end <= begin:
            raise RecordingError(f"{self.path}: frame {index} has no valid exposure timestamps "
                                 f"(exposure_begin_t={begin}, exposure_end_t={end}); the frame's t field cannot "
                                 "replace them (its meaning differs between cameras)")
        return float(begin), float(end)

    def _image(self, frame: dict[str, Any], index: int) -> np.ndarray:
        where = f"{self.path}: frame {index} (format {frame.get('format')!r})"
        fmt = frame.get("format", "L")
        if fmt not in ("L", "RGB", "RGBA", "I;16"):
            raise RecordingError(f"{where}: unsupported frame format (supported: L, RGB, RGBA, I;16)")
        width, height = int(frame.get("width", 0)), int(frame.get("height", 0))
        offset = (int(frame.get("offset_x", 0)), int(frame.get("offset_y", 0)))
        if (height, width) != self.sensor_size or offset != (0, 0):
            raise RecordingError(f"{where}: the frame is {height}x{width} at offset {offset} but the events are "
                                 f"{self.sensor_size} (H, W); frames of a region of interest are not supported")
        return to_unit_image(frame["pixels"], where)

    def _frame_info(self, frame: dict[str, Any], index: int) -> FrameInfo:
        start, end = self._exposure(frame, index)
        return FrameInfo(index, start, end, self._image(frame, index), meta={"format": frame.get("format")})

    def _chunk(self, ev: np.ndarray) -> np.ndarray:
        return structured_events(ev["x"], ev["y"], ev["t"].astype(np.float64), ev["on"], where=f"{self.path}: events")

    # the Recording interface -------------------------------------------------------------------
    def frames(self) -> Iterator[FrameInfo]:
        for packet, index in self._numbered_packets():
            if index is not None:
                yield self._frame_info(packet["frame"], index)

    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        return [(*self._exposure(packet["frame"], index), 0) for packet, index in self._numbered_packets()
                if index is not None]

    def _segmented_chunks(self) -> Iterator[np.ndarray | SegmentEnd]:
        for packet in self._packets():
            ev = packet.get("events")
            if ev is not None and len(ev):
                yield self._chunk(ev)

    def _items(self) -> Iterator[FrameInfo | np.ndarray | SegmentEnd]:
        """One pass over the packets: frames and event chunks in file order."""
        for packet, index in self._numbered_packets():
            if index is not None:
                yield self._frame_info(packet["frame"], index)
                continue
            ev = packet.get("events")
            if ev is not None and len(ev):
                yield self._chunk(ev)


def _decoder_failed(exc: BaseException) -> bool:
    """Whether ``exc`` is the decoder's own failure on a bad file: an ``Exception``, or a panic of its Rust code (pyo3's
    ``PanicException`` derives from ``BaseException``, as ``KeyboardInterrupt`` does, which must pass through)."""
    return isinstance(exc, Exception) or type(exc).__name__ == "PanicException"


def _check_header(path: Path) -> None:
    """Refuse a file whose header cannot be an IOHeader: too short for the size it gives, or without its identifier.

    Raises:
        RecordingError: naming the file and what is wrong.
    """
    with open(path, "rb") as f:
        f.seek(_HEADER_START)
        raw = f.read(4)
        size = int.from_bytes(raw, "little") if len(raw) == 4 else 0
        header = f.read(size)
    if len(raw) < 4 or len(header) < size or size < 8:
        raise RecordingError(f"{path}: cannot decode the AEDAT4 header (the file ends inside it, or it is empty)")
    if header[4:8] != _HEADER_ID:
        raise RecordingError(f"{path}: cannot decode the AEDAT4 header (no IOHeader after the magic: a corrupt file)")
