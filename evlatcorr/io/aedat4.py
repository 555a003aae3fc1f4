"""AEDAT4 recordings from DAVIS cameras (iniVation), decoded by the ``aedat`` package.

Conventions of the file and how they are converted:

- timestamps are absolute microseconds (uint64): kept as µs (float64 in our events);
- polarity is a bool field ``on`` (True = ON): converted to ±1;
- the sensor size comes from the events stream header as width × height: we use ``(H, W)``;
- APS frames carry ``exposure_begin_t`` / ``exposure_end_t`` (µs): the exposure window. Grey
  8-bit (``L``) frames become one channel, colour ``RGB``/``RGBA`` frames three (alpha dropped);
  16-bit pixels are scaled by 1/65535. A frame without exposure timestamps is refused.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np

from evlatcorr.io.base import FrameInfo, Recording, RecordingError, structured_events

__all__ = ["AedatRecording", "is_aedat4"]

MAGIC = b"#!AER-DAT4.0"


def is_aedat4(path: str | Path) -> bool:
    with open(path, "rb") as f:
        return f.read(len(MAGIC)) == MAGIC


class AedatRecording(Recording):
    """A DAVIS AEDAT4 file, streamed packet by packet (memory bounded by one frame's window).

    Example:
        >>> rec = AedatRecording("cradle_lowlight.aedat4")  # doctest: +SKIP
        >>> for batch in rec:  # EventFrames of one frame each  # doctest: +SKIP
        ...     print(batch.exposure_start, len(batch.events))
    """

    format_name = "aedat4"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None) -> None:
        super().__init__(path, before_us, after_us)
        if not is_aedat4(self.path):
            raise RecordingError(f"{self.path}: not an AEDAT4 file (missing the '#!AER-DAT4.0' header)")
        streams = self._decoder().id_to_stream()
        events = [s for s in streams.values() if s.get("type") == "events"]
        if not events:
            raise RecordingError(f"{self.path}: no event stream in this AEDAT4 file")
        self.sensor_size = (int(events[0]["height"]), int(events[0]["width"]))
        if not any(s.get("type") == "frame" for s in streams.values()):
            raise RecordingError(f"{self.path}: no frame stream: latency correction needs APS frames with exposures")

    def _decoder(self):
        import aedat

        try:
            return aedat.Decoder(str(self.path))
        except Exception as exc:  # the Rust decoder raises plain exceptions for corrupt files
            raise RecordingError(f"{self.path}: cannot decode AEDAT4 ({exc})") from exc

    def _packets(self) -> Iterator[dict]:
        decoder = self._decoder()
        index = 0
        while True:
            try:
                packet = next(decoder)
            except StopIteration:
                return
            except Exception as exc:
                raise RecordingError(f"{self.path}: corrupt or truncated after packet {index} ({exc})") from exc
            index += 1
            yield packet

    def frames(self) -> Iterator[FrameInfo]:
        index = 0
        for packet in self._packets():
            frame = packet.get("frame")
            if frame is None:
                continue
            begin, end = int(frame["exposure_begin_t"]), int(frame["exposure_end_t"])
            if begin <= 0 or end <= begin:
                raise RecordingError(f"{self.path}: frame {index} has no valid exposure timestamps "
                                     f"(begin {begin}, end {end})")
            yield FrameInfo(index, float(begin), float(end), self._image(frame, index))
            index += 1

    def _image(self, frame: dict, index: int) -> np.ndarray:
        pixels = np.asarray(frame["pixels"])
        fmt = frame.get("format", "L")
        if pixels.dtype == np.uint8:
            image = pixels.astype(np.float32) / 255.0
        elif pixels.dtype == np.uint16:
            image = pixels.astype(np.float32) / 65535.0
        else:
            raise RecordingError(f"{self.path}: frame {index} has unsupported pixel type {pixels.dtype}")
        if image.ndim == 2:
            image = image[None]
        elif fmt in ("RGB", "RGBA", "BGR", "BGRA") and image.ndim == 3:
            image = image[..., :3]
            if fmt.startswith("BGR"):
                image = image[..., ::-1]
            image = np.ascontiguousarray(image.transpose(2, 0, 1))
        else:
            raise RecordingError(f"{self.path}: frame {index} has unsupported format {fmt!r} {pixels.shape}")
        if image.shape[1:] != self.sensor_size:
            raise RecordingError(f"{self.path}: frame {index} is {image.shape[1:]} but the events are "
                                 f"{self.sensor_size} (frames with an offset/ROI are not supported)")
        return image

    def iter_event_chunks(self) -> Iterator[np.ndarray]:
        for packet in self._packets():
            ev = packet.get("events")
            if ev is None or len(ev) == 0:
                continue
            yield structured_events(ev["x"], ev["y"], ev["t"].astype(np.float64), ev["on"])
