"""A log as the Foxglove app reads it: ``retriever log export run.mcap --format foxglove -o view.mcap``.

The native log stays the system of record (msgpack, times from T0); this is a view of it, written
with Foxglove's own SDK (``foxglove-sdk``, the extra ``retriever-robotics[foxglove]``) so that every
channel has a schema the app decodes:

- an image port (uint8 arrays H×W, H×W×3 or H×W×4) is a ``foxglove.RawImage`` channel
  (``mono8``, ``rgb8``, ``rgba8``) on ``/<node>/<port>``, and so is an image field of a dataclass
  value (a camera frame with its time) or an image item of a dict value (what a ROS 2 subscriber
  sends) on ``/<node>/<port>/<field>`` (nested: ``.../<a>/<b>``), as the ROS 2 and Rerun exports
  open values (views.value_leaves);
- any other port is a JSON channel on ``/<node>/<port>`` whose messages are ``{"value": ...,
  "tag_ns", "microstep", "seq"}`` (numbers and small arrays as they are; a bigger array as its
  dtype, shape and first elements; a dataclass as its fields, whether this process registered
  its type or not), which the app plots;
- each node's step records are JSON on ``/retriever/steps/<node>`` (status, tick, consumed and
  produced ids, detail, wall time of the step), and the graph (the IR) on ``/retriever/graph``.

Times are wall-clock: a message's log time is the run's start, as wall time, plus its tag, so
the app shows the date the run happened and the order of the tags (in virtual time, the tags
laid out from the moment the run began).
"""

from __future__ import annotations

import json
import os
import time
import warnings
from collections import Counter
from pathlib import Path
from typing import Any, Iterator

import numpy as np

from ..errors import LogError, RetrieverWarning
from ..trace import NOT_KEPT, StepRecord
from .outputs import export_path
from .reader import LogHead, LogRecords, RunLog, log_records
from .views import image_encoding, to_json, value_leaves

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
                       "pip install 'retriever-robotics[foxglove]'") from None
    return foxglove, RawImageChannel, RawImage, Timestamp


def image_fields(value: Any) -> Iterator[tuple[str, np.ndarray, str]]:
    """``(path, image, encoding)`` for each image among a value's leaves (views.value_leaves: a
    dataclass's fields and a dict's items, what a ROS 2 subscriber sends, nested ones too), ``path``
    as ``/field`` or ``/field/inner``."""
    for path, leaf in value_leaves(value):
        encoding = image_encoding(leaf) if path else None
        if encoding is not None:
            yield path, leaf, encoding


def run_start_ns(log: LogRecords) -> int:
    """The wall time (Unix ns) of the run's tag 0: the earliest publish time less its tag (an
    event is published at or after its tag), else when the log was started."""
    if log.wall_start_ns is not None:
        return max(0, log.wall_start_ns)
    return int(log.head.run.get("started_unix_ns", "0") or 0)


