"""ROS messages as Retriever values and back, through CDR; type hashes against published ones."""

from __future__ import annotations

import numpy as np
import pytest
from rosbags.typesys import Stores, get_typestore

from retriever.codec import packb, unpackb
from retriever.ros2 import types

#: hashes ROS 2 Jazzy publishes (ros2 topic info -v, rmw_zenoh's design.md, rosidl's generated
#: type descriptions), as other projects record them
KNOWN_HASHES = {
    "std_msgs/msg/String": "RIHS01_df668c740482bbd48fb39d76a70dfd4bd59db1288021743503259e948f6b1a18",
    "std_msgs/msg/Header": "RIHS01_f49fb3ae2cf070f793645ff749683ac6b06203e41c891e17701b1cb597ce6a01",
    "sensor_msgs/msg/Image": "RIHS01_d31d41a9a4c4bc8eae9be757b0beed306564f7526c88ea6a4588fb9582527d47",
    "sensor_msgs/msg/CompressedImage": "RIHS01_15640771531571185e2efc8a100baf923961a4d15d5569652e6cb6691e8e371a",
    "sensor_msgs/msg/Imu": "RIHS01_7d9a00ff131080897a5ec7e26e315954b8eae3353c3f995c55faf71574000b5b",
    "sensor_msgs/msg/JointState": "RIHS01_a13ee3a330e346c9d87b5aa18d24e11690752bd33a0350f11c5882bc9179260e",
}

_jazzy = get_typestore(Stores.ROS2_JAZZY)


@pytest.mark.parametrize("name", sorted(KNOWN_HASHES))
def test_type_hashes_are_the_published_ones(name):
    assert types.type_hash(name) == KNOWN_HASHES[name]


def _through_cdr(value, name):
    """value → message → CDR → a message rosbags decodes by itself → value; and the value survives
    Retriever's codec (the log, the wire)."""
    data = types.serialize(types.from_value(value, name), name)
    back = types.to_value(_jazzy.deserialize_cdr(data, name), name)
    assert_equal(unpackb(packb(back)), back)
    return back


def assert_equal(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for key in a:
            assert_equal(a[key], b[key])
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype and np.array_equal(a, b)
    else:
        assert a == b


def test_an_image_is_an_array_of_its_encodings_dtype():
    rgb = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)
    back = _through_cdr({"image": rgb, "stamp": 1_700_000_000_000_000_123, "frame_id": "cam"}, "sensor_msgs/msg/Image")
    assert back["encoding"] == "rgb8" and back["stamp"] == 1_700_000_000_000_000_123 and back["frame_id"] == "cam"
    assert_equal(back["image"], rgb)
    depth = np.linspace(0, 3, 12, dtype=np.float32).reshape(3, 4)
    assert_equal(_through_cdr(depth, "sensor_msgs/msg/Image")["image"], depth)
    mono16 = np.arange(6, dtype=np.uint16).reshape(2, 3)
    assert _through_cdr(mono16, "sensor_msgs/msg/Image")["encoding"] == "mono16"
    assert_equal(_through_cdr(mono16.astype(">u2"), "sensor_msgs/msg/Image")["image"], mono16)


def test_an_image_with_padded_rows_or_big_endian_data_reads_right():
    Image, Header = _jazzy.types["sensor_msgs/msg/Image"], _jazzy.types["std_msgs/msg/Header"]
    Time = _jazzy.types["builtin_interfaces/msg/Time"]
    pixels = np.array([[1, 2, 3], [4, 5, 6]], dtype=np.uint16)
    rows = np.zeros((2, 8), dtype=np.uint8)  # step 8: 6 bytes of pixels and 2 of padding per row
    rows[:, :6] = pixels.astype(">u2").view(np.uint8).reshape(2, 6)
    message = Image(header=Header(stamp=Time(sec=1, nanosec=2), frame_id=""), height=2, width=3,
                    encoding="16UC1", is_bigendian=1, step=8, data=rows.reshape(-1))
    assert_equal(types.to_value(message, "sensor_msgs/msg/Image")["image"], pixels)


