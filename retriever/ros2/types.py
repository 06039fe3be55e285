"""ROS 2 messages as Retriever values, and back; CDR and type hashes from ``rosbags``.

One rule for every message type, so a type a user adds from its ``.msg`` text maps like the
standard ones:

- a message is a ``dict`` of its fields; a ``std_msgs/msg/Header`` field becomes two keys,
  ``stamp`` (int ns since the epoch) and ``frame_id``, where that is unambiguous (one Header, and
  no other field named ``stamp`` or ``frame_id``: :func:`flat_header`), else a dict of those two
  under its own field's name, so that a Header and a field ``stamp`` stay two stamps; every other
  ``builtin_interfaces`` Time or Duration is an int of ns;
- numeric arrays and sequences are numpy arrays (``uint8[]`` too), strings ``str``;
- ``geometry_msgs`` Vector3, Point and Point32 are float arrays ``[x, y, z]``, Quaternion
  ``[x, y, z, w]``.

and three refinements where the dict would be clumsy:

- ``std_msgs/msg/<X>`` whose one field is ``data`` (String, Bool, Float64, Int32, …) is that value;
  ``std_msgs/msg/*MultiArray`` is a numpy array shaped by its layout's dims;
- ``sensor_msgs/msg/Image``'s ``data``/``step``/``is_bigendian`` become ``image``: an (H, W) or
  (H, W, C) array of the encoding's dtype (``rgb8`` → uint8 × 3, ``mono16`` → uint16, ``32FC1``
  → float32, bayer and YUV 4:2:2 as their raw channels, …); an image of an encoding not read
  here keeps its raw fields. Published, an array alone is an image too (uint8 with 3 channels
  is ``rgb8``).

So ``JointState`` is ``{"stamp", "frame_id", "name": [...], "position": array, …}``, ``Twist``
``{"linear": array(3), "angular": array(3)}``, ``PoseStamped`` ``{"stamp", "frame_id",
"pose": {"position": array(3), "orientation": array(4)}}``. Going back, a missing field is its
zero value, so ``{"linear": [0.2, 0, 0]}`` is a Twist. A value converts exactly or not at all:
a string field takes a ``str``, a bool a bool, an int a whole number within its range (3.0 but
not 3.7), a float a number, a fixed-size array its length of them; anything else is a TypeError
or ValueError naming the type, the field's path and what it takes and got.

Type hashes (``RIHS01_…``, REP-2011) are rosbags', over the ROS 2 Jazzy definitions.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from rosbags.typesys import Stores, get_types_from_msg, get_typestore
from rosbags.typesys.base import Nodetype

#: the definitions of ROS 2 Jazzy, the LTS release rmw_zenoh ships for
_store = get_typestore(Stores.ROS2_JAZZY)

_TIME_TYPES = frozenset({"builtin_interfaces/msg/Time", "builtin_interfaces/msg/Duration"})
_VECTORS = {"geometry_msgs/msg/Vector3": "xyz", "geometry_msgs/msg/Point": "xyz",
            "geometry_msgs/msg/Point32": "xyz", "geometry_msgs/msg/Quaternion": "xyzw"}
_HEADER = "std_msgs/msg/Header"
_IMAGE = "sensor_msgs/msg/Image"

#: image encodings (sensor_msgs/image_encodings.hpp) → (dtype, channels)
_ENCODINGS = {"rgb8": ("u1", 3), "bgr8": ("u1", 3), "rgba8": ("u1", 4), "bgra8": ("u1", 4), "mono8": ("u1", 1),
              "rgb16": ("u2", 3), "bgr16": ("u2", 3), "rgba16": ("u2", 4), "bgra16": ("u2", 4), "mono16": ("u2", 1)}
_DEPTH_DTYPES = {"8U": "u1", "8S": "i1", "16U": "u2", "16S": "i2", "32S": "i4", "32F": "f4", "64F": "f8"}
_DEFAULT_ENCODINGS = {("u1", 1): "mono8", ("u1", 3): "rgb8", ("u1", 4): "rgba8", ("u2", 1): "mono16",
                      ("u2", 3): "rgb16", ("f4", 1): "32FC1", ("f8", 1): "64FC1"}


def register_msg(type_name: str, definition: str) -> None:
    """Add a message type from its ``.msg`` text (the types it names must be known already).
    The same definition again is taken (nothing changes); another one under a name known already
    is a ValueError, as is a name not of three parts (``pkg/msg/Name``) or a field of a type that
    is not known; nothing is registered then."""
    parts = type_name.split("/")
    if len(parts) != 3 or parts[1] != "msg" or not all(parts):
        meant = f"{parts[0]}/msg/{parts[-1]}" if len(parts) >= 2 and parts[0] and parts[-1] else "pkg/msg/Name"
        raise ValueError(f"{type_name!r} is not a ROS 2 message type name: they have three parts, like "
                         f"sensor_msgs/msg/Image\n    hint: name it {meant} (msgdef= was given)")
    parsed = get_types_from_msg(definition, type_name)
    known = set(_store.fielddefs) | set(parsed)
    for name, (_, fields) in parsed.items():
        for field, desc in fields:
            named = _named_type(desc)
            if named is not None and named not in known:
                raise ValueError(f"{name}'s msgdef names {named} (field {field}), which is not known\n    hint: "
                                 "use a standard type (sensor_msgs/msg/Image is written sensor_msgs/Image in a .msg), "
                                 "or add that one first with its own msgdef (register_msg)")
    fielddefs = {**_store.fielddefs, **parsed}
    for name in parsed:
        cycle = _cycle(name, fielddefs, [])
        if cycle:
            raise ValueError(f"{name}'s msgdef holds itself: {' -> '.join(cycle)}\n    hint: a ROS 2 message has a "
                             "fixed shape, so a type cannot contain itself, directly or through another; hold a "
                             "sequence of ids or an index instead")
    for name in parsed:
        cost = _fixed_cost((Nodetype.NAME, name), fielddefs)
        if cost > MAX_FIXED_BYTES:
            raise ValueError(f"{name}'s msgdef fixes more than {MAX_FIXED_BYTES} bytes (16 MiB, what Retriever "
                             f"takes) in fixed-size arrays (nested ones multiplied out, {_ELEMENT_COST} bytes at least "
                             "per message element)\n    hint: a message this size is made in full for every value "
                             "(a missing field is zeros); use an unbounded sequence (T[]) for bulk data")
    for name, fielddef in parsed.items():
        if name in _store.fielddefs and _store.fielddefs[name] != fielddef:
            raise ValueError(f"{name} is defined already, differently ({_described(_store.fielddefs[name])}); "
                             f"the new definition is ({_described(fielddef)})\n    hint: a type has one definition in "
                             "a program: give the new definition another name")
    _store.register(parsed)


#: the most bytes a registered type's fixed-size arrays may hold, nested ones multiplied out (16 MiB):
#: each value is made in full (a field left out is its zeros), so ``int32[4294967296] x`` would
#: allocate 16 GiB for ``{}``; the standard types fix a few hundred bytes at most (a covariance's
#: float64[36]), and bulk data goes in sequences, which hold what the value holds
MAX_FIXED_BYTES = 1 << 24
#: what one message element of a fixed-size array costs at least: made as a Python object
_ELEMENT_COST = 64


def _cycle(name: str, fielddefs: dict, path: list[str]) -> list[str]:
    """The types from ``name`` back to one on ``path`` (a type that holds itself), or []."""
    if name in path:
        return path[path.index(name):] + [name]
    for _, desc in fielddefs[name][1]:
        named = _named_type(desc)
        if named is not None and named in fielddefs:
            cycle = _cycle(named, fielddefs, path + [name])
            if cycle:
                return cycle
    return []


def _fixed_cost(desc: tuple, fielddefs: dict) -> int:
    """The bytes a field of ``desc`` holds whatever its value: base values their size, a sequence
    its length (its items are the value's), a fixed-size array its length times its element's,
    a message element at least :data:`_ELEMENT_COST`. Stops counting past :data:`MAX_FIXED_BYTES`."""
    kind, detail = desc
    if kind == Nodetype.BASE:
        return np.dtype(_BASE_DTYPES[detail[0]]).itemsize if detail[0] in _BASE_DTYPES else 4
    if kind == Nodetype.NAME:
        total = 0
        for _, field in fielddefs[detail][1]:
            total += _fixed_cost(field, fielddefs)
            if total > MAX_FIXED_BYTES:
                break
        return total
    if kind == Nodetype.SEQUENCE:
        return 4
    element, length = detail
    each = _fixed_cost(element, fielddefs) + (_ELEMENT_COST if element[0] == Nodetype.NAME else 0)
    return min(length * max(each, 1), MAX_FIXED_BYTES + 1)


def _named_type(desc: tuple) -> str | None:
    """The message type a field's description names (of an array's elements too), or None."""
    kind, detail = desc
    if kind == Nodetype.NAME:
        return detail
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        return _named_type(detail[0])
    return None


def _described(fielddef: tuple) -> str:
    """A type's fields as a .msg would list them, on one line: ``int32 a, string b``."""
    def spelled(desc: tuple) -> str:
        kind, detail = desc
        if kind == Nodetype.NAME:
            return detail
        if kind == Nodetype.BASE:
            return detail[0] + (f"<={detail[1]}" if detail[1] else "")
        element, length = detail
        bound = str(length) if kind == Nodetype.ARRAY else f"<={length}" if length else ""
        return f"{spelled(element)}[{bound}]"

    return ", ".join(f"{spelled(desc)} {name}" for name, desc in fielddef[1])


