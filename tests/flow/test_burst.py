"""Burst as a value: what a test of a step's outputs compares."""

from __future__ import annotations

import numpy as np
import pytest

from retriever import Burst


def test_bursts_of_equal_values_in_order_are_equal():
    assert Burst([1, "a", (2, 3)]) == Burst((1, "a", (2, 3)))
    assert Burst([1, 2]) != Burst([2, 1])
    assert Burst([1, 2]) != Burst([1, 2, 3])
    assert Burst([]) == Burst(())
    assert {"imu": Burst([1.5, 2.5])} == {"imu": Burst(iter([1.5, 2.5]))}


def test_arrays_in_bursts_compare_by_dtype_shape_and_content():
    frames = np.arange(12, dtype=np.uint8).reshape(3, 2, 2)
    assert Burst(frames) == Burst(list(frames.copy()))  # the rows of an array, or the same rows as a list
    assert Burst(frames) != Burst(list(frames.astype(np.int16)))
    assert Burst([frames[0]]) != Burst([frames[0].reshape(4)])
    changed = frames.copy()
    changed[2, 1, 1] = 99
    assert Burst(frames) != Burst(changed)
    assert Burst(np.array([1.0, 2.0])) == Burst([np.float64(1.0), np.float64(2.0)])  # a 1-D array's scalars
    assert Burst([np.zeros(2)]) != Burst([[0.0, 0.0]])  # an array is not a list


def test_numpy_scalars_compare_by_dtype_and_never_equal_another_kind_of_value():
    assert Burst(np.array([1, 2], np.int16)) != Burst(np.array([1, 2], np.int64))  # as rows of 2-D arrays
    assert Burst([np.float64(1.0)]) != Burst([[1.0]])
    assert Burst(np.array([1.0, 2.0])) != Burst([[1.0], [2.0]])
    assert Burst([np.float64(1.0)]) != Burst([[1.0, 1.0]])  # (numpy would broadcast: no truth value)
    assert Burst([np.array(3.0)]) != Burst([np.float64(3.0)])


def test_arrays_inside_lists_tuples_and_dicts_compare_by_content():
    assert Burst([[np.zeros(2)]]) == Burst([[np.zeros(2)]])
    assert Burst([{"p": np.zeros(2), "q": (1, np.ones(1))}]) == Burst([{"p": np.zeros(2), "q": (1, np.ones(1))}])
    assert Burst([{"p": np.zeros(2)}]) != Burst([{"p": np.ones(2)}])
    assert Burst([{"p": 1}]) != Burst([{"q": 1}])
    assert Burst([(1, 2)]) != Burst([[1, 2]])  # a tuple is not a list
    ragged = lambda: np.array([np.zeros(2), np.zeros(3)], dtype=object)  # noqa: E731
    assert Burst([ragged()]) == Burst([ragged()])


def test_nan_equals_nan_in_arrays_and_a_burst_equals_itself():
    assert Burst([np.array([np.nan, 1.0])]) == Burst([np.array([np.nan, 1.0])])
    burst = Burst([float("nan")])
    assert burst == burst


def test_a_burst_equals_nothing_but_a_burst_and_is_not_hashable():
    assert Burst([1]) != [1]
    assert Burst([1]) != (1,)
    assert not Burst([1]) == 1
    with pytest.raises(TypeError):
        hash(Burst([1]))


def test_values_whose_comparison_raises_are_unequal():
    class Touchy:
        def __eq__(self, other):
            raise RuntimeError("do not compare me")

    touchy = Touchy()
    assert Burst([touchy]) != Burst([Touchy()])
