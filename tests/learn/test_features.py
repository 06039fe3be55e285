"""A policy's inputs as LeRobot features, named as the dataset export names them."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from retriever.learn.features import ObservationFeatures

IMAGE = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)


@dataclass
class Joint:
    name: str
    q: float
    qd: np.ndarray
    locked: bool


@dataclass
class Frame:
    camera: str
    t: float
    rgb: np.ndarray


def test_convention():
    features = ObservationFeatures("P", ["cam", "qpos"])
    arrays = features({"cam": IMAGE, "qpos": np.array([1.0, 2.0])})
    assert features.keys == {"cam": "observation.images.cam", "qpos": "observation.state"}
    assert arrays["observation.images.cam"].shape == (3, 2, 3) and arrays["observation.images.cam"].dtype == np.float32
    assert arrays["observation.images.cam"][1, 0, 2] == np.float32(IMAGE[0, 2, 1]) / np.float32(255)
    assert arrays["observation.state"].dtype == np.float32
    several = ObservationFeatures("P", ["qpos", "cube"])
    several({"qpos": [1, 2], "cube": 3.0})
    assert several.keys == {"qpos": "observation.qpos", "cube": "observation.cube"}


def test_messages_are_taken_apart_as_the_export_does():
    """A dataclass: its images each a feature (``name.field``), its numeric fields one state
    vector in field order; text is left out. The frame's time is a state of its own."""
    features = ObservationFeatures("P", ["frame", "joint"])
    arrays = features({"frame": Frame("head", 0.5, IMAGE), "joint": Joint("elbow", 0.5, np.array([[1.0, 2.0]]), True)})
    assert features.keys == {"frame.rgb": "observation.images.frame.rgb", "frame": "observation.frame",
                             "joint": "observation.joint"}
    assert arrays["observation.joint"].tolist() == [0.5, 1.0, 2.0, 1.0]
    assert arrays["observation.frame"].tolist() == [0.5]
    named = ObservationFeatures("P", ["frame", "joint"], {"frame.rgb": "observation.images.head",
                                                          "joint": "observation.state"})
    named({"frame": Frame("head", 0.5, IMAGE), "joint": Joint("elbow", 0.5, np.zeros(2), True)})
    assert named.keys == {"frame.rgb": "observation.images.head", "frame": "observation.frame",
                          "joint": "observation.state"}


def test_problems_are_named():
    with pytest.raises(ValueError, match=r"(?s)P: features\['qpos'\] = 3 is not a feature key.*features names "
                                         r"'camera', which is none of P's inputs \(cam, qpos\).*hint: features="):
        ObservationFeatures("P", ["cam", "qpos"], {"camera": "observation.images.cam", "qpos": 3})
    twice = ObservationFeatures("P", ["a", "b"], {"a": "observation.state", "b": "observation.state"})
    with pytest.raises(ValueError, match="'a' and 'b' would both be feature 'observation.state'"):
        twice({"a": 1.0, "b": 2.0})
    with pytest.raises(ValueError, match="input 'q' carries a str, which no feature holds"):
        ObservationFeatures("P", ["q"])({"q": "up"})
    with pytest.raises(ValueError, match=r"input 'cam' carries a uint8 array of shape \(2, 3\), which is neither an "
                                         "image .* nor a state vector"):
        ObservationFeatures("P", ["cam"])({"cam": np.zeros((2, 3), np.uint8)})
    changing = ObservationFeatures("P", ["cam"])
    changing({"cam": Frame("c", 0.0, IMAGE)})
    with pytest.raises(ValueError, match="this observation gives cam; the first gave cam.rgb, cam: a feature comes"):
        changing({"cam": 1.0})