def check_type(type_name: str) -> None:
    if type_name not in _store.fielddefs:
        raise ValueError(f"ROS message type {type_name!r} is not known\n    hint: standard types are written "
                         "like sensor_msgs/msg/Image; add your own with its .msg text (msgdef=...)")


def type_hash(type_name: str) -> str:
    """The type's RIHS01 hash (REP-2011), as rmw_zenoh puts it in key expressions."""
    return _store.hash_rihs01(type_name)


def serialize(message: Any, type_name: str) -> bytes:
    """A rosbags message as CDR bytes (little endian, with its encapsulation header)."""
    return bytes(_store.serialize_cdr(message, type_name))


def deserialize(data: bytes, type_name: str) -> Any:
    return _store.deserialize_cdr(data, type_name)


# ---------------------------------------------------------------------------------------------
# message → value
# ---------------------------------------------------------------------------------------------
def to_value(message: Any, type_name: str) -> Any:
    """The Retriever value of a rosbags message of ``type_name`` (the rules above)."""
    if type_name in _TIME_TYPES:
        return message.sec * 1_000_000_000 + message.nanosec
    if type_name in _VECTORS:
        return np.array([getattr(message, axis) for axis in _VECTORS[type_name]], dtype=np.float64)
    fields = _fields(type_name)
    if type_name.startswith("std_msgs/msg/"):
        if [name for name, _ in fields] == ["data"]:
            return _field_to_value(message.data, fields[0][1])
        if type_name.endswith("MultiArray"):
            shape = [dim.size for dim in message.layout.dim]
            data = np.array(message.data)
            return data.reshape(shape) if shape and int(np.prod(shape)) == data.size else data
    value: dict[str, Any] = {}
    flat = flat_header(type_name)
    for name, desc in fields:
        field = getattr(message, name)
        if name == flat:
            value["stamp"] = to_value(field.stamp, "builtin_interfaces/msg/Time")
            value["frame_id"] = field.frame_id
        else:
            value[name] = _field_to_value(field, desc)
    if type_name == _IMAGE and _known_encoding(message.encoding):
        value["image"] = _image_array(value.pop("data"), message)
        del value["step"], value["is_bigendian"]
    return value


