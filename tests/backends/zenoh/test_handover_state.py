"""The hand-over state file (node/handover.py: a restarting flow's old process writes it, the new
one reads it, decoded by protocol/handover.py), attacked: garbage, a map of other fields, fields
of the wrong type, another node's inputs. Each is refused with an error that names the file and
the field, before the new process goes on from it; a state as the old process writes it comes
back whole. The decoder alone, without a loop: test_protocol_handover.py."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from retriever import Burst
from retriever.backends.zenoh.node import handover
from retriever.codec import packb
from retriever.errors import WorkerError

from . import test_restart_afresh as by_hand
from .test_restart_afresh import MS, STREAM, data

loop = by_hand.loop  # its fixture: the NodeLoop of a Queue consumer of counter.value (session: conftest.py)


def _filled(loop) -> None:
    """Events in the buffer, one early (seq 3 before 2), held LET outputs (one a burst)."""
    for seq, t in ((0, 50), (1, 100), (3, 150)):
        loop.handle(data(seq, t))
    loop.outputs.held = [((5 * MS, 0), "saw", Burst(["a", "b"]), 3), ((6 * MS, 0), "saw", "c", 5)]


def _state_file(tmp_path, state: dict):
    path = tmp_path / "where.handover"
    path.write_bytes(packb(state))
    return path


def test_a_state_as_the_old_process_writes_it_comes_back_whole(loop, tmp_path):
    _filled(loop)
    written = loop.handover_state()
    state = handover.read_state(_state_file(tmp_path, written), loop)
    assert state.streams[0][:2] == STREAM and sorted(m[1] for m in state.streams[0][4]) == [3]
    assert len(state.buffers[0][1]) == 2 and state.values is True
    loop.outputs.held, loop.streams.early[STREAM] = [], {}
    handover.take_over(loop, state)
    assert loop.handover_state() == written
    assert type(loop.outputs.held[0][2]) is Burst and loop.outputs.held[0][2].values == ("a", "b")


def test_a_buffer_goes_as_runs_and_comes_back_as_its_entries(loop, tmp_path):
    """A run: one tag, producer and port, consecutive seqs (a burst, or what is left of one);
    arrays of one dtype and shape as the rows of one array. What is read back is what was there."""
    rows = np.arange(12, dtype=np.float32).reshape(4, 3)
    entries = [((50 * MS, 0), "counter", "value", 0, "a"), ((50 * MS, 0), "counter", "value", 1, ("b", 1)),
               ((50 * MS, 0), "counter", "value", 3, "after a gap"),
               ((60 * MS, 0), "counter", "value", 4, rows[0]), ((60 * MS, 0), "counter", "value", 5, rows[1]),
               ((65 * MS, 0), "counter", "value", 6, np.zeros(2, np.int8)),
               ((70 * MS, 1), "counter", "value", 7, np.float32(2.5)), ((70 * MS, 1), "counter", "value", 8, {"c": 3}),
               ((70 * MS, 1), "counter", "value", 9, rows[2])]  # arrays beside other values: one by one
    (_, buf, *_), = loop.steps.inputs
    buf.entries, buf.visible, buf.cursor = list(entries), 3, 2
    written = loop.handover_state()
    assert [run[3] for run in written["buffers"][0][1]] == [0, 3, 4, 6, 7]
    assert type(written["buffers"][0][1][2][4]) is np.ndarray  # rows 0 and 1, stacked
    state = handover.read_state(_state_file(tmp_path, written), loop)
    buf.entries = []
    handover.take_over(loop, state)
    assert [e[:4] for e in buf.entries] == [e[:4] for e in entries] and (buf.visible, buf.cursor) == (3, 2)
    assert Burst.unchecked(tuple(e[4] for e in buf.entries)) == Burst.unchecked(tuple(e[4] for e in entries))


@pytest.mark.parametrize("content, says", [
    (b"", r"not Retriever codec data \(ValueError"),
    (b"not msgpack at all \xc1", r"not Retriever codec data \(ExtraData"),
    (msgpack.packb([1, 2, 3]), r"the state is a map of its fields, got list \[1, 2, 3\]"),
    (msgpack.packb({"k": 1}), "fields missing: buffers, held, last_stamp, last_tick, next_rate, pending"),
    (bytes([0xD4, 99, 0]), r"not Retriever codec data \(CodecError: unknown msgpack extension type 99\)"),
])
def test_a_garbage_file_is_refused_naming_the_file(loop, tmp_path, content, says):
    path = tmp_path / "where.handover"
    path.write_bytes(content)
    with pytest.raises(WorkerError, match=rf"the hand-over state file {path} is no state of node 'where': {says}"):
        handover.read_state(path, loop)


def test_a_missing_file_is_refused_with_the_hint(loop, tmp_path):
    path = tmp_path / "gone.handover"
    with pytest.raises(WorkerError, match=rf"cannot read the hand-over state file {path}: .*\n    hint: .*same Retriever"):
        handover.read_state(path, loop)


def _buffer(state: dict, **changes) -> list:
    """The state's buffer with ``changes``; its entries are ``runs``: [tag, producer, port, first seq, values]."""
    port, runs, visible, cursor, last_id = state["buffers"][0]
    row = {"port": port, "runs": runs, "visible": visible, "cursor": cursor, "last_id": last_id, **changes}
    return [list(row.values())]


