"""A log as ROS 2 tools read it (issue 39 §2): the ROS 2 profile of MCAP, checked with readers
nobody here wrote. ``rosbags``' reader (through AnyReader, which builds its types from the
schemas in the file, not from a type store of ours) and ``mcap-ros2-support``'s decoder each
decode every message, and find the log's counts, stamps, sequence numbers, values and image
bytes."""

from __future__ import annotations

import contextlib
import io
import json
import resource
import subprocess
import sys
from collections import Counter

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from mcap_ros2.decoder import DecoderFactory
from rosbags.highlevel import AnyReader
from rosbags.typesys import Stores, get_typestore

from retriever import LogError, read_log
from retriever.log.ros2 import Ros2Bag, export_ros2
from tests.log.export_flows import (Frame, camera_log, event_data, hand_written_log, kinds_log, ros_camera_log,
                                   shadowed_steps_log)
from tests.log.helpers import cli_env
from tests.log.log_flows import build_emit


#: each leaf of the log's values: its topic in the export, and the ROS type it is written as
EXPECTED_TYPES = {
    "/cam/frame/rgb": "sensor_msgs/msg/Image", "/cam/frame/mask": "sensor_msgs/msg/Image",
    "/cam/frame/exposure": "std_msgs/msg/Float64", "/cam/rgba": "sensor_msgs/msg/Image",
    "/stats/mean": "std_msgs/msg/Float64", "/stats/hist": "std_msgs/msg/Int64MultiArray",
    "/stats/pixels": "sensor_msgs/msg/Image", "/stats/count": "std_msgs/msg/Int64",
    "/stats/bright": "std_msgs/msg/Bool", "/stats/label": "std_msgs/msg/String", "/stats/extra": "std_msgs/msg/String",
    "/retriever/steps/cam": "std_msgs/msg/String", "/retriever/steps/stats": "std_msgs/msg/String",
}


def _leaf(value, topic: str):
    """The value a topic's message must hold, taken from the log's value by hand."""
    field = topic.split("/")[3:]
    return getattr(value, field[0]) if field else value


def _expected(log) -> dict[str, list[tuple[int, int, int, object]]]:
    """Per topic: ``(log time, publish time, sequence, value)`` of each message, from the log."""
    expected: dict[str, list] = {}
    for event in log.iter_events():
        value = log.value(event)
        for topic in EXPECTED_TYPES:
            if topic.startswith(f"/{event.node}/{event.port}"):
                expected.setdefault(topic, []).append((event.tag[0], event.publish_ns, event.seq, _leaf(value, topic)))
    for index, step in enumerate(log.iter_steps()):
        expected.setdefault(f"/retriever/steps/{step.node}", []).append(
            (step.tag[0], step.wall_start_ns, index, step))
    return expected


def _check(topic: str, message, value) -> None:
    """One decoded message (either reader's) holds ``value``, as its type says it should."""
    kind = EXPECTED_TYPES[topic]
    if kind == "sensor_msgs/msg/Image":
        channels = 1 if value.ndim == 2 else value.shape[2]
        height, width = value.shape[:2]
        assert (message.height, message.width, message.step) == (height, width, width * channels * value.itemsize)
        assert message.encoding == ("32FC1" if value.dtype == np.float32 else {1: "mono8", 3: "rgb8", 4: "rgba8"}[
            channels])  # a 2-D float32 array: a depth image
        assert message.is_bigendian == 0 and bytes(message.data) == value.astype("<" + value.dtype.str[1:]).tobytes()
    elif kind.endswith("MultiArray"):
        assert [(d.size, d.stride) for d in message.layout.dim] == [
            (n, int(np.prod(value.shape[i:]))) for i, n in enumerate(value.shape)]
        assert np.asarray(message.data).tolist() == value.reshape(-1).tolist()
    elif topic.startswith("/retriever/steps/"):
        record = json.loads(message.data)
        assert (record["node"], record["status"], record["tag_ns"], record["microstep"]) == (
            value.node, value.status, *value.tag)
        assert record["consumed"] == {p: [list(i) for i in ids] for p, ids in value.consumed.items()}
        assert record["produced"] == [list(i) for i in value.produced]
    elif topic == "/stats/extra":
        assert json.loads(message.data) == value
    else:
        assert message.data == value


