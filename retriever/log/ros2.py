"""A log as ROS 2 tools read it: ``retriever log export run.mcap --format ros2 -o run_ros2.mcap``.

The ROS 2 profile of MCAP (the file of a ROS 2 bag's MCAP storage, which ``ros2 bag``, ``rosbags``,
Foxglove and PlotJuggler read): ``ros2msg`` schemas and CDR payloads, both made by ``rosbags``'
type store of ROS 2 Jazzy (the extra ``retriever-robotics[ros2]``; the standard messages written
here are the same in every ROS 2 release since Humble), the file by ``mcap``'s writer, which,
unlike ``rosbags``' own bag writer, keeps each message's publish time and sequence number.
Each output port is a topic ``/<node>/<port>``, and a dataclass value's fields or a dict value's items
(what a ROS 2 subscriber sends) each a topic of their own (``/<node>/<port>/<field>``,
views.value_leaves); a value is

- an image (uint8 H×W, H×W×3, H×W×4): ``sensor_msgs/msg/Image`` (``mono8``, ``rgb8``, ``rgba8``),
  its ``header.stamp`` the event's tag and its ``frame_id`` the node; a depth image too (a 2-D
  uint16 array: ``16UC1``, float32: ``32FC1``); and an ``image`` beside an ``encoding`` in a
  dict (what a Ros2Subscriber makes of a ``sensor_msgs/msg/Image``: mono16, bgr8, yuv422,
  bayer...) in that encoding, when the array holds what it says (``ros_image_encoding``);
- a number (bool, int, float, NumPy's of each width): ``std_msgs/msg/Bool``, ``Int64``,
  ``Float64``, ``Float32``, ``UInt8``...; an array of numbers, or a flat list of them,
  ``std_msgs/msg/<Type>MultiArray`` with its shape as the layout's dimensions (row-major);
- text: ``std_msgs/msg/String``;
- bytes: ``std_msgs/msg/UInt8MultiArray`` holding them;
- a complex number or array (complex64, complex128): ``std_msgs/msg/Float32MultiArray`` or
  ``Float64MultiArray`` of its real and imaginary parts, along a last dimension of size 2 added to
  its shape (``[re, im, re, im...]``; a complex scalar is shape ``[2]``);
- an array that holds no element but has a dimension past a uint32 (``(0, 2**40)``): JSON (below),
  its dtype and shape;
- anything else (a nested list, a dict with a key that names no path part, a number too big for 64 bits...): ``std_msgs/msg/String``
  holding the value as JSON (bigger arrays summarised: foxglove.to_json), counted as ``as_json``.

A topic's type is its first value's. A later value that fits it without loss is written in it
(an int on a Float64 topic, an int8 on an Int64 one); one that does not (a float on an Int64
topic, a negative int on a UInt64 one, an int past the width of the topic's type) goes, as JSON,
on ``<topic>/json``: an integer is never written wrapped around.

Names: each node, port and field name is made a ROS name token (``ros_name``: a character no
token holds becomes ``_``, a run of ``_`` one, since ROS 2 names hold no ``__``; a leading digit
gets a ``_`` before it). Names that differ can then meet (``cam-left`` and ``cam_left``): two
things never share a topic. The step records' topics (``/retriever/steps/<node>``) and the ports'
are named first, before any value is read, those whose names needed no change before the others,
each in the order of its names; a topic already taken goes to the first free ``<topic>_2``,
``<topic>_3``...; a field's or a ``json`` topic, met later, likewise (the fields of one value
named as the ports are: ``{"#": 2.0, "_": 3.0}`` gives ``_`` the topic ``.../_``, ``#`` ``.../_2``;
a field first met in a later value than another's finds what that one took). A topic longer than rmw
takes (247 characters: a long dict key's, say) is cut to that length, and one cut to a name
taken takes the next free ``_N`` the same way (``fitted``). So the same log always
gives the same topics, whatever the order of its records; ``Ros2Export.renamed`` says which
moved, and where.

A ROS 2 message holds sizes as uint32 (an Image's ``height``, ``width`` and ``step``, a
MultiArray dimension's ``size`` and ``stride``, and the length of every sequence): a value whose
sizes do not fit (an image with rows of more than 4 GiB, an array of more than 2**32 - 1
elements) stops the export with a LogError naming its event, port and shape (``sizes_too_big``),
before anything the size of the value is made.

Step records are JSON in ``std_msgs/msg/String`` on ``/retriever/steps/<node>`` (views.step_json):
every ROS tool reads and replays a standard type as it is, where a message type of our own would
need its interface package built before ``ros2 bag play`` or ``ros2 topic echo`` could show it.

Times: a message's log time (and an image's ``header.stamp``) is the event's tag, ns from the
run's T0, so that the bag replays in event time; its publish time is the wall clock of its
publication when the log has it, else the tag. A step's log time is its tick, its publish time
the wall clock when the step began. Each event's ``seq`` is its message's sequence number; a
tag's microstep is in the step records only (events of one instant share their stamp).
"""

