"""The msgpack codec round-trips every supported value exactly and names what it cannot encode."""

from __future__ import annotations

import dataclasses
import math
import struct

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from retriever import CodecError, io
from retriever.codec import Encoder, array_encoding_head, packb, unpackb


@io
class Point:
    x: float
    y: float
    tags: tuple = ()


@io
class Obs:
    image: np.ndarray
    point: Point
    meta: dict = dataclasses.field(default_factory=dict)


class Opaque:
    pass


# ---------------------------------------------------------------------------------------------
# Exact comparison: type for type, bit for bit
# ---------------------------------------------------------------------------------------------
def assert_same(a, b, path="value"):
    assert type(a) is type(b), f"{path}: {type(a).__name__} came back as {type(b).__name__}"
    if isinstance(a, float):
        assert struct.pack("<d", a) == struct.pack("<d", b), f"{path}: {a!r} != {b!r} bit for bit"
    elif isinstance(a, np.ndarray):
        assert a.dtype == b.dtype, f"{path}: dtype {a.dtype} != {b.dtype}"
        assert a.shape == b.shape, f"{path}: shape {a.shape} != {b.shape}"
        assert np.ascontiguousarray(a).tobytes() == b.tobytes(), f"{path}: array bytes differ"
    elif isinstance(a, np.generic):
        assert a.dtype == b.dtype, f"{path}: dtype {a.dtype} != {b.dtype}"
        assert a.tobytes() == b.tobytes(), f"{path}: scalar bytes differ"
    elif isinstance(a, (list, tuple)):
        assert len(a) == len(b), f"{path}: length {len(a)} != {len(b)}"
        for i, (x, y) in enumerate(zip(a, b)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, dict):
        assert list(a) == list(b), f"{path}: keys {list(a)} != {list(b)}"
        for k in a:
            assert_same(a[k], b[k], f"{path}[{k!r}]")
    elif dataclasses.is_dataclass(a):
        for f in dataclasses.fields(a):
            assert_same(getattr(a, f.name), getattr(b, f.name), f"{path}.{f.name}")
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def roundtrip(value):
    return unpackb(packb(value))


# ---------------------------------------------------------------------------------------------
# Strategies
# ---------------------------------------------------------------------------------------------
DTYPES = ["bool", "int8", "uint8", "int16", "uint16", ">i4", "int32", "uint32", "int64", "uint64",
          "float16", "float32", ">f8", "float64", "complex64", "complex128", "<U3", "S4", "datetime64[ns]"]

big_ints = st.integers(min_value=-(2**200), max_value=2**200)
ints = st.integers() | big_ints | st.sampled_from([2**63 - 1, 2**63, 2**64 - 1, 2**64, -(2**63), -(2**63) - 1])
floats = st.floats(allow_nan=True, allow_infinity=True) | st.sampled_from([-0.0, 0.0, math.nan, -math.nan])


@st.composite
def arrays(draw):
    dtype = np.dtype(draw(st.sampled_from(DTYPES)))
    shape = draw(hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=4))
    arr = draw(hnp.arrays(dtype, shape))
    view = draw(st.sampled_from(["as is", "transposed", "strided", "fortran"]))
    if view == "transposed":
        arr = arr.T
    elif view == "strided" and arr.ndim:
        arr = arr[::2]
    elif view == "fortran":
        arr = np.asfortranarray(arr)
    return arr


@st.composite
def np_scalars(draw):
    dtype = np.dtype(draw(st.sampled_from(DTYPES)))
    return np.asarray(draw(hnp.from_dtype(dtype)), dtype=dtype)[()]


leaves = (st.none() | st.booleans() | ints | floats | st.text(max_size=8) | st.binary(max_size=8)
          | arrays() | np_scalars())
keys = st.text(max_size=6) | st.integers(min_value=-(2**63), max_value=2**64 - 1) | big_ints | st.binary(max_size=4)


def points(children):
    return st.builds(Point, floats, floats, st.lists(children, max_size=2).map(tuple))


values = st.recursive(
    leaves,
    lambda children: (st.lists(children, max_size=4)
                      | st.lists(children, max_size=4).map(tuple)
                      | st.dictionaries(keys, children, max_size=4)
                      | points(children)),
    max_leaves=20,
)