def _fields(type_name: str) -> list:
    return _store.fielddefs[type_name][1]


def _field_to_value(field: Any, desc: tuple) -> Any:
    kind, detail = desc
    if kind == Nodetype.NAME:
        return to_value(field, detail)
    if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
        element = detail[0]
        if isinstance(field, np.ndarray):
            return field.copy()  # rosbags' arrays may view the sample's buffer
        return [_field_to_value(item, element) for item in field]
    return field


def _image_array(data: np.ndarray, message: Any) -> np.ndarray:
    dtype, channels = _encoding(message.encoding)
    dtype = np.dtype(dtype).newbyteorder(">" if message.is_bigendian else "<")
    row_bytes = message.width * channels * dtype.itemsize
    rows = np.asarray(data, dtype=np.uint8).reshape(message.height, message.step)[:, :row_bytes]
    image = np.ascontiguousarray(rows).view(dtype).astype(dtype.newbyteorder("="))
    return image.reshape((message.height, message.width) + ((channels,) if channels > 1 else ()))


def _known_encoding(encoding: str) -> bool:
    try:
        _encoding(encoding)
    except ValueError:
        return False
    return True


def _encoding(encoding: str) -> tuple[str, int]:
    if encoding in _ENCODINGS:
        return _ENCODINGS[encoding]
    if encoding.startswith("bayer_") and encoding[-1] in "86":  # one channel: the sensor's mosaic
        return ("u1" if encoding.endswith("8") else "u2"), 1
    if encoding in ("yuv422", "uyvy", "yuyv", "yuv422_yuy2"):
        return "u1", 2
    depth, _, channels = encoding.partition("C")
    if depth in _DEPTH_DTYPES and channels.isdigit():
        return _DEPTH_DTYPES[depth], int(channels)
    raise ValueError(f"image encoding {encoding!r} is not one Retriever reads (rgb8, bgr8, mono8, mono16, "
                     "8UC3, 32FC1, …); subscribe to sensor_msgs/msg/CompressedImage for compressed ones")


