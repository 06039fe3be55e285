"""A policy flow's observation as LeRobot features, named as ``retriever log export --format
lerobot`` names a dataset's, so a policy reads its inputs under the names it was trained on.

Values become features by their type, as the export's do:

- a ``uint8`` H×W×3 array is an image: source ``name``, or ``name.field`` for an image inside a
  dataclass (or a dict); default key ``observation.images.<source>``;
- numbers, numeric arrays, lists or tuples of them, and a dataclass's (or dict's) numeric fields,
  in field order and flattened, are one state vector per name: ``observation.state`` when it is
  the only one, else ``observation.<name>``; text and ``None`` fields are left out;
- ``features={"source": "key"}`` names any source's key (the export's ``--map``).

The keys are fixed by the first observation; a later one must give the same sources. The policy
gets images as ``float32`` 3×H×W in [0, 1] (as LeRobot's loader gives them) and state vectors as
``float32``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

IMAGES = "observation.images."
STATE = "observation.state"


def is_image(value: Any) -> bool:
    return (isinstance(value, np.ndarray) and value.dtype == np.uint8 and value.ndim == 3 and value.shape[2] == 3
            and min(value.shape[:2]) > 1)


@dataclass
class _Parts:
    """One value taken apart: its images by source, its numeric leaves in order."""

    images: dict[str, np.ndarray] = field(default_factory=dict)
    numbers: list[np.ndarray] = field(default_factory=list)


def _fields(value: Any) -> dict[str, Any] | None:
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {f.name: getattr(value, f.name) for f in dataclasses.fields(value)}
    if isinstance(value, dict) and all(isinstance(k, str) for k in value):
        return value
    return None


def _numeric(value: Any) -> np.ndarray | None:
    if isinstance(value, (bool, int, float, np.bool_, np.integer, np.floating)):
        return np.asarray(value)
    if isinstance(value, np.ndarray):
        return value if value.dtype.kind in "biuf" else None
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):
        parts = [_numeric(v) for v in value]
        if any(p is None for p in parts) or len({p.shape for p in parts}) > 1:
            return None
        return np.stack(parts) if parts else np.zeros(0)
    return None


def _take_apart(value: Any, path: str, parts: _Parts) -> str | None:
    """Fill ``parts`` from ``value`` at ``path``; the reason it cannot, else None."""
    if is_image(value):
        parts.images[path] = value
        return None
    fields = _fields(value)
    if fields is not None:
        for name, inner in fields.items():
            if not (isinstance(inner, (str, bytes)) or inner is None):
                problem = _take_apart(inner, f"{path}.{name}", parts)
                if problem is not None:
                    return problem
        return None
    if isinstance(value, np.ndarray) and value.dtype == np.uint8 and value.ndim >= 2:
        return (f"a uint8 array of shape {value.shape}, which is neither an image (uint8 H×W×3) nor a state "
                "vector; convert it to RGB in the flow, or leave it out")
    numbers = _numeric(value)
    if numbers is None:
        what = (f"a {value.dtype} array of shape {value.shape}" if isinstance(value, np.ndarray)
                else f"a {type(value).__name__}")
        return f"{what}, which no feature holds (images uint8 H×W×3, numbers, and dataclasses of them do)"
    parts.numbers.append(numbers.reshape(-1))
    return None


class ObservationFeatures:
    """Turns a policy's named inputs into ``{feature key: float32 array}``, keys fixed by the
    first observation (see the module docstring)."""

    def __init__(self, owner: str, names: Iterable[str], features: Mapping[str, str] | None = None):
        self.owner, self.names = owner, tuple(names)
        self.given = dict(features or {})
        bad = [f"features[{source!r}] = {key!r} is not a feature key (a str such as 'observation.state')"
               for source, key in self.given.items() if type(key) is not str or not key]
        bad += [f"features names {source!r}, which is none of {owner}'s inputs ({', '.join(self.names)}) nor a "
                "field of one" for source in self.given if source.partition(".")[0] not in self.names]
        if bad:
            raise ValueError(f"{owner}: " + "\n    ".join(bad) + "\n    hint: features={'joints': 'observation.state', "
                             "'camera': 'observation.images.front', 'frame.rgb': 'observation.images.head'}")
        #: source -> feature key, fixed by the first observation
        self.keys: dict[str, str] | None = None

    def __call__(self, values: Mapping[str, Any]) -> dict[str, np.ndarray]:
        found: dict[str, np.ndarray] = {}  # source -> array
        states: list[str] = []
        for name in self.names:
            parts = _Parts()
            problem = _take_apart(values[name], name, parts)
            if problem is not None:
                raise ValueError(f"{self.owner}: input {name!r} carries {problem}")
            found.update(parts.images)
            if parts.numbers:
                found[name] = np.concatenate(parts.numbers) if len(parts.numbers) > 1 else parts.numbers[0]
                states.append(name)
        if self.keys is None:
            self.keys = self._fix(found, states)
        if found.keys() != self.keys.keys():
            raise ValueError(f"{self.owner}: this observation gives {', '.join(found) or 'nothing'}; the first gave "
                             f"{', '.join(self.keys)}: a feature comes from the same source at every tick")
        return {self.keys[source]: _as_model_input(array) for source, array in found.items()}

    def _fix(self, found: dict[str, np.ndarray], states: list[str]) -> dict[str, str]:
        keys = {}
        for source, array in found.items():
            if source in self.given:
                keys[source] = self.given[source]
            elif source in states:
                keys[source] = STATE if len(states) == 1 else f"observation.{source}"
            else:
                keys[source] = IMAGES + source
        problems = [f"features names {source!r}, which the observation has no feature from (its sources: "
                    f"{', '.join(found)})" for source in self.given if source not in found]
        twice = sorted({key for key in keys.values() if list(keys.values()).count(key) > 1})
        problems += [f"two sources would both be feature {key!r}" for key in twice]
        problems += [f"{source!r} is an image, but features names it {keys[source]!r} (an image's key starts with "
                     f"{IMAGES!r})" for source in found if source not in states and not keys[source].startswith(IMAGES)]
        if problems:
            raise ValueError(f"{self.owner}: " + "\n    ".join(problems) + "\n    hint: features={'source': 'key'}")
        return keys


def _as_model_input(array: np.ndarray) -> np.ndarray:
    if is_image(array):
        return np.ascontiguousarray(array.transpose(2, 0, 1), dtype=np.float32) / np.float32(255)
    return array.astype(np.float32)
