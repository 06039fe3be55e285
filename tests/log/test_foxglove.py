"""``retriever log export --format foxglove``: a log as the Foxglove app reads it (issue 19 §3).
Every channel of the export decodes with its own schema (protobuf for images, JSON Schema for
the rest), times are wall-clock, and images arrive as the flow made them."""

from __future__ import annotations

import json
import subprocess
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from retriever import Flow, LogError, Pipeline, Rate, Trigger, io, read_log
from retriever.log.foxglove import export_foxglove
from retriever.log.views import JSON_DEPTH_MAX, to_json
from tests.log.export_flows import ros_camera_log

ROOT = Path(__file__).resolve().parents[2]


@io
@dataclass
class Camera:
    rgb: np.ndarray
    depth: np.ndarray
    exposure: float


class Cam(Flow[None, Camera]):
    def __init__(self):
        self.k = 0

    def step(self) -> Camera:
        self.k += 1
        rgb = np.full((6, 8, 3), self.k, dtype=np.uint8)
        rgb[0, 0] = (255, 0, 7)
        return Camera(rgb=rgb, depth=np.arange(48, dtype=np.uint8).reshape(6, 8), exposure=0.01 * self.k)


class Stats(Flow):
    def step(self, rgb):
        return {"mean": float(rgb.mean()), "hist": np.bincount(rgb.reshape(-1), minlength=4)[:4],
                "big": np.zeros(5000, dtype=np.float32), "label": f"frame {int(rgb[1, 1, 0])}"}


def _log(tmp_path: Path) -> Path:
    with Pipeline("fox") as pipe:
        cam = Cam().configure(name="cam") @ Rate(hz=10)
        stats = Stats().configure(name="stats") @ Trigger("rgb")
        cam.then(stats, map={"rgb": "rgb"})
    path = tmp_path / "run.mcap"
    pipe.run(duration=0.5, log=path)
    return path


def _protobuf_class(schema):
    files = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
    pool = descriptor_pool.DescriptorPool()
    for proto in files.file:
        pool.Add(proto)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(schema.name))


def test_every_channel_of_the_export_decodes_with_its_schema(tmp_path):
    log_path = _log(tmp_path)
    out = tmp_path / "view.mcap"
    written = export_foxglove(read_log(log_path), out)
    with out.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        kinds = {c.topic: (c.message_encoding, summary.schemas[c.schema_id].name) for c in summary.channels.values()}
        decoded: dict[str, list] = {}
        started = read_log(log_path).run["started_unix_ns"]
        for schema, channel, message in reader.iter_messages():
            assert message.log_time >= int(started) - 10**9, "times are wall-clock (the run's), not from 1970"
            if channel.message_encoding == "protobuf":
                assert schema.encoding == "protobuf"
                decoded.setdefault(channel.topic, []).append(_protobuf_class(schema).FromString(message.data))
            else:
                assert (channel.message_encoding, schema.encoding) == ("json", "jsonschema"), channel.topic
                body, spec = json.loads(message.data), json.loads(schema.data)
                assert set(body) <= set(spec["properties"]), (channel.topic, body)
                decoded.setdefault(channel.topic, []).append(body)
    assert kinds["/cam/rgb"] == kinds["/cam/depth"] == ("protobuf", "foxglove.RawImage")
    assert kinds["/stats/mean"] == ("json", "retriever.Value") and kinds["/retriever/steps/cam"][1] == "retriever.Step"
    assert sum(written.values()) == sum(len(v) for v in decoded.values())

    images = decoded["/cam/rgb"]
    assert len(images) == 5 and images[0].encoding == "rgb8" and (images[0].width, images[0].height) == (8, 6)
    first = np.frombuffer(images[0].data, dtype=np.uint8).reshape(6, 8, 3)
    assert first[0, 0].tolist() == [255, 0, 7] and first[1, 1].tolist() == [1, 1, 1]
    assert decoded["/cam/depth"][2].encoding == "mono8"
    assert np.array_equal(np.frombuffer(decoded["/cam/depth"][2].data, np.uint8).reshape(6, 8),
                          np.arange(48).reshape(6, 8))
    assert [m["value"] for m in decoded["/cam/exposure"]] == pytest.approx([0.01, 0.02, 0.03, 0.04, 0.05])
    assert decoded["/stats/hist"][0]["value"] == [1, 141, 0, 0]  # small arrays as lists (the first frame)
    assert decoded["/stats/big"][0]["value"] == {"dtype": "float32", "shape": [5000], "head": [0.0] * 8}
    assert decoded["/stats/label"][3]["value"] == "frame 4"
    assert [s["status"] for s in decoded["/retriever/steps/stats"]] == ["ok"] * 5
    assert decoded["/retriever/steps/stats"][0]["consumed"] == {"rgb": [["cam", "rgb", 0]]}
    graph = decoded["/retriever/graph"][0]
    assert [n["id"] for n in graph["ir"]["nodes"]] == ["cam", "stats"] and graph["mermaid"].startswith("flowchart")


