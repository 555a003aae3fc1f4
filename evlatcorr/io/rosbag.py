"""ROS1 bags recorded from a DAVIS with the ``rpg_dvs_ros`` driver, read with the ``rosbags`` package.

Conventions of the bag and how they are converted (once, here):

- events: ``dvs_msgs/EventArray`` messages (``height``, ``width``, and events of ``uint16 x, uint16 y, time ts,
  bool polarity``). Each ``ts`` is a ROS time on the clock of the images' stamps: kept as µs (float64, exact to
  0.25 µs for dates before 2255); polarity True (ON) becomes +1. The messages' bytes are decoded with one NumPy
  view each, not event by event;
- frames: ``sensor_msgs/Image`` (``mono8``, ``mono16``, ``rgb8``, ``bgr8``, ``rgba8``, ``bgra8``; alpha dropped).
  The driver stamps an image with the middle of its exposure (libcaer's frame timestamp, the median of the
  exposure's start and end);
- exposure: the driver publishes each image's exposure time on ``<namespace>/exposure`` (``std_msgs/Int32``, µs)
  right after the image; each image takes the one recorded nearest to it. A bag without that topic needs
  ``exposure_us`` (the exposure set on the camera), placed around the stamp as ``timestamp_is`` says.

The topics are found by their message types. A bag with several event or image topics (stereo, or a colour and a
raw image) needs ``events_topic`` / ``image_topic``; an image topic in the events' namespace is preferred.
ROS2 bags are not read: DAVIS drivers for ROS2 publish ``event_camera_msgs``, whose events are encoded by the
driver.
"""

from __future__ import annotations

import contextlib
import struct
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from evlatcorr.io.base import Recording
from evlatcorr.io.conversions import structured_events, to_unit_image
from evlatcorr.io.records import FrameInfo, RecordingError, starts_with
from evlatcorr.sample_warnings import user_stacklevel

__all__ = ["RosbagRecording", "is_rosbag1"]

MAGIC = b"#ROSBAG V2.0\n"
EVENTS_TYPE, IMAGE_TYPE, EXPOSURE_TYPE = "dvs_msgs/msg/EventArray", "sensor_msgs/msg/Image", "std_msgs/msg/Int32"
# one dvs_msgs/Event as ROS1 serialises it: packed, little-endian
_EVENT = np.dtype([("x", "<u2"), ("y", "<u2"), ("secs", "<u4"), ("nsecs", "<u4"), ("polarity", "u1")])
_PIXELS = {"mono8": (np.uint8, 1), "mono16": (np.uint16, 1), "8UC1": (np.uint8, 1), "16UC1": (np.uint16, 1),
           "rgb8": (np.uint8, 3), "bgr8": (np.uint8, 3), "rgba8": (np.uint8, 4), "bgra8": (np.uint8, 4)}


def is_rosbag1(path: str | Path) -> bool:
    """Whether ``path`` is a file starting with the ROS1 bag magic ``#ROSBAG V2.0``."""
    return starts_with(path, MAGIC)


def _after_header(data: bytes, where: str) -> tuple[float, int]:
    """A message's ``std_msgs/Header``: its stamp (µs) and the offset of the field after it."""
    try:
        _seq, secs, nsecs, length = struct.unpack_from("<IIII", data, 0)
    except struct.error:
        raise RecordingError(f"{where}: a message too short for its header") from None
    return secs * 1e6 + nsecs / 1e3, 16 + length


def decode_event_array(data: bytes, where: str) -> tuple[np.ndarray, tuple[int, int]]:
    """One serialised ``dvs_msgs/EventArray``: its events (our structured layout) and ``(height, width)``.

    Example:
        >>> header = struct.pack("<IIII", 0, 0, 0, 0)  # seq, stamp, empty frame_id
        >>> body = struct.pack("<III", 2, 3, 1) + struct.pack("<HHIIB", 1, 0, 5, 2000, 1)
        >>> events, size = decode_event_array(header + body, "a.bag")
        >>> size, float(events["t"][0]), int(events["p"][0])
        ((2, 3), 5000002.0, 1)
    """
    _, offset = _after_header(data, where)
    try:
        height, width, count = struct.unpack_from("<III", data, offset)
    except struct.error:
        raise RecordingError(f"{where}: an EventArray message too short for its size fields") from None
    offset += 12
    if len(data) != offset + count * _EVENT.itemsize:
        raise RecordingError(f"{where}: an EventArray message of {len(data)} bytes cannot hold the {count} events it "
                             "announces (corrupt, or not dvs_msgs/EventArray)")
    raw = np.frombuffer(data, dtype=_EVENT, count=count, offset=offset)
    t = raw["secs"].astype(np.float64) * 1e6 + raw["nsecs"].astype(np.float64) / 1e3
    return structured_events(raw["x"], raw["y"], t, raw["polarity"] != 0, where=where), (height, width)


