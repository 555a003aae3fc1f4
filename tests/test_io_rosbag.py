"""ROS1 bags as the rpg_dvs_ros DAVIS driver records them: written here by the ``rosbags`` package's own serialiser
from a simulated recording, read back by :class:`~evlatcorr.io.RosbagRecording`."""

from __future__ import annotations

import csv
import re
import warnings

import numpy as np
import pytest
import torch

from evlatcorr.io import RecordingError, RosbagRecording, open_recording
from evlatcorr.io.rosbag import decode_event_array
from evlatcorr.simulate import simulate
from tests.commands import run_command

EPOCH_NS = 1_600_000_000 * 10**9  # the bag's clock: ROS time since the Unix epoch
PACKET_US = 1000.0  # the driver publishes the events in messages of about this span


def _typestore():
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC)
    types = get_types_from_msg("uint16 x\nuint16 y\ntime ts\nbool polarity\n", "dvs_msgs/msg/Event")
    types.update(get_types_from_msg("Header header\nuint32 height\nuint32 width\nEvent[] events\n",
                                    "dvs_msgs/msg/EventArray"))
    store.register(types)
    return store


def _time(store, ns: int):
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 10**9, nanosec=ns % 10**9)


def _header(store, ns: int):
    return store.types["std_msgs/msg/Header"](seq=0, stamp=_time(store, ns), frame_id="")