def test_rosbags_and_mcap_ros2_read_the_logs_counts_stamps_values_and_images(tmp_path):
    log_path = camera_log(tmp_path)
    out = tmp_path / "run_ros2.mcap"
    summary = export_ros2(read_log(log_path), out)
    assert summary.types == EXPECTED_TYPES and summary.as_json == 5  # the lists of /stats/extra
    log = read_log(log_path)
    expected = _expected(log)
    assert summary.written == Counter({topic: len(messages) for topic, messages in expected.items()})
    assert len(expected["/cam/frame/rgb"]) == 5 and len(expected["/retriever/steps/stats"]) == 5

    with out.open("rb") as f:  # mcap-ros2-support: the file's own schemas, every message decoded
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        assert reader.get_header().profile == "ros2"
        by_mcap: dict[str, list] = {}
        for schema, channel, message, decoded in reader.iter_decoded_messages(log_time_order=False):
            assert (schema.encoding, channel.message_encoding) == ("ros2msg", "cdr")
            assert schema.name == EXPECTED_TYPES[channel.topic]
            by_mcap.setdefault(channel.topic, []).append(
                (message.log_time, message.publish_time, message.sequence, decoded))
    assert {topic: len(m) for topic, m in by_mcap.items()} == {topic: len(m) for topic, m in expected.items()}
    for topic, messages in by_mcap.items():
        for (log_time, publish, seq, decoded), (tag, wall, logged_seq, value) in zip(messages, expected[topic]):
            assert (log_time, publish, seq) == (tag, wall, logged_seq), topic
            if EXPECTED_TYPES[topic] == "sensor_msgs/msg/Image":
                assert decoded.header.stamp.sec * 10**9 + decoded.header.stamp.nanosec == tag
                assert decoded.header.frame_id == topic.split("/")[1]
            _check(topic, decoded, value)

    # rosbags: no type store given, so the types are the ones the file's schemas define
    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        by_rosbags: dict[str, list] = {}
        for connection, timestamp, raw in reader.messages():
            assert connection.msgtype == EXPECTED_TYPES[connection.topic]
            by_rosbags.setdefault(connection.topic, []).append((timestamp, reader.deserialize(raw, connection.msgtype)))
    assert {topic: len(m) for topic, m in by_rosbags.items()} == {topic: len(m) for topic, m in expected.items()}
    for topic, messages in by_rosbags.items():
        in_time_order = sorted(expected[topic], key=lambda m: m[0])  # sorted as rosbags reads: by log time
        assert [timestamp for timestamp, _ in messages] == [m[0] for m in in_time_order]
        for (_, decoded), (_, _, _, value) in zip(messages, in_time_order):
            _check(topic, decoded, value)


def test_a_port_whose_values_change_kind_keeps_its_type_and_sends_the_rest_as_json(tmp_path):
    """The topic's type is its first value's; an int fits a Float64 topic; text, a number too
    big for 64 bits or for a float64 without loss, and a value no message holds go on
    ``<topic>/json``, counted."""
    path = tmp_path / "emit.mcap"
    values = [1.5, 2, "two", 2**70, np.uint64(2**64 - 1), None, [1, [2]], np.float32(0.25), b"\x00\x01"]
    build_emit(values).run(duration=1, log=path)
    out = tmp_path / "emit_ros2.mcap"
    summary = export_ros2(read_log(path), out)
    assert summary.types["/emit/value"] == "std_msgs/msg/Float64"
    assert summary.types["/emit/value/json"] == "std_msgs/msg/String"
    with out.open("rb") as f:
        decoded = {}
        for _, channel, _, message in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            decoded.setdefault(channel.topic, []).append(message.data)
    assert decoded["/emit/value"] == [1.5, 2.0, 0.25]
    as_json = [json.loads(text) for text in decoded["/emit/value/json"]]
    assert as_json == ["two", 2**70, 2**64 - 1, [1, [2]], [0, 1]]  # the bytes' content, not their length
    assert summary.as_json == 5  # JSON keeps 2**70 whole; uint64 max is no float64; None is no event