def decode_image(data: bytes, where: str) -> tuple[float, np.ndarray]:
    """One serialised ``sensor_msgs/Image``: its stamp (µs) and pixels ``(H, W)`` or ``(H, W, C)``, RGB order."""
    stamp, offset = _after_header(data, where)
    try:
        height, width, length = struct.unpack_from("<III", data, offset)
        encoding = data[offset + 12:offset + 12 + length].decode()
        offset += 12 + length
        big_endian, step, size = struct.unpack_from("<BII", data, offset)
    except (struct.error, UnicodeDecodeError):
        raise RecordingError(f"{where}: an Image message too short or garbled") from None
    offset += 9
    if encoding not in _PIXELS:
        raise RecordingError(f"{where}: image encoding {encoding!r} is not supported (supported: "
                             f"{', '.join(sorted(_PIXELS))})")
    dtype, channels = _PIXELS[encoding]
    row = width * channels * np.dtype(dtype).itemsize
    if step < row or size != step * height or len(data) < offset + size:
        raise RecordingError(f"{where}: an Image message whose {size} bytes do not hold {height} rows of {step} "
                             f"bytes ({width} px of {encoding})")
    rows = np.frombuffer(data, dtype=np.uint8, count=size, offset=offset).reshape(height, step)[:, :row]
    pixels = rows.copy().view(np.dtype(dtype).newbyteorder(">" if big_endian else "<"))
    pixels = pixels.astype(dtype).reshape(height, width, channels)
    if encoding.startswith("bgr"):
        pixels = pixels[..., [2, 1, 0, *range(3, channels)]]
    return stamp, pixels[..., 0] if channels == 1 else pixels


