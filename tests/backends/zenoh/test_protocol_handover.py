"""The hand-over state file's decoder (protocol/handover.py: decode_handover_state), attacked on
its own, without a loop: garbage, extension types, tags of the wrong type, runs out of order,
lists past their bounds. Each is refused with a WireError naming the field, never anything else
(no crash, no state half read); a state as node/handover.py writes it comes back whole. What
needs the new process's loop (its ports, its streams) is in test_handover_state.py."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retriever.backends.zenoh.protocol import HANDOVER_EVENTS_MAX, HandoverState, decode_handover_state
from retriever.backends.zenoh.wire import WireError
from retriever.codec import packb

ROWS = np.arange(6, dtype=np.float32).reshape(3, 2)


def state(**changes) -> dict:
    """A state as the old process writes it: a buffer of two runs (the second an array's rows),
    an early message and a promise, a held burst and a held value; ``changes`` replace fields."""
    return {
        "buffers": [["x", [[(5, 0), "counter", "value", 0, ["a", "b"]], [(6, 0), "counter", "value", 2, ROWS]],
                     1, 0, ("counter", "value", 1)]],
        "streams": [["counter", "value", (4, 0), 5, [((9, 0), 6, (9, 1), "counter", "value", "early")], [(7, (8, 0))]]],
        "pending": [(7, 0)], "k": 3, "next_rate": None, "last_tick": (-1, 0), "last_stamp": 0,
        "seqs": {"saw": 6}, "sent": {"saw": -1},
        "held": [((5, 0), "saw", ("a", "b"), 3, "burst"), ((6, 0), "saw", "c", 5)],
        "pending_detail": {"restarted": {"seqs": {}}}, "values": True, **changes}


def run(seq: int, values, tag=(5, 0)) -> list:
    return [tag, "counter", "value", seq, values]


def buffer(*runs, visible: int = 0, cursor: int = 0) -> list:
    return ["x", list(runs), visible, cursor, None]


def test_a_state_as_written_comes_back_whole_its_runs_as_entries():
    decoded = decode_handover_state(packb(state()))
    assert type(decoded) is HandoverState
    (port, entries, visible, cursor, last_id), = decoded.buffers
    assert (port, visible, cursor, last_id) == ("x", 1, 0, ("counter", "value", 1))
    assert [e[:4] for e in entries] == [((5, 0), "counter", "value", 0), ((5, 0), "counter", "value", 1),
                                        ((6, 0), "counter", "value", 2), ((6, 0), "counter", "value", 3),
                                        ((6, 0), "counter", "value", 4)]
    assert [e[4] for e in entries[:2]] == ["a", "b"] and all((e[4] == r).all() for e, r in zip(entries[2:], ROWS))
    assert decoded.streams == (("counter", "value", (4, 0), 5, (((9, 0), 6, (9, 1), "counter", "value", "early"),),
                                ((7, (8, 0)),)),)
    assert decoded.held == (((5, 0), "saw", ("a", "b"), 3, "burst"), ((6, 0), "saw", "c", 5))
    assert (decoded.pending, decoded.k, decoded.next_rate, decoded.last_tick) == (((7, 0),), 3, None, (-1, 0))
    assert (decoded.seqs, decoded.sent, decoded.values) == ({"saw": 6}, {"saw": -1}, True)


#: (the file's bytes, what the error must say)
GARBAGE = [
    (b"", r"^not Retriever codec data \(ValueError"),
    (b"\xc1", r"^not Retriever codec data \("),
    (packb([1, 2]), r"^the state is a map of its fields, got list \[1, 2\]$"),
    (packb(None), r"^the state is a map of its fields, got NoneType None$"),
    (packb((1, 2)), r"^the state is a map of its fields, got tuple \(1, 2\)$"),
    (bytes([0xD4, 99, 0]), r"^not Retriever codec data \(CodecError: unknown msgpack extension type 99\)$"),
    (msgpack.packb({**state(buffers=[]), "held": [msgpack.ExtType(99, b"")]}),
     r"^not Retriever codec data \(CodecError: unknown msgpack extension type 99\)$"),
    (packb({1: 2}), r"^fields missing: buffers, held, .*, values$"),
    (packb({**state(), (1, 2): 3}), r"^a field the state has none of: \(1, 2\)$"),
]


@pytest.mark.parametrize("data, says", GARBAGE, ids=[f"garbage{i}" for i in range(len(GARBAGE))])
def test_garbage_is_refused_saying_what_it_is(data, says):
    with pytest.raises(WireError, match=says):
        decode_handover_state(data)


#: (fields to change, what the error must say)
WRONG = [
    # tags are tuples of two integers: not lists, not floats, not booleans, not negative
    ({"last_tick": [-1, 0]}, r"^'last_tick' must be a tag \(t_ns, microstep\), got list \[-1, 0\]$"),
    ({"last_tick": (-2, 0)}, r"^'last_tick' must be a tag"),
    ({"next_rate": (1.0, 0)}, r"^'next_rate' must be a tag"),
    ({"next_rate": (True, 0)}, r"^'next_rate' must be a tag"),
    ({"pending": [(1, -1)]}, r"^'pending\[0\]' must be a tag"),
    ({"pending": [(1, 0, 0)]}, r"^'pending\[0\]' must be a tag"),
    ({"streams": [["counter", "value", (4, 0), 5, [], [(7, [8, 0])]]]},
     r"^'streams\[0\]\[5\]\[0\]\[1\]' must be a tag"),
    ({"buffers": [buffer(run(0, [1], tag=[5, 0]))]}, r"^'buffers\[0\]\[1\]\[0\]\[0\]' must be a tag"),
    # rows: tuples where the codec decodes tuples, lists where it decodes lists
    ({"buffers": [tuple(buffer(run(0, [1])))]}, r"^'buffers\[0\]' must be a list of 5, got tuple"),
    ({"streams": [["counter", "value", (4, 0), 5, [[(9, 0), 6, (9, 1), "counter", "value", 1]], []]]},
     r"^'streams\[0\]\[4\]\[0\]' must be a tuple of 6, got list"),
    ({"buffers": [["x", [], 0, 0, ["counter", "value", 1]]]}, r"^'buffers\[0\]\[4\]' must be a tuple of 3, got list"),
    # a run: in order after the one before, its values a list or an array of rows that hold bytes
    ({"buffers": [buffer(run(1, [1]), run(0, [2]))]},
     r"^'buffers\[0\]\[1\]\[1\]' starts at \(\(5, 0\), 'counter', 'value', 0\), not after the run before it$"),
    ({"buffers": [buffer(run(0, [1, 2]), run(1, [3]))]}, r"^'buffers\[0\]\[1\]\[1\]' starts at .* not after"),
    ({"buffers": [buffer(run(0, [1]), run(1, [2], tag=(4, 0)))]}, r"^'buffers\[0\]\[1\]\[1\]' starts at .* not after"),
    ({"buffers": [buffer(run(0, np.zeros((1000, 0))))]},
     r"^'buffers\[0\]\[1\]\[0\]\[4\]' must be a list of the run's values or an array of them, got ndarray"),
    ({"buffers": [buffer(run(0, ("a", "b")))]}, r"^'buffers\[0\]\[1\]\[0\]\[4\]' must be a list of the run's values"),
    ({"buffers": [buffer(run(0, [1]), visible=2)]},
     r"^'buffers\[0\]\[2\]' \(visible\) is 2, past the buffer's 1 entries$"),
    ({"buffers": [buffer(run(0, [1]), cursor=2)]},
     r"^'buffers\[0\]\[3\]' \(cursor\) is 2, past the buffer's 1 entries$"),
    ({"buffers": [buffer(run(0, [1]))[:4] + [None, None]]}, r"^'buffers\[0\]' must be a list of 5"),
    # names, seqs, held outputs
    ({"seqs": {7: 0}}, r"^'seqs key 7' must be a name, got int 7$"),
    ({"seqs": {"": 0}}, r"^'seqs key ''' must be a name"),
    ({"sent": {"saw": -2}}, r"^'sent\[saw\]' must be an integer >= -1, got int -2$"),
    ({"k": True}, r"^'k' must be an integer >= 0, got bool True$"),
    ({"held": [((1, 0), "saw", ("a",), 3, np.arange(3))]}, r"^'held\[0\]' must be a held burst"),  # no array compared
    ({"held": [((1, 0), "saw", (), 3, "burst")]}, r"^'held\[0\]' must be a held burst"),
    ({"held": [((1, 0), "saw", ["a"], 3, "burst")]}, r"^'held\[0\]' must be a held burst"),
    ({"held": [((1, 0), "saw", "c", "3")]}, r"^'held\[0\]\[3\]' must be an integer >= 0, got str"),
    ({"pending_detail": None}, r"^'pending_detail' must be a map with string keys, got NoneType"),
]


@pytest.mark.parametrize("changes, says", WRONG, ids=[f"wrong{i}" for i in range(len(WRONG))])
def test_a_field_of_the_wrong_kind_is_refused_naming_it(changes, says):
    with pytest.raises(WireError, match=says):
        decode_handover_state(packb(state(**changes)))


def test_a_run_past_the_events_a_hand_over_holds_is_refused_before_it_is_expanded():
    """An array of more rows than HANDOVER_EVENTS_MAX (a byte each: cheap to send, not to expand)."""
    rows = np.zeros((HANDOVER_EVENTS_MAX + 1, 1), np.int8)
    with pytest.raises(WireError, match=rf"^'buffers\[0\]\[1\]\[0\]' takes the buffer past {HANDOVER_EVENTS_MAX:,} "
                                        r"entries \(HANDOVER_EVENTS_MAX\)$"):
        decode_handover_state(packb(state(buffers=[buffer(run(0, rows))])))


def test_buffers_past_the_events_a_hand_over_holds_together_are_refused():
    half = [0] * (HANDOVER_EVENTS_MAX // 2 + 1)
    both = [buffer(run(0, half)), ["y", [run(0, half)], 0, 0, None]]
    with pytest.raises(WireError, match=rf"^'buffers' hold {HANDOVER_EVENTS_MAX + 2:,} entries, past "
                                        rf"{HANDOVER_EVENTS_MAX:,} \(HANDOVER_EVENTS_MAX\)$"):
        decode_handover_state(packb(state(buffers=both)))


def test_a_list_past_its_bound_is_refused():
    promises = [(seq, (9, 1)) for seq in range((1 << 16) + 1)]
    with pytest.raises(WireError, match=r"^'streams\[0\]\[5\]' must be a list of 0 to 65536 items, got list"):
        decode_handover_state(packb(state(streams=[["counter", "value", (4, 0), 5, [], promises]])))


#: values a hostile or broken file may hold where a field is expected
ANY = st.recursive(
    st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=4)
    | st.binary(max_size=4) | st.just(np.arange(3)) | st.just(np.zeros((2, 0))),
    lambda inner: st.lists(inner, max_size=6) | st.lists(inner, max_size=6).map(tuple)
    | st.dictionaries(st.text(max_size=3), inner, max_size=3), max_leaves=12)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(sorted(state())), ANY)
def test_any_value_in_any_field_decodes_to_a_state_or_raises_wire_error(name, value):
    try:
        assert type(decode_handover_state(packb(state(**{name: value})))) is HandoverState
    except WireError:
        pass


@settings(max_examples=300, deadline=None)
@given(st.binary(max_size=64) | st.builds(lambda data, cut: data[:cut], st.just(packb(state())), st.integers(0, 400)))
def test_any_bytes_decode_to_a_state_or_raise_wire_error(data):
    try:
        decode_handover_state(data)
    except WireError:
        pass