def test_an_image_whose_array_disagrees_with_its_encoding_is_refused():
    with pytest.raises(ValueError, match="'mono8' is 1 channel"):
        types.from_value({"image": np.zeros((2, 2, 3), np.uint8), "encoding": "mono8"}, "sensor_msgs/msg/Image")
    with pytest.raises(ValueError, match="needs an encoding"):
        types.from_value(np.zeros((2, 2, 2), np.int16), "sensor_msgs/msg/Image")


def test_the_standard_types_a_robot_needs():
    joints = _through_cdr({"stamp": 5, "name": ["a", "b"], "position": [0.5, -1.0]}, "sensor_msgs/msg/JointState")
    assert joints["name"] == ["a", "b"] and joints["stamp"] == 5
    assert_equal(joints["position"], np.array([0.5, -1.0]))
    assert_equal(joints["velocity"], np.zeros(0))
    twist = _through_cdr({"linear": [0.2, 0, 0]}, "geometry_msgs/msg/Twist")
    assert_equal(twist["angular"], np.zeros(3))
    assert_equal(twist["linear"], np.array([0.2, 0, 0]))
    pose = _through_cdr({"frame_id": "map", "pose": {"position": [1, 2, 3], "orientation": [0, 0, 0, 1]}},
                        "geometry_msgs/msg/PoseStamped")
    assert_equal(pose["pose"]["orientation"], np.array([0.0, 0, 0, 1]))
    imu = _through_cdr({"angular_velocity": [0, 0, 1], "orientation_covariance": np.eye(3).reshape(-1)},
                       "sensor_msgs/msg/Imu")
    assert imu["orientation_covariance"].shape == (9,) and imu["angular_velocity"][2] == 1.0
    jpeg = _through_cdr({"format": "jpeg", "data": np.frombuffer(b"\xff\xd8\xff", np.uint8)},
                        "sensor_msgs/msg/CompressedImage")
    assert jpeg["data"].tobytes() == b"\xff\xd8\xff" and jpeg["format"] == "jpeg"


def test_std_msgs_wrappers_are_their_data_and_multi_arrays_are_shaped_arrays():
    assert _through_cdr("hello", "std_msgs/msg/String") == "hello"
    assert _through_cdr(2.5, "std_msgs/msg/Float64") == 2.5
    assert _through_cdr(True, "std_msgs/msg/Bool") is True
    assert _through_cdr(-7, "std_msgs/msg/Int32") == -7
    matrix = np.arange(6, dtype=np.float32).reshape(2, 3)
    assert_equal(_through_cdr(matrix, "std_msgs/msg/Float32MultiArray"), matrix)
    assert _through_cdr({"stamp": 3, "frame_id": "x"}, "std_msgs/msg/Header") == {"stamp": 3, "frame_id": "x"}


def test_a_type_added_from_its_msg_text_maps_by_the_same_rules():
    types.register_msg("retriever_test_msgs/msg/Grip", "std_msgs/Header header\nfloat64 width\nstring[] fingers\n"
                       "geometry_msgs/Vector3 force")
    value = {"stamp": 9, "frame_id": "hand", "width": 0.04, "fingers": ["l", "r"], "force": [0, 0, 1.5]}
    data = types.serialize(types.from_value(value, "retriever_test_msgs/msg/Grip"), "retriever_test_msgs/msg/Grip")
    back = types.to_value(types.deserialize(data, "retriever_test_msgs/msg/Grip"), "retriever_test_msgs/msg/Grip")
    assert_equal(back, {**value, "force": np.array([0, 0, 1.5])})
    assert types.type_hash("retriever_test_msgs/msg/Grip").startswith("RIHS01_")


