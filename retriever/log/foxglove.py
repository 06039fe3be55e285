"""A log as the Foxglove app reads it: ``retriever log export run.mcap --format foxglove -o view.mcap``.

The native log stays the system of record (msgpack, times from T0); this is a view of it, written
with Foxglove's own SDK (``foxglove-sdk``, the extra ``retriever[foxglove]``) so that every
channel has a schema the app decodes:

- an image port (uint8 arrays H×W, H×W×3 or H×W×4) is a ``foxglove.RawImage`` channel
  (``mono8``, ``rgb8``, ``rgba8``) on ``/<node>/<port>``;
- any other port is a JSON channel on ``/<node>/<port>`` whose messages are ``{"value": ...,
  "tag_ns", "microstep", "seq"}`` (numbers and small arrays as they are; a bigger array as its
  dtype, shape and first elements), which the app plots;
- each node's step records are JSON on ``/retriever/steps/<node>`` (status, tick, consumed and
  produced ids, detail, wall time of the step), and the graph (the IR) on ``/retriever/graph``.

Times are wall-clock: a message's log time is the run's start, as wall time, plus its tag, so
the app shows the date the run happened and the order of the tags (in virtual time, the tags
laid out from the moment the run began).
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import LogError
from .reader import RunLog

#: arrays up to this many elements go into JSON whole; bigger ones as dtype, shape and a head
JSON_ARRAY_MAX = 1024
IMAGE_ENCODINGS = {2: "mono8", 3: "rgb8", 4: "rgba8"}  # by channels (H×W is 2 dims: mono8)

VALUE_SCHEMA = {"type": "object", "properties": {
    "value": {}, "tag_ns": {"type": "integer"}, "microstep": {"type": "integer"}, "seq": {"type": "integer"}}}
STEP_SCHEMA = {"type": "object", "properties": {
    "node": {"type": "string"}, "status": {"type": "string"}, "tag_ns": {"type": "integer"},
    "microstep": {"type": "integer"}, "consumed": {"type": "object"}, "produced": {"type": "array"},
    "detail": {}, "wall_ns": {"type": "integer"}}}
GRAPH_SCHEMA = {"type": "object", "properties": {"ir": {"type": "object"}, "mermaid": {"type": "string"}}}


def _schema(foxglove, name: str, schema: dict):
    return foxglove.Schema(name=name, encoding="jsonschema", data=json.dumps(schema).encode())


def _sdk():
    try:
        import foxglove
        from foxglove.channels import RawImageChannel
        from foxglove.messages import RawImage, Timestamp
    except ImportError:
        raise LogError("the Foxglove export needs Foxglove's SDK (the foxglove-sdk package), which is not installed",
                       "pip install 'retriever[foxglove]'") from None
    return foxglove, RawImageChannel, RawImage, Timestamp


def image_encoding(value: Any) -> str | None:
    """``mono8``, ``rgb8`` or ``rgba8`` for a uint8 array shaped as an image; else None."""
    if not isinstance(value, np.ndarray) or value.dtype != np.uint8 or value.ndim not in (2, 3):
        return None
    if value.ndim == 2:
        return "mono8" if min(value.shape) > 1 else None
    return IMAGE_ENCODINGS.get(value.shape[2]) if min(value.shape[:2]) > 1 else None


def to_json(value: Any) -> Any:
    """A value as JSON: numbers, strings, lists and dicts as they are, small arrays as lists,
    bigger ones summarised, anything else as its text."""
    if value is None or isinstance(value, (bool, int, float, str)):
        return value if not isinstance(value, float) or np.isfinite(value) else str(value)
    if isinstance(value, np.generic):
        return to_json(value.item())
    if isinstance(value, np.ndarray):
        if value.size <= JSON_ARRAY_MAX and value.dtype.kind in "biuf":
            return to_json(value.tolist())
        return {"dtype": str(value.dtype), "shape": list(value.shape),
                "head": to_json(value.reshape(-1)[:8].tolist()) if value.dtype.kind in "biuf" else None}
    if isinstance(value, dict):
        return {str(k): to_json(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [to_json(v) for v in value]
    if isinstance(value, bytes):
        return {"bytes": len(value)}
    if hasattr(value, "__dataclass_fields__"):
        return {name: to_json(getattr(value, name)) for name in value.__dataclass_fields__}
    return str(value)


def run_start_ns(log: RunLog) -> int:
    """The wall time (Unix ns) of the run's tag 0: the earliest publish time less its tag (an
    event is published at or after its tag), else when the log was started."""
    starts = [e.publish_ns - e.tag[0] for e in log.iter_events() if e.publish_ns]
    if starts:
        return max(0, min(starts))
    return int(log.run.get("started_unix_ns", "0") or 0)


def export_foxglove(log: RunLog, out: str | Path, *, overwrite: bool = False) -> Counter:
    """Write ``log`` as a Foxglove MCAP to ``out``; the messages written, per topic."""
    foxglove, RawImageChannel, RawImage, Timestamp = _sdk()
    out = Path(out)
    if out.exists() and not overwrite:
        raise LogError(f"{out} exists", "pass --force (overwrite=True) to replace it")
    if out.resolve() == Path(log.path).resolve():
        raise LogError(f"{out} is the log being exported", "write the export to another file")
    zero = run_start_ns(log)
    ir = log.ir
    written: Counter = Counter()
    context = foxglove.Context()
    try:
        writer = foxglove.open_mcap(str(out), allow_overwrite=overwrite, context=context)
    except Exception as e:  # the SDK's own error for a path it cannot create
        raise LogError(f"cannot write {out}: {e}") from None
    try:
        value_schema = _schema(foxglove, "retriever.Value", VALUE_SCHEMA)
        step_schema = _schema(foxglove, "retriever.Step", STEP_SCHEMA)
        graph = foxglove.Channel("/retriever/graph", schema=_schema(foxglove, "retriever.Graph", GRAPH_SCHEMA),
                                 message_encoding="json", context=context)
        graph.log({"ir": ir.doc, "mermaid": ir.visualize("mermaid")}, log_time=zero)
        written["/retriever/graph"] += 1
        channels: dict[tuple[str, str], tuple[str, Any]] = {}
        for event in log.iter_events():
            value = log.value(event, keep_unregistered=True)
            topic = f"/{event.node}/{event.port}"
            kind, channel = channels.get((event.node, event.port), (None, None))
            encoding = image_encoding(value)
            if channel is None:
                kind = "image" if encoding is not None else "json"
                channel = (RawImageChannel(topic, context=context) if kind == "image"
                           else foxglove.Channel(topic, schema=value_schema, message_encoding="json", context=context))
                channels[(event.node, event.port)] = (kind, channel)
            when = zero + event.tag[0]
            if kind == "image" and encoding is not None:
                image = np.ascontiguousarray(value)
                channel.log(RawImage(timestamp=Timestamp(sec=when // 10**9, nsec=when % 10**9), frame_id=event.node,
                                     width=image.shape[1], height=image.shape[0], encoding=encoding,
                                     step=image.strides[0], data=image.tobytes()), log_time=when)
            else:  # (a port that began as images and later sent something else: as JSON, on its own topic)
                if kind == "image":
                    topic += "/other"
                    other = channels.get((event.node, event.port + "/other"))
                    if other is None:
                        other = channels[(event.node, event.port + "/other")] = (
                            "json", foxglove.Channel(topic, schema=value_schema, message_encoding="json", context=context))
                    channel = other[1]
                channel.log({"value": to_json(value), "tag_ns": event.tag[0], "microstep": event.tag[1],
                             "seq": event.seq}, log_time=when)
            written[topic] += 1
        steps: dict[str, Any] = {}
        for step in log.iter_steps():
            channel = steps.get(step.node)
            if channel is None:
                channel = steps[step.node] = foxglove.Channel(f"/retriever/steps/{step.node}", schema=step_schema,
                                                              message_encoding="json", context=context)
            channel.log({"node": step.node, "status": step.status, "tag_ns": step.tag[0], "microstep": step.tag[1],
                         "consumed": {p: [list(i) for i in ids] for p, ids in step.consumed.items()},
                         "produced": [list(i) for i in step.produced],
                         "detail": json.loads(json.dumps(to_json(step.detail))),
                         "wall_ns": step.wall_ns}, log_time=zero + step.tag[0])
            written[f"/retriever/steps/{step.node}"] += 1
    finally:
        writer.close()
    return written