class RosbagRecording(Recording):
    """A ROS1 bag of a DAVIS recorded with ``rpg_dvs_ros`` (events, images and their exposures), streamed.

    Args:
        path: the ``.bag`` file.
        before_us: events to include before exposure start (µs).
        after_us: events to include after exposure end (µs); ``None``: the exposure time.
        events_topic: the ``dvs_msgs/EventArray`` topic (default: the bag's only one).
        image_topic: the ``sensor_msgs/Image`` topic (default: the only one, or the one in the events' namespace).
        exposure_us: the exposure time (µs) for bags without the driver's ``<namespace>/exposure`` topic.
        timestamp_is: which moment of the exposure an image's stamp is (``"middle"``, the driver's; ``"start"``,
            ``"end"``), where ``exposure_us`` places the exposure.

    Example:
        >>> rec = RosbagRecording("davis.bag", after_us=20_000)  # doctest: +SKIP
        >>> rec.sensor_size, rec.exposure_topic  # doctest: +SKIP
        ((260, 346), '/dvs/exposure')
        >>> for batch in rec:  # one EventFrames per frame  # doctest: +SKIP
        ...     print(float(batch.exposure_time), len(batch.events))
    """

    format_name = "rosbag1"

    def __init__(self, path: str | Path, before_us: float = 0.0, after_us: float | None = None,
                 events_topic: str | None = None, image_topic: str | None = None, exposure_us: float | None = None,
                 timestamp_is: str = "middle") -> None:
        super().__init__(path, before_us, after_us)
        if not is_rosbag1(self.path):
            raise RecordingError(f"{self.path}: not a ROS1 bag (it does not start with '#ROSBAG V2.0')")
        if exposure_us is not None and not (np.isfinite(exposure_us) and exposure_us > 0):
            raise ValueError(f"exposure_us must be a positive number of us, got {exposure_us}")
        if timestamp_is not in ("middle", "start", "end"):
            raise ValueError(f"timestamp_is must be 'middle', 'start' or 'end', got {timestamp_is!r}")
        self.exposure_us, self.timestamp_is = exposure_us, timestamp_is
        with self._reader() as reader:
            topics = {c.topic: c.msgtype for c in reader.connections}
            self.events_topic = self._pick(topics, EVENTS_TYPE, events_topic, "events_topic")
            namespace = self.events_topic.rsplit("/", 1)[0]
            self.image_topic = self._pick(topics, IMAGE_TYPE, image_topic, "image_topic", prefer=namespace)
            exposure = f"{self.image_topic.rsplit('/', 1)[0]}/exposure"
            self.exposure_topic = exposure if topics.get(exposure) == EXPOSURE_TYPE else None
            first = next(reader.messages([c for c in reader.connections if c.topic == self.events_topic]), None)
            image = next(reader.messages([c for c in reader.connections if c.topic == self.image_topic]), None)
        if first is None or image is None:
            raise RecordingError(f"{self.path}: {self.events_topic if first is None else self.image_topic} holds no "
                                 "messages")
        self.sensor_size = decode_event_array(first[2], f"{self.path}: {self.events_topic}")[1]
        if 0 in self.sensor_size:  # a driver that leaves the array's size unset: the images tell it
            self.sensor_size = decode_image(image[2], f"{self.path}: {self.image_topic}")[1].shape[:2]
        if self.exposure_topic is not None and exposure_us is not None:
            warnings.warn(f"{self.path}: each image's exposure is read from {self.exposure_topic}; exposure_us="
                          f"{exposure_us:g} is not used", stacklevel=user_stacklevel())
        if self.exposure_topic is None and exposure_us is None:
            raise RecordingError(f"{self.path}: no {exposure} topic (std_msgs/Int32, the driver's exposure of each "
                                 "image): pass exposure_us (--exposure-us), the exposure time set on the camera")

    @contextlib.contextmanager
    def _reader(self) -> Iterator[Any]:
        """The bag opened by ``rosbags`` (its index read), closed on the way out."""
        from rosbags.rosbag1 import Reader, ReaderError

        reader = Reader(self.path)
        try:
            reader.open()
        except ReaderError as exc:
            raise RecordingError(f"{self.path}: cannot read the bag ({exc}); a bag whose recording was cut off "
                                 "(.bag.active) needs 'rosbag reindex' first") from exc
        try:
            yield reader
        finally:
            reader.close()

    def _pick(self, topics: dict[str, str], msgtype: str, wanted: str | None, option: str,
              prefer: str | None = None) -> str:
        found = sorted(topic for topic, kind in topics.items() if kind == msgtype)
        name = msgtype.replace("/msg/", "/")
        if wanted is not None:
            if topics.get(wanted) != msgtype:
                raise RecordingError(f"{self.path}: {option}={wanted!r} is not a {name} topic of this bag "
                                     f"(its {name} topics: {found or 'none'})")
            return wanted
        if prefer is not None and len(found) > 1:
            found = [topic for topic in found if topic.rsplit("/", 1)[0] == prefer] or found
        if len(found) == 1:
            return found[0]
        if not found:
            raise RecordingError(f"{self.path}: no {name} topic (its topics: {sorted(topics) or 'none'}); "
                                 "a DAVIS recorded with rpg_dvs_ros has events and images")
        raise RecordingError(f"{self.path}: {len(found)} {name} topics {found}: choose one with {option} "
                             f"(--{option.replace('_', '-')})")

    def _messages(self, topic: str) -> Iterator[tuple[int, bytes]]:
        """``(record time ns, bytes)`` of a topic's messages, in the order recorded."""
        from rosbags.rosbag1 import ReaderError

        with self._reader() as reader:
            try:
                for _, recorded, data in reader.messages([c for c in reader.connections if c.topic == topic]):
                    yield recorded, data
            except ReaderError as exc:
                raise RecordingError(f"{self.path}: cannot read {topic} ({exc}): truncated or corrupt") from exc

    # exposures ------------------------------------------------------------------------------------
    def _exposures(self, stamps: list[float], recorded: np.ndarray) -> list[tuple[float, float]]:
        """Each image's exposure ``(start, end)`` µs from its stamp and its exposure message (or ``exposure_us``)."""
        if self.exposure_topic is None:
            offset = {"middle": 0.5, "start": 0.0, "end": 1.0}[self.timestamp_is] * self.exposure_us
            return [(stamp - offset, stamp - offset + self.exposure_us) for stamp in stamps]
        times, lengths = [], []
        for when, data in self._messages(self.exposure_topic):
            if len(data) != 4:
                raise RecordingError(f"{self.path}: {self.exposure_topic}: a message of {len(data)} bytes is not a "
                                     "std_msgs/Int32")
            times.append(when)
            lengths.append(struct.unpack("<i", data)[0])
        nearest = _nearest(np.asarray(times, dtype=np.int64), recorded)
        shared = len(nearest) - len(np.unique(nearest[nearest >= 0])) - int((nearest < 0).sum())
        if shared:  # the exposure is set on the camera and changes slowly: a neighbour's is the best left
            warnings.warn(f"{self.path}: {shared} image(s) have no exposure message of their own on "
                          f"{self.exposure_topic} (not recorded?): they take the nearest image's",
                          stacklevel=user_stacklevel())
        exposures = []
        for i, (stamp, j) in enumerate(zip(stamps, nearest)):
            if j < 0 or lengths[j] <= 0:
                raise RecordingError(f"{self.path}: image {i} has no exposure on {self.exposure_topic} "
                                     f"({'none recorded' if j < 0 else f'{lengths[j]} us'})")
            exposures.append((stamp - lengths[j] / 2, stamp + lengths[j] / 2))  # the driver stamps mid-exposure
        return exposures

    def _frame_exposures(self) -> list[tuple[float, float]]:
        stamps, recorded = [], []
        for when, data in self._messages(self.image_topic):
            stamps.append(_after_header(data, f"{self.path}: {self.image_topic}")[0])
            recorded.append(when)
        if not stamps:
            raise RecordingError(f"{self.path}: {self.image_topic} holds no images")
        if any(b <= a for a, b in zip(stamps, stamps[1:])):
            raise RecordingError(f"{self.path}: {self.image_topic}: the images' stamps do not increase in the order "
                                 "they were recorded")
        return self._exposures(stamps, np.asarray(recorded, dtype=np.int64))

    # the Recording interface ----------------------------------------------------------------------
    def _read_frame_times(self) -> list[tuple[float, float, int]]:
        return [(start, end, 0) for start, end in self._frame_exposures()]

    def frames(self) -> Iterator[FrameInfo]:
        times = self.frame_times()
        where = f"{self.path}: {self.image_topic}"
        for index, ((_, data), (start, end, _)) in enumerate(zip(self._messages(self.image_topic), times)):
            _, pixels = decode_image(data, f"{where} image {index}")
            if pixels.shape[:2] != self.sensor_size:
                raise RecordingError(f"{where} image {index}: {pixels.shape[0]}x{pixels.shape[1]} but the events are "
                                     f"{self.sensor_size} (H, W): frames and events must be pixel-aligned")
            yield FrameInfo(index, start, end, to_unit_image(pixels, where), meta={"topic": self.image_topic})

    def info(self) -> dict[str, Any]:
        """The summary of :meth:`Recording.info`, with the topics read."""
        topics = {"events_topic": self.events_topic, "image_topic": self.image_topic,
                  "exposure_topic": self.exposure_topic or f"none (exposure_us={self.exposure_us:g})"}
        summary = super().info()
        return {**{k: summary[k] for k in ("file", "format")}, **topics,
                **{k: v for k, v in summary.items() if k not in ("file", "format")}}

    def _segmented_chunks(self) -> Iterator[np.ndarray]:
        where = f"{self.path}: {self.events_topic}"
        for _, data in self._messages(self.events_topic):
            events, size = decode_event_array(data, where)
            if size != self.sensor_size and 0 not in size:
                raise RecordingError(f"{where}: a message of a {size} sensor among {self.sensor_size} ones")
            if len(events):
                yield events


def _nearest(times: np.ndarray, queries: np.ndarray) -> np.ndarray:
    """For each query, the index of the nearest of the sorted ``times`` (-1 where there are none)."""
    if not len(times):
        return np.full(len(queries), -1)
    after = np.clip(np.searchsorted(times, queries), 0, len(times) - 1)
    before = np.clip(after - 1, 0, None)
    return np.where(np.abs(times[after] - queries) < np.abs(queries - times[before]), after, before)