def test_a_header_beside_a_field_named_stamp_stays_two_stamps():
    """sensor_msgs/msg/TimeReference-like types carry a Header and a time of their own: flattened,
    the Header's stamp and the field ``stamp`` were one key, and one of the two was lost (issue 39)."""
    name = "retriever_test_msgs/msg/Stamped"
    types.register_msg(name, "std_msgs/Header header\nbuiltin_interfaces/Time stamp\nstring frame_id\nfloat64 x")
    value = {"header": {"stamp": 5, "frame_id": "base"}, "stamp": 7, "frame_id": "other", "x": 1.5}
    back = types.to_value(types.deserialize(types.serialize(types.from_value(value, name), name), name), name)
    assert back == value
    assert types.flat_header(name) is None and types.flat_header("sensor_msgs/msg/Image") == "header"
    with pytest.raises(ValueError, match=r"Stamped field header \(a std_msgs/msg/Header\) has no field\(s\) seq"):
        types.from_value({"header": {"seq": 1}}, name)
    with pytest.raises(TypeError, match=r"Stamped field header: takes a dict \{\"stamp\": ns, \"frame_id\": str\}"):
        types.from_value({"header": 5}, name)


def test_two_headers_stay_apart():
    name = "retriever_test_msgs/msg/TwoHeaders"
    types.register_msg(name, "std_msgs/Header left\nstd_msgs/Header right")
    value = {"left": {"stamp": 1, "frame_id": "l"}, "right": {"stamp": 2, "frame_id": "r"}}
    assert types.to_value(types.deserialize(types.serialize(types.from_value(value, name), name), name), name) == value


def test_a_header_without_a_frame_id_gets_the_one_given():
    image = np.zeros((2, 3, 3), dtype=np.uint8)
    message = types.from_value(image, "sensor_msgs/msg/Image", frame_id="camera_optical")
    assert message.header.frame_id == "camera_optical"
    said = types.from_value({"image": image, "frame_id": "left"}, "sensor_msgs/msg/Image", frame_id="camera_optical")
    assert said.header.frame_id == "left"
    assert types.from_value(image, "sensor_msgs/msg/Image").header.frame_id == ""


def test_unknown_types_and_fields_are_named():
    with pytest.raises(ValueError, match="'my_msgs/msg/Nope' is not known"):
        types.check_type("my_msgs/msg/Nope")
    with pytest.raises(ValueError, match="has no field.*lineer"):
        types.from_value({"lineer": [1, 0, 0]}, "geometry_msgs/msg/Twist")


def test_an_image_of_an_encoding_not_read_here_keeps_its_raw_fields():
    Image, Header = _jazzy.types["sensor_msgs/msg/Image"], _jazzy.types["std_msgs/msg/Header"]
    Time = _jazzy.types["builtin_interfaces/msg/Time"]
    message = Image(header=Header(stamp=Time(sec=0, nanosec=0), frame_id=""), height=1, width=2, encoding="nv21",
                    is_bigendian=0, step=3, data=np.arange(3, dtype=np.uint8))
    value = types.to_value(message, "sensor_msgs/msg/Image")
    assert "image" not in value and value["encoding"] == "nv21" and value["step"] == 3
    assert_equal(value["data"], np.arange(3, dtype=np.uint8))
    assert_equal(_through_cdr(value, "sensor_msgs/msg/Image"), value)
    bayer = types.to_value(types.from_value({"image": np.ones((2, 2), np.uint8), "encoding": "bayer_rggb8"},
                                            "sensor_msgs/msg/Image"), "sensor_msgs/msg/Image")
    assert_equal(bayer["image"], np.ones((2, 2), np.uint8))


@pytest.mark.parametrize("shape, type_name, said", [
    ((2, 2**31, 3), "sensor_msgs/msg/Image", r"shape \(2, 2147483648, 3\): its step 6442450944, length 12884901888 are past"),
    ((2**32 + 1,), "std_msgs/msg/UInt8MultiArray", r"its length 4294967297, dimension 0 4294967297 are past"),
])
def test_a_value_past_what_a_ros_message_holds_is_refused_before_its_bytes_are_copied(shape, type_name, said):
    """Publishing such a value copied it whole (gigabytes) before the serializer failed on it."""
    from tests.log.test_ros2_export import _no_gigabytes, _view

    with _no_gigabytes(), pytest.raises(ValueError, match=said + r" the uint32 a ROS 2 message holds sizes in"):
        types.from_value(_view(shape, np.uint8), type_name)