from __future__ import annotations

import json
import os
import re
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import Writer

from ..errors import LogError
from ..trace import StepRecord
from .format import parse_data_topic
from .outputs import CountedStream, export_path, stdout_stream, to_stdout
from .reader import LogHead, LogRecords, RunLog, log_records
from .views import image_encoding, numeric_array, step_json, to_json, value_leaves

IMAGE = "sensor_msgs/msg/Image"
STRING = "std_msgs/msg/String"
JSON = "json"  # a leaf no standard message fits: its JSON text in a String
#: a number's message, by its NumPy type (float16 and bool arrays travel widened: no such message)
SCALARS = {"bool": "Bool", "int8": "Int8", "int16": "Int16", "int32": "Int32", "int64": "Int64",
           "uint8": "UInt8", "uint16": "UInt16", "uint32": "UInt32", "uint64": "UInt64",
           "float16": "Float32", "float32": "Float32", "float64": "Float64"}
ARRAYS = {**{name: f"{kind}MultiArray" for name, kind in SCALARS.items()}, "bool": "UInt8MultiArray"}
#: a complex number's parts' NumPy type (a complex one is written as its parts: message_kind)
COMPLEX = {"complex64": "float32", "complex128": "float64"}
#: the NumPy type each std_msgs number message holds
MESSAGE_DTYPES = {"Bool": "bool", "Float32": "float32", "Float64": "float64",
                  **{kind: name for name, kind in SCALARS.items() if kind[0] in "IU"}}
#: ``ros2 bag`` reads the QoS a topic was recorded with from this channel metadata; none: its defaults
CHANNEL_METADATA = {"offered_qos_profiles": ""}
MAX_STAMP_NS = (2**31) * 10**9  # builtin_interfaces/Time holds int32 seconds
#: what a ROS 2 message's sizes are held in (an Image's height, width, step; a MultiArray
#: dimension's size, stride; every sequence's length in CDR): uint32
UINT32_MAX = 2**32 - 1
#: what to do with a value too big for a ROS 2 message
TOO_BIG_HINT = ("ROS 2 messages hold sizes, row strides and lengths as uint32: have the flow send such a "
                "value in parts (tiles of the image, chunks of the array)")
STEPS_PREFIX = "/retriever/steps/"
#: a bare 2-D array of these is an image too: a depth image (16UC1 in mm, 32FC1 in m, as ROS
#: depth cameras publish them); uint8 ones are views.image_encoding's (mono8, rgb8, rgba8)
DEPTH_ENCODINGS = {"uint16": "16UC1", "float32": "32FC1"}
#: sensor_msgs/image_encodings.hpp: what an encoding holds, ``(dtype, channels)`` (as
#: retriever/ros2/types.py reads them; bayer_*, yuv422 and <depth>C<n> are read by rule)
IMAGE_LAYOUTS = {"rgb8": ("uint8", 3), "bgr8": ("uint8", 3), "rgba8": ("uint8", 4), "bgra8": ("uint8", 4),
                 "mono8": ("uint8", 1), "rgb16": ("uint16", 3), "bgr16": ("uint16", 3), "rgba16": ("uint16", 4),
                 "bgra16": ("uint16", 4), "mono16": ("uint16", 1), "yuv422": ("uint8", 2), "uyvy": ("uint8", 2),
                 "yuyv": ("uint8", 2), "yuv422_yuy2": ("uint8", 2)}
