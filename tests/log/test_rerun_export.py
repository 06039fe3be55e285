"""A log as the Rerun viewer shows it (issue 39 §3): the ``.rrd`` read back with Rerun's own
loader (its dataframe API) holds, per entity, as many rows as the log has events, at their tags
on the event timeline and their publish times on the wall timeline, with the log's values and
image bytes."""

from __future__ import annotations

import json
import sys

import numpy as np
import pyarrow as pa
import pytest
import rerun as rr

from retriever import LogError, read_log
from retriever.log import rerun as rerun_export
from retriever.log.rerun import export_rerun
from tests.log.export_flows import (burst_log, camera_log, event_data, hand_written_log, kinds_log, ros_camera_log,
                                    shadowed_steps_log)

#: each entity, the archetype it is logged as, and how a leaf is read from the log's value
ENTITIES = {
    "/cam/frame/rgb": "Image", "/cam/frame/mask": "Image", "/cam/frame/exposure": "Scalars", "/cam/rgba": "Image",
    "/stats/mean": "Scalars", "/stats/hist": "Scalars", "/stats/pixels": "Tensor", "/stats/count": "Scalars",
    "/stats/bright": "Scalars", "/stats/label": "TextLog", "/stats/extra": "TextLog",
    "/retriever/steps/cam": "TextLog", "/retriever/steps/stats": "TextLog",
}


def _expected(log) -> dict[str, list[tuple[int, int, object]]]:
    """Per entity: ``(tag, wall time, value)`` of each row, taken from the log by hand."""
    expected: dict[str, list] = {}
    for event in log.iter_events():
        value = log.value(event)
        for entity in ENTITIES:
            node, port, *field = entity.split("/")[1:]
            if (node, port) == (event.node, event.port):
                expected.setdefault(entity, []).append(
                    (event.tag[0], event.publish_ns, getattr(value, field[0]) if field else value))
    for step in log.iter_steps():
        expected.setdefault(f"/retriever/steps/{step.node}", []).append((step.tag[0], step.wall_start_ns, step))
    return expected


def _rows(recording, entity: str) -> dict[str, list]:
    """An entity's rows, one per logged row (indexed by Rerun's own log_tick), times as ns."""
    table = recording.view(index="log_tick", contents=entity).select().read_all()
    columns = {name.rpartition(":")[2] if ":" in name else name: table.column(name) for name in table.column_names}
    for timeline in ("event_time", "wall_time"):
        columns[timeline] = columns[timeline].cast(pa.int64())
    return {name: column.to_pylist() for name, column in columns.items()}


def _check(entity: str, rows: dict[str, list], index: int, value) -> None:
    kind = ENTITIES[entity]
    if kind == "Image":
        image_format = rows["format"][index][0]
        assert (image_format["height"], image_format["width"]) == value.shape[:2]
        assert bytes(rows["buffer"][index][0]) == value.tobytes()
    elif kind == "Scalars":
        assert rows["scalars"][index] == np.asarray(value, dtype=np.float64).reshape(-1).tolist()
    elif kind == "Tensor":
        tensor = rows["data"][index][0]
        assert tensor["shape"] == list(value.shape)
        assert tensor["buffer"] == value.reshape(-1).tolist()  # the union's float32 member, as Python floats
    elif entity.startswith("/retriever/steps/"):
        record = json.loads(rows["text"][index][0])
        assert (record["node"], record["status"], record["tag_ns"], record["microstep"]) == (
            value.node, value.status, *value.tag)
        assert record["produced"] == [list(i) for i in value.produced]
        assert rows["level"][index] == ["INFO"]
    elif entity == "/stats/extra":
        assert json.loads(rows["text"][index][0]) == value
    else:
        assert rows["text"][index] == [value]


