"""How a port's value becomes named features: the one convention the dataset export
(``retriever log export --format lerobot|npz``, :mod:`retriever.log.frames`) and the policy flows
(:mod:`retriever.learn.features`) share, so that a policy reads its inputs under the names its
dataset gave them (docs/learning.md).

Values become features by their type (:func:`port_features`):

- a ``uint8`` array H×W×3 is an image feature;
- numbers, numeric arrays, and lists or tuples of them are a state vector (flattened);
- a dataclass (or a dict with str keys) is its fields: its images each an image feature, its
  numeric fields one state vector, in field order, nested dataclasses too; its text and ``None``
  fields are left out (and listed);
- text as the port's whole value is no feature (the export may take it as each frame's task);
- anything else is refused (:class:`FeatureError`).

A feature's *source* is the path into a port's value: ``port`` (the port's state vector, or the
port itself when it is an image) or ``port.field`` (an image field of a dataclass,
``port.field.inner`` when nested). A state vector's elements are named by their paths too:
``pose.x``, ``pose.q.0``, ``joints.3``.

A feature's key (:func:`feature_keys`): an image's is ``<side>.images.<source>``; a state
vector's is ``observation.state`` (``action``) when it is its side's only one, else
``observation.<port>`` (``action.<port>``), the side being ``observation`` for an input and
``action`` for an output. ``maps`` (the export's ``--map``, a policy flow's ``features=``) gives
any source another key; an observation's image keeps an image key (``observation.image`` or
``observation.images.<name>``, LeRobot's). ``exclude`` leaves a path, and all inside it, out.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Collection, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .codec import dataclass_fields
from .errors import FeatureError

IMAGE, STATE = "image", "state"
OBSERVATION, ACTION = "observation", "action"
#: LeRobot's keys for an observation's images: ``observation.image``, or ``observation.images.<name>``
OBSERVATION_IMAGE = "observation.image"


def is_image(value: Any) -> bool:
    return (isinstance(value, np.ndarray) and value.dtype == np.uint8 and value.ndim == 3 and value.shape[2] == 3
            and min(value.shape[:2]) > 1)


def excluded(path: str, exclude: Collection[str]) -> bool:
    """``path`` is one of ``exclude``, or inside one (``pose.q`` inside ``pose``)."""
    return any(path == e or path.startswith(e + ".") for e in exclude)


@dataclass
class PortFeatures:
    """One port's value as features: its images by source, its numbers as one state vector."""

    port: str
    images: dict[str, np.ndarray] = field(default_factory=dict)
    state: np.ndarray | None = None  # flattened, in field order, in the dtype its parts promote to
    state_parts: list[tuple[str, tuple[int, ...]]] = field(default_factory=list)  # path and shape of each part
    text: str | None = None  # the port's value, when it is text
    left_out: list[str] = field(default_factory=list)  # the paths of text and None fields

    @property
    def state_names(self) -> tuple[str, ...]:
        """The path of each element of ``state`` (computed on asking: a large vector has many)."""
        return tuple(name for path, shape in self.state_parts for name in element_names(path, shape))

    def sources(self) -> dict[str, tuple[str, np.ndarray]]:
        """``{source: (IMAGE or STATE, array)}``."""
        found = {source: (IMAGE, image) for source, image in self.images.items()}
        if self.state is not None:
            found[self.port] = (STATE, self.state)
        return found


def port_features(port: str, value: Any, exclude: Collection[str] = ()) -> PortFeatures:
    """The features of ``value`` on ``port`` (see the module docstring), leaving out the paths
    in ``exclude``; FeatureError saying what the value holds that no feature can."""
    taken = PortFeatures(port)
    numbers: list[tuple[str, np.ndarray]] = []
    if isinstance(value, str):
        taken.text = value
    else:
        _take_apart(value, port, taken, numbers, exclude)
    if numbers:
        vectors = [array.reshape(-1) for _, array in numbers]
        taken.state = np.concatenate(vectors) if len(vectors) > 1 else vectors[0]
        taken.state_parts = [(path, array.shape) for path, array in numbers]
    return taken


def _take_apart(value: Any, path: str, taken: PortFeatures, numbers: list[tuple[str, np.ndarray]],
                exclude: Collection[str]) -> None:
    if excluded(path, exclude):
        return
    if is_image(value):
        taken.images[path] = value
        return
    fields = dataclass_fields(value)
    if fields is None and isinstance(value, dict) and all(isinstance(k, str) for k in value):
        fields = value
    if fields is not None:
        for name, inner in fields.items():
            if isinstance(inner, (str, bytes)) or inner is None:
                taken.left_out.append(f"{path}.{name}")
            else:
                _take_apart(inner, f"{path}.{name}", taken, numbers, exclude)
        return
    if isinstance(value, np.ndarray) and value.dtype == np.uint8 and value.ndim >= 2:
        raise FeatureError([f"a uint8 array of shape {value.shape}, which is neither an image (uint8 H×W×3) nor a "
                            "state vector; convert it to RGB in the flow, or leave it out"])
    array = _numeric(value)
    where = "" if path == taken.port else f" at {path}"
    if array is None:
        raise FeatureError([f"{_describe(value)}{where}, which no feature holds (images uint8 H×W×3, numbers, and "
                            "dataclasses of them do)"])
    if array.size == 0:
        raise FeatureError([f"{_describe(value)}{where} with no element, which no feature holds (a feature has at "
                            "least one)"])
    numbers.append((path, array))