def test_the_command_writes_the_export_and_refuses_to_overwrite(tmp_path):
    log_path = _log(tmp_path)
    out = tmp_path / "view.mcap"

    def export(*flags):
        return subprocess.run([str(Path(sys.executable).parent / "retriever"), "log", "export", str(log_path),
                               "--format", "foxglove", "-o", str(out), *flags], capture_output=True, text=True,
                              timeout=120, cwd=ROOT)

    done = export()
    assert done.returncode == 0, done.stderr
    assert f"wrote {out}: " in done.stdout and out.stat().st_size > 0
    again = export()
    assert again.returncode == 1 and "exists" in again.stderr and "--force" in again.stderr
    assert export("--force").returncode == 0
    with pytest.raises(LogError, match="is the log being exported"):
        export_foxglove(read_log(log_path), log_path, overwrite=True)


def test_without_the_sdk_the_export_says_how_to_get_it(tmp_path, monkeypatch):
    log = read_log(_log(tmp_path))
    monkeypatch.setitem(sys.modules, "foxglove", None)  # what an environment without the extra has
    with pytest.raises(LogError, match=r"needs Foxglove's SDK \(the foxglove-sdk package\)(.|\n)*"
                                       r"hint: pip install 'retriever-robotics\[foxglove\]'"):
        export_foxglove(log, tmp_path / "view.mcap")
    assert not (tmp_path / "view.mcap").exists()


@io
@dataclass
class Shot:
    """A camera frame as the demo's camera sends it: one port whose value holds the image."""

    camera: str
    t: float
    rgb: np.ndarray
    mask: np.ndarray


@io
@dataclass
class Pair:
    left: Shot
    exposure: float


class Shooter(Flow):
    def __init__(self):
        self.k = 0

    def step(self):
        self.k += 1
        shot = Shot(camera="head", t=0.1 * self.k, rgb=np.full((4, 5, 3), self.k, dtype=np.uint8),
                    mask=np.eye(4, 5, dtype=np.uint8) * self.k)
        return {"frame": shot, "pair": Pair(left=shot, exposure=0.5)}


def _messages(path: Path) -> dict[str, list]:
    """Every message of an export, per topic: JSON decoded, protobuf as its bytes."""
    messages: dict[str, list] = {}
    with path.open("rb") as f:
        for _, channel, message in make_reader(f).iter_messages():
            body = json.loads(message.data) if channel.message_encoding == "json" else bytes(message.data)
            messages.setdefault(channel.topic, []).append((message.log_time, body))
    return messages


def test_images_inside_dataclass_values_are_raw_images_and_the_cli_writes_the_same_json(tmp_path):
    """The demo's camera frames are fields of a dataclass value: each image field is a RawImage
    channel, and the command (which reads values without their types) writes the same export
    as the Python function (whose process registered them)."""
    with Pipeline("shots") as pipe:
        Shooter().configure(name="cam") @ Rate(hz=10)
    log_path = tmp_path / "run.mcap"
    pipe.run(duration=0.3, log=log_path)
    python_export, cli_export = tmp_path / "python.mcap", tmp_path / "cli.mcap"
    export_foxglove(read_log(log_path), python_export)
    done = subprocess.run([str(Path(sys.executable).parent / "retriever"), "log", "export", str(log_path),
                           "--format", "foxglove", "-o", str(cli_export)], capture_output=True, text=True,
                          timeout=120, cwd=tmp_path)
    assert done.returncode == 0, done.stderr
    by_python, by_cli = _messages(python_export), _messages(cli_export)
    assert by_cli == by_python
    with python_export.open("rb") as f:
        summary = make_reader(f).get_summary()
    kinds = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert {topic: kind for topic, kind in kinds.items() if kind == "foxglove.RawImage"} == {
        topic: "foxglove.RawImage" for topic in
        ("/cam/frame/rgb", "/cam/frame/mask", "/cam/pair/left/rgb", "/cam/pair/left/mask")}
    schema = summary.schemas[next(c.schema_id for c in summary.channels.values() if c.topic == "/cam/frame/rgb")]
    images = [_protobuf_class(schema).FromString(body) for _, body in by_python["/cam/frame/rgb"]]
    assert [(i.encoding, i.width, i.height, i.data[0]) for i in images] == [("rgb8", 5, 4, k) for k in (1, 2, 3)]
    masks = [_protobuf_class(schema).FromString(body) for _, body in by_python["/cam/pair/left/mask"]]
    assert masks[1].encoding == "mono8" and masks[1].data[:6] == bytes([2, 0, 0, 0, 0, 0])
    frame = by_python["/cam/frame"][0][1]["value"]
    assert frame == {"camera": "head", "t": 0.1, "rgb": [[[1] * 3] * 5] * 4, "mask": np.eye(4, 5, dtype=int).tolist()}
    assert by_python["/cam/pair"][0][1]["value"]["left"] == frame


