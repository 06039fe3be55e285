"""The Zenoh runtime's wire format: exact round trips, and garbage refused with WireError only."""

from __future__ import annotations

import math
import sys
from dataclasses import dataclass
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retriever import Burst, io
from retriever.backends.zenoh.protocol import Report
from retriever.backends.zenoh.wire import (
    DataMessage,
    KeySpace,
    WireEncoder,
    WireError,
    decode_data,
    decode_events,
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
    assert keys.run_control() == "retriever/lab-1/ctl/run" and keys.start() == "retriever/lab-1/ctl/start"
    assert {keys.run_control(), keys.start()} == {keys.ctl(name) for name in KeySpace.COORDINATOR_CONTROL}
    assert KeySpace.every_control() == "retriever/*/ctl/**"
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


@pytest.mark.parametrize("value", [
    {"left": np.zeros((4, 6), np.uint8), "right": np.ones((2, 3, 5), ">f4")[:, ::2]},  # non-contiguous
    (np.arange(3), [np.float64(2.5), np.zeros(0, np.int8)]),
    Pose(xyz=np.arange(3.0)),
    np.zeros(3, "M8[ns]"),
    np.zeros(2, dtype=[("a", "<i4"), ("b", "<f8")]),
])
def test_arrays_anywhere_in_a_value_travel_out_of_band(value):
    data = WireEncoder().data((1, 0), 0, (1, 0), "a", "b", value)
    assert len(msgpack.unpackb(data)) > 1  # envelope + one bin per array
    assert packb(decode_data(data, ("a", "b")).value) == packb(value)


def test_received_arrays_are_read_only_views_of_the_message():
    frame = np.arange(1 << 16, dtype=np.uint16).reshape(256, 256)
    data = WireEncoder().data((1, 0), 0, (1, 0), "cam", "frame", {"image": frame, "t": 3})
    image = decode_data(data, ("cam", "frame")).value["image"]
    assert np.array_equal(image, frame) and not image.flags.writeable
    start = np.frombuffer(data, np.uint8).__array_interface__["data"][0]
    inside = image.__array_interface__["data"][0]
    assert start <= inside and inside + image.nbytes <= start + len(data)  # no copy was made
    with pytest.raises(ValueError, match="read-only"):
        image[0, 0] = 1


def test_a_plain_msgpack_reader_can_decode_data_messages():
    """docs/security.md's recipe: unpack the array of bins, unpack the envelope, arrays from the bins."""
    data = WireEncoder().data((5, 0), 0, (5, 0), "cam", "frame", {"x": 1.0, "image": np.eye(2, dtype="<f4")})
    envelope, *buffers = msgpack.unpackb(data)

    def ext_hook(code, payload):
        assert code == 6
        descr, shape, index = msgpack.unpackb(payload)
        return np.frombuffer(buffers[index], dtype=descr).reshape(shape)

    decoded = msgpack.unpackb(envelope, ext_hook=ext_hook)
    assert decoded[:6] == [2, [5, 0], 0, [5, 0], "cam", "frame"]
    assert decoded[6]["x"] == 1.0 and np.array_equal(decoded[6]["image"], np.eye(2))
    data = WireEncoder().data((5, 0), 0, (5, 0), "cam", "frame", Burst(np.eye(3, dtype="<f4")))  # docs/security.md
    envelope, *buffers = msgpack.unpackb(data)
    *_, value, count = msgpack.unpackb(envelope, ext_hook=ext_hook)
    assert count == 3 and [list(row) for row in value] == np.eye(3).tolist()


def _message(envelope: list, *buffers: bytes) -> bytes:
    """A data message built by hand, the way another msgpack library would."""
    return msgpack.packb([msgpack.packb(envelope), *buffers])


def _ext_array(descr, shape, index):
    return msgpack.ExtType(6, msgpack.packb([descr, shape, index]))


def test_a_burst_is_one_message_of_its_events():
    """Each event at the tag with its own seq; the frontier after the last only (the others
    promise no more than their own tag); arrays out of band, read-only views, as for one event."""
    frames = [np.full((2, 3), i, np.uint8) for i in range(3)]
    data = WireEncoder().data((5, 1), 10, (9, 0), "cam", "frame", Burst([frames[0], "text", frames[2]]))
    events = decode_events(data, ("cam", "frame"))
    assert [e[:5] for e in events] == [((5, 1), 10, (5, 1), "cam", "frame"), ((5, 1), 11, (5, 1), "cam", "frame"),
                                       ((5, 1), 12, (9, 0), "cam", "frame")]
    assert np.array_equal(events[0].value, frames[0]) and events[1].value == "text"
    assert not events[2].value.flags.writeable
    assert len(msgpack.unpackb(data)) == 3  # the envelope and one bin per array
    with pytest.raises(WireError, match="a burst of 3 events where one event was expected"):
        decode_data(data)
    assert decode_events(WireEncoder().data((5, 1), 0, (5, 1), "a", "b", 7)) == [((5, 1), 0, (5, 1), "a", "b", 7)]


@pytest.mark.parametrize("values, count, match", [
    ([1, 2], 3, "as many values as its count"), ([1, 2], 1, "as many values"), ("ab", 2, "as many values"),
    ({"a": 1}, 1, "as many values"), ([], 0, "count must be an integer from 1 to 65536"), ([1], True, "count must be"),
    ([1], 1.0, "count must be"), ([1], -1, "count must be"), ([1] * 3, (1 << 16) + 1, "count must be"),
    (None, 2**64 - 1, "count must be"), (["x"], msgpack.ExtType(3, b"9" * 100), "count must be"),  # a big int
    (None, 2, "as many values"),  # values left out: only in a report (blank_ok), never on a data key
    (_ext_array("<f8", [3, 2], 0), 2, "an array of as many rows"),  # 3 rows, count 2
    (_ext_array("|V0", [1 << 16], 0), 1 << 16, "an array of as many rows|cannot be decoded"),
])
def test_a_burst_whose_count_is_not_its_values_is_a_wire_error(values, count, match):
    with pytest.raises(WireError, match=match):
        decode_events(_message([2, [0, 0], 0, [0, 0], "a", "b", values, count], b"\x00" * 48), ("a", "b"))


def test_a_few_bytes_cannot_make_a_burst_of_empty_rows():
    empty_rows = _ext_array("<f8", [1 << 16, 0], 0)
    with pytest.raises(WireError, match="an array of as many rows"):
        decode_events(_message([2, [0, 0], 0, [0, 0], "a", "b", empty_rows, 1 << 16], b""), ("a", "b"))


def test_a_burst_may_not_run_past_the_last_seq():
    with pytest.raises(WireError, match="runs past the last seq a stream has"):
        decode_events(_message([2, [0, 0], (1 << 63) - 1, [0, 0], "a", "b", [1, 2], 2]), ("a", "b"))
    with pytest.raises(WireError, match="seq must be an integer from 0 to 2"):
        decode_events(_message([2, [0, 0], 1 << 63, [0, 0], "a", "b", 1]), ("a", "b"))


def test_a_blank_burst_is_taken_from_a_report_only():
    blank = _message([2, [0, 0], 0, [0, 0], "a", "b", None, 3])
    assert [e.value for e in decode_events(blank, ("a", "b"), blank_ok=True)] == [None] * 3
    with pytest.raises(WireError, match="as many values"):
        decode_events(blank, ("a", "b"))


def test_a_burst_of_a_1d_array_is_its_numpy_scalars_as_one_array():
    burst = Burst(np.arange(1000, dtype=">f8"))
    data = WireEncoder().data((5, 1), 0, (5, 1), "a", "b", burst)
    got = [e.value for e in decode_events(data)]
    assert len(msgpack.unpackb(data)) == 2 and [packb(g) for g in got] == [packb(v) for v in burst]
    assert type(got[0]) is np.float64  # (a numpy scalar is native, as the values in-process are)


def test_a_burst_of_arrays_of_one_dtype_and_shape_is_one_array_of_rows():
    for rows in (np.arange(24, dtype=np.int16).reshape(4, 3, 2), np.arange(24, dtype=">i2").reshape(4, 3, 2)):
        for burst in (Burst(rows), Burst(list(rows))):
            data = WireEncoder().data((5, 1), 0, (5, 1), "a", "b", burst)
            # one bin; but numpy stacks arrays of another byte order into native ones: not those
            one_array = burst.rows is not None or rows.dtype.isnative
            assert len(msgpack.unpackb(data)) == (2 if one_array else 5)  # the envelope and the bins
            got = [e.value for e in decode_events(data)]
            assert [packb(g) for g in got] == [packb(r) for r in rows] and not got[0].flags.writeable
    mixed = Burst([np.zeros(2), np.zeros(3), np.zeros(2, np.float32), np.float64(1), np.array(2.0)])
    got = [e.value for e in decode_events(WireEncoder().data((5, 1), 0, (5, 1), "a", "b", mixed))]
    assert [packb(g) for g in got] == [packb(v) for v in mixed] and type(got[3]) is np.float64


def test_an_envelope_of_nine_is_a_wire_error():
    with pytest.raises(WireError, match="must be an array of 7 \\(an event\\) or 8 \\(a burst\\)"):
        decode_events(_message([2, [0, 0], 0, [0, 0], "a", "b", [1], 1, 0]), ("a", "b"))


def test_progress_round_trip():
    data = WireEncoder().progress((99, 3), "controller", {"chunk": 4, "state": -1})
    assert decode_progress(data, "controller") == ((99, 3), "controller", {"chunk": 4, "state": -1})
    with pytest.raises(WireError, match="progress of controller arrived on the key of camera"):
        decode_progress(data, "camera")


@pytest.mark.parametrize("data, match", [
    (b"", "truncated"),
    (b"hello world", "msgpack array of bins"),
    (msgpack.packb({"tag": 1}), "msgpack array of bins"),
    (msgpack.packb([2, [0, 0], 0, [0, 0], "a", "b", 1]), "msgpack array of bins"),  # not framed
    (msgpack.packb([]), "must hold an envelope"),
    (b"\x91\xc6\x00\x00\x01\x00abc", "truncated"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b", 1]) + b"\x01", "trailing bytes"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b"]), "array of 7"),
    (_message({"tag": 1}), "array of 7"),
    (_message([1, [0, 0], 0, [0, 0], "a", "b", 1]), "wire format 1"),
    (_message([2, [0], 0, [0, 0], "a", "b", 1]), "tag must be"),
    (_message([2, [0, -1], 0, [0, 0], "a", "b", 1]), "tag must be"),
    (_message([2, [0, 0], -3, [0, 0], "a", "b", 1]), "seq must be"),
    (_message([2, [9, 0], 0, [5, 0], "a", "b", 1]), "frontier .* before the event's own tag"),
    (_message([2, [0, 0], 0, [0, 0], 7, "b", 1]), "producer and port must be strings"),
    (_message([2, [0, 0], 0, [0, 0], "x", "b", 1]), "for x.b arrived on the key of a.b"),
    (msgpack.packb([msgpack.packb([2, [0, 0], 0, [0, 0], "a", "b", 1]) + b"\x01"]), "not valid msgpack"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b", msgpack.ExtType(99, b"")]), "cannot be decoded"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b",
               msgpack.ExtType(4, msgpack.packb(["not_imported_module_xyz:Thing", {}]))]),
     "'not_imported_module_xyz:Thing': no value type of that name is registered"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b", _ext_array("<f8", [2], 0)]), "buffer 0, which the message does not"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b", _ext_array("<f8", [2], 1)], b"\x00" * 16), "buffer 1"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b", _ext_array("<f8", [3], 0)], b"\x00" * 16), "does not fit"),
    (_message([2, [0, 0], 0, [0, 0], "a", "b", _ext_array("no such dtype", [2], 0)], b"\x00" * 16),
     "cannot be decoded|not valid"),
])
def test_garbage_is_a_wire_error(data, match):
    with pytest.raises(WireError, match=match):
        decode_data(data, ("a", "b"))