_DEPTHS = {"8U": "uint8", "8S": "int8", "16U": "uint16", "16S": "int16", "32S": "int32", "32F": "float32",
           "64F": "float64"}


def _typestore():
    try:
        from rosbags.typesys import Stores, get_typestore
    except ImportError:
        raise LogError("the ROS 2 export needs the rosbags package, which is not installed",
                       "pip install 'retriever-robotics[ros2]'") from None
    return get_typestore(Stores.ROS2_JAZZY)


@dataclass
class Ros2Export:
    """What :func:`export_ros2` wrote: the messages per topic, each topic's ROS type, and how
    many leaves of values no standard message fits (written as JSON text)."""

    written: Counter = field(default_factory=Counter)
    types: dict[str, str] = field(default_factory=dict)
    as_json: int = 0
    #: what had to move to a topic of its own (``node.port[.field]``, ``the step records of
    #: NODE``, ``... as JSON``) because another took the one its names make: the topic it got
    renamed: dict[str, str] = field(default_factory=dict)


def ros_name(text: str) -> str:
    """``text`` as one token of a ROS name: ASCII letters, digits and single underscores (ROS 2
    names hold no ``__``), not starting with a digit; every other character becomes ``_``, a run
    of ``_`` one (a log's names are checked, not trusted; a Retriever node name may hold ``-``)."""
    token = re.sub(r"_{2,}", "_", re.sub(r"[^A-Za-z0-9_]", "_", text)) or "_"
    return "_" + token if token[0].isdigit() else token


#: the longest fully qualified topic rmw takes (rmw/validate_full_topic_name.h:
#: RMW_TOPIC_MAX_NAME_LENGTH, 255 less 8 kept for a DDS rmw's prefixes)
MAX_TOPIC_LENGTH = 255 - 8


def fitted(wanted: str, n: int) -> str:
    """The ``n``-th topic ``wanted`` may take: itself (``n`` 1), else ``<wanted>_<n>`` (no ``_``
    added after one: never a ``__``); a topic past :data:`MAX_TOPIC_LENGTH` is cut to leave room
    for its ``_<n>``, then stripped of a trailing ``/`` or ``_`` (a valid ROS name again), so
    that two long names cut to one prefix are kept apart by the same ``_<n>`` rule."""
    if n == 1:
        return wanted if len(wanted) <= MAX_TOPIC_LENGTH else _cut(wanted, MAX_TOPIC_LENGTH)
    topic = f"{wanted}{'' if wanted.endswith('_') else '_'}{n}"
    return topic if len(topic) <= MAX_TOPIC_LENGTH else f"{_cut(wanted, MAX_TOPIC_LENGTH - len(str(n)) - 1)}_{n}"


def _cut(topic: str, length: int) -> str:
    """``topic``'s first ``length`` characters, less a trailing ``/`` or ``_`` (``/topic`` if
    nothing else is left)."""
    return topic[:length].rstrip("/_") or "/topic"


#: what a topic stands for: ``("steps", node)``, the step records of a node; ``("port", node,
#: port, path)``, a port's values (``path`` ``""``) or a field of them (``"/field/inner"``);
#: ``("json", origin)``, what did not fit the message of another origin's topic
Origin = tuple


def origin_text(origin: Origin) -> str:
    """What ``origin`` is, as ``Ros2Export.renamed`` says it."""
    if origin[0] == "steps":
        return f"the step records of {origin[1]}"
    if origin[0] == "port":
        return f"{origin[1]}.{origin[2]}{origin[3].replace('/', '.')}"
    return f"{origin_text(origin[1])} as JSON"