def test_an_integer_is_written_in_a_topics_type_only_when_that_type_holds_it_else_as_json(tmp_path):
    """Values of both signs and at the edges of each width: a value the topic's type (its first
    value's) holds is written exactly; one it does not (a sign it has not, a width past its own)
    goes on ``<topic>/json`` whole: none wraps around (2**64 - 1 as Int64 -1, -3 as UInt64
    2**64 - 3, uint32 4294967295 as Int32 -1)."""
    columns = {
        "i64": [1, np.uint64(2**64 - 1), -1, 2**63 - 1, -2**63],
        "u64": [np.uint64(5), -3, np.uint64(2**64 - 1), 0, np.uint8(255)],
        "i32": [np.int32(7), np.uint32(2**32 - 1), np.int32(-2**31), np.int64(2**31), np.int64(-2**31)],
        "u8s": [np.array([1, 2], np.uint8), np.array([-1, 255]), np.array([0, 255], np.int64), np.array([256, 0]),
                np.array([3, 4], np.uint16)],
        "f32": [np.float32(0.5), 2**24 + 1, 2**24, 0.1, -2],
    }
    path = tmp_path / "ints.mcap"
    build_emit([{name: column[k] for name, column in columns.items()} for k in range(5)]).run(duration=1, log=path)
    out = tmp_path / "ints_ros2.mcap"
    summary = export_ros2(read_log(path), out)
    with out.open("rb") as f:
        decoded: dict[str, list] = {}
        for _, channel, _, message in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            data = message.data
            decoded.setdefault(channel.topic, []).append(
                json.loads(data) if channel.topic.endswith("/json") else data if isinstance(data, (int, float)) else list(data))
    assert {topic: summary.types[topic] for topic in decoded if not topic.startswith("/retriever")} == {
        "/emit/value/i64": "std_msgs/msg/Int64", "/emit/value/u64": "std_msgs/msg/UInt64",
        "/emit/value/i32": "std_msgs/msg/Int32", "/emit/value/u8s": "std_msgs/msg/UInt8MultiArray",
        "/emit/value/f32": "std_msgs/msg/Float32", **{f"/emit/value/{name}/json": "std_msgs/msg/String"
                                                      for name in columns}}
    assert {topic: m for topic, m in decoded.items() if not topic.startswith("/retriever")} == {
        "/emit/value/i64": [1, -1, 2**63 - 1, -2**63], "/emit/value/i64/json": [2**64 - 1],
        "/emit/value/u64": [5, 2**64 - 1, 0, 255], "/emit/value/u64/json": [-3],
        "/emit/value/i32": [7, -2**31, -2**31], "/emit/value/i32/json": [2**32 - 1, 2**31],
        "/emit/value/u8s": [[1, 2], [0, 255], [3, 4]], "/emit/value/u8s/json": [[-1, 255], [256, 0]],
        "/emit/value/f32": [0.5, 2.0**24, -2.0], "/emit/value/f32/json": [2**24 + 1, 0.1],
    }
    assert summary.as_json == 8

def test_each_kind_of_number_keeps_its_width_and_what_no_message_holds_is_json(tmp_path):
    out = tmp_path / "kinds_ros2.mcap"
    summary = export_ros2(read_log(kinds_log(tmp_path)), out)
    assert summary.types == {
        "/kinds/u64": "std_msgs/msg/UInt64", "/kinds/f16": "std_msgs/msg/Float32",
        "/kinds/flags": "std_msgs/msg/UInt8MultiArray", "/kinds/big_endian": "std_msgs/msg/Int32MultiArray",
        "/kinds/two_channels": "std_msgs/msg/UInt8MultiArray",  # H×W×2 is no image
        "/kinds/records": "std_msgs/msg/String", "/kinds/empty": "std_msgs/msg/Float64MultiArray",
        "/kinds/pair": "std_msgs/msg/Float64MultiArray", "/kinds/blob": "std_msgs/msg/UInt8MultiArray",
        "/retriever/steps/kinds": "std_msgs/msg/String"}
    assert summary.as_json == 2 and set(summary.written.values()) == {2}
    with out.open("rb") as f:
        decoded = {channel.topic: message for _, channel, _, message in
                   make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages()}
    assert decoded["/kinds/u64"].data == 2**64 - 1 and decoded["/kinds/f16"].data == 1.5
    assert list(decoded["/kinds/flags"].data) == [1, 0] and list(decoded["/kinds/big_endian"].data) == [1, 2]
    two_channels = decoded["/kinds/two_channels"]
    assert [(d.size, d.stride) for d in two_channels.layout.dim] == [(2, 12), (3, 6), (2, 2)]
    assert list(two_channels.data) == list(range(12))
    assert [d.size for d in decoded["/kinds/empty"].layout.dim] == [0, 3] and list(decoded["/kinds/empty"].data) == []
    assert list(decoded["/kinds/pair"].data) == [1.0, 2.5]
    assert json.loads(decoded["/kinds/records"].data) == {"dtype": "[('a', '<f4')]", "shape": [2], "head": None}
    assert bytes(decoded["/kinds/blob"].data) == b"\x00\x01"


