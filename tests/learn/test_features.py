"""Ports as LeRobot feature keys, and their values as the arrays a policy reads."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from retriever.learn.features import feature_map, to_array


def test_convention():
    assert feature_map("P", ["image", "wrist_image", "qpos"], None) == {
        "image": "observation.images.image", "wrist_image": "observation.images.wrist_image",
        "qpos": "observation.state"}
    assert feature_map("P", ["qpos", "cube_pose"], None) == {
        "qpos": "observation.qpos", "cube_pose": "observation.cube_pose"}
    assert feature_map("P", ["qpos", "cube_pose"], {"qpos": "observation.state"}) == {
        "qpos": "observation.state", "cube_pose": "observation.cube_pose"}


def test_explicit_names_win_and_problems_come_at_once():
    assert feature_map("P", ["cam", "qpos"], {"cam": "observation.images.front"}) == {
        "cam": "observation.images.front", "qpos": "observation.state"}
    with pytest.raises(ValueError, match=r"(?s)P: features names 'camera', which is none of P's inputs \("
                                         r"cam, qpos\).*features\['qpos'\] = 3 is not a feature key.*hint: features="):
        feature_map("P", ["cam", "qpos"], {"camera": "observation.images.cam", "qpos": 3})
    with pytest.raises(ValueError, match="ports 'a' and 'b' both map to feature 'observation.state'"):
        feature_map("P", ["a", "b"], {"a": "observation.state", "b": "observation.state"})


@dataclass
class Joint:
    name: str
    q: float
    qd: np.ndarray
    locked: bool


def test_values():
    image = np.arange(2 * 3 * 3, dtype=np.uint8).reshape(2, 3, 3)
    chw = to_array("P", "cam", "observation.images.cam", image)
    assert chw.shape == (3, 2, 3) and chw.dtype == np.float32
    assert chw[1, 0, 2] == np.float32(image[0, 2, 1]) / np.float32(255)
    assert to_array("P", "q", "observation.state", 2).tolist() == [2.0]
    assert to_array("P", "q", "observation.state", [[1, 2], [3, 4]]).tolist() == [1, 2, 3, 4]
    joint = Joint("elbow", 0.5, np.array([1.0, 2.0]), True)
    assert to_array("P", "j", "observation.state", joint).tolist() == [0.5, 1.0, 2.0, 1.0]  # the name is no number
    with pytest.raises(ValueError, match="port 'q' feeds feature 'observation.state', which takes numbers .*; got str"):
        to_array("P", "q", "observation.state", "up")
    with pytest.raises(ValueError, match="takes a uint8 H×W×3 array, or a dataclass with one; got list"):
        to_array("P", "cam", "observation.images.cam", [[0]])
    frame = Frame("head", 0.5, image)
    np.testing.assert_array_equal(to_array("P", "frame", "observation.images.head", frame), chw)
    with pytest.raises(ValueError, match="got Joint"):
        to_array("P", "frame", "observation.images.head", joint)


@dataclass
class Frame:
    camera: str
    t: float
    rgb: np.ndarray
