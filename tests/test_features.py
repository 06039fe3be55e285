"""How a port's value becomes named features (retriever/features.py), the one convention of the
dataset export and the policy flows."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from retriever.codec import UnregisteredValue
from retriever.features import (
    ACTION, IMAGE, OBSERVATION, STATE, FeatureError, feature_keys, is_image, port_features,
)

IMAGE_ARRAY = np.arange(4 * 5 * 3, dtype=np.uint8).reshape(4, 5, 3)


@dataclass
class Pose:
    x: float
    q: np.ndarray
    label: str
    covariance: np.ndarray | None


@dataclass
class Frame:
    rgb: np.ndarray
    t: float
    pose: Pose


def test_a_dataclass_is_its_images_and_one_state_vector_named_by_paths():
    frame = Frame(IMAGE_ARRAY, 0.5, Pose(1.0, np.array([[2, 3]], np.int32), "cube", None))
    taken = port_features("frame", frame)
    assert list(taken.images) == ["frame.rgb"] and taken.images["frame.rgb"] is IMAGE_ARRAY
    assert taken.state.tolist() == [0.5, 1.0, 2.0, 3.0] and taken.state.dtype == np.float64
    assert taken.state_names == ("frame.t", "frame.pose.x", "frame.pose.q.0.0", "frame.pose.q.0.1")
    assert taken.left_out == ["frame.pose.label", "frame.pose.covariance"] and taken.text is None
    assert list(taken.sources()) == ["frame.rgb", "frame"]
    assert [kind for kind, _ in taken.sources().values()] == [IMAGE, STATE]


def test_a_logged_dataclass_decoded_without_its_class_is_taken_apart_alike():
    """An export reads a log whose classes this process may not have registered."""
    frame = Frame(IMAGE_ARRAY, 0.5, Pose(1.0, np.array([2.0]), "cube", None))
    inert = UnregisteredValue("robot.msgs:Frame", {"rgb": IMAGE_ARRAY, "t": 0.5, "pose": UnregisteredValue(
        "robot.msgs:Pose", {"x": 1.0, "q": np.array([2.0]), "label": "cube", "covariance": None})})
    live, logged = port_features("frame", frame), port_features("frame", inert)
    assert live.state_names == logged.state_names and np.array_equal(live.state, logged.state)
    assert live.images.keys() == logged.images.keys() and live.left_out == logged.left_out


def test_plain_values_dicts_text_and_exclusion():
    assert port_features("cam", IMAGE_ARRAY).images == {"cam": IMAGE_ARRAY}
    scalar = port_features("grip", 0.25)
    assert scalar.state.tolist() == [0.25] and scalar.state_names == ("grip",)
    rows = port_features("q", [(1, 2), (3, 4)])
    assert rows.state.tolist() == [1, 2, 3, 4] and rows.state_names == ("q.0.0", "q.0.1", "q.1.0", "q.1.1")
    nested = port_features("obs", {"cam": IMAGE_ARRAY, "joints": np.zeros(2), "name": "arm"})
    assert list(nested.images) == ["obs.cam"] and nested.state_names == ("obs.joints.0", "obs.joints.1")
    assert port_features("note", "pick the cube").text == "pick the cube"
    kept = port_features("frame", Frame(IMAGE_ARRAY, 0.5, Pose(1.0, np.zeros(2), "", None)), exclude=["frame.pose"])
    assert kept.state_names == ("frame.t",) and kept.left_out == []


def test_what_no_feature_holds_is_refused_with_where_it_is():
    with pytest.raises(FeatureError, match=r"^a set, which no feature holds"):
        port_features("joints", {1, 2})
    with pytest.raises(FeatureError, match=r"^a <U1 array of shape \(2,\) at frame.pose.q, which no feature holds"):
        port_features("frame", Frame(IMAGE_ARRAY, 0.0, Pose(0.0, np.array(["a", "b"]), "", None)))
    with pytest.raises(FeatureError, match=r"a uint8 array of shape \(4, 5\), which is neither an image"):
        port_features("depth", np.zeros((4, 5), np.uint8))
    assert not is_image(np.zeros((1, 5, 3), np.uint8)) and not is_image(np.zeros((4, 5, 3), np.float32))


def test_default_keys_by_side_and_count():
    sides = {"cam": OBSERVATION, "joints": OBSERVATION, "cmd": ACTION}
    keys = feature_keys({"cam": IMAGE, "joints": STATE, "cmd": STATE}, sides)
    assert keys == {"cam": "observation.images.cam", "joints": "observation.state", "cmd": "action"}
    sides = {"frame": OBSERVATION, "joints": OBSERVATION, "cmd": ACTION, "grip": ACTION, "view": ACTION}
    keys = feature_keys({"frame.rgb": IMAGE, "frame": STATE, "joints": STATE, "cmd": STATE, "grip": STATE,
                         "view": IMAGE}, sides)
    assert keys == {"frame.rgb": "observation.images.frame.rgb", "frame": "observation.frame",
                    "joints": "observation.joints", "cmd": "action.cmd", "grip": "action.grip",
                    "view": "action.images.view"}


def test_maps_rename_and_their_problems_are_all_named_at_once():
    sides = {"cam": OBSERVATION, "joints": OBSERVATION, "pose": OBSERVATION}
    sources = {"cam": IMAGE, "joints": STATE, "pose": STATE}
    keys = feature_keys(sources, sides, {"cam": "observation.image", "joints": "observation.state"})
    assert keys == {"cam": "observation.image", "joints": "observation.state", "pose": "observation.pose"}
    with pytest.raises(FeatureError) as refused:
        feature_keys(sources, sides, {"camera": "observation.images.front", "cam": "observation.state",
                                      "joints": "observation.pose"}, "features")
    assert refused.value.problems == [
        "features names 'camera', which no feature comes from (the sources: cam, joints, pose)",
        "'joints' and 'pose' would both be feature 'observation.pose'",
        "'cam' is an image, but features names it 'observation.state': an observation's image is "
        "'observation.image' or observation.images.<name>",
    ]
