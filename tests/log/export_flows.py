"""Flows whose logs the exports to other viewers (ROS 2, Rerun) are checked on: a camera sending
a dataclass frame (images among plain fields) and an RGBA image, and a flow sending numbers,
arrays, text and a list of dicts computed from each frame; and logs written by hand, with what no run
writes."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from retriever import Burst, Flow, Pipeline, Rate, Trigger, io
from retriever.codec import packb
from retriever.log.mcap_writer import McapWriter


@io
@dataclass
class Frame:
    """A camera frame as one value: an image and a mask among plain fields."""

    rgb: np.ndarray
    mask: np.ndarray
    exposure: float


class Camera(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        rgb = np.full((6, 8, 3), self.k, dtype=np.uint8)
        rgb[0, 0] = (255, 0, 7)
        return {"frame": Frame(rgb=rgb, mask=np.eye(6, 8, dtype=np.uint8) * self.k, exposure=0.01 * self.k),
                "rgba": np.full((2, 3, 4), 200 + self.k, dtype=np.uint8)}


class Stats(Flow):
    def step(self, frame):
        rgb = frame.rgb
        return {"mean": float(rgb.mean()), "hist": np.bincount(rgb.reshape(-1), minlength=4)[:4],
                "pixels": rgb[:2, :2, 0].astype(np.float32), "count": int(rgb[1, 1, 0]), "bright": bool(rgb.mean() > 3),
                "label": f"frame {int(rgb[1, 1, 0])}", "extra": [{"k": int(rgb[1, 1, 0])}]}


def camera_log(tmp_path: Path) -> Path:
    """A log of a camera (a Frame value, an RGBA image) and the stats of its frames, 0.5 s at 10 Hz."""
    with Pipeline("camera") as pipe:
        camera = Camera().configure(name="cam") @ Rate(hz=10)
        stats = Stats().configure(name="stats") @ Trigger("frame")
        camera.then(stats, map={"frame": "frame"})
    path = tmp_path / "run.mcap"
    pipe.run(duration=0.5, log=path)
    return path


def hand_written_log(path: Path, events: list[tuple[str, int, bytes]]) -> Path:
    """A log of ``(topic, log time, message data)`` events, written with the log's own writer."""
    with open(path, "wb") as f:
        writer = McapWriter(f, profile="retriever")
        channels = {topic: writer.add_channel(topic, "msgpack", {}) for topic, _, _ in events}
        for seq, (topic, log_time, data) in enumerate(events):
            writer.add_message(channels[topic], log_time, 0, seq, data)
        writer.finish()
    return path


def event_data(value) -> bytes:
    """An event message's data: microstep 0 and the value as the codec encodes it."""
    return b"\x92\x00" + packb(value)


class Kinds(Flow):
    """A source sending, on each of its ports, a kind of value a viewer has to decide about."""

    def step(self):
        return {"u64": np.uint64(2**64 - 1), "f16": np.float16(1.5), "flags": np.array([True, False]),
                "big_endian": np.array([1, 2], dtype=">i4"),
                "two_channels": np.arange(12, dtype=np.uint8).reshape(2, 3, 2),
                "records": np.zeros(2, dtype=[("a", "<f4")]), "empty": np.zeros((0, 3)), "pair": (1, 2.5),
                "blob": b"\x00\x01"}


def kinds_log(tmp_path: Path) -> Path:
    """A log of two ticks of :class:`Kinds`."""
    with Pipeline("kinds") as pipe:
        Kinds().configure(name="kinds") @ Rate(hz=10)
    path = tmp_path / "kinds.mcap"
    pipe.run(duration=0.2, log=path)
    return path


@io
@dataclass
class Shadow:
    """A value whose field's topic is the one a node's step records take: ``/retriever/steps/cam``
    from node ``retriever``, port ``steps``, field ``cam``."""

    cam: float


class Impostor(Flow):
    def step(self):
        return {"steps": Shadow(cam=0.5)}


class Exposure(Flow):
    def step(self):
        return {"exposure": 0.01}


def shadowed_steps_log(tmp_path: Path) -> Path:
    """A log where a node ``retriever`` sends, on port ``steps``, a value with a field ``cam``,
    beside a node ``cam``."""
    with Pipeline("shadow") as pipe:
        Impostor().configure(name="retriever") @ Rate(hz=10)
        Exposure().configure(name="cam") @ Rate(hz=10)
    path = tmp_path / "shadow.mcap"
    pipe.run(duration=0.3, log=path)
    return path


class Counter(Flow):
    """A number and a small array at every tick: many small events, each quick to log."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"x": float(self.k), "v": np.arange(3) + self.k}


def long_log(path: Path, seconds: float = 60.0) -> Path:
    """A log of ``seconds`` of a :class:`Counter` at 1 kHz, in virtual time (60 s: 120,000 events
    and 60,000 step records, 4.7 MB, written in about a second; its ros2 or foxglove export takes
    several seconds, its rerun one longer): an export still running when a test signals it."""
    with Pipeline("long") as pipe:
        Counter().configure(name="count") @ Rate(hz=1000)
    pipe.run(duration=seconds, log=path, keep="counters")
    return path


class RosCamera(Flow):
    """A source sending what a ROS 2 subscriber of ``sensor_msgs/msg/Image`` and of
    ``sensor_msgs/msg/JointState`` sends (ros2/types.py ``to_value``): dicts, an image, a stamp
    and a frame among them."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        image = np.full((4, 5, 3), self.k, dtype=np.uint8)
        image[0, 0] = (255, 0, 7)
        stamp = 1_700_000_000_000_000_000 + self.k
        return {"image": {"image": image, "stamp": stamp, "frame_id": "cam", "height": 4, "width": 5,
                          "encoding": "rgb8"},
                "joints": {"stamp": stamp, "frame_id": "", "name": ["shoulder", "elbow"],
                           "position": np.array([0.5, -0.25]) * self.k, "velocity": np.zeros(2)}}


def ros_camera_log(tmp_path: Path) -> Path:
    """A log of three ticks of :class:`RosCamera`."""
    with Pipeline("roscam") as pipe:
        RosCamera().configure(name="cam") @ Rate(hz=10)
    path = tmp_path / "roscam.mcap"
    pipe.run(duration=0.3, log=path)
    return path


class Bursts(Flow):
    """A source sending three events at each tag (a Burst: three events of one tag, seqs apart)."""

    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        return {"x": Burst([10.0 * self.k + i for i in range(3)])}


def burst_log(tmp_path: Path) -> Path:
    """A log of three ticks of :class:`Bursts`: 9 events at 3 tags."""
    with Pipeline("bursts") as pipe:
        Bursts().configure(name="burst") @ Rate(hz=10)
    path = tmp_path / "bursts.mcap"
    pipe.run(duration=0.3, log=path)
    return path