# ---------------------------------------------------------------------------------------------
# value → message
# ---------------------------------------------------------------------------------------------
def from_value(value: Any, type_name: str, *, frame_id: str = "") -> Any:
    """The rosbags message of ``type_name`` for a Retriever value (the inverse of :func:`to_value`;
    missing fields are zero, but a Header's ``frame_id``, which is ``frame_id``). Conversions are
    exact or refused: a value a field cannot take as it is (a list for a string, ``"false"`` or 1
    for a bool, 3.7 for an int, 4 numbers for a Vector3, 300 for a uint8) is a TypeError or
    ValueError that names the type, the field's path in it, what the field takes and what it got.
    An int-valued float (3.0) passes for an int."""
    return _message(value, type_name, _Where(type_name, "", frame_id))


def flat_header(type_name: str) -> str | None:
    """The name of ``type_name``'s Header field if its ``stamp`` and ``frame_id`` are keys of the
    value itself: when it has one Header and no other field is named ``stamp`` or ``frame_id``
    (``{"header": ..., "stamp": ...}`` would collapse two stamps into one key); else None, and
    each Header is a dict ``{"stamp", "frame_id"}`` under its own field's name."""
    fields = _fields(type_name)
    headers = [name for name, desc in fields if desc == (Nodetype.NAME, _HEADER)]
    if len(headers) != 1 or any(name in ("stamp", "frame_id") for name, _ in fields):
        return None
    return headers[0]


class _Where:
    """Where in the published value a conversion is: the message type published, the field's path,
    and the frame_id a Header the value leaves without one gets."""

    def __init__(self, root: str, path: str, frame_id: str = ""):
        self.root, self.path, self.frame_id = root, path, frame_id

    def field(self, name: str) -> _Where:
        return _Where(self.root, f"{self.path}.{name}" if self.path else name, self.frame_id)

    def item(self, index: int) -> _Where:
        return _Where(self.root, f"{self.path}[{index}]", self.frame_id)

    def refuse(self, takes: str, value: Any, error: type = TypeError, why: str = "") -> Exception:
        place = f"{self.root} field {self.path}" if self.path else self.root
        return error(f"{place}: takes {takes}, got {_given(value)}{why}")


def list_of_numbers_is_one_value(type_name: str) -> bool:
    """Whether a list of numbers is one value of ``type_name``: a Vector3, Point, Point32 or
    Quaternion (``[x, y, z]``), or a ``std_msgs`` MultiArray (its data); of every other type a
    value is never a list of numbers."""
    return type_name in _VECTORS or type_name.startswith("std_msgs/msg/") and type_name.endswith("MultiArray")


def _given(value: Any) -> str:
    if isinstance(value, np.ndarray):
        return f"an array of {value.dtype} of shape {value.shape}"
    text = repr(value)
    text = text if len(text) <= 60 else text[:57] + "..."
    if isinstance(value, (list, tuple)):
        return f"{type(value).__name__} of {len(value)} {text}"
    return f"{type(value).__name__} {text}"