@pytest.mark.parametrize("value, type_name, error, said", [
    ([["x"]], "std_msgs/msg/String", TypeError,
     r"std_msgs/msg/String field data: takes a str.*got list of 1 \[\['x'\]\]"),
    (b"x", "std_msgs/msg/String", TypeError, r"std_msgs/msg/String field data: takes a str.*got bytes"),
    ({"stamp": 1}, "std_msgs/msg/String", ValueError, r"std_msgs/msg/String has no field\(s\) stamp"),
    ("false", "std_msgs/msg/Bool", TypeError, r"std_msgs/msg/Bool field data: takes a bool.*got str 'false'"),
    (1, "std_msgs/msg/Bool", TypeError, r"std_msgs/msg/Bool field data: takes a bool.*got int 1"),
    (3.7, "std_msgs/msg/Int32", ValueError, r"std_msgs/msg/Int32 field data: takes an int32.*got float 3.7"),
    ("3", "std_msgs/msg/Int32", TypeError, r"std_msgs/msg/Int32 field data: takes an int32.*got str '3'"),
    (True, "std_msgs/msg/Float64", TypeError, r"std_msgs/msg/Float64 field data: takes a float64.*got bool True"),
    (2**31, "std_msgs/msg/Int32", ValueError, r"std_msgs/msg/Int32 field data: takes an int32 .*-2147483648.*"
                                              r"2147483647.*got int 2147483648"),
    (-1, "std_msgs/msg/UInt8", ValueError, r"std_msgs/msg/UInt8 field data: takes a uint8 .*got int -1"),
    (1e39, "std_msgs/msg/Float32", ValueError, r"std_msgs/msg/Float32 field data: takes a float32.*got float 1e\+39"),
    ({"linear": [1, 2, 3, 4]}, "geometry_msgs/msg/Twist", ValueError,
     r"geometry_msgs/msg/Twist field linear: takes 3 numbers \[x, y, z\].*got list of 4 \[1, 2, 3, 4\]"),
    ({"linear": [1, "a", 3]}, "geometry_msgs/msg/Twist", TypeError,
     r"geometry_msgs/msg/Twist field linear.y: takes a float64.*got str 'a'"),
    ({"pose": {"orientation": [0, 0, 1]}}, "geometry_msgs/msg/PoseStamped", ValueError,
     r"geometry_msgs/msg/PoseStamped field pose.orientation: takes 4 numbers \[x, y, z, w\].*got list of 3"),
    ({"pose": [1, 2]}, "geometry_msgs/msg/PoseStamped", TypeError,
     r"geometry_msgs/msg/PoseStamped field pose: takes a dict of the fields of a geometry_msgs/msg/Pose.*got list"),
    ({"name": "ab"}, "sensor_msgs/msg/JointState", TypeError,
     r"sensor_msgs/msg/JointState field name: takes a sequence of string.*got str 'ab'"),
    ({"name": ["a", 1]}, "sensor_msgs/msg/JointState", TypeError,
     r"sensor_msgs/msg/JointState field name\[1\]: takes a str.*got int 1"),
    ({"position": [0.5, "x"]}, "sensor_msgs/msg/JointState", TypeError,
     r"sensor_msgs/msg/JointState field position: takes a sequence of float64.*got list of 2 \[0.5, 'x'\]"),
    ({"position": [[0.5], [1.0]]}, "sensor_msgs/msg/JointState", ValueError,
     r"sensor_msgs/msg/JointState field position: takes a sequence of float64.*"
     r"got an array of float64 of shape \(2, 1\)"),
    ({"orientation_covariance": np.zeros(8)}, "sensor_msgs/msg/Imu", ValueError,
     r"sensor_msgs/msg/Imu field orientation_covariance: takes 9 float64.*got an array of float64 of shape \(8,\)"),
    ({"data": [1, 256]}, "sensor_msgs/msg/CompressedImage", ValueError,
     r"sensor_msgs/msg/CompressedImage field data: takes a sequence of uint8 .*0.*255.*got .*256"),
    ({"data": [1.5]}, "sensor_msgs/msg/CompressedImage", ValueError,
     r"sensor_msgs/msg/CompressedImage field data: takes a sequence of uint8.*got .*not whole"),
    ({"data": [True]}, "sensor_msgs/msg/CompressedImage", TypeError,
     r"sensor_msgs/msg/CompressedImage field data: takes a sequence of uint8.*got an array of bool"),
    ({"stamp": 1.5}, "sensor_msgs/msg/JointState", ValueError,
     r"sensor_msgs/msg/JointState field stamp: takes an int of ns.*got float 1.5"),
    ({"stamp": "1"}, "sensor_msgs/msg/JointState", TypeError,
     r"sensor_msgs/msg/JointState field stamp: takes an int of ns.*got str '1'"),
    ({"frame_id": 7}, "sensor_msgs/msg/JointState", TypeError,
     r"sensor_msgs/msg/JointState field frame_id: takes a str.*got int 7"),
])
def test_a_value_that_does_not_convert_exactly_is_refused_naming_the_type_and_the_field(value, type_name, error, said):
    """Publishing converted silently: [['x']] became the String "[['x']]", "false" a True Bool, 3.7
    the Int32 3, a fourth element of a Vector3 was dropped, and an int past int32 failed in the
    serializer with struct's "'i' format requires ...", naming no field."""
    with pytest.raises(error, match=said):
        types.serialize(types.from_value(value, type_name), type_name)


