"""How much Python a message costs on its hot path (issue 42; benchmarks/hot_path_cost.py counts
its instructions): a data message's decoding, its delivery to an input buffer, a step's outputs
read and stamped, an array's encoding. Each is counted in calls (``sys.setprofile``), so a
change that puts calls back on the path fails here; and the short ways these counts ask for
still refuse what the long ways refuse, and give what they give.

Real node loops, rebuilt from the IR as a worker does, on a real (unconnected) Zenoh session.
"""

from __future__ import annotations

import sys

import msgpack
import numpy as np
import pytest

from retriever import Pipeline, Rate, Trigger
from retriever.backends.zenoh.wire import DataMessage, WireEncoder, WireError, decode_events
from retriever.backends.zenoh.worker.build import build_loop
from retriever.codec import OutOfBandEncoder, unpackb_out_of_band
from retriever.errors import CodecError
from retriever.flow.core import make_output_reader

from .payload_flows import Camera, Frame, Viewer, frame
from .specs import run_spec

MS = 1_000_000


def calls(function, *args) -> tuple[list[str], list]:
    """What ``function(*args)`` calls, itself first: its Python functions' names, and the C
    functions it calls."""
    python, c = [], []

    def profile(frame, event, arg):
        if event == "call":
            python.append(frame.f_code.co_name)
        elif event == "c_call":
            c.append(arg)

    sys.setprofile(profile)
    try:
        function(*args)
    finally:
        sys.setprofile(None)
    return python, c


def locked(c_calls: list) -> int:
    """How often a lock was released (``with lock``: its ``__exit__``) among ``c_calls``."""
    return sum(1 for f in c_calls if getattr(f, "__name__", "") == "__exit__"
               and "lock" in type(getattr(f, "__self__", None)).__name__)


@pytest.fixture(scope="module")
def spec():
    with Pipeline("hot-path") as pipe:
        cam = Camera(size=4096).named("cam") @ Rate(20)
        cam.then(Viewer().named("viewer") @ Trigger("image"))
    return run_spec(pipe.compile().to_ir().doc, "hot-path-test")


def message(k: int, array: np.ndarray) -> bytes:
    return WireEncoder().data((k * 50 * MS, 0), k, (k * 50 * MS + 1, 0), "cam", "image",
                              {"image": array, "k": k})


def bins(data: bytes) -> tuple[bytes, bytes]:
    """The envelope and the array of a message of one array, as bytes."""
    assert data[0] == 0x92 and data[1] == 0xC6
    end = 6 + int.from_bytes(data[2:6], "big")
    return data[6:end], data[end + 5:]


def of_bins(*parts: bytes) -> bytes:
    return bytes((0x90 + len(parts),)) + b"".join(b"\xc6" + len(p).to_bytes(4, "big") + p for p in parts)


def test_a_message_of_an_array_decodes_with_three_calls_once_its_array_head_is_known():
    """decode_events, its bins, msgpack with its hook, and the hook: no call to check the
    array's head again (it decoded before), none to make the DataMessage."""
    array = frame(1, 4096).reshape(-1, 1024)
    decode_events(message(0, array), expected=("cam", "image"))
    data = message(1, array)
    python, _ = calls(decode_events, data, ("cam", "image"))
    assert python == ["decode_events", "_bins", "unpackb_out_of_band", "hook"]
    (event,) = decode_events(data, expected=("cam", "image"))
    assert type(event) is DataMessage and event[:5] == ((50 * MS, 0), 1, (50 * MS + 1, 0), "cam", "image")
    got = event.value["image"]
    assert got.shape == (4, 1024) and got.dtype == np.uint8 and not got.flags.writeable
    assert np.array_equal(got, array)
    flat = decode_events(message(2, frame(2, 4096)))[0].value["image"]  # the same bytes, 1-D: a head of its own
    assert flat.shape == (4096,) and np.array_equal(flat, frame(2, 4096)) and not flat.flags.writeable


