"""What the exports of a log to other viewers (ROS 2, Rerun, Foxglove) share: a value as the
leaves a viewer shows, an image's encoding, a number as a plain NumPy value, a value and a step
record as JSON.

A viewer plots a number and shows an image, but knows nothing of a dataclass or a dict: a
dataclass value (registered here or not) is opened into its fields, and a dict (what a ROS 2
subscriber's message becomes: ``{"image": ..., "stamp": ..., "frame_id": ...}``) into its items,
each a leaf at its own path (``/rgb``, ``/left/rgb`` when nested), so that a camera frame's image
and its exposure are an image and a plot of their own. A dict is opened only when each of its
keys can name a path part (a non-empty str without ``/``); an empty dict, or one with other keys,
is one leaf, as is everything else, at the port's own path.
"""

from __future__ import annotations

import json
from typing import Any, Iterator

import numpy as np

from ..codec import dataclass_fields
from ..trace import StepRecord


#: arrays up to this many elements go into JSON whole; bigger ones as dtype, shape and a head
JSON_ARRAY_MAX = 1024
IMAGE_ENCODINGS = {3: "rgb8", 4: "rgba8"}  # H×W×channels (an H×W array is mono8; H×W×2 is no image)


def image_encoding(value: Any) -> str | None:
    """``mono8``, ``rgb8`` or ``rgba8`` for a uint8 array shaped as an image; else None."""
    if not isinstance(value, np.ndarray) or value.dtype != np.uint8 or value.ndim not in (2, 3):
        return None
    if value.ndim == 2:
        return "mono8" if min(value.shape) > 1 else None
    return IMAGE_ENCODINGS.get(value.shape[2]) if min(value.shape[:2]) > 1 else None


#: how deep to_json opens nested lists, dicts and dataclasses; deeper is said, not opened (a
#: value from a log is hostile: a thousand nested lists must not exhaust the stack)
JSON_DEPTH_MAX = 32


def to_json(value: Any, depth: int = 0) -> Any:
    """A value as JSON: numbers, strings, lists and dicts as they are, small arrays as lists,
    bigger ones summarised, a dataclass as its fields, anything else as its text."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value if not isinstance(value, float) or np.isfinite(value) else str(value)
    if isinstance(value, np.generic):
        return to_json(value.item())
    if isinstance(value, np.ndarray):
        # by its size and by each dimension: a (10**8, 0) array holds nothing, yet as lists it is 10**8 of them
        small = value.size <= JSON_ARRAY_MAX and max(value.shape, default=0) <= JSON_ARRAY_MAX
        if small and value.dtype.kind in "biuf":
            return to_json(value.tolist(), depth)
        return {"dtype": str(value.dtype), "shape": list(value.shape),
                "head": to_json(value.reshape(-1)[:8].tolist()) if value.dtype.kind in "biuf" else None}
    if depth >= JSON_DEPTH_MAX:
        return f"<{type(value).__name__} nested deeper than {JSON_DEPTH_MAX}>"
    fields = dataclass_fields(value)  # before tuples: an UnregisteredValue is one
    if fields is not None:
        return {name: to_json(v, depth + 1) for name, v in fields.items()}
    if isinstance(value, dict):
        return {str(k): to_json(v, depth + 1) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v, depth + 1) for v in value]
    if isinstance(value, bytes):
        return {"bytes": len(value)}
    return str(value)


def value_leaves(value: Any, path: str = "") -> Iterator[tuple[str, Any]]:
    """``(path, leaf)`` for ``value``: a dataclass's fields or a dict's items, nested ones opened
    too, each at ``path/field`` (``path/key``); any other value (and a dataclass without fields,
    an empty dict, a dict with a key that is no path part) as itself at ``path``."""
    fields = dict_items(value) if isinstance(value, dict) else dataclass_fields(value)
    if not fields:
        yield path, value
        return
    for name, field_value in fields.items():
        yield from value_leaves(field_value, f"{path}/{name}")


def dict_items(value: dict) -> dict[str, Any] | None:
    """``value`` itself if each of its keys can name a path part (a non-empty str holding no
    ``/``), else None."""
    if all(isinstance(key, str) and key and "/" not in key for key in value):
        return value
    return None


def numeric_array(value: Any) -> np.ndarray | None:
    """``value`` as a native-order NumPy array if it is numbers: a bool, int or float array or
    scalar (NumPy's or Python's), or a flat list or tuple of Python numbers; else None. An int
    that no NumPy integer holds is not a number here (it has no fixed-size message)."""
    if isinstance(value, (list, tuple)):
        if not value or not all(isinstance(v, (bool, int, float)) for v in value):
            return None
    elif not isinstance(value, (bool, int, float, np.generic, np.ndarray)):
        return None
    try:
        array = np.asarray(value)
    except (OverflowError, ValueError):
        return None
    if array.dtype.kind not in "biuf":
        return None
    return array.astype(array.dtype.newbyteorder("="), copy=False)


def step_json(step: StepRecord) -> str:
    """A step record as one JSON object: node, status, tick tag, the event ids it consumed and
    produced (``[node, port, seq]``), its detail and the wall time of its step."""
    return json.dumps({
        "node": step.node, "status": step.status, "tag_ns": step.tag[0], "microstep": step.tag[1],
        "consumed": {port: [list(i) for i in ids] for port, ids in step.consumed.items()},
        "produced": [list(i) for i in step.produced], "detail": to_json(step.detail),
        "wall_start_ns": step.wall_start_ns, "wall_ns": step.wall_ns}, allow_nan=False)