@pytest.mark.parametrize("flush_bytes", [rerun_export.FLUSH_BYTES, 1], ids=["default", "each-record"])
def test_rerun_loads_the_logs_rows_times_values_and_images(tmp_path, monkeypatch, flush_bytes):
    """Whether Rerun's SDK is flushed once or after every record (FLUSH_BYTES: what keeps the
    export's memory flat), the recording holds every row."""
    monkeypatch.setattr(rerun_export, "FLUSH_BYTES", flush_bytes)
    log_path = camera_log(tmp_path)
    out = tmp_path / "run.rrd"
    written = export_rerun(read_log(log_path), out).written
    expected = _expected(read_log(log_path))
    assert written == {entity: len(rows) for entity, rows in expected.items()}
    assert set(expected) == set(ENTITIES) and len(expected["/cam/frame/rgb"]) == 5

    recording = rr.dataframe.load_recording(out)
    archetypes = {c.entity_path: c.archetype.rpartition(".")[2] for c in recording.schema().component_columns()}
    assert archetypes.pop("/__properties") == "RecordingInfo" and archetypes == ENTITIES
    properties = recording.view(index=None, contents="/__properties").select().read_all()
    assert properties.column("property:RecordingInfo:name").to_pylist() == [["camera"]]  # the pipeline's name
    timelines = {c.name for c in recording.schema().index_columns()}
    assert {"event_time", "wall_time"} <= timelines
    for entity, logged in expected.items():
        rows = _rows(recording, entity)
        assert len(rows["event_time"]) == len(logged), entity
        assert rows["event_time"] == [tag for tag, _, _ in logged], entity
        assert rows["wall_time"] == [wall for _, wall, _ in logged], entity
        for index, (_, _, value) in enumerate(logged):
            _check(entity, rows, index, value)


def test_each_kind_of_value_is_shown_as_what_it_is(tmp_path):
    out = tmp_path / "kinds.rrd"
    written = export_rerun(read_log(kinds_log(tmp_path)), out).written
    assert set(written.values()) == {2}
    recording = rr.dataframe.load_recording(out)
    archetypes = {c.entity_path: c.archetype.rpartition(".")[2] for c in recording.schema().component_columns()}
    assert archetypes == {
        "/__properties": "RecordingInfo", "/kinds/u64": "Scalars", "/kinds/f16": "Scalars", "/kinds/flags": "Scalars",
        "/kinds/big_endian": "Scalars", "/kinds/two_channels": "Tensor",  # H×W×2 is no image
        "/kinds/records": "TextLog", "/kinds/empty": "Tensor", "/kinds/pair": "Scalars", "/kinds/blob": "TextLog",
        "/retriever/steps/kinds": "TextLog"}
    scalars = {entity: _rows(recording, entity)["scalars"][0]
               for entity in ("/kinds/u64", "/kinds/f16", "/kinds/flags", "/kinds/big_endian", "/kinds/pair")}
    assert scalars == {"/kinds/u64": [float(2**64 - 1)], "/kinds/f16": [1.5], "/kinds/flags": [1.0, 0.0],
                       "/kinds/big_endian": [1.0, 2.0], "/kinds/pair": [1.0, 2.5]}
    tensor = _rows(recording, "/kinds/two_channels")["data"][0][0]
    assert tensor["shape"] == [2, 3, 2] and tensor["buffer"] == list(range(12))
    assert json.loads(_rows(recording, "/kinds/blob")["text"][0][0]) == {"bytes": 2}


def test_a_dicts_leaves_are_shown_by_their_kind_an_image_as_an_image(tmp_path):
    """What a ROS 2 subscriber sends (a dict: image, stamp, frame...) is opened as a dataclass is."""
    log_path = ros_camera_log(tmp_path)
    out = tmp_path / "roscam.rrd"
    export_rerun(read_log(log_path), out)
    log = read_log(log_path)
    values = {port: [log.value(e) for e in log.iter_events() if e.port == port] for port in ("image", "joints")}
    recording = rr.dataframe.load_recording(out)
    archetypes = {c.entity_path: c.archetype.rpartition(".")[2] for c in recording.schema().component_columns()}
    assert archetypes == {
        "/__properties": "RecordingInfo", "/cam/image/image": "Image", "/cam/image/stamp": "Scalars",
        "/cam/image/frame_id": "TextLog", "/cam/image/height": "Scalars", "/cam/image/width": "Scalars",
        "/cam/image/encoding": "TextLog", "/cam/joints/stamp": "Scalars", "/cam/joints/frame_id": "TextLog",
        "/cam/joints/name": "TextLog", "/cam/joints/position": "Scalars", "/cam/joints/velocity": "Scalars",
        "/retriever/steps/cam": "TextLog"}
    images = _rows(recording, "/cam/image/image")
    assert len(values["image"]) == 3
    assert [bytes(buffer[0]) for buffer in images["buffer"]] == [v["image"].tobytes() for v in values["image"]]
    assert [(f[0]["height"], f[0]["width"]) for f in images["format"]] == [(4, 5)] * 3
    assert _rows(recording, "/cam/joints/position")["scalars"] == [v["position"].tolist() for v in values["joints"]]
    assert _rows(recording, "/cam/image/frame_id")["text"] == [["cam"]] * 3