# ---------------------------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------------------------
@settings(max_examples=300, deadline=None)
@given(values)
def test_round_trip_is_exact(value):
    assert_same(value, roundtrip(value))


@settings(deadline=None)
@given(values)
def test_encoding_is_deterministic(value):
    assert packb(value) == packb(roundtrip(value))


@given(ints)
def test_ints_of_any_size(n):
    assert_same(n, roundtrip(n))
    assert_same([n, {"k": (n,)}], roundtrip([n, {"k": (n,)}]))


@given(floats)
def test_floats_bit_exact(x):
    assert_same(x, roundtrip(x))


@pytest.mark.parametrize("x", [-0.0, math.nan, -math.nan, math.inf, -math.inf, 5e-324,
                               struct.unpack("<d", struct.pack("<Q", 0x7FF8_0000_0000_0001))[0]])
def test_special_floats_bit_exact(x):
    assert_same(x, roundtrip(x))


@settings(deadline=None)
@given(arrays())
def test_numpy_arrays(arr):
    back = roundtrip(arr)
    assert_same(arr, back)
    assert back.flags.writeable


@st.composite
def any_arrays(draw):
    """arrays() and bigger ones (an encoding's bin 16/32 and ext 16/32 heads), structured ones too."""
    kind = draw(st.sampled_from(["small", "big", "structured"]))
    if kind == "small":
        return draw(arrays())
    if kind == "structured":
        dtype = np.dtype([("a", "<i4"), ("b", ">f8", (2,)), ("c", "S3")])
        return np.zeros(draw(st.integers(0, 3)), dtype=dtype)
    dtype = np.dtype(draw(st.sampled_from(["uint8", ">f8", "float32"])))
    n = draw(st.sampled_from([255, 256, 65535, 65536, 70000, 300000])) // dtype.itemsize
    arr = np.arange(n, dtype=dtype)
    return arr[::2] if draw(st.booleans()) else arr


def _msgpack_encoding(arr):
    """An array's encoding as the codec defines it, spelt with msgpack's own ExtType."""
    descr = np.lib.format.dtype_to_descr(arr.dtype) if arr.dtype.fields else arr.dtype.str
    payload = msgpack.packb([descr, list(arr.shape), arr.tobytes()], use_bin_type=True)
    return msgpack.packb(msgpack.ExtType(1, payload), use_bin_type=True)


@settings(max_examples=300, deadline=None)
@given(any_arrays())
def test_an_arrays_encoding_is_its_cached_head_then_its_bytes(arr):
    """The fast path (Encoder.pack, the log writer's records: a head cached by dtype and shape,
    then tobytes()) writes what msgpack writes of the array's ExtType, byte for byte, and what
    packb writes of an array inside a value, the first time and from the cache."""
    expected = _msgpack_encoding(arr)
    assert array_encoding_head(arr) + arr.tobytes() == expected
    encoder = Encoder()
    assert encoder.pack(arr) == encoder.pack(arr) == expected
    assert packb([arr]) == b"\x91" + expected


def test_zero_d_array_stays_an_array():
    arr = np.array(3.5, dtype=np.float32)
    back = roundtrip(arr)
    assert isinstance(back, np.ndarray) and back.shape == () and back.dtype == np.float32


def test_non_contiguous_views():
    base = np.arange(60, dtype=np.int32).reshape(3, 4, 5)
    for view in (base[:, ::2, 1:], base.transpose(2, 0, 1), base[::-1], np.asfortranarray(base)):
        assert_same(view, roundtrip(view))


def test_structured_arrays_round_trip_or_are_refused():
    # The codec promises any non-object dtype; a structured one must not come back as raw void.
    arr = np.array([(1, 2.5), (3, 4.5)], dtype=[("a", "<i4"), ("b", "<f8")])
    try:
        back = roundtrip(arr)
    except CodecError:
        return
    assert back.dtype == arr.dtype
    assert back.tolist() == arr.tolist()


@given(np_scalars())
def test_numpy_scalars(x):
    assert_same(x, roundtrip(x))


@pytest.mark.parametrize("x", [np.float64(-0.0), np.float32(math.nan), np.int64(-(2**63)), np.uint64(2**64 - 1),
                               np.bool_(True), np.complex64(1 - 2j), np.datetime64("2024-01-01T00:00:00.5")])