def test_a_known_array_head_is_still_refused_with_a_buffer_it_does_not_fit():
    """The head decoded before, with a buffer one byte short, or none: refused as before."""
    array = frame(1, 4096)
    decode_events(message(0, array))
    envelope, raw = bins(message(1, array))
    with pytest.raises(WireError, match="does not fit its buffer of 4095 bytes"):
        decode_events(of_bins(envelope, raw[:-1]))
    with pytest.raises(WireError, match="refers to buffer 0, which the message does not carry"):
        decode_events(of_bins(envelope))
    with pytest.raises(CodecError, match="refers to buffer 0"):
        unpackb_out_of_band(envelope, [])
    other = np.zeros(1024, np.float32)  # the same 4096 bytes, another dtype: another head
    decode_events(message(0, other))
    assert decode_events(of_bins(envelope, raw))[0].value["image"].dtype == np.uint8


@pytest.mark.parametrize("cut, error", [
    (lambda d: d + b"\x00", "trailing bytes"),
    (lambda d: d[:-1], "truncated"),
    (lambda d: d[:7], "truncated"),
    (lambda d: d[:4], "truncated"),
    (lambda d: d[:2] + (2**32 - 1).to_bytes(4, "big") + d[6:], "truncated"),
])
def test_a_message_of_two_bins_cut_or_padded_is_refused_as_before(cut, error):
    """The short way through a message of an envelope and one array (``_bins``) refuses what
    the general one does, with the same words."""
    data = message(1, frame(1, 64))
    assert decode_events(data)[0].seq == 1
    with pytest.raises(WireError, match=error):
        decode_events(cut(data))


def test_an_event_in_order_is_delivered_with_one_call(session, spec):
    """Streams.in_order puts an event after its buffer's last one without sync.fill and
    PortBuffer.insert (inline); an event before it still goes in its place by tag."""
    loop = build_loop(spec, "viewer", session)
    loop.run_clock.start(0, 10**12)
    streams, stream = loop.streams, ("cam", "image")
    buf = streams.edges[0].buf

    def event(seq: int, t: int) -> DataMessage:
        return DataMessage((t, 0), seq, (t + 1, 0), "cam", "image", Frame(image=frame(seq, 4096), k=seq))

    streams.in_order(stream, event(0, 10 * MS))
    python, c = calls(streams.in_order, stream, event(1, 20 * MS))
    assert python == ["in_order", "deliver"]
    assert locked(c) == 1, "its frontier and its tick pending, under one acquisition of the lock"
    streams.in_order(stream, event(2, 15 * MS))  # (a producer's clock may step back: its tag orders it)
    assert [entry[0] for entry in buf.entries] == [(10 * MS, 0), (15 * MS, 0), (20 * MS, 0)]
    assert [entry[3] for entry in buf.entries] == [0, 2, 1]
    assert loop.schedule.pending == [(10 * MS, 0), (20 * MS, 0), (15 * MS, 0)]
    assert streams.frontiers[stream] == (20 * MS + 1, 0) and streams.expect[stream] == 3


def test_an_event_is_taken_and_delivered_by_its_fields_positions_not_their_names(session, spec):
    """A NamedTuple's field read by name is a generic attribute lookup at every read in CPython
    3.11 (no specialisation): Streams.in_order and deliver read a DataMessage's fields by
    position (one unpacking), so a plain tuple of the same fields is taken the same way."""
    loop = build_loop(spec, "viewer", session)
    loop.run_clock.start(0, 10**12)
    streams, stream = loop.streams, ("cam", "image")
    value = Frame(image=frame(0, 4096), k=0)
    streams.in_order(stream, ((10 * MS, 0), 0, (10 * MS + 1, 0), "cam", "image", value))  # (no field names)
    streams.in_order(stream, DataMessage((20 * MS, 0), 1, (20 * MS + 1, 0), "cam", "image", value))
    buf = streams.edges[0].buf
    assert [entry[:4] for entry in buf.entries] == [((10 * MS, 0), "cam", "image", 0), ((20 * MS, 0), "cam", "image", 1)]
    assert buf.entries[0][4] is value and streams.frontiers[stream] == (20 * MS + 1, 0)
    assert loop.schedule.pending == [(10 * MS, 0), (20 * MS, 0)]