def test_images_inside_dict_values_are_raw_images_as_the_other_exports_open_them(tmp_path):
    """What a ROS 2 subscriber sends is a dict (``{"image": ..., "stamp": ..., "frame_id": ...}``):
    its image is a RawImage channel of its own, as the ROS 2 and Rerun exports open it item by
    item (views.value_leaves); before, the image was only JSON in the port's value, summarised."""
    log_path = ros_camera_log(tmp_path)
    out = tmp_path / "view.mcap"
    written = export_foxglove(log_path, out)
    assert written["/cam/image/image"] == 3
    by_topic = _messages(out)
    with out.open("rb") as f:
        summary = make_reader(f).get_summary()
    kinds = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
    assert kinds["/cam/image/image"] == "foxglove.RawImage" and kinds["/cam/image"] == "retriever.Value"
    images = [_protobuf_class(summary.schemas[next(c.schema_id for c in summary.channels.values()
                                                  if c.topic == "/cam/image/image")]).FromString(body)
              for _, body in by_topic["/cam/image/image"]]
    assert [(i.encoding, i.width, i.height, i.data[:3], i.data[3]) for i in images] == [
        ("rgb8", 5, 4, bytes([255, 0, 7]), k) for k in (1, 2, 3)]
    assert by_topic["/cam/image"][0][1]["value"]["frame_id"] == "cam"


def _with_a_damaged_frame(log_path: Path, out: Path) -> Path:
    """A copy of a log, written by mcap's own Writer, whose first rgb frame is an array extension
    that does not decode (as a changed file would hold)."""
    import msgpack
    from mcap.writer import CompressionType, Writer

    with log_path.open("rb") as f, out.open("wb") as g:
        reader = make_reader(f)
        writer = Writer(g, compression=CompressionType.ZSTD)
        writer.start(profile=reader.get_header().profile, library="test")
        summary = reader.get_summary()
        ids = {cid: writer.register_channel(c.topic, c.message_encoding, 0, c.metadata)
               for cid, c in summary.channels.items()}
        damaged = False
        for _, channel, message in reader.iter_messages(log_time_order=False):
            data = message.data
            if not damaged and channel.metadata.get("port") == "rgb":
                microstep, _ = msgpack.unpackb(data, strict_map_key=False, ext_hook=lambda code, raw: None)
                data, damaged = msgpack.packb([microstep, msgpack.ExtType(1, b"garbage")]), True
            writer.add_message(ids[channel.id], message.log_time, data, message.publish_time, message.sequence)
        for attachment in reader.iter_attachments():
            writer.add_attachment(attachment.create_time, attachment.log_time, attachment.name,
                                  attachment.media_type, attachment.data)
        for metadata in reader.iter_metadata():
            writer.add_metadata(metadata.name, metadata.metadata)
        writer.finish()
    return out


def test_a_failed_export_leaves_the_file_it_would_replace_as_it_was(tmp_path):
    log_path = _with_a_damaged_frame(_log(tmp_path), tmp_path / "damaged.mcap")
    out = tmp_path / "view.mcap"
    out.write_bytes(b"an earlier export")
    with pytest.raises(LogError, match=r"event cam.rgb #0 is damaged"):
        export_foxglove(read_log(log_path), out, overwrite=True)
    assert out.read_bytes() == b"an earlier export" and sorted(p.name for p in tmp_path.iterdir()) == [
        "damaged.mcap", "run.mcap", "view.mcap"]  # and no partial file beside it


def test_an_export_over_a_hard_link_to_its_log_is_refused(tmp_path):
    log_path = _log(tmp_path)
    link = tmp_path / "link.mcap"
    os.link(log_path, link)
    before = log_path.read_bytes()
    with pytest.raises(LogError, match="is the log being exported"):
        export_foxglove(read_log(log_path), link, overwrite=True)
    assert log_path.read_bytes() == before


def test_to_json_summarises_what_a_hostile_log_could_blow_up():
    """An array that holds nothing yet has 10**7 rows is summarised, not made 10**7 lists; lists
    nested 500 deep are said past JSON_DEPTH_MAX, not a RecursionError (the three exports use it)."""
    started = time.perf_counter()
    assert to_json(np.zeros((10**7, 0))) == {"dtype": "float64", "shape": [10**7, 0], "head": []}
    assert time.perf_counter() - started < 1.0
    deep: list = []
    for _ in range(500):
        deep = [deep]
    shown = to_json(deep)
    for _ in range(JSON_DEPTH_MAX):
        (shown,) = shown
    assert shown == f"<list nested deeper than {JSON_DEPTH_MAX}>"
    assert to_json({"a": [np.arange(3)]}) == {"a": [[0, 1, 2]]}