#: (what to change in a valid state, what the error must say)
WRONG = [
    (lambda s: {"k": "3"}, r"'k' must be an integer >= 0, got str"),
    (lambda s: {"k": -1}, r"'k' must be an integer >= 0, got int -1"),
    (lambda s: {"values": 1}, r"'values' must be true or false, got int"),
    (lambda s: {"next_rate": [100, 0]}, r"'next_rate' must be a tag \(t_ns, microstep\), got list"),
    (lambda s: {"last_tick": (-2, 0)}, r"'last_tick' must be a tag"),
    (lambda s: {"pending": [(1, 0), (1,)]}, r"'pending\[1\]' must be a tag"),
    (lambda s: {"last_stamp": 1.5}, r"'last_stamp' must be an integer"),
    (lambda s: {"seqs": {"saw": -3}}, r"'seqs\[saw\]' must be an integer >= 0"),
    (lambda s: {"sent": ["saw", 2]}, r"'sent' must be a map of ports to seqs, got list"),
    (lambda s: {"pending_detail": {1: "x"}}, r"'pending_detail' must be a map with string keys"),
    (lambda s: {"held": [((1, 0), "saw", ("a",), 3, "bunch")]}, r"'held\[0\]' must be a held burst"),
    (lambda s: {"held": [((1, 0), "saw", "c")]}, r"'held\[0\]' must be a tuple of 4"),
    (lambda s: {"buffers": []}, r"'buffers' holds the ports \[\]; the node's are \['x'\]"),
    (lambda s: {"buffers": _buffer(s, port="y")}, r"'buffers' holds the ports \['y'\]; the node's are \['x'\]"),
    (lambda s: {"buffers": _buffer(s, visible=99)}, r"'buffers\[0\]\[2\]' \(visible\) is 99, past the buffer's 2"),
    (lambda s: {"buffers": _buffer(s, cursor=-1)}, r"'buffers\[0\]\[3\]' must be an integer >= 0"),
    (lambda s: {"buffers": _buffer(s, last_id=("counter", "value"))}, r"'buffers\[0\]\[4\]' must be a tuple of 3"),
    (lambda s: {"buffers": _buffer(s, runs=[[(50 * MS, 0), 7, "value", 0, [0]]])},
     r"'buffers\[0\]\[1\]\[0\]\[1\]' must be a name, got int"),
    (lambda s: {"buffers": _buffer(s, runs=[((50 * MS, 0), "counter", "value", 0, [0])])},
     r"'buffers\[0\]\[1\]\[0\]' must be a list of 5, got tuple"),
    (lambda s: {"buffers": _buffer(s, runs=[[(50 * MS, 0), "counter", "value", 0, []]])},
     r"'buffers\[0\]\[1\]\[0\]\[4\]' must be a list of the run's values or an array of them, got list \[\]"),
    (lambda s: {"buffers": _buffer(s, runs=[[(50 * MS, 0), "counter", "value", 0, [0, 1]],
                                            [(50 * MS, 0), "counter", "value", 1, [2]]])},
     r"'buffers\[0\]\[1\]\[1\]' starts at \(\(50000000, 0\), 'counter', 'value', 1\), not after the run before it"),
    (lambda s: {"streams": [["counter", "other", (0, 0), 0, [], []]]},
     r"'streams' holds \[\('counter', 'other'\)\]; the node's are \[\('counter', 'value'\)\]"),
    (lambda s: {"streams": [["counter", "value", (0, 0), 0, [], [(1, (0, 0), 9)]]]},
     r"'streams\[0\]\[5\]\[0\]' must be a tuple of 2"),
    (lambda s: {"streams": [["counter", "value", (0, 0), 0, [((1, 0), "1", (2, 0), "counter", "value", 5)], []]]},
     r"'streams\[0\]\[4\]\[0\]\[1\]' must be an integer >= 0, got str"),
    (lambda s: {"stranger": 1}, r"a field the state has none of: 'stranger'"),
]


@pytest.mark.parametrize("change, says", WRONG, ids=[f"wrong{i}" for i in range(len(WRONG))])
def test_a_field_of_the_wrong_type_is_refused_naming_it(loop, tmp_path, change, says):
    _filled(loop)
    state = loop.handover_state()
    path = _state_file(tmp_path, {**state, **change(state)})
    with pytest.raises(WorkerError, match=rf"the hand-over state file {path} is no state of node 'where': {says}"):
        handover.read_state(path, loop)