def _message(value: Any, type_name: str, where: _Where) -> Any:
    cls = _store.types[type_name]
    if type_name in _TIME_TYPES:
        ns = _integer(0 if value is None else value, "an int of ns", where)
        if not -2**31 * 1_000_000_000 <= ns < 2**31 * 1_000_000_000:
            raise where.refuse("an int of ns within an int32 of seconds", value, ValueError)
        return cls(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)
    if type_name in _VECTORS:
        axes = _VECTORS[type_name]
        takes = f"{len(axes)} numbers [{', '.join(axes)}] (a {type_name})"
        if isinstance(value, (str, bytes, dict)) or not hasattr(value, "__len__"):
            raise where.refuse(takes, value)
        if len(value) != len(axes) or isinstance(value, np.ndarray) and value.ndim != 1:
            raise where.refuse(takes, value, ValueError)
        return cls(**{axis: _base_value(item, "float64", where.field(axis)) for axis, item in zip(axes, value)})
    fields = _fields(type_name)
    if type_name.startswith("std_msgs/msg/") and not isinstance(value, dict):
        return _wrapped_value(value, type_name, fields, where)
    if type_name == _IMAGE and (isinstance(value, np.ndarray) or isinstance(value, dict) and "image" in value):
        value = _image_fields(value)
    if not isinstance(value, dict):
        if where.path:
            raise where.refuse(f"a dict of the fields of a {type_name}", value)
        raise TypeError(f"a {type_name} is published from a dict of its fields, got {type(value).__name__}")
    flat = flat_header(type_name)
    unknown = set(value) - {name for name, _ in fields if name != flat} - ({"stamp", "frame_id"} if flat else set())
    if unknown:
        place = f"{where.root} field {where.path}" if where.path else where.root
        raise ValueError(f"{place} has no field(s) {', '.join(sorted(map(str, unknown)))}")
    kwargs = {}
    for name, desc in fields:
        if name == flat:  # its stamp and frame_id are keys of the value itself
            kwargs[name] = _header(value, where)
        elif desc == (Nodetype.NAME, _HEADER):
            header = value.get(name)
            if header is not None and not isinstance(header, dict):
                raise where.field(name).refuse('a dict {"stamp": ns, "frame_id": str} (a std_msgs/msg/Header)', header)
            place = where.field(name)
            if header and set(header) - {"stamp", "frame_id"}:
                raise ValueError(f"{place.root} field {place.path} (a std_msgs/msg/Header) has no field(s) "
                                 f"{', '.join(sorted(map(str, set(header) - {'stamp', 'frame_id'})))}")
            kwargs[name] = _header(header or {}, place)
        else:
            kwargs[name] = _field_from_value(value.get(name), desc, where.field(name))
    return cls(**kwargs)


def _header(value: dict, where: _Where) -> Any:
    """The Header of ``value``'s ``stamp`` and ``frame_id`` (``where.frame_id`` when it has none)."""
    frame_id = value.get("frame_id")
    return _store.types[_HEADER](
        stamp=_message(value.get("stamp"), "builtin_interfaces/msg/Time", where.field("stamp")),
        frame_id=_base_value(where.frame_id if frame_id is None else frame_id, "string", where.field("frame_id")))


#: what a ROS 2 message holds sizes, strides and a sequence's length in (CDR's uint32)
UINT32_MAX = 2**32 - 1


def _check_sizes(type_name: str, shape: tuple, sizes: dict[str, int]) -> None:
    """Refuse a value whose ``sizes`` (name → number) a ``type_name`` cannot hold, before its
    bytes are copied (a 4 GiB row would be, and then fail in the serializer)."""
    past = [f"{name} {number}" for name, number in sizes.items() if number > UINT32_MAX]
    if past:
        raise ValueError(f"a {type_name} cannot hold an array of shape {tuple(shape)}: its {', '.join(past)} "
                         f"{'is' if len(past) == 1 else 'are'} past the uint32 a ROS 2 message holds sizes in "
                         f"({UINT32_MAX}); publish it in parts")