def test_a_message_cannot_make_the_receiver_import_a_module():
    module = "json.tool"  # importable, but not imported by this test process
    sys.modules.pop(module, None)
    data = _message([2, [0, 0], 0, [0, 0], "a", "b", msgpack.ExtType(4, msgpack.packb([f"{module}:main", {}]))])
    with pytest.raises(WireError, match="no value type of that name is registered in this process"):
        decode_data(data, ("a", "b"))
    assert module not in sys.modules


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64) | st.builds(lambda parts: msgpack.packb(parts), st.lists(
    st.one_of(st.integers(-5, 2**64 - 1), st.text(max_size=5), st.lists(st.integers(-2, 5), max_size=3),
              st.binary(max_size=8), st.none()), max_size=8))
       | st.builds(lambda parts: msgpack.packb([msgpack.packb(parts), b"\x00" * 8]), st.lists(
           st.one_of(st.integers(-5, 5), st.text(max_size=3), st.just([0, 0]),
                     st.builds(_ext_array, st.sampled_from(["<f8", "|u1", "<i4"]), st.lists(st.integers(-1, 9),
                                                                                           max_size=2),
                               st.integers(-1, 2))), max_size=8)))
def test_any_bytes_decode_or_raise_wire_error(data):
    """Fuzz: nothing but a decoded message or a WireError ever comes out of the decoders."""
    for decode in (decode_data, decode_progress, Report.decode):
        try:
            decode(data)
        except WireError:
            pass


