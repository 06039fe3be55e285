"""What the exports of a log to other viewers (ROS 2, Rerun) share: a value as the leaves a
viewer shows, a number as a plain NumPy value, a step record as JSON.

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
from .foxglove import to_json


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