def test_a_pass_reads_the_next_tick_without_the_lock(session, spec):
    """The loop's thread is the schedule's only writer: reading it, it takes no lock (the lock
    is for the progress queryable, which reads it from another thread)."""
    loop = build_loop(spec, "viewer", session)
    loop.run_clock.start(0, 10**12)
    loop.schedule.pending, loop.schedule.pending_set = [(30 * MS, 0)], {(30 * MS, 0)}
    python, c = calls(loop.try_tick, 10 * MS)
    assert python == ["try_tick"] and locked(c) == 0
    assert loop.try_tick(10 * MS) == 30 * MS


def test_a_steps_outputs_are_read_and_stamped_without_calls(session, spec):
    """The step's output object read into events (no comprehension) and stamped with the HLC
    (read inline): one Python call each."""
    loop = build_loop(spec, "cam", session)
    loop.run_clock.start(session.new_timestamp().get_time_as_ntp64().as_nanos(), 10**12)
    read = make_output_reader(loop.node.spec)
    out = Frame(image=frame(1, 4096), k=1)
    python, _ = calls(read, out)
    assert python == ["read_io"]
    assert read(out) == [("image", out.image), ("k", 1)]
    assert read(Frame(image=None, k=2)) == [("k", 2)]
    python, _ = calls(loop.outputs.stamp, (0, 0), [("k", 1)])
    assert python == ["stamp"]
    tag, batch, produced = loop.outputs.stamp((0, 0), [("k", 2)])
    assert tag[0] > 0 and tag[1] == 0 and batch == [(tag, "k", 2, 1)] and produced == (("cam", "k", 1),)
    assert loop.outputs.stamp((0, 0), [("k", 3)])[0] > tag, "strictly increasing"


def test_a_steps_end_reads_the_frontier_its_outputs_carry_in_the_lock_section_that_ends_the_tick(session, spec):
    """Steps.finish_tick marks the tick done and reads the frontier the outputs carry under one
    acquisition of the lock (not one each); the put's end takes its own. The
    message carries the frontier a publish read itself would have."""
    loop = build_loop(spec, "cam", session)
    loop.declare()
    heard = session.declare_subscriber(loop.keys.data("cam", "k"))  # (the same session: heard in the put)
    try:
        loop.run_clock.start(session.new_timestamp().get_time_as_ntp64().as_nanos(), 10**12)
        outputs, steps = loop.outputs, loop.steps
        outputs.consumed = True

        def end(k: int) -> None:
            loop.schedule.running = (k * MS, 0)
            tag, batch, produced = outputs.stamp((k * MS, 0), [("k", k)])
            steps.finish_tick((k * MS, 0), {}, produced, "ok", None, 0, 1, publish=batch)

        end(1)
        python, c = calls(end, 2)
        assert "frontier_held" in python and "frontier" not in python
        assert locked(c) == 2, "the tick's end with its frontier, and the put's end: one section each"
        assert loop.schedule.running is None and outputs.sending is None
        sent = [heard.try_recv(), heard.try_recv()]
        assert sent[1] is not None and heard.try_recv() is None, "one message per tick's end"
        assert decode_events(sent[1].payload.to_bytes())[0].frontier == outputs.frontier(True)
    finally:
        heard.undeclare()
        loop.undeclare()


def test_an_arrays_index_is_packed_as_msgpack_packs_it():
    """An array's extension data is its cached head and its buffer index: a positive fixint
    from a table up to 127 (no packer's call; msgpack's Cython calls are not profiled, so what
    is checked here is only that it packs as msgpack does), packed by msgpack past that."""
    encoder = OutOfBandEncoder()
    arrays = [np.full(3, i % 256, np.uint8) for i in range(130)]
    body, buffers = encoder.pack(arrays)
    exts = msgpack.unpackb(body)
    assert [msgpack.unpackb(e.data)[2] for e in exts] == list(range(130))
    assert [e.data[-1:] for e in exts[:128]] == [msgpack.packb(i) for i in range(128)]
    got = unpackb_out_of_band(body, [b.tobytes() for b in buffers])
    assert all(np.array_equal(g, a) for g, a in zip(got, arrays))


