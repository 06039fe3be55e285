"""A policy flow's input ports as LeRobot feature keys, and their values as the arrays a policy reads.

The convention is the one ``retriever log export --format lerobot`` writes datasets with, so a
policy trained on an export reads its ports under the names it was trained on:

- a port whose name contains ``image`` → ``observation.images.<port>``; its value is a ``uint8``
  H×W×3 array (or a dataclass with exactly one such field, as a camera frame), handed to the
  policy as ``float32`` 3×H×W in [0, 1] (as LeRobot's loader does);
- if exactly one other port is left (and no port is named ``observation.state`` explicitly), it
  is ``observation.state``; otherwise each other port is ``observation.<port>``;
- its value is a number, a numeric array or list (flattened), or a dataclass whose numeric fields
  are concatenated in field order (fields of other types are left out), as ``float32``.

``features={"port": "key"}`` names any port's key explicitly (the export's ``--map port=key``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from numbers import Real

import numpy as np

IMAGES = "observation.images."
STATE = "observation.state"


def is_image_key(key: str) -> bool:
    return key.startswith(IMAGES)


def feature_map(owner: str, ports: Iterable[str], features: Mapping[str, str] | None) -> dict[str, str]:
    """Port → feature key: ``features`` where it names the port, else the convention above. Each
    problem (a port that does not exist, a key that is no string, two ports on one key) is listed
    in one ValueError."""
    ports = list(ports)
    given = dict(features or {})
    problems = [f"features names {port!r}, which is none of {owner}'s inputs ({', '.join(ports)})"
                for port in given if port not in ports]
    problems += [f"features[{port!r}] = {key!r} is not a feature key (a str such as 'observation.state')"
                 for port, key in given.items() if type(key) is not str or not key]
    unnamed = [p for p in ports if p not in given]
    images = [p for p in unnamed if "image" in p]
    others = [p for p in unnamed if p not in images]
    mapping = {p: given[p] for p in ports if p in given}
    mapping.update({p: IMAGES + p for p in images})
    state_left = len(others) == 1 and STATE not in given.values()
    mapping.update({p: STATE if state_left else f"observation.{p}" for p in others})
    seen: dict[str, str] = {}
    for port, key in mapping.items():
        if key in seen:
            problems.append(f"ports {seen[key]!r} and {port!r} both map to feature {key!r}")
        seen[key] = port
    if problems:
        raise ValueError(f"{owner}: " + "\n    ".join(problems)
                         + "\n    hint: features={'port': 'observation.state', 'camera': 'observation.images.camera'}")
    return mapping


def to_array(owner: str, port: str, key: str, value: object) -> np.ndarray:
    """The value of ``port`` as the ``float32`` array feature ``key`` holds, or a ValueError
    naming the port, the key and what arrived."""
    if is_image_key(key):
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            images = [v for f in dataclasses.fields(value) if _is_image(v := getattr(value, f.name))]
            value = images[0] if len(images) == 1 else value
        if not _is_image(value):
            what = (f"a {value.dtype} array of shape {value.shape}" if isinstance(value, np.ndarray)
                    else type(value).__qualname__)
            raise ValueError(f"{owner}: port {port!r} feeds the image feature {key!r}, which takes a uint8 H×W×3 "
                             f"array, or a dataclass with one; got {what}")
        return np.ascontiguousarray(value.transpose(2, 0, 1), dtype=np.float32) / np.float32(255)
    numbers = _numbers(value)
    if numbers is None:
        raise ValueError(f"{owner}: port {port!r} feeds feature {key!r}, which takes numbers (a number, a numeric "
                         f"array or list, a dataclass of numeric fields); got {type(value).__qualname__}")
    return numbers


def _is_image(value: object) -> bool:
    return isinstance(value, np.ndarray) and value.dtype == np.uint8 and value.ndim == 3 and value.shape[2] == 3


def _numbers(value: object) -> np.ndarray | None:
    if isinstance(value, (bool, np.bool_)) or isinstance(value, Real):
        return np.array([value], dtype=np.float32)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        parts = [part for f in dataclasses.fields(value) if (part := _numeric_field(getattr(value, f.name))) is not None]
        return np.concatenate(parts) if parts else None
    if isinstance(value, (np.ndarray, list, tuple)):
        try:
            array = np.asarray(value)
        except ValueError:  # ragged
            return None
        if array.dtype.kind not in "biuf":
            return None
        return array.astype(np.float32).reshape(-1)
    return None


def _numeric_field(value: object) -> np.ndarray | None:
    if isinstance(value, (str, bytes)) or dataclasses.is_dataclass(value):
        return None
    return _numbers(value)