def write_bag(path, seq, *, ns="/dvs", exposure=True, event_topics=("events",), encoding="mono8", image_size=None,
              array_size=None):
    """``seq``'s delayed events, blurry frames (stamped mid-exposure) and exposures, in record-time order."""
    from rosbags.rosbag1 import Writer

    store = _typestore()
    height, width = seq.sensor_size if array_size is None else array_size
    ev = seq.delayed_events
    t_ns = EPOCH_NS + np.round(ev.t.numpy() * 1000).astype(np.int64)
    messages = []  # (record time ns, topic, serialised)
    packets = np.floor((ev.t.numpy() - float(ev.t.min())) / PACKET_US).astype(np.int64)
    event_cls, array_cls = store.types["dvs_msgs/msg/Event"], store.types["dvs_msgs/msg/EventArray"]
    for packet in np.unique(packets):
        idx = np.flatnonzero(packets == packet)
        events = [event_cls(x=int(ev.x[i]), y=int(ev.y[i]), ts=_time(store, int(t_ns[i])), polarity=bool(ev.p[i] > 0))
                  for i in idx]
        msg = array_cls(header=_header(store, int(t_ns[idx[-1]])), height=height, width=width, events=events)
        for topic in event_topics:
            messages.append((int(t_ns[idx[-1]]) + 50_000, f"{ns}/{topic}",
                             store.serialize_ros1(msg, "dvs_msgs/msg/EventArray")))
    image_cls = store.types["sensor_msgs/msg/Image"]
    for i in range(seq.num_frames):
        start, end = float(seq.exposure_start[i]), float(seq.exposure_end[i])
        stamp = EPOCH_NS + round((start + end) / 2 * 1000)
        grey = (seq.blurry[i].mean(0).numpy() * 255).round().astype(np.uint8)
        if image_size is not None:
            grey = np.zeros(image_size, dtype=np.uint8)
        pixels = {"mono8": grey, "bgr8": np.stack([grey // 4, grey // 2, grey], -1),
                  "mono16": grey.astype(">u2") * 257}[encoding]
        step = pixels.strides[0]
        data = np.frombuffer(pixels.tobytes(), dtype=np.uint8)
        msg = image_cls(header=_header(store, stamp), height=pixels.shape[0], width=pixels.shape[1], encoding=encoding,
                        is_bigendian=int(encoding == "mono16"), step=step, data=data)
        recorded = EPOCH_NS + round(end * 1000) + 2_000_000  # read out after the exposure
        messages.append((recorded, f"{ns}/image_raw", store.serialize_ros1(msg, "sensor_msgs/msg/Image")))
        if exposure:
            value = store.types["std_msgs/msg/Int32"](data=round(end - start))
            messages.append((recorded + 30_000, f"{ns}/exposure", store.serialize_ros1(value, "std_msgs/msg/Int32")))
    kinds = {"events": "dvs_msgs/msg/EventArray", "image_raw": "sensor_msgs/msg/Image",
             "exposure": "std_msgs/msg/Int32"}
    with Writer(path) as writer:
        connections = {topic: writer.add_connection(topic, kinds.get(topic.rsplit("/", 1)[1], kinds["events"]),
                                                    typestore=store)
                       for topic in sorted({m[1] for m in messages})}
        for recorded, topic, data in sorted(messages, key=lambda m: m[0]):
            writer.write(connections[topic], recorded, data)
    return path


@pytest.fixture(scope="module")
def seq():
    return simulate("camera", num_frames=3, height=24, width=32, exposure_us=4000.0, frame_interval_us=6000.0,
                    latency_us=1500.0, seed=0)


@pytest.fixture(scope="module")
def bag(tmp_path_factory, seq):
    return write_bag(tmp_path_factory.mktemp("bag") / "davis.bag", seq)


def test_reads_the_driver_s_events_images_and_exposures(bag, seq):
    rec = open_recording(bag, after_us=2000.0)
    assert isinstance(rec, RosbagRecording) and rec.format_name == "rosbag1"
    assert (rec.events_topic, rec.image_topic, rec.exposure_topic) == ("/dvs/events", "/dvs/image_raw", "/dvs/exposure")
    assert rec.sensor_size == (24, 32) and len(rec) == 3
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the simulated events start at the first exposure
        batches = list(rec)
    offset = EPOCH_NS / 1000
    for i, batch in enumerate(batches):
        assert float(batch.exposure_start[0]) - offset == pytest.approx(float(seq.exposure_start[i]), abs=0.5)
        assert float(batch.exposure_end[0]) - offset == pytest.approx(float(seq.exposure_end[i]), abs=0.5)
        grey = (seq.blurry[i].mean(0) * 255).round() / 255
        torch.testing.assert_close(batch.blurry[0, 0], grey.float(), rtol=0, atol=1e-6)
        want = seq.delayed_events.window(float(seq.exposure_start[i]), float(seq.exposure_end[i]) + 2000.0)
        assert len(batch.events) == len(want) > 0
        assert torch.equal(batch.events.x, want.x) and torch.equal(batch.events.y, want.y)
        assert torch.equal(batch.events.p, want.p)
        torch.testing.assert_close(batch.events.t - offset, want.t.double(), rtol=0, atol=0.5)


def test_without_the_exposure_topic_the_exposure_must_be_given(tmp_path, seq):
    path = write_bag(tmp_path / "noexp.bag", seq, exposure=False)
    with pytest.raises(RecordingError, match="noexp.bag: no /dvs/exposure topic .* pass exposure_us"):
        open_recording(path)
    mid = open_recording(path, exposure_us=4000.0)
    assert mid.exposure_topic is None
    start, end, _ = mid.frame_times()[1]
    assert start - EPOCH_NS / 1000 == pytest.approx(float(seq.exposure_start[1]), abs=0.5) and end - start == 4000.0
    at_start = RosbagRecording(path, exposure_us=1000.0, timestamp_is="start")
    assert at_start.frame_times()[1][0] == pytest.approx(start + 2000.0, abs=1e-6)
    with pytest.raises(ValueError, match="exposure_us must be a positive"):
        RosbagRecording(path, exposure_us=-1.0)


def test_several_event_topics_need_a_choice(tmp_path, seq):
    path = write_bag(tmp_path / "two.bag", seq, event_topics=("events", "events_right"))
    with pytest.raises(RecordingError, match=r"2 dvs_msgs/EventArray topics \['/dvs/events', '/dvs/events_right'\]: "
                                             "choose one with events_topic"):
        open_recording(path)
    assert RosbagRecording(path, events_topic="/dvs/events_right").events_topic == "/dvs/events_right"
    r = run_command("info", str(path), cwd=tmp_path)
    assert r.returncode == 2 and "choose one with events_topic" in r.stderr
    r = run_command("info", str(path), "--events-topic", "/dvs/events_right", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with pytest.raises(RecordingError, match="events_topic='/dvs/image_raw' is not a dvs_msgs/EventArray topic"):
        RosbagRecording(path, events_topic="/dvs/image_raw")


@pytest.mark.parametrize("encoding", ["bgr8", "mono16"])
def test_colour_and_16_bit_images(tmp_path, seq, encoding):
    rec = RosbagRecording(write_bag(tmp_path / f"{encoding}.bag", seq, encoding=encoding))
    blurry = rec.frame(0).blurry[0]
    grey = (seq.blurry[0].mean(0) * 255).round()
    if encoding == "bgr8":  # stored blue, green, red: read red first
        torch.testing.assert_close(blurry[0] * 255, grey.float(), rtol=0, atol=1e-4)
        torch.testing.assert_close(blurry[2] * 255, (grey // 4).float(), rtol=0, atol=1e-4)
    else:
        torch.testing.assert_close(blurry[0] * 255, grey.float(), rtol=0, atol=1e-4)


def test_event_arrays_without_a_size_take_the_images(tmp_path, seq):
    rec = RosbagRecording(write_bag(tmp_path / "nosize.bag", seq, array_size=(0, 0)))
    assert rec.sensor_size == (24, 32) and len(rec.frame(1).events) > 0


def test_images_of_another_size_than_the_events_are_refused(tmp_path, seq):
    rec = RosbagRecording(write_bag(tmp_path / "roi.bag", seq, image_size=(12, 32)))
    with pytest.raises(RecordingError, match=r"image 0: 12x32 but the events are \(24, 32\)"):
        rec.frame(0)


def test_a_cut_off_or_garbled_bag_is_refused_with_a_message(tmp_path, bag):
    cut = tmp_path / "cut.bag"
    cut.write_bytes(bag.read_bytes()[:2000])  # the index, at the end, is gone
    with pytest.raises(RecordingError, match="cut.bag: cannot read the bag .*rosbag reindex"):
        open_recording(cut)
    with pytest.raises(RecordingError, match="cannot hold the 5 events it announces"):
        decode_event_array(bytes(16) + np.array([2, 3, 5], dtype="<u4").tobytes() + bytes(13), "a.bag")


def test_the_command_line_corrects_a_bag(tmp_path, bag):
    out = tmp_path / "corrected.h5"
    r = run_command("correct", str(bag), str(out), "--num-bins", "100", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    rows = list(csv.DictReader(open(out.with_suffix(".csv"))))
    assert len(rows) == 3 and all(row["latency_us"] for row in rows)
    info = run_command("info", str(bag), cwd=tmp_path)
    assert info.returncode == 0 and "rosbag1" in info.stdout
    assert re.search(r"events_topic +/dvs/events\n", info.stdout) and "exposure_topic" in info.stdout


def test_the_command_line_s_exposure_reaches_a_bag_without_the_exposure_topic(tmp_path, seq):
    path = write_bag(tmp_path / "noexp.bag", seq, exposure=False)
    r = run_command("info", str(path), cwd=tmp_path)
    assert r.returncode == 2 and "pass exposure_us (--exposure-us)" in r.stderr
    r = run_command("info", str(path), "--exposure-us", "4000", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert "(4000.0, 4000.0)" in r.stdout  # exposure_us (min, max)


def test_an_exposure_given_for_a_bag_with_the_exposure_topic_is_not_used_and_says_so(bag):
    with pytest.warns(UserWarning, match="exposure is read from /dvs/exposure; exposure_us=1000 is not used"):
        rec = RosbagRecording(bag, exposure_us=1000.0)
    start, end, _ = rec.frame_times()[0]
    assert end - start == pytest.approx(4000.0)


def test_ros2_bags_and_old_bags_are_named(tmp_path):
    ros2 = tmp_path / "ros2_bag"
    ros2.mkdir()
    (ros2 / "metadata.yaml").write_text("rosbag2_bagfile_information: {}\n")
    with pytest.raises(RecordingError, match="a ROS2 bag; only ROS1 bags"):
        open_recording(ros2)
    old = tmp_path / "old.bag"
    old.write_bytes(b"#ROSBAG V1.2\n" + bytes(64))
    with pytest.raises(RecordingError, match=r"an old version \(#ROSBAG V1.2\); only version 2.0"):
        open_recording(old)