def _wrapped_value(value: Any, type_name: str, fields: list, where: _Where) -> Any:
    if [name for name, _ in fields] == ["data"]:
        return _store.types[type_name](data=_field_from_value(value, fields[0][1], where.field("data")))
    if type_name.endswith("MultiArray"):
        array = _array(value, fields[1][1][1][0][1][0], where.field("data"), any_shape=True)
        _check_sizes(type_name, array.shape, {"length": array.size, **{f"dimension {i}": int(np.prod(
            array.shape[i:], dtype=object)) for i in range(array.ndim)}})
        dims = [{"label": f"dim{i}", "size": size, "stride": int(np.prod(array.shape[i:]))}
                for i, size in enumerate(array.shape)]
        return _message({"layout": {"dim": dims}, "data": array.reshape(-1)}, type_name, where)
    raise TypeError(f"a {type_name} is published from a dict of its fields, got {type(value).__name__}")


def _field_from_value(value: Any, desc: tuple, where: _Where) -> Any:
    kind, detail = desc
    if kind == Nodetype.NAME:
        return _message(_zero_value(detail) if value is None else value, detail, where)
    if kind == Nodetype.BASE:
        return _base_value(value, detail[0], where, detail[1])
    element, length = detail
    fixed = kind == Nodetype.ARRAY
    if element[0] == Nodetype.BASE and element[1][0] not in ("string", "wstring"):
        if value is None:
            return np.zeros(length if fixed else 0, _BASE_DTYPES[element[1][0]])
        array = _array(value, element[1][0], where, length=length, fixed=fixed)
        return array
    name = element[1] if element[0] == Nodetype.NAME else element[1][0]
    takes = f"{length} {name}" if fixed else f"a sequence of {name}" + (f" (at most {length})" if length else "")
    if value is None:
        items = [None] * (length if fixed else 0)
    elif isinstance(value, (str, bytes, dict)) or not hasattr(value, "__iter__"):
        raise where.refuse(takes, value)
    else:
        items = list(value)
    if fixed and len(items) != length or not fixed and length and len(items) > length:
        raise where.refuse(takes, value, ValueError)
    return [_field_from_value(item, element, where.item(i)) for i, item in enumerate(items)]


def _zero_value(type_name: str) -> Any:
    """The value of a message field left out: zero ns, a zero vector, or a message of zeros."""
    if type_name in _TIME_TYPES:
        return 0
    return [0.0] * len(_VECTORS[type_name]) if type_name in _VECTORS else {}


_BASE_DTYPES = {"bool": np.bool_, "byte": np.uint8, "char": np.uint8, "int8": np.int8, "uint8": np.uint8,
                "int16": np.int16, "uint16": np.uint16, "int32": np.int32, "uint32": np.uint32,
                "int64": np.int64, "uint64": np.uint64, "float32": np.float32, "float64": np.float64}


#: the largest finite float32, as a Python float (compared with one, numpy would cast the other to float32)
_FLOAT32_MAX = float(np.finfo(np.float32).max)


def _takes(base: str) -> str:
    """What a field of ``base`` takes, in words."""
    if base == "bool":
        return "a bool (or numpy bool)"
    dtype = np.dtype(_BASE_DTYPES[base])
    if dtype.kind == "f":
        return f"a {base} (an int or a float)"
    info = np.iinfo(dtype)
    return f"a{'n' if base[0] in 'i' else ''} {base} (a whole number from {info.min} to {info.max})"


