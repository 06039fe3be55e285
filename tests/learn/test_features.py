"""A policy's inputs as LeRobot features, named as the dataset export names them: the same keys,
and the same values up to the policy's float32 and 3×H×W, for a logged run's every tick."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest

from retriever import Latest, Pipeline, Rate
from retriever.learn.features import ObservationFeatures
from retriever.log import export_dataset

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


# -- the export and the policy flow, on one logged run -------------------------------------------
#: the export's --map and the policy's features=, the same
NAMES = {"joints": "observation.state", "image": "observation.image"}
INPUTS = ("image", "joints", "pose")


@pytest.fixture
def observed_run(tmp_path):
    """A logged run of the dataset tests' camera into a policy flow that keeps the observation it
    built at each tick; the policy's ticks are the frames the export makes."""
    pytest.importorskip("torch", reason="policy flows run torch models (the retriever[lerobot] extra)")
    from tests.learn.policies import Observer, observing_checkpoint
    from tests.log.dataset_flows import Camera

    with Pipeline("observe") as pipe:
        camera = Camera().named("camera") @ Rate(20)
        policy = Observer(str(observing_checkpoint(tmp_path / "ckpt")), features=NAMES).named("policy") @ Rate(10)
        camera.then(policy, sync=Latest())
    pipe.run(duration=1.0, log=str(tmp_path / "run.mcap"))
    assert len(policy.seen) == 9  # the first tick comes before the camera's first frame
    return tmp_path / "run.mcap", policy.seen


def _observation(features) -> dict:
    """The export's features of the policy's inputs, by key."""
    return {f.key: f for f in features if f.source.partition(".")[0] in INPUTS}


def test_the_policy_observes_what_the_export_writes_for_each_tick(tmp_path, observed_run):
    log, seen = observed_run
    summary = export_dataset([log], tmp_path / "np", flow="policy", format="npz", maps=NAMES)
    written = np.load(tmp_path / "np" / "episode_000000.npz")
    observation = _observation(summary.features)
    assert set(observation) == {"observation.image", "observation.state", "observation.pose"}
    assert summary.frames == len(seen)
    for k, built in enumerate(seen):
        assert built.keys() == observation.keys()
        for key, feature in observation.items():
            array = written[key][k]
            # the policy's documented conversion: an image float32 3×H×W in [0, 1], a state float32
            expected = (array.transpose(2, 0, 1).astype(np.float32) / np.float32(255) if feature.kind == "image"
                        else array.astype(np.float32))
            assert built[key].dtype == np.float32 and np.array_equal(built[key], expected), (k, key)
    assert observation["observation.pose"].names == ("pose.x", "pose.y", "pose.q.0", "pose.q.1")


def test_the_policy_observes_what_lerobot_loads_from_the_exported_dataset(tmp_path, observed_run, monkeypatch):
    lerobot = pytest.importorskip("lerobot.datasets.lerobot_dataset", reason="the LeRobot export needs lerobot")
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    log, seen = observed_run
    summary = export_dataset([log], tmp_path / "ds", flow="policy", format="lerobot", maps=NAMES)
    dataset = lerobot.LeRobotDataset("retriever/ds", root=tmp_path / "ds")
    observation = _observation(summary.features)
    assert len(dataset) == len(seen) and dataset.meta.camera_keys == ["observation.image"]
    for k, built in enumerate(seen):
        frame = dataset[k]
        for key in observation:
            loaded = frame[key].numpy()
            assert loaded.shape == built[key].shape and np.array_equal(loaded.astype(np.float32), built[key]), (k, key)