def plain_topic(origin: Origin) -> str:
    """The topic ``origin``'s names would make if each were a ROS name token as it is."""
    if origin[0] == "steps":
        return STEPS_PREFIX + origin[1]
    if origin[0] == "port":
        return f"/{origin[1]}/{origin[2]}{origin[3]}"
    return plain_topic(origin[1]) + "/json"


def image_layout(encoding: str) -> tuple[str, int] | None:
    """``(dtype name, channels)`` an image of ``encoding`` holds, None for one not known here."""
    if encoding in IMAGE_LAYOUTS:
        return IMAGE_LAYOUTS[encoding]
    if encoding.startswith("bayer_") and encoding.endswith(("8", "16")):
        return ("uint8" if encoding.endswith("8") else "uint16"), 1
    depth, _, channels = encoding.partition("C")
    if depth in _DEPTHS and channels.isdecimal() and 1 <= int(channels) <= 4:
        return _DEPTHS[depth], int(channels)
    return None


def ros_image_encoding(value: Any, declared: Any = None) -> str | None:
    """The encoding ``value`` is exported in as a ``sensor_msgs/msg/Image``, or None if it is no
    image: ``declared`` (the ``encoding`` beside it in a dict: what a Ros2Subscriber's image
    is) when the array holds what that encoding does, else a uint8 image's (views.image_encoding),
    else a 2-D uint16 or float32 array's (DEPTH_ENCODINGS)."""
    if not isinstance(value, np.ndarray) or value.ndim not in (2, 3) or min(value.shape[:2]) < 2:
        return None
    channels = value.shape[2] if value.ndim == 3 else 1
    if isinstance(declared, str) and image_layout(declared) == (value.dtype.name, channels):
        return declared
    encoding = image_encoding(value)
    if encoding is None and value.ndim == 2:
        encoding = DEPTH_ENCODINGS.get(value.dtype.name)
    return encoding


def message_kind(value: Any, declared: Any = None) -> tuple[str, Any]:
    """``(ROS type, value made ready for it)`` for one leaf: an image as a contiguous array,
    a number or array as NumPy's, text as itself; anything else ``(JSON, its JSON text)``.
    A LogError (:func:`sizes_too_big`) for an array whose sizes no such message holds, said
    before the array is copied."""
    if ros_image_encoding(value, declared) is not None:
        _refuse_sizes(IMAGE, value)
        return IMAGE, np.ascontiguousarray(value, dtype=value.dtype.newbyteorder("<"))  # is_bigendian 0
    if isinstance(value, str):
        return STRING, value
    if isinstance(value, (bytes, bytearray)):  # its content, as the bytes of a UInt8MultiArray
        value = np.frombuffer(value, np.uint8)
    elif isinstance(value, (complex, np.complexfloating, np.ndarray)) and np.asarray(value).dtype.name in COMPLEX:
        # each number as its real and imaginary parts, along a trailing dimension of 2
        array = np.asarray(value)
        if array.size == 0 and max(array.shape, default=0) > UINT32_MAX:
            return JSON, json_text(array)
        _refuse_sizes(f"std_msgs/msg/{ARRAYS[COMPLEX[array.dtype.name]]}", array)
        value = np.stack((array.real, array.imag), axis=-1)
    if isinstance(value, np.ndarray) and value.ndim and value.dtype.name in ARRAYS:  # before any copy
        if value.size == 0 and max(value.shape) > UINT32_MAX:  # holds nothing: its shape, as JSON
            return JSON, json_text(value)
        _refuse_sizes(f"std_msgs/msg/{ARRAYS[value.dtype.name]}", value)
    array = numeric_array(value)
    if array is None:
        return JSON, json_text(value)
    kinds = SCALARS if array.ndim == 0 else ARRAYS
    return f"std_msgs/msg/{kinds[array.dtype.name]}", array


def multiarray_dims(shape: tuple[int, ...]) -> list[tuple[int, int]]:
    """``(size, stride)`` of each dimension of a row-major MultiArray layout of ``shape``: the
    stride of a dimension is the number of elements one step along it spans."""
    dims, stride = [], int(np.prod(shape, dtype=object))
    for size in shape:
        dims.append((int(size), stride))
        stride //= max(int(size), 1)
    return dims