def test_a_process_that_never_imported_the_value_types_writes_the_same_file(tmp_path):
    """What ``retriever log export`` does: values decoded without their types (a dataclass as
    its fields, kept inert) give the same topics, types and bytes."""
    log_path = camera_log(tmp_path)
    here, there = tmp_path / "here.mcap", tmp_path / "there.mcap"
    export_ros2(read_log(log_path), here)
    code = ("import sys; from retriever import read_log; from retriever.log.ros2 import export_ros2; "
            "export_ros2(read_log(sys.argv[1]), sys.argv[2]); "
            "assert not any(m.startswith('tests') for m in sys.modules), 'the flows were imported'")
    done = subprocess.run([sys.executable, "-c", code, str(log_path), str(there)], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path, env=cli_env())
    assert done.returncode == 0, done.stderr
    assert there.read_bytes() == here.read_bytes()


def test_without_rosbags_the_export_says_how_to_get_it(tmp_path, monkeypatch):
    log = read_log(camera_log(tmp_path))
    monkeypatch.setitem(sys.modules, "rosbags.typesys", None)  # what an environment without the extra has
    with pytest.raises(LogError, match=r"needs the rosbags package(.|\n)*"
                                       r"hint: pip install 'retriever-robotics\[ros2\]'"):
        export_ros2(log, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()



# ---------------------------------------------------------------------------------------------
# A log is input: one written by hand, with what no run writes, gives a LogError and no file
# ---------------------------------------------------------------------------------------------
def test_names_no_ros_name_allows_are_made_ros_names(tmp_path):
    """Each character no ROS name token holds becomes '_', a run of '_' one (ROS 2 names hold no
    '__'), a token starting with a digit gets a '_' before it; a token may end with '_'."""
    log = read_log(hand_written_log(tmp_path / "odd.mcap", [
        ("data/nöde/1-port", 5, event_data(3.0)), ("data/a-_b/x_", 6, event_data(4.0)),
        ("data/__init__/p--q", 7, event_data(5.0))]))
    out = tmp_path / "out.mcap"
    topics = ["/n_de/_1_port", "/a_b/x_", "/_init_/p_q"]
    assert export_ros2(log, out).types == dict.fromkeys(topics, "std_msgs/msg/Float64")
    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        assert [(c.topic, t) for c, t, _ in reader.messages()] == list(zip(topics, [5, 6, 7]))


def test_names_that_map_to_one_topic_are_kept_apart_the_same_way_every_time(tmp_path):
    """``cam-left``, ``cam_left`` and ``cam__left`` are one ROS name: the name that needed no
    change keeps its topic (as does ``x_2``, which already is one), the others take the next free
    ``_N`` in the order of their names, whatever the order of the file; said in ``renamed``."""
    events = [("data/cam-left/x", 5, event_data(1.0)), ("data/cam__left/x", 6, event_data(2.0)),
              ("data/cam_left/x", 7, event_data(3.0)), ("data/cam_left/x_2", 8, event_data(4.0))]
    topics = {"/cam_left/x": 3.0, "/cam_left/x_2": 4.0, "/cam_left/x_3": 1.0, "/cam_left/x_4": 2.0}
    for order in (events, events[::-1]):
        out = tmp_path / "out.mcap"
        summary = export_ros2(read_log(hand_written_log(tmp_path / "apart.mcap", order)), out, overwrite=True)
        assert summary.types == dict.fromkeys(topics, "std_msgs/msg/Float64")
        assert summary.renamed == {"cam-left.x": "/cam_left/x_3", "cam__left.x": "/cam_left/x_4"}
        with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
            assert {c.topic: reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()} == topics


def test_a_field_never_takes_the_topic_of_a_nodes_step_records(tmp_path):
    """``/retriever/steps/<node>`` is the step records' (the convention the export documents):
    node ``retriever``'s port ``steps`` with a field ``cam`` goes beside it, not onto it."""
    summary = export_ros2(read_log(shadowed_steps_log(tmp_path)), tmp_path / "out.mcap")
    assert summary.types["/retriever/steps/cam"] == "std_msgs/msg/String"
    assert summary.types["/retriever/steps/cam_2"] == "std_msgs/msg/Float64"
    assert summary.renamed == {"retriever.steps.cam": "/retriever/steps/cam_2"}
    with AnyReader([tmp_path / "out.mcap"], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        records = [json.loads(reader.deserialize(raw, c.msgtype).data) for c, _, raw in reader.messages()
                   if c.topic == "/retriever/steps/cam"]
    assert records and {r["node"] for r in records} == {"cam"}


@pytest.mark.parametrize("events, message", [
    ([("data/cam/rgb", 0, b"\x92\x00\xc1")], r"event cam\.rgb #0 is not valid msgpack"),
    ([("data/cam/rgb", 2**63, event_data(np.zeros((2, 2), np.uint8)))], r"past what a ROS Time holds"),
])
def test_a_damaged_log_is_a_log_error_and_leaves_no_file(tmp_path, events, message):
    log = read_log(hand_written_log(tmp_path / "odd.mcap", events))
    with pytest.raises(LogError, match=message):
        export_ros2(log, tmp_path / "out.mcap")
    assert [p.name for p in tmp_path.iterdir()] == ["odd.mcap"]


def test_a_dicts_leaves_are_exported_by_their_kind_an_image_as_an_image(tmp_path):
    """What a ROS 2 subscriber sends (a dict: image, stamp, frame...) is opened as a dataclass
    is: the image a sensor_msgs/msg/Image with the log's bytes, numbers numbers, arrays arrays."""
    log_path = ros_camera_log(tmp_path)
    out = tmp_path / "roscam_ros2.mcap"
    summary = export_ros2(read_log(log_path), out)
    assert summary.types == {
        "/cam/image/image": "sensor_msgs/msg/Image", "/cam/image/stamp": "std_msgs/msg/Int64",
        "/cam/image/frame_id": "std_msgs/msg/String", "/cam/image/height": "std_msgs/msg/Int64",
        "/cam/image/width": "std_msgs/msg/Int64", "/cam/image/encoding": "std_msgs/msg/String",
        "/cam/joints/stamp": "std_msgs/msg/Int64", "/cam/joints/frame_id": "std_msgs/msg/String",
        "/cam/joints/name": "std_msgs/msg/String", "/cam/joints/position": "std_msgs/msg/Float64MultiArray",
        "/cam/joints/velocity": "std_msgs/msg/Float64MultiArray", "/retriever/steps/cam": "std_msgs/msg/String"}
    log = read_log(log_path)
    values = {port: [log.value(e) for e in log.iter_events() if e.port == port] for port in ("image", "joints")}
    assert len(values["image"]) == 3 and summary.as_json == 3  # the joints' names: a list of text
    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        by_rosbags: dict[str, list] = {}
        for connection, _, raw in reader.messages():
            by_rosbags.setdefault(connection.topic, []).append(reader.deserialize(raw, connection.msgtype))
    with out.open("rb") as f:
        by_mcap: dict[str, list] = {}
        for _, channel, _, decoded in make_reader(f, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
            by_mcap.setdefault(channel.topic, []).append(decoded)
    for decoded in (by_rosbags, by_mcap):
        for message, value in zip(decoded["/cam/image/image"], values["image"], strict=True):
            assert (message.height, message.width, message.encoding) == (4, 5, "rgb8")
            assert bytes(message.data) == value["image"].tobytes()
        assert [m.data for m in decoded["/cam/image/stamp"]] == [v["stamp"] for v in values["image"]]
        assert [m.data for m in decoded["/cam/image/frame_id"]] == ["cam"] * 3
        assert [list(m.data) for m in decoded["/cam/joints/position"]] == [
            v["position"].tolist() for v in values["joints"]]
        assert [json.loads(m.data) for m in decoded["/cam/joints/name"]] == [["shoulder", "elbow"]] * 3


# ---------------------------------------------------------------------------------------------
# ROS 2 messages hold sizes as uint32: a value past that is said, naming its port and shape
# ---------------------------------------------------------------------------------------------
def _bag() -> Ros2Bag:
    """A bag writing into memory, with the type store the export uses."""
    writer = Writer(io.BytesIO())
    writer.start(profile="ros2", library="test")
    return Ros2Bag(writer, get_typestore(Stores.ROS2_JAZZY))


@contextlib.contextmanager
def _no_gigabytes():
    """While the block runs, the process may map at most 1 GiB more than it has: code that copies
    one of these views fails with a MemoryError instead of taking the machine's memory."""
    try:
        with open("/proc/self/status") as status:
            mapped = next(int(line.split()[1]) * 1024 for line in status if line.startswith("VmSize:"))
    except OSError:  # no /proc: no guard
        yield
        return
    soft, hard = resource.getrlimit(resource.RLIMIT_AS)
    resource.setrlimit(resource.RLIMIT_AS, (mapped + 2**30, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_AS, (soft, hard))


def _view(shape: tuple[int, ...], dtype) -> np.ndarray:
    """An array of ``shape`` that holds one element: a broadcast view, so that no test allocates
    the gigabytes such a value would take."""
    return np.broadcast_to(np.zeros((1,) * len(shape), dtype), shape)


@pytest.mark.parametrize("value, said", [
    (_view((2**32, 2), np.uint8), r"height 4294967296"),  # a mono8 image too tall
    (_view((2, 2**31, 3), np.uint8), r"step 6442450944"),  # its width fits, its row stride does not
    (_view((2**32,), np.float64), r"dimension 0 size 4294967296"),
    (_view((2, 2**31), np.float64), r"dimension 0 stride 4294967296"),  # each size fits, the first stride not
    (_view((2, 2**31), np.float32), r"step 8589934592"),  # a 32FC1 depth image whose rows are past a uint32
    (_view((2**32,), ">i4"), r"dimension 0 size 4294967296"),  # said before it is made native-endian
])
def test_a_size_past_what_a_ros_message_holds_is_a_log_error_naming_the_port_and_the_shape(value, said):
    """sensor_msgs/Image's height, width and step and a MultiArray dimension's size and stride
    are uint32: a value whose sizes do not fit is refused before it is converted (nothing the
    size of the value is made), with its node.port, shape and what to do, not rosbags' error."""
    bag = _bag()
    shape = ", ".join(map(str, value.shape))
    said = (rf"event cam\.big #3: its value, {value.dtype.name}\[{shape}\], does not fit a (std_msgs|sensor_msgs)/msg/"
            rf"\w+: its {said} is more than the uint32 a ROS 2 message holds it in \(4294967295\)\n    hint: ")
    with _no_gigabytes(), pytest.raises(LogError, match=said):
        bag.event("cam", "big", value, 10, 10, 3)
    assert bag.summary.written == {}


def test_a_field_too_big_for_a_ros_message_is_named_with_its_port():
    bag = _bag()
    frame = Frame(rgb=_view((2, 2**31, 3), np.uint8), mask=np.zeros((2, 2), np.uint8), exposure=0.5)
    said = (r"event cam\.frame #0, field rgb: its value, uint8\[2, 2147483648, 3\], does not fit a "
            r"sensor_msgs/msg/Image: its step 6442450944 is more than")
    with _no_gigabytes(), pytest.raises(LogError, match=said):
        bag.event("cam", "frame", frame, 10, 10, 0)


def test_a_topic_past_rmws_length_is_cut_to_it_and_long_names_cut_alike_are_kept_apart(tmp_path):
    """A dict key of 300 characters made a topic no rmw takes (RMW_TOPIC_MAX_NAME_LENGTH: 247)."""
    long_a, long_b = "k" * 300 + "a", "k" * 300 + "b"
    events = [("data/cam/v", 5, event_data({long_a: 1.0, long_b: 2.0, "short": 3.0}))]
    out = tmp_path / "out.mcap"
    summary = export_ros2(read_log(hand_written_log(tmp_path / "long.mcap", events)), out)
    cut = "/cam/v/" + "k" * 240
    assert len(cut) == 247
    assert summary.types == {cut: "std_msgs/msg/Float64", cut[:245] + "_2": "std_msgs/msg/Float64",
                             "/cam/v/short": "std_msgs/msg/Float64"}
    assert summary.renamed == {f"cam.v.{long_a}": cut, f"cam.v.{long_b}": cut[:245] + "_2"}
    with AnyReader([out], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        got = {c.topic: reader.deserialize(raw, c.msgtype).data for c, _, raw in reader.messages()}
    assert got == {cut: 1.0, cut[:245] + "_2": 2.0, "/cam/v/short": 3.0}
    assert all(len(topic) <= 247 for topic in got)


def test_what_goes_as_json_beside_a_cut_topic_is_cut_too():
    bag = _bag()
    long = "k" * 300
    bag.event("cam", "v", {long: 1.0}, 5, 0, 0)
    bag.event("cam", "v", {long: "text"}, 6, 0, 1)  # not a Float64: as JSON, beside it
    topics = dict(bag.summary.types)
    assert all(len(topic) <= 247 for topic in topics)
    assert sorted(topics.values()) == ["std_msgs/msg/Float64", "std_msgs/msg/String"]
    assert bag.summary.renamed[f"cam.v.{long} as JSON"] == "/cam/v/" + "k" * 238 + "_2"


# ---------------------------------------------------------------------------------------------
# images sensor_msgs/msg/Image holds besides uint8 ones: depth arrays, a subscriber's encodings
# ---------------------------------------------------------------------------------------------
def _images(events) -> tuple[Ros2Bag, dict]:
    """What a bag writes of ``events`` (``(port, value)``): its summary, and per topic the
    decoded messages."""
    buffer = io.BytesIO()
    writer = Writer(buffer)
    writer.start(profile="ros2", library="test")
    bag = Ros2Bag(writer, get_typestore(Stores.ROS2_JAZZY))
    for seq, (port, value) in enumerate(events):
        bag.event("cam", port, value, 10 + seq, 0, seq)
    writer.finish()
    buffer.seek(0)
    decoded: dict[str, list] = {}
    for _, channel, _, message in make_reader(buffer, decoder_factories=[DecoderFactory()]).iter_decoded_messages():
        decoded.setdefault(channel.topic, []).append(message)
    return bag, decoded


@pytest.mark.parametrize("array, encoding", [
    (np.arange(12, dtype=np.uint16).reshape(3, 4) * 1000, "16UC1"),  # a depth camera's mm
    (np.arange(12, dtype=">u2").reshape(3, 4) * 1000, "16UC1"),  # big-endian: written little, as is_bigendian 0 says
    (np.linspace(0.5, 4.0, 12, dtype=np.float32).reshape(3, 4), "32FC1"),  # metres
])
def test_a_2d_uint16_or_float32_array_is_a_depth_image(array, encoding):
    """A uint16 depth image was a UInt16MultiArray, which no image panel shows."""
    bag, decoded = _images([("depth", array)])
    assert bag.summary.types == {"/cam/depth": "sensor_msgs/msg/Image"}
    (message,) = decoded["/cam/depth"]
    assert (message.height, message.width, message.encoding, message.is_bigendian, message.step) == \
        (3, 4, encoding, 0, 4 * array.itemsize)
    assert np.array_equal(np.frombuffer(bytes(message.data), "<" + array.dtype.str[1:]).reshape(3, 4), array)


@pytest.mark.parametrize("encoding, array", [
    ("mono16", np.arange(20, dtype=np.uint16).reshape(4, 5) * 3000),
    ("yuv422", np.arange(40, dtype=np.uint8).reshape(4, 5, 2)),
    ("bgr8", np.arange(60, dtype=np.uint8).reshape(4, 5, 3)),  # was written as rgb8: its colours swapped
    ("32FC1", np.linspace(0, 1, 20, dtype=np.float32).reshape(4, 5)),
    ("16UC1", np.arange(20, dtype=np.uint16).reshape(4, 5)),
    ("bayer_rggb8", np.arange(20, dtype=np.uint8).reshape(4, 5)),
])
def test_a_ros2_subscribers_image_is_exported_as_an_image_in_its_own_encoding(encoding, array):
    """What a Ros2Subscriber made of a sensor_msgs/msg/Image (ros2/types.py to_value): mono16 and
    yuv422 ones went to MultiArrays or JSON; each is an Image again, in the encoding it came in,
    and reads back (to_value) as the same array."""
    from retriever.ros2 import types

    channels = 1 if array.ndim == 2 else array.shape[2]
    height, width = array.shape[:2]
    received = types.to_value(types.from_value({"image": array, "encoding": encoding, "frame_id": "cam"},
                                               "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
    assert received["encoding"] == encoding and np.array_equal(received["image"], array)
    bag, decoded = _images([("image", received)])
    assert bag.summary.types["/cam/image/image"] == "sensor_msgs/msg/Image"
    (message,) = decoded["/cam/image/image"]
    assert (message.encoding, message.height, message.width, message.step) == \
        (encoding, height, width, width * channels * array.itemsize)
    store = get_typestore(Stores.ROS2_JAZZY)
    again = types.to_value(store.deserialize_cdr(store.serialize_cdr(
        store.types["sensor_msgs/msg/Image"](header=store.types["std_msgs/msg/Header"](
            stamp=store.types["builtin_interfaces/msg/Time"](sec=0, nanosec=0), frame_id="cam"),
            height=message.height, width=message.width, encoding=message.encoding,
            is_bigendian=message.is_bigendian, step=message.step, data=np.frombuffer(bytes(message.data), np.uint8)),
        "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
    assert np.array_equal(again["image"], array)


def test_an_encoding_that_does_not_match_its_array_is_not_trusted():
    """A dict whose 'encoding' says rgb8 beside a 2-D uint16 array: the array's own (16UC1)."""
    _, decoded = _images([("image", {"image": np.zeros((2, 3), np.uint16), "encoding": "rgb8"})])
    assert decoded["/cam/image/image"][0].encoding == "16UC1"


def test_bytes_and_complex_values_are_exported_with_their_content():
    """Bytes are a UInt8MultiArray of them (not their length); a complex array (or number) a
    Float64/Float32MultiArray of its real and imaginary parts along a last dimension of 2."""
    z = np.array([[1 + 2j, -3.5j], [0.25, 4 - 1j]])
    bag, decoded = _images([("blob", b"\x00\x01\xff"), ("z", z), ("z32", np.complex64(1.5 - 2j)),
                            ("nothing", b"")])
    assert bag.summary.types["/cam/blob"] == "std_msgs/msg/UInt8MultiArray"
    assert bytes(decoded["/cam/blob"][0].data) == b"\x00\x01\xff"
    assert list(decoded["/cam/nothing"][0].data) == []
    message = decoded["/cam/z"][0]
    assert bag.summary.types["/cam/z"] == "std_msgs/msg/Float64MultiArray"
    assert [(d.size, d.stride) for d in message.layout.dim] == [(2, 8), (2, 4), (2, 2)]
    assert list(message.data) == [1.0, 2.0, 0.0, -3.5, 0.25, 0.0, 4.0, -1.0]
    assert bag.summary.types["/cam/z32"] == "std_msgs/msg/Float32MultiArray"
    assert list(decoded["/cam/z32"][0].data) == [1.5, -2.0] and bag.summary.as_json == 0


def test_an_array_of_no_element_with_a_dimension_past_a_uint32_is_exported_as_json():
    """It holds 0 bytes: its dtype and shape go as JSON, the export goes on (no size error)."""
    bag, decoded = _images([("empty", np.zeros((0, 2**40, 3), np.uint8)), ("ok", 1.0),
                            ("zc", np.zeros((2**33, 0), np.complex128))])
    assert json.loads(decoded["/cam/empty"][0].data) == {"dtype": "uint8", "shape": [0, 2**40, 3], "head": []}
    assert json.loads(decoded["/cam/zc"][0].data) == {"dtype": "complex128", "shape": [2**33, 0], "head": None}
    assert decoded["/cam/ok"][0].data == 1.0 and bag.summary.as_json == 2


def test_a_field_whose_name_needed_no_change_keeps_its_topic_whatever_the_key_order():
    """``#`` and ``_`` both make the ROS name ``_``: ``_`` needed no change and keeps ``/cam/p/_``,
    ``#`` takes ``/cam/p/_2``, in either key order (as docs/log.md says)."""
    for value in ({"#": 2.0, "_": 3.0}, {"_": 3.0, "#": 2.0}):
        bag, decoded = _images([("p", value)])
        assert {topic: [m.data for m in ms] for topic, ms in decoded.items()} == {"/cam/p/_": [3.0], "/cam/p/_2": [2.0]}
        assert bag.summary.renamed == {"cam.p.#": "/cam/p/_2"}