class FoxgloveWriter:
    """Logs a run's events, step records and graph on channels of one Foxglove context (its
    sinks: an MCAP file for the export, a WebSocket server for the live view)."""

    def __init__(self, context, ir, when_ns: int):
        foxglove, self._RawImageChannel, self._RawImage, self._Timestamp = _sdk()
        self._foxglove, self._context = foxglove, context
        self._value_schema = _schema(foxglove, "retriever.Value", VALUE_SCHEMA)
        self._step_schema = _schema(foxglove, "retriever.Step", STEP_SCHEMA)
        self._channels: dict[str, Any] = {}
        self.written: Counter = Counter()
        graph = foxglove.Channel("/retriever/graph", schema=_schema(foxglove, "retriever.Graph", GRAPH_SCHEMA),
                                 message_encoding="json", context=context)
        graph.log({"ir": ir.doc, "mermaid": ir.visualize("mermaid")}, log_time=when_ns)
        self._channels["/retriever/graph"] = graph
        self.written["/retriever/graph"] += 1

    def _json_channel(self, topic: str, schema):
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self._foxglove.Channel(topic, schema=schema, message_encoding="json",
                                                                     context=self._context)
        return channel

    def event(self, node: str, port: str, tag: tuple[int, int], seq: int, value: Any, when: int) -> None:
        """One event at ``when`` (Unix ns): an image on a RawImage channel, else JSON, and the
        images among a dataclass value's fields each on its own RawImage channel too. A port that
        began as images and later sends something else goes on as JSON on ``<topic>/other``."""
        topic = f"/{node}/{port}"
        encoding = image_encoding(value)
        if encoding is None:
            for path, image, image_kind in image_fields(value):
                channel = self._image_channel(topic + path)
                if channel is not None:
                    self._log_image(channel, topic + path, node, image, image_kind, when)
        elif self._image_channel(topic) is not None:
            self._log_image(self._channels[topic], topic, node, value, encoding, when)
            return
        if isinstance(self._channels.get(topic), self._RawImageChannel):
            topic += "/other"
        self._json_channel(topic, self._value_schema).log(
            {"value": to_json(value), "tag_ns": tag[0], "microstep": tag[1], "seq": seq}, log_time=when)
        self.written[topic] += 1

    def _image_channel(self, topic: str):
        """The RawImage channel on ``topic`` (made on first use), or None if ``topic`` is JSON."""
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self._RawImageChannel(topic, context=self._context)
        return channel if isinstance(channel, self._RawImageChannel) else None

    def _log_image(self, channel, topic: str, node: str, image: np.ndarray, encoding: str, when: int) -> None:
        image = np.ascontiguousarray(image)
        channel.log(self._RawImage(timestamp=self._Timestamp(sec=when // 10**9, nsec=when % 10**9), frame_id=node,
                                   width=image.shape[1], height=image.shape[0], encoding=encoding,
                                   step=image.strides[0], data=image.tobytes()), log_time=when)
        self.written[topic] += 1

    def step(self, node: str, tag: tuple[int, int], consumed: dict, produced, status: str, detail, wall_ns: int,
             when: int) -> None:
        """One step record at ``when`` (Unix ns), on ``/retriever/steps/<node>``."""
        topic = f"/retriever/steps/{node}"
        self._json_channel(topic, self._step_schema).log(
            {"node": node, "status": status, "tag_ns": tag[0], "microstep": tag[1],
             "consumed": {p: [list(i) for i in ids] for p, ids in consumed.items()},
             "produced": [list(i) for i in produced], "detail": json.loads(json.dumps(to_json(detail))),
             "wall_ns": wall_ns}, log_time=when)
        self.written[topic] += 1


def export_foxglove(log: RunLog | str | Path, out: str | Path, *, overwrite: bool = False) -> Counter:
    """Write ``log`` (read whole, or its path: streamed, reader.log_records) as a Foxglove MCAP to
    ``out``; the messages written, per topic."""
    foxglove = _sdk()[0]
    out = export_path(log.path if isinstance(log, LogHead) else log, out, overwrite)
    source = log_records(log)
    head = source.head
    zero = run_start_ns(source)
    ir = head.ir
    context = foxglove.Context()
    # written beside it, then renamed: an export that fails leaves no file that looks whole, and
    # never writes into the file that stands at ``out`` (a hard link to the log, say)
    partial = out.with_name(f".{out.name}.{os.getpid()}.partial")
    try:  # (the file's removal guards its creation too: a signal may come as open_mcap returns)
        try:
            writer = foxglove.open_mcap(str(partial), allow_overwrite=True, context=context)
        except Exception as e:  # the SDK's own error for a path it cannot create
            raise LogError(f"cannot write {out}: {e}") from None
        try:
            view = FoxgloveWriter(context, ir, zero)
            for record in source.records():
                if type(record) is StepRecord:
                    view.step(record.node, record.tag, record.consumed, record.produced, record.status,
                              record.detail, record.wall_ns, zero + record.tag[0])
                else:
                    view.event(record.node, record.port, record.tag, record.seq,
                               head.value(record, keep_unregistered=True), zero + record.tag[0])
        finally:
            writer.close()
        os.replace(partial, out)
    finally:
        partial.unlink(missing_ok=True)
    return view.written


class LiveView:
    """``retriever run --foxglove [PORT]``: Foxglove's WebSocket server in the coordinating
    process, fed with what the run records as it arrives (the workers' reports: never on the
    flows' path), so the app shows cameras, numbers and skips as they happen. Times are the
    events' publish times (wall clock). A failure of the view stops the view, not the run."""

    title = "the Foxglove live view"

    def __init__(self, port: int, ir, host: str = "127.0.0.1"):
        foxglove = _sdk()[0]
        self._context = foxglove.Context()
        try:
            self._server = foxglove.start_server(name=f"retriever {ir.name}", host=host, port=port,
                                                 context=self._context)
        except Exception as e:
            raise LogError(f"cannot serve the Foxglove live view on {host}:{port}: {e}",
                           "give another port: --foxglove PORT") from None
        self.port = self._server.port
        self._view: FoxgloveWriter | None = FoxgloveWriter(self._context, ir, time.time_ns())
        self.error: str | None = None

    def _guard(self, method: str, *args) -> None:
        if self._view is None:
            return
        try:
            getattr(self._view, method)(*args)
        except Exception as e:  # noqa: BLE001 - the view is not the run: it stops, the run goes on
            self._view, self.error = None, f"{type(e).__name__}: {e}"
            warnings.warn(f"the Foxglove live view stopped: {self.error}", RetrieverWarning, stacklevel=2)

    def event(self, node: str, port: str, tag, seq: int, value: Any, wall_ns: int) -> None:
        if value is not NOT_KEPT:
            self._guard("event", node, port, tag, seq, value, wall_ns or time.time_ns())

    def step(self, node: str, tag, consumed, produced, status: str, detail, start_ns: int, wall_ns: int) -> None:
        self._guard("step", node, tag, consumed, produced, status, detail, wall_ns, start_ns or time.time_ns())

    def close(self) -> None:
        self._view = None
        try:
            self._server.stop()
        except Exception:  # noqa: BLE001 - already stopped
            pass