@pytest.mark.parametrize("array, numpy_calls", [
    (np.arange(64, dtype=np.uint8), []),  # bytes, flat: its own buffer
    (np.arange(16, dtype=np.float32), ["view"]),  # flat: viewed as bytes
    (np.arange(64, dtype=np.uint8).reshape(8, 8), ["reshape", "view"]),
    (np.arange(64, dtype=np.uint8).reshape(8, 8)[:, ::2], ["reshape", "view"]),  # made contiguous first
    (np.array(7, dtype=np.int64), ["reshape", "view"]),  # 0-d
])
def test_an_array_is_sent_as_its_bytes_with_no_more_numpy_calls_than_its_shape_needs(array, numpy_calls):
    """A flat array of bytes is its own buffer; another flat one is viewed as bytes; others
    flattened first. The message is what it was, and decodes to the array."""
    encoder = OutOfBandEncoder()
    encoder.pack({"a": array})
    _, c = calls(encoder.pack, {"a": array})
    assert [f.__name__ for f in c if type(getattr(f, "__self__", None)) is np.ndarray] == numpy_calls
    data = message(3, array)
    assert data == b"".join(WireEncoder().data_parts((150 * MS, 0), 3, (150 * MS + 1, 0), "cam", "image",
                                                      {"image": array, "k": 3}))
    contiguous = np.ascontiguousarray(array)
    assert data.endswith(contiguous.tobytes()) and bins(data)[1] == contiguous.tobytes()
    got = decode_events(data)[0].value["image"]
    assert got.dtype == array.dtype and got.shape == array.shape and np.array_equal(got, array)


def test_a_publish_reads_the_frontier_and_a_tick_trims_its_input_without_min_or_max(session, spec):
    """builtin min and max parse keywords at every call: the stamp, the frontier a publish
    carries, the tick bound and a Latest input's trim compare inline, with the same results."""
    loop = build_loop(spec, "viewer", session)
    loop.run_clock.start(session.new_timestamp().get_time_as_ntp64().as_nanos(), 10**12)
    streams, outputs = loop.streams, loop.outputs
    streams.frontiers[("cam", "image")] = (40 * MS, 3)
    loop.schedule.pending = [(30 * MS, 0)]
    python, c = calls(streams.tick_bound)
    assert python == ["tick_bound"] and not [f for f in c if f in (min, max)]
    assert streams.tick_bound() == (30 * MS, 0)
    loop.schedule.pending = [(50 * MS, 0)]
    assert streams.tick_bound() == (40 * MS, 3)
    outputs.last_stamp = 10**13  # past the HLC: the stamp goes on from the last one
    python, c = calls(outputs.stamp, (0, 0), [("checksum", 1)])
    assert python == ["stamp"] and not [f for f in c if f in (min, max)]
    assert outputs.stamp((0, 0), [("checksum", 2)])[0] == (10**13 + 2, 0)
    python, c = calls(outputs.frontier_held, True)
    assert python == ["frontier_held", "tick_bound"] and not [f for f in c if f in (min, max)]
    assert outputs.frontier(True) == (10**13 + 3, 0)
    outputs.last_stamp = 0
    assert outputs.frontier(True) == (40 * MS + 1, 0), "past the tick bound"
    buf = streams.edges[0].buf
    buf.entries[:] = [((t * MS, 0), "cam", "image", t, None) for t in range(6)]
    buf.visible, buf.cursor = 6, 2
    python, c = calls(buf.trim, 5)
    assert python == ["trim"] and not [f for f in c if f in (min, max)]
    assert len(buf.entries) == 1 and buf.visible == 1 and buf.cursor == 0
