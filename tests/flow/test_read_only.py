"""flow/read_only.py: an event's arrays made read-only where they are, through every container a
value may hold them in; nothing else touched."""

import sys
from dataclasses import dataclass
from typing import ClassVar, NamedTuple

import numpy as np
import pytest

from retriever import Burst, io
from retriever.errors import CodecError
from retriever.flow.read_only import make_read_only


@io
@dataclass
class Pose:
    xyz: np.ndarray
    label: str = "a"


class Pair(NamedTuple):
    left: np.ndarray
    right: np.ndarray


class Frame(np.ndarray):
    pass


def _arrays():
    return [np.arange(3.0) for _ in range(12)]


def test_every_array_in_a_value_becomes_read_only_where_it_is():
    a = _arrays()
    value = {"pose": Pose(a[0]), "list": [a[1], (a[2], {"deep": a[3]})], "pair": Pair(a[4], a[5]),
             "sub": a[6].view(Frame), "scalar": np.float64(1.0), "text": "x", "n": 3, "none": None}
    make_read_only(value)
    for arr in (value["pose"].xyz, a[1], a[2], a[3], a[4], a[5], value["sub"]):
        assert not arr.flags.writeable
        with pytest.raises(ValueError, match="read-only"):
            arr[0] = 7.0
    assert a[6].flags.writeable  # the view is read-only, not the array it views (docs: not caught)
    assert value["pose"].label == "a" and value["n"] == 3


def test_a_bursts_values_and_rows_become_read_only():
    rows = np.zeros((4, 2))
    burst = Burst(rows)
    make_read_only(burst)
    assert not rows.flags.writeable
    assert all(not row.flags.writeable for row in burst.values)
    items = _arrays()[:3]
    make_read_only(Burst(items))
    assert not any(item.flags.writeable for item in items)


def test_plain_values_and_arrays_already_read_only_are_left_as_they_are():
    for value in (1, 2.5, "s", b"b", True, None, 1j, np.int32(3)):
        make_read_only(value)
    frozen = np.frombuffer(b"\x00" * 8, dtype=np.float64)
    make_read_only(frozen)
    assert not frozen.flags.writeable
    class Plain:  # not a value the codec encodes: nothing inside is looked at
        def __init__(self):
            self.a = np.zeros(2)
    plain = Plain()
    make_read_only(plain)
    assert plain.a.flags.writeable


@io
@dataclass
class Tree:
    parent: object = None
    leaf: object = None


def test_a_value_that_holds_itself_is_the_codecs_error_not_a_recursion_error():
    """Such a value cannot be walked (nor encoded): a CodecError that says so, not a RecursionError
    from deep in the runtime (on zenoh, where the arrays are made read-only before the value is
    encoded, that crashed the worker)."""
    itself: list = [np.zeros(2)]
    itself.append(itself)
    mapping: dict = {"a": np.zeros(2)}
    mapping["self"] = mapping
    tree = Tree(leaf=np.zeros(2))
    tree.parent = [tree]
    for value in (itself, mapping, tree, Burst([1, itself])):
        with pytest.raises(CodecError, match=r"nested too deeply \(it may contain itself"):
            make_read_only(value)


@io
@dataclass
class Scaled:
    SCALE: ClassVar[np.ndarray] = np.ones(2)  # a class-level constant, not an instance's field
    v: np.ndarray = None


def test_a_dataclass_values_fields_become_read_only_not_its_class_constants():
    value = Scaled(np.zeros(2))
    make_read_only(value)
    assert not value.v.flags.writeable
    assert Scaled.SCALE.flags.writeable  # every instance's, and the flow's own: not the event's


def test_a_flat_dict_or_list_of_arrays_and_plain_values_takes_one_call():
    """The arrays and plain values directly in a dict, list or tuple are handled in the loop over
    them, not a call each (this runs per event emitted); nested containers still get theirs."""
    seen = []

    def profile(frame, event, arg):
        if event == "call":
            seen.append(frame.f_code.co_name)

    def calls(value) -> list[str]:
        seen.clear()
        sys.setprofile(profile)
        try:
            make_read_only(value)
        finally:
            sys.setprofile(None)
        return list(seen)

    a = _arrays()
    for value in ({"data": a[0], "sent_ns": 7, "none": None}, [1, 2, 3, a[1]], (a[2], "x", 1.5)):
        assert calls(value) == ["make_read_only"], value
    assert not any(arr.flags.writeable for arr in a[:3])
    # the dict walked, the list in it (its array in the loop), the dataclass and each of its fields
    assert calls({"list": [a[3]], "pose": Pose(a[4])}) == ["make_read_only"] + ["_walk"] * 5
    assert not a[3].flags.writeable and not a[4].flags.writeable