def test_numpy_scalar_examples(x):
    assert_same(x, roundtrip(x))


def test_io_dataclasses():
    obs = Obs(image=np.eye(3, dtype=np.uint8)[:, ::-1], point=Point(1.5, -0.0, ("a", 2**70)), meta={1: b"x"})
    back = roundtrip(obs)
    assert isinstance(back, Obs) and isinstance(back.point, Point)
    assert_same(obs, back)


def test_tuples_stay_tuples_and_lists_stay_lists():
    value = ((1, [2, (3,)]), [(), []])
    assert_same(value, roundtrip(value))


def test_dict_keys_of_several_types():
    value = {"a": 1, 2: "b", b"c": 3.0, 2**80: None, -1: [1]}
    assert_same(value, roundtrip(value))


# ---------------------------------------------------------------------------------------------
# What the codec refuses
# ---------------------------------------------------------------------------------------------
def test_unknown_object_names_its_type():
    with pytest.raises(CodecError, match=r"cannot encode a value of type tests\.test_codec\.Opaque\n"
                                         r"    hint: use numbers, str, bytes, lists, dicts, numpy arrays or @io"):
        packb(Opaque())


def test_codec_error_is_a_type_error():
    with pytest.raises(TypeError):
        packb({1, 2})


def test_unknown_object_deep_inside_names_the_path():
    # codec.py's docstring: CodecError names "the type and the path to it inside the value".
    with pytest.raises(CodecError, match=r"tests\.test_codec\.Opaque") as info:
        packb({"a": [1, Opaque()]})
    assert "['a'][1]" in str(info.value), str(info.value)


def test_object_arrays_are_refused():
    with pytest.raises(CodecError, match=r"numpy arrays of dtype object cannot be encoded"):
        packb(np.array([1, "a"], dtype=object))


def test_sets_are_refused_naming_the_type():
    with pytest.raises(CodecError, match=r"builtins\.set"):
        packb({1, 2})


def test_unknown_extension_type_on_decode():
    import msgpack

    with pytest.raises(CodecError, match=r"unknown msgpack extension type 42"):
        unpackb(msgpack.packb(msgpack.ExtType(42, b"")))


def test_decoding_a_dataclass_that_is_not_registered():
    import msgpack

    from retriever.codec import EXT_DATACLASS

    data = msgpack.packb(msgpack.ExtType(EXT_DATACLASS, packb(["tests.no_such_module:Gone", {"x": 1}])))
    with pytest.raises(CodecError, match=r"cannot decode a value of type 'tests\.no_such_module:Gone': no value type"):
        unpackb(data)


# ---------------------------------------------------------------------------------------------
# Nested values reuse this thread's packers (codec._IdlePackers)
# ---------------------------------------------------------------------------------------------
NESTED = [(i, (i + 1, Point(float(i), 2.0, ((i, 2**70),))), [(), (b"x",)]) for i in range(50)]


def test_an_error_deep_inside_a_value_leaves_later_encodings_intact():
    expected = [packb(v) for v in NESTED]
    for bad in [(1, (2, Opaque())), Point(1.0, 2.0, (Opaque(),)), (1, (2, {3}))]:
        with pytest.raises(CodecError):
            packb(bad)
        assert [packb(v) for v in NESTED] == expected