def _numeric(value: Any) -> np.ndarray | None:
    """A number, numeric array, or list/tuple of them as an array (bool, integer or float, never
    an object array: an int beyond int64 is none); None for anything else."""
    if isinstance(value, (bool, int, float, np.bool_, np.integer, np.floating)):
        array = np.asarray(value)
    elif isinstance(value, np.ndarray):
        array = value
    elif isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):
        parts = [_numeric(v) for v in value]
        if any(p is None for p in parts) or len({p.shape for p in parts}) > 1:
            return None
        array = np.stack(parts) if parts else np.zeros(0)
    else:
        return None
    return array if array.dtype.kind in "biuf" else None


def _describe(value: Any) -> str:
    """What a value is, for a message: an array's dtype and shape, a list's first part no feature holds."""
    if isinstance(value, np.ndarray):
        return f"a {'structured ' if value.dtype.names else ''}{value.dtype} array of shape {value.shape}"
    if isinstance(value, int) and not isinstance(value, bool) and _numeric(value) is None:
        return f"an int beyond int64 ({str(value)[:24]})"
    if isinstance(value, np.generic):
        return f"a {value.dtype} number"
    if isinstance(value, (list, tuple)) and not hasattr(value, "_fields"):
        if not value:
            return f"a {type(value).__name__}"
        bad = next((v for v in value if _numeric(v) is None), None)
        inner = f"holding {_describe(bad)}" if bad is not None else "of parts of different shapes"
        return f"a {type(value).__name__} {inner}"
    return f"a {type(value).__name__}"


def element_names(path: str, shape: tuple[int, ...]) -> list[str]:
    """The names of the elements of a state vector's part at ``path`` of ``shape``, in C order:
    ``pose.q.0.1`` (a scalar's is ``path`` itself). One string per element, so a wide vector has
    many: the export names its vectors at the first frame only."""
    if not shape:
        return [path]
    return [".".join([path, *map(str, index)]) for index in np.ndindex(shape)]


def feature_keys(sources: Mapping[str, str], sides: Mapping[str, str], maps: Mapping[str, str] | None = None,
                 maps_name: str = "--map") -> dict[str, str]:
    """``{source: key}`` for the features ``{source: IMAGE or STATE}`` of ports on ``sides``
    (``{port: OBSERVATION or ACTION}``), ``maps`` naming some of them (see the module docstring).
    FeatureError, one line per problem, for a map of no source, two sources given one key, or an
    observation's image given a key that is no image key; ``maps_name`` is how the messages call
    the maps (``--map``, ``features``)."""
    maps = dict(maps or {})
    states = Counter(sides[source] for source, kind in sources.items() if kind == STATE)
    keys: dict[str, str] = {}
    for source, kind in sources.items():
        port = source.partition(".")[0]
        side = sides[port]
        if source in maps:
            keys[source] = maps[source]
        elif kind == IMAGE:
            keys[source] = f"{side}.images.{source}"
        elif states[side] == 1:
            keys[source] = "observation.state" if side == OBSERVATION else "action"
        else:
            keys[source] = f"{side}.{port}"
    problems = [f"{maps_name} names {source!r}, which no feature comes from (the sources: {', '.join(sources)})"
                for source in maps if source not in sources]
    by_key: dict[str, list[str]] = {}
    for source, key in keys.items():
        by_key.setdefault(key, []).append(source)
    problems += [f"{' and '.join(repr(s) for s in both)} would both be feature {key!r}"
                 for key, both in by_key.items() if len(both) > 1]
    problems += [f"{source!r} is an image, but {maps_name} names it {keys[source]!r}: an observation's image is "
                 f"{OBSERVATION_IMAGE!r} or {OBSERVATION_IMAGE}s.<name>" for source, kind in sources.items()
                 if kind == IMAGE and sides[source.partition('.')[0]] == OBSERVATION
                 and not _is_image_key(keys[source])]
    if problems:
        raise FeatureError(problems)
    return keys


def _is_image_key(key: str) -> bool:
    return key == OBSERVATION_IMAGE or key.startswith(OBSERVATION_IMAGE + "s.")