def test_exact_conversions_still_pass():
    assert _through_cdr(3.0, "std_msgs/msg/Int32") == 3
    assert _through_cdr(np.int64(-4), "std_msgs/msg/Int8") == -4
    assert _through_cdr(np.bool_(False), "std_msgs/msg/Bool") is False
    assert _through_cdr(2, "std_msgs/msg/Float64") == 2.0
    assert _through_cdr(np.float32(0.5), "std_msgs/msg/Float32") == 0.5
    assert _through_cdr(2**64 - 1, "std_msgs/msg/UInt64") == 2**64 - 1
    assert _through_cdr(float("inf"), "std_msgs/msg/Float32") == float("inf")
    assert_equal(_through_cdr({"linear": np.array([1, 2, 3])}, "geometry_msgs/msg/Twist")["linear"],
                 np.array([1.0, 2, 3]))
    assert _through_cdr({"data": b"\xff\xd8"}, "sensor_msgs/msg/CompressedImage")["data"].tobytes() == b"\xff\xd8"
    assert _through_cdr({"stamp": 5.0}, "std_msgs/msg/Header")["stamp"] == 5
    assert_equal(_through_cdr({"data": np.array([1.0, 255.0])}, "std_msgs/msg/UInt8MultiArray"),
                 np.array([1, 255], np.uint8))


def test_a_msgdef_naming_an_unknown_type_is_refused_naming_it_and_registers_nothing():
    """It was a bare KeyError('nope_msgs/msg/Thing') from the type hash, and the type stayed
    registered half-made: a corrected definition then clashed with it."""
    from retriever.ros2 import Ros2Publisher

    with pytest.raises(ValueError, match=r"retriever_test_msgs/msg/Broken's msgdef names nope_msgs/msg/Thing "
                                         r"\(field x\), which is not known"):
        Ros2Publisher("/x", "retriever_test_msgs/msg/Broken", msgdef="nope_msgs/Thing x")
    Ros2Publisher("/x", "retriever_test_msgs/msg/Broken", msgdef="geometry_msgs/Point x")  # the fix is taken


