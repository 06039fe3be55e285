"""A policy flow's observation as LeRobot features, named as ``retriever log export --format
lerobot`` names a dataset's, so a policy reads its inputs under the names it was trained on.

The names are :mod:`retriever.features`'s, the export's own: every input is on the observation
side, so a ``uint8`` H×W×3 array is ``observation.images.<source>`` (``name``, or ``name.field``
for an image inside a dataclass or a dict), and a name's numbers (a dataclass's numeric fields in
field order, flattened) are one state vector, ``observation.state`` when it is the only one, else
``observation.<name>``; text and ``None`` fields are left out. ``features={"source": "key"}``
names any source's key (the export's ``--map``).

The keys are fixed by the first observation; a later one must give the same sources. What the
policy gets differs from the dataset's arrays only in dtype and layout, as LeRobot's loader gives
them: an image as ``float32`` 3×H×W in [0, 1] (its ``uint8`` pixels / 255), a state vector as
``float32``.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from typing import Any

import numpy as np

from ..features import IMAGE, OBSERVATION, FeatureError, feature_keys, port_features


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
            raise ValueError(f"{owner}: " + "\n    ".join(bad) + _HINT)
        #: source -> feature key, fixed by the first observation
        self.keys: dict[str, str] | None = None

    def __call__(self, values: Mapping[str, Any]) -> dict[str, np.ndarray]:
        found: dict[str, tuple[str, np.ndarray]] = {}  # source -> (kind, array)
        for name in self.names:
            try:
                taken = port_features(name, values[name])
            except FeatureError as e:
                raise ValueError(f"{self.owner}: input {name!r} carries {e}") from None
            if taken.text is not None:
                raise ValueError(f"{self.owner}: input {name!r} carries a str, which no feature holds (text is a "
                                 f"dataset's task, not an observation): {taken.text[:40]!r}")
            found.update(taken.sources())
        if self.keys is None:
            try:
                self.keys = feature_keys({source: kind for source, (kind, _) in found.items()},
                                         dict.fromkeys(self.names, OBSERVATION), self.given, "features")
            except FeatureError as e:
                raise ValueError(f"{self.owner}: " + "\n    ".join(e.problems) + _HINT) from None
        if found.keys() != self.keys.keys():
            raise ValueError(f"{self.owner}: this observation gives {', '.join(found) or 'nothing'}; the first gave "
                             f"{', '.join(self.keys)}: a feature comes from the same source at every tick")
        return {self.keys[source]: _as_model_input(kind, array) for source, (kind, array) in found.items()}


_HINT = ("\n    hint: features={'joints': 'observation.state', 'camera': 'observation.images.front', "
         "'frame.rgb': 'observation.images.head'}")


def _as_model_input(kind: str, array: np.ndarray) -> np.ndarray:
    """A feature's array as the policy gets it: an image ``float32`` 3×H×W in [0, 1], a state
    vector ``float32``."""
    if kind == IMAGE:
        return np.ascontiguousarray(array.transpose(2, 0, 1), dtype=np.float32) / np.float32(255)
    return array.astype(np.float32)