def sizes_too_big(ros_type: str, value: np.ndarray) -> str | None:
    """The first size of ``value`` written as ``ros_type`` that is past a uint32 (``"height
    4294967296"``, ``"dimension 0 stride 4294967296"``...); None when all fit. From the shape
    alone: nothing is copied."""
    if ros_type == IMAGE:
        height, width = value.shape[:2]
        step = int(np.prod(value.shape[1:], dtype=object)) * value.dtype.itemsize  # a contiguous row's bytes
        sizes = [("height", height), ("width", width), ("step", step), ("data length", height * step)]
    elif ros_type.endswith("MultiArray"):
        sizes = [(f"dimension {i} {name}", number) for i, dim in enumerate(multiarray_dims(value.shape))
                 for name, number in zip(("size", "stride"), dim)]
        sizes.append(("data length", int(value.size)))
    else:
        return None
    return next((f"{name} {int(number)}" for name, number in sizes if number > UINT32_MAX), None)


def _refuse_sizes(ros_type: str, value: np.ndarray) -> None:
    """A LogError (without the event: :meth:`Ros2Bag.event` adds it) for an array whose sizes no
    ``ros_type`` holds (``sizes_too_big``'s words)."""
    said = sizes_too_big(ros_type, value)
    if said is not None:
        shape = ", ".join(map(str, value.shape))
        raise LogError(f"its value, {value.dtype.name}[{shape}], does not fit a {ros_type}: its {said} is more than "
                       f"the uint32 a ROS 2 message holds it in ({UINT32_MAX})")


def json_text(value: Any) -> str:
    return json.dumps(to_json(value))


def fit(value: Any, ros_type: str) -> Any | None:
    """``value`` as a number of the std_msgs type ``ros_type`` (a scalar's or an array's) if
    it converts without loss, else None (and None for any other type). An integer goes into an
    integer type only if it is within that type's range: a cast and back alone would pass what
    two's complement wraps around (2**64 - 1 as Int64 -1, -3 as UInt64 2**64 - 3)."""
    kind = ros_type.removeprefix("std_msgs/msg/")
    scalar = kind.removesuffix("MultiArray")
    dtype = MESSAGE_DTYPES.get(scalar)
    array = numeric_array(value)
    if dtype is None or array is None or (array.ndim == 0) != (scalar == kind):
        return None
    if array.dtype.kind in "iu" and np.dtype(dtype).kind in "iu" and array.size:
        limits = np.iinfo(dtype)
        if int(array.min()) < limits.min or int(array.max()) > limits.max:  # Python ints: compared exactly
            return None
    with np.errstate(all="ignore"):  # a cast that overflows is caught by the way back
        cast = array.astype(dtype)
        back = cast.astype(array.dtype)
    same = back == array
    if array.dtype.kind == "f":
        same |= np.isnan(back) & np.isnan(array)
    return cast if bool(np.all(same)) else None