def test_a_msgdef_under_a_name_not_of_three_parts_says_so_not_that_msgdef_is_missing():
    from retriever.ros2 import Ros2Publisher

    with pytest.raises(ValueError, match=r"(?s)'retriever_test_msgs/Short' is not a ROS 2 message type name.*"
                                         r"retriever_test_msgs/msg/Short"):
        Ros2Publisher("/x", "retriever_test_msgs/Short", msgdef="int32 a")


def test_a_type_defined_again_the_same_is_taken_and_differently_is_refused_clearly():
    """Defining it differently raised rosbags' TypesysError."""
    types.register_msg("retriever_test_msgs/msg/Twice", "int32 a\nstring b")
    types.register_msg("retriever_test_msgs/msg/Twice", "int32 a\nstring b")
    with pytest.raises(ValueError, match=r"(?s)retriever_test_msgs/msg/Twice is defined already, differently "
                                         r"\(int32 a, string b\).*give the new definition another name"):
        types.register_msg("retriever_test_msgs/msg/Twice", "float64 a\nstring b")


@pytest.mark.parametrize("name, definition, cycle", [
    ("retriever_test_msgs/msg/Rec", "retriever_test_msgs/Rec r",
     "retriever_test_msgs/msg/Rec -> retriever_test_msgs/msg/Rec"),
    ("retriever_test_msgs/msg/RecArray", "int32 a\nretriever_test_msgs/RecArray[2] more",
     "retriever_test_msgs/msg/RecArray -> retriever_test_msgs/msg/RecArray"),
    ("retriever_test_msgs/msg/RecSeq", "retriever_test_msgs/RecSeq[] children",
     "retriever_test_msgs/msg/RecSeq -> retriever_test_msgs/msg/RecSeq"),
])
def test_a_type_that_holds_itself_is_refused_at_registration_and_registers_nothing(name, definition, cycle):
    """It was registered, and its type hash (so the flow) or from_value then raised RecursionError."""
    from retriever.ros2 import Ros2Publisher

    with pytest.raises(ValueError, match=rf"(?s){name}'s msgdef holds itself: {cycle}.*hint: "):
        Ros2Publisher("/x", name, msgdef=definition)
    with pytest.raises(ValueError, match="is not known"):
        types.check_type(name)


def test_a_type_that_holds_itself_through_another_is_refused():
    ping, pong = "retriever_test_msgs/msg/Ping", "retriever_test_msgs/msg/Pong"
    definition = ("retriever_test_msgs/Pong pong\n"
                  "================================================================================\n"
                  f"MSG: {pong}\nretriever_test_msgs/Ping ping\n")
    with pytest.raises(ValueError, match=rf"holds itself: {ping} -> {pong} -> {ping}"):
        types.register_msg(ping, definition)
    for name in (ping, pong):
        with pytest.raises(ValueError, match="is not known"):
            types.check_type(name)


@pytest.mark.parametrize("definition", [
    "int32[4294967296] x",  # 16 GiB of zeros for {}
    "float64[2097153] x",  # one byte past 16 MiB
    "geometry_msgs/Point[200000] points",  # 200000 x (24 bytes + a Python object each)
])
def test_a_type_whose_fixed_arrays_hold_more_than_16_mib_is_refused(definition):
    """``int32[4294967296] x`` was registered, and from_value({}) then tried to allocate 16 GiB."""
    with pytest.raises(ValueError, match=r"(?s)retriever_test_msgs/msg/Huge's msgdef fixes more than 16777216 bytes "
                                         r"\(16 MiB.*hint: .*unbounded sequence"):
        types.register_msg("retriever_test_msgs/msg/Huge", definition)
    with pytest.raises(ValueError, match="is not known"):
        types.check_type("retriever_test_msgs/msg/Huge")


def test_fixed_arrays_up_to_16_mib_and_every_standard_type_are_taken():
    types.register_msg("retriever_test_msgs/msg/Big", "float64[2097151] x\nint32[] free")
    assert types.from_value({}, "retriever_test_msgs/msg/Big").x.shape == (2097151,)
    assert types.type_hash("nav_msgs/msg/Odometry").startswith("RIHS01_")