def test_the_readmes_plain_msgpack_snippet_decodes_every_kind_of_value():
    """docs/security.md shows how a plain Zenoh subscriber decodes a data message; run that very
    code on arrays (plain, structured, nested in containers), numpy scalars and tuples."""
    readme = (Path(__file__).resolve().parents[3] / "docs" / "security.md").read_text(encoding="utf-8")
    snippet = readme.split("Decoding a data message with plain msgpack:", 1)[1].split("```python\n", 1)[1]
    snippet = snippet.split("```", 1)[0]
    structured = np.zeros(2, dtype=[("a", "<f4"), ("b", "<i8", (2,))])
    values = [np.arange(6).reshape(2, 3), structured, {"k": [np.ones(3)]}, np.float32(1.5), (1, 2), "text"]
    for value in values:
        message = WireEncoder().data((5, 0), 3, (6, 0), "cam", "frame", value)

        class Sample:
            class payload:  # noqa: N801 - shaped like zenoh's sample.payload
                @staticmethod
                def to_bytes() -> bytes:
                    return message

        scope = {"msgpack": msgpack, "np": np, "sample": Sample}
        exec(snippet, scope)
        assert (scope["version"], scope["tag"], scope["seq"], scope["producer"], scope["port"]) == (
            2, [5, 0], 3, "cam", "frame")
        got = scope["value"]
        if isinstance(value, np.ndarray):
            assert got.dtype == value.dtype and np.array_equal(got, value)
        elif isinstance(value, dict):
            assert np.array_equal(got["k"][0], value["k"][0])
        elif isinstance(value, (np.generic, tuple)):
            assert isinstance(got, msgpack.ExtType) and got.code in (2, 5)  # left to retriever/codec.py
        else:
            assert got == value


def test_a_data_message_whose_version_is_an_array_is_garbage():
    # found by benchmarks/fuzz.py: the envelope decodes with the codec, and an array's != is an
    # array, whose truth value raised ValueError
    from retriever.codec import packb

    envelope = b"\x97" + packb(np.array([2, 2])) + b"".join(msgpack.packb(x) for x in [[0, 0], 0, [0, 0], "a", "b", 1])
    with pytest.raises(WireError, match=r"a data message of wire format array\(\[2, 2\]\); this process speaks 2"):
        decode_data(msgpack.packb([envelope]))