class Ros2Bag:
    """Messages written into an MCAP of the ROS 2 profile: a schema per type, a channel per topic,
    each message serialised to CDR by ``rosbags``' type store."""

    def __init__(self, writer: Writer, typestore):
        self._writer, self._store, self._types = writer, typestore, typestore.types
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._kinds: dict[str, str] = {}  # topic -> its ROS type, or JSON
        self._taken: dict[str, Origin] = {}  # topic -> what it stands for
        self._named: dict[Origin, str] = {}  # and back
        self.summary = Ros2Export()

    def reserve(self, origins) -> None:
        """Name the topics of ``origins`` (those known before any value is read: step records,
        ports): first those whose names need no change, then the others, each in its names'
        order, so that the same log gives the same topics whatever the order of its records."""
        for origin in sorted(set(origins), key=lambda o: (o[0] != "steps", self.wanted(o) != plain_topic(o), o)):
            self.topic_of(origin)

    def wanted(self, origin: Origin) -> str:
        """The topic ``origin``'s names make, as ROS name tokens (taken or not)."""
        if origin[0] == "steps":
            return STEPS_PREFIX + ros_name(origin[1])
        if origin[0] == "port":
            _, node, port, path = origin
            return f"/{ros_name(node)}/{ros_name(port)}" + "".join("/" + ros_name(part) for part in path.split("/")[1:])
        return self.topic_of(origin[1]) + "/json"

    def topic_of(self, origin: Origin) -> str:
        """``origin``'s topic: the one it was given, else the one its names make if free, else the
        first free ``<that>_2``, ``<that>_3``... (said in ``summary.renamed``); each cut to
        rmw's length first (:func:`fitted`)."""
        topic = self._named.get(origin)
        if topic is None:
            wanted = self.wanted(origin)
            topic, n = fitted(wanted, 1), 1
            while topic in self._taken:
                n += 1
                topic = fitted(wanted, n)
            self._taken[topic], self._named[origin] = origin, topic
            if topic != wanted:
                self.summary.renamed[origin_text(origin)] = topic
        return topic

    def write(self, topic: str, ros_type: str, message, log_time: int, publish_time: int, sequence: int) -> None:
        channel = self._channels.get(topic)
        if channel is None:
            schema = self._schemas.get(ros_type)
            if schema is None:
                text = self._store.generate_msgdef(ros_type, ros_version=2)[0]
                schema = self._schemas[ros_type] = self._writer.register_schema(ros_type, "ros2msg", text.encode())
            channel = self._channels[topic] = self._writer.register_channel(topic, "cdr", schema, CHANNEL_METADATA)
            self.summary.types[topic] = ros_type
        self._writer.add_message(channel, log_time=log_time, publish_time=publish_time, sequence=sequence,
                                 data=bytes(self._store.serialize_cdr(message, ros_type)))
        self.summary.written[topic] += 1

    def topic_for(self, origin: Origin, kind: str, value: Any) -> tuple[str, str, Any]:
        """Where a leaf of ``origin`` of ``kind`` (a ROS type, or JSON) goes, and as what: its own
        topic if that is new or of its kind (or of a number type it fits without loss), else as
        JSON: on its topic if that is a JSON topic, else on ``<topic>/json``."""
        while True:
            topic = self.topic_of(origin)
            known = self._kinds.setdefault(topic, kind)
            if known == kind:
                return topic, STRING if kind == JSON else kind, value
            cast = fit(value, known) if kind != JSON else None
            if cast is not None:
                return topic, known, cast
            if kind != JSON:
                value, kind = json_text(value), JSON
                self.summary.as_json += 1
                continue
            origin = ("json", origin)

    def message(self, ros_type: str, value: Any, stamp_ns: int, frame_id: str, encoding: str | None = None):
        """The ``rosbags`` message of ``ros_type`` holding ``value`` (an image in ``encoding``, else
        its own: ros_image_encoding)."""
        types = self._types
        if ros_type == IMAGE:
            if stamp_ns >= MAX_STAMP_NS:
                raise LogError(f"an image's tag ({stamp_ns} ns) is past what a ROS Time holds (int32 seconds)",
                               "the log's times are damaged")
            height, width = value.shape[:2]
            stamp = types["builtin_interfaces/msg/Time"](sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
            return types[IMAGE](header=types["std_msgs/msg/Header"](stamp=stamp, frame_id=frame_id),
                                height=height, width=width, encoding=encoding or ros_image_encoding(value),
                                is_bigendian=0, step=value.strides[0], data=value.reshape(-1).view(np.uint8))
        if ros_type == STRING:
            return types[STRING](data=value)
        if not ros_type.endswith("MultiArray"):
            return types[ros_type](data=value.item())
        dtype = MESSAGE_DTYPES[ros_type.rsplit("/", 1)[1].removesuffix("MultiArray")]
        dims = [types["std_msgs/msg/MultiArrayDimension"](label="", size=size, stride=stride)
                for size, stride in multiarray_dims(value.shape)]
        layout = types["std_msgs/msg/MultiArrayLayout"](dim=dims, data_offset=0)
        return types[ros_type](layout=layout, data=np.ascontiguousarray(value, dtype=dtype).reshape(-1))

    def event(self, node: str, port: str, value: Any, tag_ns: int, publish_ns: int, seq: int) -> None:
        """One event: each of its leaves as a message on its topic (those not named yet named
        first, as :meth:`reserve` does: a field whose name needed no change keeps its topic)."""
        leaves = list(value_leaves(value))
        fresh = [origin for path, _ in leaves if (origin := ("port", node, port, path)) not in self._named]
        if fresh:
            self.reserve(fresh)
        for path, leaf in leaves:
            declared = declared_encoding(value, path)
            try:
                kind, ready = message_kind(leaf, declared)
            except LogError as e:  # (only sizes past a uint32: message_kind)
                field = f", field {path[1:].replace('/', '.')}" if path else ""
                raise LogError(f"event {node}.{port} #{seq}{field}: {e}", TOO_BIG_HINT) from None
            self.summary.as_json += kind == JSON
            topic, ros_type, ready = self.topic_for(("port", node, port, path), kind, ready)
            encoding = ros_image_encoding(ready, declared) if ros_type == IMAGE else None
            self.write(topic, ros_type, self.message(ros_type, ready, tag_ns, node, encoding), tag_ns,
                       publish_ns or tag_ns, seq)


def declared_encoding(value: Any, path: str) -> Any:
    """The ``encoding`` beside the leaf at ``path`` (``/.../image``) in a dict of ``value``: what
    a Ros2Subscriber's sensor_msgs/msg/Image is (ros2/types.py), else None."""
    parts = path.split("/")[1:]
    if not parts or parts[-1] != "image":
        return None
    for part in parts[:-1]:
        value = value.get(part) if isinstance(value, dict) else None
    return value.get("encoding") if isinstance(value, dict) else None


def export_ros2(log: RunLog | str | Path, out: str | Path, *, overwrite: bool = False) -> Ros2Export:
    """Write ``log`` (read whole, or its path: streamed, reader.log_records) as a ROS 2 MCAP to
    ``out`` (``-``: standard output, a pipe); what was written, per topic."""
    store = _typestore()
    if to_stdout(out):
        source = log_records(log)
        return _write_ros2(source, CountedStream(stdout_stream("ros2")), store)
    out = export_path(log.path if isinstance(log, LogHead) else log, out, overwrite)
    source = log_records(log)
    # written beside it, then renamed: an export that fails leaves no file that looks whole
    partial = out.with_name(f".{out.name}.{os.getpid()}.partial")
    try:  # (the file's removal guards its creation too: a signal may come as open returns)
        try:
            stream = open(partial, "wb")
        except OSError as e:
            raise LogError(f"cannot write {out}: {e.strerror}") from None
        with stream:
            summary = _write_ros2(source, stream, store)
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return summary


def _write_ros2(source: LogRecords, stream, store) -> Ros2Export:
    """The log's records as a ROS 2 MCAP written front to back onto ``stream``."""
    head = source.head
    writer = Writer(stream)
    writer.start(profile="ros2", library="retriever log export --format ros2 (rosbags CDR)")
    bag = Ros2Bag(writer, store)
    bag.reserve([("steps", node) for node in source.step_nodes] +
                [("port", *port, "") for c in head.channels.values() if (port := parse_data_topic(c.topic))])
    steps = 0
    for record in source.records():
        if type(record) is StepRecord:
            topic, _, text = bag.topic_for(("steps", record.node), JSON, step_json(record))
            bag.write(topic, STRING, bag.message(STRING, text, 0, ""), record.tag[0],
                      record.wall_start_ns or record.tag[0], steps)
            steps += 1
        else:
            bag.event(record.node, record.port, head.value(record, keep_unregistered=True), record.tag[0],
                      record.publish_ns, record.seq)
    writer.finish()
    return bag.summary
