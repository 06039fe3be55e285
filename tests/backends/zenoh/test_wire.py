"""The Zenoh runtime's wire format: exact round trips, and garbage refused with WireError only."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retriever import io
from retriever.backends.zenoh.wire import (
    DataMessage,
    KeySpace,
    WireEncoder,
    WireError,
    decode_data,
    decode_progress,
)
from retriever.codec import packb


@io
@dataclass
class Pose:
    xyz: np.ndarray
    frame: str = "world"


def test_key_space():
    keys = KeySpace("lab-1")
    assert keys.data("camera", "frame") == "retriever/lab-1/data/camera/frame"
    assert keys.all_data() == "retriever/lab-1/data/**"
    assert keys.progress("camera") == "retriever/lab-1/progress/camera"
    assert keys.parse_data("retriever/lab-1/data/camera/frame") == ("camera", "frame")
    assert keys.parse_data("retriever/other/data/camera/frame") is None
    assert keys.parse_data("retriever/lab-1/data/camera/frame/extra") is None
    for bad in ["", "a/b", "a*", "$x", "a?b", "#"]:
        with pytest.raises(ValueError, match="cannot be a Zenoh key chunk"):
            KeySpace(bad)


@pytest.mark.parametrize("value", [
    None, 1.5, -0.0, math.inf, 2**70, "text", b"\x00\xff", [1, (2, 3)], {"a": {1: [2.5]}},
    np.arange(12, dtype=np.float32).reshape(3, 4), np.array(7, dtype=np.int16),
    Pose(xyz=np.array([1.0, 2.0, 3.0])),
])
def test_data_round_trip(value):
    enc = WireEncoder()
    data = enc.data((1_000_000, 2), 41, (1_500_000, 0), "policy", "chunk", value)
    msg = decode_data(data, ("policy", "chunk"))
    assert msg[:5] == ((1_000_000, 2), 41, (1_500_000, 0), "policy", "chunk")
    assert packb(msg.value) == packb(value)  # bit-exact, whatever the type
    assert isinstance(msg, DataMessage)


def test_a_plain_msgpack_reader_can_decode_data_messages():
    data = WireEncoder().data((5, 0), 0, (5, 0), "cam", "frame", {"x": 1.0})
    assert msgpack.unpackb(data) == [1, [5, 0], 0, [5, 0], "cam", "frame", {"x": 1.0}]


def test_progress_round_trip():
    data = WireEncoder().progress((99, 3), "controller", {"chunk": 4, "state": -1})
    assert decode_progress(data, "controller") == ((99, 3), "controller", {"chunk": 4, "state": -1})
    with pytest.raises(WireError, match="progress of controller arrived on the key of camera"):
        decode_progress(data, "camera")


@pytest.mark.parametrize("data, match", [
    (b"", "msgpack array"),
    (b"hello world", "msgpack array"),
    (msgpack.packb({"tag": 1}), "msgpack array"),
    (msgpack.packb([1, [0, 0], 0, [0, 0], "a", "b"]), "array of 7, got 6"),
    (msgpack.packb([2, [0, 0], 0, [0, 0], "a", "b", 1]), "wire format 2"),
    (msgpack.packb([1, [0], 0, [0, 0], "a", "b", 1]), "tag must be"),
    (msgpack.packb([1, [0, -1], 0, [0, 0], "a", "b", 1]), "tag must be"),
    (msgpack.packb([1, [0, 0], -3, [0, 0], "a", "b", 1]), "seq must be"),
    (msgpack.packb([1, [9, 0], 0, [5, 0], "a", "b", 1]), "frontier .* before the event's own tag"),
    (msgpack.packb([1, [0, 0], 0, [0, 0], 7, "b", 1]), "producer and port must be strings"),
    (msgpack.packb([1, [0, 0], 0, [0, 0], "x", "b", 1]), "for x.b arrived on the key of a.b"),
    (msgpack.packb([1, [0, 0], 0, [0, 0], "a", "b", 1]) + b"\x01", "not valid msgpack"),
    (msgpack.packb([1, [0, 0], 0, [0, 0], "a", "b", msgpack.ExtType(99, b"")]), "cannot be decoded"),
    (msgpack.packb([1, [0, 0], 0, [0, 0], "a", "b",
                    msgpack.ExtType(4, msgpack.packb(["not_imported_module_xyz:Thing", {}]))]),
     "refusing to decode .*not_imported_module_xyz"),
])
def test_garbage_is_a_wire_error(data, match):
    with pytest.raises(WireError, match=match):
        decode_data(data, ("a", "b"))


def test_a_message_cannot_make_the_receiver_import_a_module():
    module = "json.tool"  # importable, but not imported by this test process
    sys.modules.pop(module, None)
    data = msgpack.packb([1, [0, 0], 0, [0, 0], "a", "b",
                          msgpack.ExtType(4, msgpack.packb([f"{module}:main", {}]))])
    with pytest.raises(WireError, match="refusing"):
        decode_data(data, ("a", "b"))
    assert module not in sys.modules


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64) | st.builds(lambda parts: msgpack.packb(parts), st.lists(
    st.one_of(st.integers(-5, 2**64 - 1), st.text(max_size=5), st.lists(st.integers(-2, 5), max_size=3),
              st.binary(max_size=8), st.none()), max_size=8)))
def test_any_bytes_decode_or_raise_wire_error(data):
    """Fuzz: nothing but a DataMessage or a WireError ever comes out of the decoders."""
    for decode in (decode_data, decode_progress):
        try:
            decode(data)
        except WireError:
            pass