def _integer(value: Any, takes: str, where: _Where) -> int:
    """``value`` as an int: an int, or a float that is one (3.0, not 3.7); never a bool or a str."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise where.refuse(takes, value)
    if isinstance(value, (float, np.floating)):
        if not np.isfinite(value) or not float(value).is_integer():
            raise where.refuse(takes, value, ValueError, " (not a whole number)")
    return int(value)


def _base_value(value: Any, base: str, where: _Where, bound: int = 0) -> Any:
    if base in ("string", "wstring"):
        if value is None:
            return ""
        if not isinstance(value, str):
            raise where.refuse("a str" + (f" of at most {bound} characters" if bound else ""), value)
        if bound and len(value) > bound:
            raise where.refuse(f"a str of at most {bound} characters", value, ValueError)
        return str(value)
    if base == "bool":
        if value is None:
            return False
        if not isinstance(value, (bool, np.bool_)):
            raise where.refuse(_takes(base), value)
        return bool(value)
    if value is None:
        value = 0
    if base.startswith("float"):
        if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
            raise where.refuse(_takes(base), value)
        try:
            number = float(value)
        except OverflowError:
            raise where.refuse(_takes(base), value, ValueError) from None
        if base == "float32" and np.isfinite(number) and abs(number) > _FLOAT32_MAX:
            raise where.refuse(_takes(base), value, ValueError, " (past float32's range)")
        return number
    number = _integer(value, _takes(base), where)
    info = np.iinfo(_BASE_DTYPES[base])
    if not info.min <= number <= info.max:
        raise where.refuse(_takes(base), value, ValueError)
    return number


def _array(value: Any, base: str, where: _Where, *, length: int = 0, fixed: bool = False,
           any_shape: bool = False) -> np.ndarray:
    """A numeric array or sequence field's value as a numpy array of its dtype, exactly: bools for
    bool only, whole numbers within range for ints, numbers for floats (bytes for uint8/byte/char);
    a fixed-size array of its length, a bounded sequence within its bound."""
    dtype = np.dtype(_BASE_DTYPES[base])
    what = (f"{length} {base}" if fixed else f"a sequence of {base}" + (f" (at most {length})" if length else ""))
    takes = what + (f" (whole numbers from {np.iinfo(dtype).min} to {np.iinfo(dtype).max})"
                    if dtype.kind in "iu" else "")
    if isinstance(value, (bytes, bytearray, memoryview)) and dtype == np.uint8:
        array = np.frombuffer(value, np.uint8)
    elif isinstance(value, (str, bytes, bytearray, dict)) or not hasattr(value, "__len__"):
        raise where.refuse(takes, value)
    else:
        try:
            array = np.asarray(value)
        except ValueError:  # ragged
            raise where.refuse(takes, value, ValueError) from None
    if array.ndim != 1 and not any_shape:
        raise where.refuse(takes, array, ValueError)
    kind = array.dtype.kind
    if array.size == 0 and kind in "fO":  # [] is float64 to numpy, an empty sequence to us
        return array.astype(dtype).reshape(array.shape)
    if (dtype.kind == "b") != (kind == "b") or kind not in "biuf":
        raise where.refuse(takes, array if kind in "biuf" else value)
    if dtype.kind in "iu" and array.size:
        if kind == "f":
            if not np.all(np.isfinite(array)) or not np.all(array == np.floor(array)):
                raise where.refuse(takes, array, ValueError, " (not whole numbers)")
        low, high = int(array.min()), int(array.max())
        info = np.iinfo(dtype)
        if low < info.min or high > info.max:
            raise where.refuse(takes, array, ValueError, f" (from {low} to {high})")
    if dtype == np.float32 and kind == "f" and array.size:
        finite = array[np.isfinite(array)]
        if finite.size and float(np.abs(finite).max()) > _FLOAT32_MAX:
            raise where.refuse(takes, array, ValueError, " (past float32's range)")
    if fixed and array.shape != (length,) or not fixed and length and array.size > length:
        raise where.refuse(takes, array, ValueError)
    return array.astype(dtype, copy=False)


def _image_fields(value: Any) -> dict:
    """An Image's dict with ``image`` (or an array alone) turned into its wire fields."""
    if isinstance(value, np.ndarray):
        value = {"image": value}
    fields = dict(value)
    image = np.asarray(fields.pop("image"))
    image = image.astype(image.dtype.newbyteorder("="), copy=False)
    channels = image.shape[2] if image.ndim == 3 else 1
    encoding = fields.get("encoding") or _DEFAULT_ENCODINGS.get((image.dtype.str[1:], channels))
    if encoding is None:
        raise ValueError(f"an image of dtype {image.dtype} with {channels} channel(s) needs an encoding "
                         "(pass {'image': array, 'encoding': ...})")
    dtype, expected = _encoding(encoding)
    if np.dtype(dtype) != image.dtype or expected != channels:
        raise ValueError(f"image encoding {encoding!r} is {expected} channel(s) of {np.dtype(dtype)}, "
                         f"the array is {channels} of {image.dtype}")
    step = image.shape[1] * channels * image.dtype.itemsize
    _check_sizes(_IMAGE, image.shape, {"height": image.shape[0], "width": image.shape[1], "step": step,
                                       "length": image.shape[0] * step})
    little = np.ascontiguousarray(image, dtype=image.dtype.newbyteorder("<"))
    fields.update(height=image.shape[0], width=image.shape[1], encoding=encoding, is_bigendian=0,
                  step=step, data=little.reshape(-1).view(np.uint8))
    return fields