def test_every_event_of_a_burst_is_a_row_at_its_tag_on_the_seq_timeline(tmp_path):
    """A Burst's events share their tag, so ``event_time`` holds one row per tag; the ``seq``
    timeline (an event's seq on its port) holds each event as a row, its tag on event_time."""
    log_path = burst_log(tmp_path)
    out = tmp_path / "bursts.rrd"
    export_rerun(read_log(log_path), out)
    log = read_log(log_path)
    events = list(log.iter_events())
    assert len(events) == 9 and len({e.tag for e in events}) == 3
    recording = rr.dataframe.load_recording(out)
    assert "seq" in {c.name for c in recording.schema().index_columns()}
    by_time = recording.view(index="event_time", contents="/burst/x").select().read_all()
    assert by_time.num_rows == 3  # Rerun's one row per time of an entity: why seq is there
    table = recording.view(index="seq", contents="/burst/x").select().read_all()
    rows = {name.rpartition(":")[2]: table.column(name).to_pylist() for name in table.column_names}
    assert rows["seq"] == [e.seq for e in events]
    assert table.column("event_time").cast(pa.int64()).to_pylist() == [e.tag[0] for e in events]
    assert rows["scalars"] == [[log.value(e)] for e in events]
    steps = recording.view(index="seq", contents="/retriever/steps/burst").select().read_all()
    assert steps.column("seq").to_pylist() == [0, 1, 2]  # a step record's number among its node's


def test_without_the_sdk_the_export_says_how_to_get_it(tmp_path, monkeypatch):
    log = read_log(camera_log(tmp_path))
    monkeypatch.setitem(sys.modules, "rerun", None)  # what an environment without the extra has
    with pytest.raises(LogError, match=r"needs Rerun's SDK \(the rerun-sdk package\)(.|\n)*"
                                       r"hint: pip install 'retriever-robotics\[rerun\]'"):
        export_rerun(log, tmp_path / "run.rrd")
    assert not (tmp_path / "run.rrd").exists()



@pytest.mark.parametrize("events, message", [
    ([("data/cam/rgb", 0, b"\x92\x00\xc1")], r"event cam\.rgb #0 is not valid msgpack"),
    ([("data/cam/rgb", 2**63, event_data(1.0))], r"past what Rerun's times hold"),
])
def test_a_damaged_log_is_a_log_error_and_leaves_no_file(tmp_path, events, message):
    log = read_log(hand_written_log(tmp_path / "odd.mcap", events))
    with pytest.raises(LogError, match=message):
        export_rerun(log, tmp_path / "run.rrd")
    assert [p.name for p in tmp_path.iterdir()] == ["odd.mcap"]


def test_a_field_never_shares_the_entity_of_a_nodes_step_records(tmp_path):
    """Node ``retriever``'s port ``steps`` with a field ``cam``, beside a node ``cam``: the step
    records keep ``/retriever/steps/cam``, the field goes to ``/retriever/steps/cam_2``, said in
    ``renamed``; each entity holds one archetype."""
    out = tmp_path / "shadow.rrd"
    done = export_rerun(read_log(shadowed_steps_log(tmp_path)), out)
    recording = rr.dataframe.load_recording(out)
    archetypes: dict[str, set] = {}
    for c in recording.schema().component_columns():
        archetypes.setdefault(c.entity_path, set()).add(c.archetype.rpartition(".")[2])
    assert archetypes["/retriever/steps/cam"] == {"TextLog"} and archetypes["/retriever/steps/cam_2"] == {"Scalars"}
    texts = _rows(recording, "/retriever/steps/cam")["text"]
    assert texts and {json.loads(t[0])["node"] for t in texts} == {"cam"}
    assert done.renamed == {"retriever.steps.cam": "/retriever/steps/cam_2"}