def test_threads_packing_nested_values_at_once_get_the_same_bytes():
    import threading

    expected = [packb(v) for v in NESTED]
    results: dict[int, list[bytes]] = {}
    start = threading.Barrier(4)

    def pack_all(k: int) -> None:
        start.wait()
        results[k] = [packb(v) for _ in range(20) for v in NESTED]

    threads = [threading.Thread(target=pack_all, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert all(results[k] == expected * 20 for k in range(4))
    assert [unpackb(b) for b in expected] == NESTED


#: a process that decodes tuples nested ``depth`` deep, on a thread with a 2 MiB stack (as
#: Zenoh's are), through the codec and a wire data message; it prints what each raised
DEEP_DECODE = r"""
import sys, threading
import msgpack
from retriever.backends.zenoh.wire import WireError, decode_data
from retriever.codec import unpackb

depth = int(sys.argv[1])
value = msgpack.packb(None)
for _ in range(depth):
    value = msgpack.packb(msgpack.ExtType(2, b"\x91" + value))
envelope = b"\x97" + b"".join(msgpack.packb(x) for x in [2, [0, 0], 0, [0, 0], "a", "b"]) + value

def decode():
    for name, call, error in (("codec", lambda: unpackb(value), Exception),
                              ("wire", lambda: decode_data(msgpack.packb([envelope])), WireError)):
        try:
            call()
            print(name, "decoded")
        except error as e:
            print(name, type(e).__name__, e)

threading.stack_size(2 << 20)
thread = threading.Thread(target=decode)
thread.start()
thread.join()
"""


@pytest.mark.parametrize("depth", [50, 400])
def test_a_value_nesting_tuples_too_deep_is_refused_not_a_crash(depth):
    # unbounded, each level a nested msgpack decode, 50 levels (a 200-byte message) overflowed
    # a 2 MiB thread's stack: the process died of SIGSEGV (found by benchmarks/fuzz.py)
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    done = subprocess.run([sys.executable, "-c", DEEP_DECODE, str(depth)], capture_output=True, text=True,
                          cwd=root, env={"PYTHONPATH": str(root)}, timeout=60)
    assert done.returncode == 0, done.stderr[-2000:]
    assert done.stdout.splitlines() == [
        "codec CodecError a value nests tuples or dataclasses deeper than 16 levels, which this codec does not "
        "decode", "    hint: nest tuples and @io dataclasses at most 16 deep",
        "wire WireError the value of a data message cannot be decoded: a value nests tuples or dataclasses deeper "
        "than 16 levels, which this codec does not decode", "    hint: nest tuples and @io dataclasses at most 16 deep"]


def test_values_nested_as_deep_as_the_codec_decodes_round_trip():
    value: object = Point(1.0, 2.0, tags=())  # 2 levels: the dataclass and its tuple
    for _ in range(14):
        value = (value,)
    assert unpackb(packb(value)) == value
    # one level more is refused when encoding: no process could decode it
    with pytest.raises(CodecError, match="deeper than 16 levels"):
        packb((value,))
    from retriever.codec import OutOfBandEncoder

    with pytest.raises(CodecError, match="deeper than 16 levels"):
        OutOfBandEncoder().pack((value,))
    assert unpackb(packb(value)) == value  # the depth count is back at 0 after the error


def _ext(code: int, payload) -> bytes:
    import msgpack

    return msgpack.packb(msgpack.ExtType(code, msgpack.packb(payload, use_bin_type=True)))


@pytest.mark.parametrize("data", [
    _ext(1, 5),  # an array that is no [descr, shape, bytes]
    _ext(1, ["<f8", "abc", b"\0" * 8]),  # a shape that is text
    _ext(1, ["<f8", [2, 19], b"\0" * 8]),  # a shape its bytes do not fill
    _ext(5, ["<f8", [], None]),
    __import__("msgpack").packb(__import__("msgpack").ExtType(3, b"nan")),  # a big int that is none
    __import__("msgpack").packb(__import__("msgpack").ExtType(3, b"\xff")),
])
def test_a_malformed_extension_value_is_a_codec_error(data):
    # found by benchmarks/fuzz.py: numpy's and int()'s own errors escaped, where callers catch CodecError
    with pytest.raises(CodecError, match="a malformed value of msgpack extension type"):
        unpackb(data)


@pytest.mark.parametrize("descr", ["(2,)f8", "i4,f8", "f8 ", {"descr": "O"}, [["a", "(2,)f8"]], [["a", "<f8", ["2"]]]])
def test_a_dtype_numpy_would_parse_as_text_is_refused_without_compiling_it(descr):
    # numpy reads "(2,)f8" with ast.literal_eval (a compile() of the message's text), found by
    # benchmarks/fuzz.py's audit hook: only type strings such as '<f8' reach numpy now
    import sys

    compiled = []
    armed = [True]
    sys.addaudithook(lambda event, args: compiled.append(args[0]) if armed[0] and event == "compile" else None)
    try:
        with pytest.raises(CodecError, match="an array's dtype .* is not a numpy type string"):
            unpackb(_ext(1, [descr, [1], b"\0" * 16]))
    finally:
        armed[0] = False
    assert compiled == []


# ---------------------------------------------------------------------------------------------
# The fast paths give the bytes and values of the general one
# ---------------------------------------------------------------------------------------------
def _one_level_at_a_time(value):
    """What packb packs for a value of plain items, lists, dicts and tuples, made with msgpack's
    own packer: each tuple an extension whose payload is packed on its own, a level deeper."""
    import msgpack

    if type(value) is tuple:
        return msgpack.ExtType(2, msgpack.packb([_one_level_at_a_time(v) for v in value], use_bin_type=True))
    if type(value) is list:
        return [_one_level_at_a_time(v) for v in value]
    if type(value) is dict:
        return {_one_level_at_a_time(k): _one_level_at_a_time(v) for k, v in value.items()}
    if type(value) is int and not -(2**63) <= value < 2**64:
        return msgpack.ExtType(3, str(value).encode())
    return value


plain_values = st.recursive(
    st.none() | st.booleans() | ints | floats | st.text(max_size=8) | st.binary(max_size=8),
    lambda children: (st.lists(children, max_size=4) | st.lists(children, max_size=4).map(tuple)
                      | st.dictionaries(keys, children, max_size=4)),
    max_leaves=20,
)


@settings(max_examples=300, deadline=None)
@given(plain_values)
def test_tuples_of_plain_values_pack_as_a_level_at_a_time(value):
    import msgpack

    # event ids and tags (tuples of plain values, of tuples of them) are packed at once (codec._plain_tuple)
    expected = msgpack.packb(_one_level_at_a_time(value), use_bin_type=True)
    assert packb(value) == expected
    assert packb(("step", value, (value, ((1, "a"), value)))) == msgpack.packb(
        _one_level_at_a_time(("step", value, (value, ((1, "a"), value)))), use_bin_type=True)


def test_arrays_as_long_as_one_decoded_before_decode_as_themselves():
    # an array's encoding that begins as one of the same length decoded before decodes without
    # msgpack (codec._array_decodings): what it decodes to, and what it refuses, stay the same
    first, same_length = np.array([1.5, -2.0]), np.array([7, 8], dtype="<i8")
    assert len(packb(first)) == len(packb(same_length))
    for arr in [first, np.array([3.0, 4.0]), same_length, np.array([[9, 10]], dtype="<i8"), first[::-1]]:
        data = packb(arr)
        for _ in range(2):
            assert_same(np.ascontiguousarray(arr), unpackb(data))
        decoded = unpackb(data)
        assert decoded.flags.writeable and decoded.flags.owndata  # a copy, as msgpack's way gives
    head = packb(first)[:-16]
    wrong_dtype = head.replace(b"<f8", b"<O8") + bytes(16)  # same length, another head: refused as before
    with pytest.raises(CodecError, match="cannot create an OBJECT array"):
        unpackb(wrong_dtype)
    short = bytearray(packb(first))
    short[-17] = 15  # the bin's length says 15 of the 16 bytes: msgpack's ExtraData, as before
    with pytest.raises(CodecError, match="ExtraData"):
        unpackb(bytes(short))


def test_unpackb_read_only_is_unpackb_an_array_a_read_only_view():
    """``unpackb_read_only`` decodes as ``unpackb`` does; an array that decodes surely (one of that
    length decoded before, the same head) is a read-only view of the bytes, not a copy; bytes of
    that length with another head are decoded, as ``unpackb`` decodes (or refuses) them."""
    from retriever.codec import packb, unpackb, unpackb_read_only

    first, second = packb(np.arange(6.0).reshape(2, 3)), packb(np.arange(6.0).reshape(2, 3) + 1)
    assert unpackb(first).flags.writeable  # (and the encoding's head is now known)
    view = unpackb_read_only(second)
    assert not view.flags.writeable and view.base is not None
    np.testing.assert_array_equal(view, unpackb(second))
    other = packb(np.arange(6, dtype=np.int64).reshape(3, 2))  # as long, another head
    assert len(other) == len(second)
    decoded = unpackb_read_only(other)
    assert decoded.dtype == np.int64 and decoded.shape == (3, 2)
    assert unpackb_read_only(packb({"a": [1, 2]})) == {"a": [1, 2]}
