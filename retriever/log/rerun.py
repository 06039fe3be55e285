"""A log as the Rerun viewer shows it: ``retriever log export run.mcap --format rerun -o run.rrd``.

Written with Rerun's own SDK (``rerun-sdk``, the extra ``retriever-robotics[rerun]``): a
recording stream saved to an ``.rrd`` file, no viewer started, named after the pipeline. Each
output port is an entity ``/<node>/<port>``, and a dataclass value's fields or a dict value's
items (what a ROS 2 subscriber sends) each an entity of their own (``/<node>/<port>/<field>``,
views.value_leaves); a value is

- an image (uint8 H×W, H×W×3, H×W×4): ``rr.Image`` (L, RGB, RGBA);
- a number, or a flat array or list of at most SCALARS_MAX numbers: ``rr.Scalars``, which the
  viewer plots (an array as one series per element);
- any other array of numbers: ``rr.Tensor``;
- text: ``rr.TextLog``; anything else: ``rr.TextLog`` of its JSON (foxglove.to_json).

Step records are ``rr.TextLog`` on ``/retriever/steps/<node>`` (views.step_json), at level INFO
when the step ran, WARN when it was skipped, incomplete, late or overran, ERROR when it failed.

Two things never share an entity (node ``retriever``'s port ``steps`` with a field ``x``, beside
a node ``x``, would make ``/retriever/steps/x`` twice): as in the ROS 2 export, the step records'
entities and the ports' are named first (the export knows them before it reads a value), and
what finds its entity taken gets the first free ``<entity>_2``, ``<entity>_3``... (its last part
suffixed), said in ``RerunExport.renamed``; a field, met later, likewise.

Three timelines: ``event_time``, the tag (a duration from the run's T0: a replayed run and the live
one line up on it), which the recording's blueprint selects; ``wall_time``, when the event was
published (a step: when it began), where the log has it; and ``seq``, a sequence: an event's seq
on its port, a step record's number among its node's (0, 1, 2...). Events of one tag (a
``Burst``'s) share their event time, where Rerun keeps one row per time of an entity, the last;
on ``seq`` each is a row of its own, its tag beside it. Rerun adds ``log_time`` and ``log_tick``
of its own: when this export wrote each row.

:class:`RerunRecording` is the one writer of this mapping: the export feeds it from a log, the
live view (rerun_live.py) from a running pipeline's reports.
"""

from __future__ import annotations

import errno
import json
import os
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import LogError
from ..trace import StepRecord, StepStatus
from .format import parse_data_topic
from .outputs import export_path, stdout_reader_gone, stdout_stream, to_stdout
from .reader import LogHead, LogRecords, RunLog, log_records
from .views import image_encoding, numeric_array, step_json, to_json, value_leaves

#: the URL of the Rerun viewer that ``rerun`` starts on this machine (rerun-sdk's own default)
RERUN_VIEWER_URL = "rerun+http://127.0.0.1:9876/proxy"
#: a flat array of up to this many numbers is plotted, one series per element; a bigger one is a tensor
SCALARS_MAX = 16
EVENT_TIME, WALL_TIME, SEQ = "event_time", "wall_time", "seq"
STEP_LEVELS = {StepStatus.OK: "INFO", StepStatus.ERROR: "ERROR"}  # any other status: WARN
MAX_NS = 2**63 - 1  # Rerun's times are signed 64-bit nanoseconds
#: what the export hands Rerun's SDK between two blocking flushes, in bytes of values, a record
#: counting RECORD_BYTES more (about what a row of a few numbers or a step record costs the SDK
#: while it holds it, its values as Python-made Arrow arrays). The SDK holds a row until its
#: entity has 1 MiB of rows or its 200 ms tick, which it skips whenever an entity flushed for
#: its bytes since the last (an image stream does, many times a tick in an export), and queues
#: what it is handed without bound (to its batcher, to its file writer): without these flushes a
#: log's numbers and step records were held whole, and a fast export held what it had not written
FLUSH_BYTES = 4 << 20
RECORD_BYTES = 4096
#: the bytes of rows the export's stream makes a chunk of (the SDK's default: 1 MiB): 1 MiB
#: chunks of images left the SDK's allocator holding ~10 MB more after a few hundred frames
CHUNK_BYTES = 256 << 10


def rerun_sdk(what: str = "the Rerun export"):
    """Rerun's SDK, imported when first needed (it is an extra), or a LogError saying how to get it."""
    try:
        import rerun
        import rerun.blueprint
    except ImportError:
        raise LogError(f"{what} needs Rerun's SDK (the rerun-sdk package), which is not installed",
                       "pip install 'retriever-robotics[rerun]'") from None
    return rerun


def new_stream(rr, batcher=None):
    """A recording stream of a run, no sink yet (no viewer spawned, no properties sent);
    ``batcher``: its rr.ChunkBatcherConfig, else the SDK's default."""
    return rr.RecordingStream("retriever", send_properties=False, batcher_config=batcher)


def export_stream(rr):
    """The export's recording stream: chunks of CHUNK_BYTES (_write_rerun flushes it every
    FLUSH_BYTES)."""
    return new_stream(rr, rr.ChunkBatcherConfig(flush_num_bytes=CHUNK_BYTES))


def event_time_blueprint(rr):
    """The blueprint that opens the recording on the event timeline (tags, from the run's T0)."""
    return rr.blueprint.Blueprint(rr.blueprint.TimePanel(timeline=EVENT_TIME))


def entity_path(*parts: str) -> list[str]:
    """An entity path as its parts (the SDK escapes each); an empty part is shown as ``_``."""
    return [part or "_" for part in parts]


def archetype(rr, value: Any):
    """The Rerun archetype that shows one leaf of a value."""
    if image_encoding(value) is not None:
        return rr.Image(np.ascontiguousarray(value))
    if isinstance(value, str):
        return rr.TextLog(value)
    array = numeric_array(value)
    if array is None:
        return rr.TextLog(json.dumps(to_json(value)))
    if array.ndim == 0 or (array.ndim == 1 and 0 < array.size <= SCALARS_MAX):
        return rr.Scalars(array.astype(np.float64).reshape(-1))
    return rr.Tensor(array.astype(np.uint8) if array.dtype.kind == "b" else array)


@dataclass
class RerunExport:
    """What :func:`export_rerun` wrote: the rows per entity, and what had to move to an entity of
    its own (``node.port[.field]``, ``the step records of NODE``) because another had taken the
    one its names make: the entity it got."""

    written: Counter = field(default_factory=Counter)
    renamed: dict[str, str] = field(default_factory=dict)


def origin_text(origin: tuple) -> str:
    if origin[0] == "steps":
        return f"the step records of {origin[1]}"
    _, node, port, path = origin
    return ".".join([node, port, *path.split("/")[1:]])


class RerunRecording:
    """A run's events and step records logged on one recording stream, on both timelines."""

    def __init__(self, rr, stream):
        self._rr, self._stream = rr, stream
        self.written: Counter = Counter()
        self.renamed: dict[str, str] = {}
        self._steps: Counter = Counter()  # step records logged, per node: the next one's seq
        self._taken: dict[tuple[str, ...], tuple] = {}  # entity parts -> what they stand for
        self._named: dict[tuple, list[str]] = {}  # and back

    def reserve(self, step_nodes, ports) -> None:
        """Name the entities of the step records of ``step_nodes`` and of ``ports`` (``(node,
        port)``) before any value is logged, each in its names' order: the same log gives the
        same entities whatever the order of its records."""
        for node in sorted(step_nodes):
            self.entity(("steps", node))
        for node, port in sorted(ports):
            self.entity(("port", node, port, ""))

    def entity(self, origin: tuple) -> list[str]:
        """``origin``'s entity parts: the ones it was given, else the ones its names make if
        free, else those with the first free ``_2``, ``_3``... after the last (said in ``renamed``)."""
        parts = self._named.get(origin)
        if parts is None:
            wanted = (entity_path("retriever", "steps", origin[1]) if origin[0] == "steps"
                      else entity_path(origin[1], origin[2], *origin[3].split("/")[1:]))
            parts, n = wanted, 1
            while tuple(parts) in self._taken:
                n += 1
                parts = [*wanted[:-1], f"{wanted[-1]}_{n}"]
            self._taken[tuple(parts)], self._named[origin] = origin, parts
            if parts != wanted:
                self.renamed[origin_text(origin)] = "/" + "/".join(parts)
        return parts

    def at(self, tag_ns: int, wall_ns: int, seq: int) -> None:
        """Log what follows at ``tag_ns`` on the event timeline, ``seq`` on the sequence one and,
        when known, ``wall_ns`` on the wall one."""
        if tag_ns > MAX_NS or wall_ns > MAX_NS:
            raise LogError(f"a time in the log ({max(tag_ns, wall_ns)} ns) is past what Rerun's times hold "
                           "(signed 64-bit nanoseconds)", "the log's times are damaged")
        self._stream.set_time(EVENT_TIME, duration=np.timedelta64(tag_ns, "ns"))
        self._stream.set_time(SEQ, sequence=seq)
        if wall_ns:
            self._stream.set_time(WALL_TIME, timestamp=np.datetime64(wall_ns, "ns"))
        else:
            self._stream.disable_timeline(WALL_TIME)

    def event(self, node: str, port: str, value: Any) -> None:
        for path, leaf in value_leaves(value):
            parts = self.entity(("port", node, port, path))
            self._stream.log(parts, archetype(self._rr, leaf))
            self.written["/" + "/".join(parts)] += 1

    def step(self, node: str, text: str, status: str) -> None:
        parts = self.entity(("steps", node))
        self._stream.log(parts, self._rr.TextLog(text, level=STEP_LEVELS.get(status, "WARN")))
        self.written["/" + "/".join(parts)] += 1

    def log_event(self, node: str, port: str, tag_ns: int, publish_ns: int, seq: int, value: Any) -> None:
        """One event at its tag, its seq, and its publish time on the wall timeline (0: unknown)."""
        self.at(tag_ns, publish_ns, seq)
        self.event(node, port, value)

    def log_step(self, step: StepRecord) -> None:
        """One step record at its tick's tag, its number among its node's, and at when its step
        began on the wall timeline."""
        self.at(step.tag[0], step.wall_start_ns, self._steps[step.node])
        self._steps[step.node] += 1
        self.step(step.node, step_json(step), step.status)


def export_rerun(log: RunLog | str | Path, out: str | Path, *, overwrite: bool = False) -> RerunExport:
    """Write ``log`` (read whole, or its path: streamed, reader.log_records) as a Rerun recording
    (``.rrd``) to ``out`` (``-``: standard output, a pipe: ``| rerun -``); the rows written, per
    entity, and the entities renamed."""
    rr = rerun_sdk()
    if to_stdout(out):
        stdout_stream("rerun")  # a LogError for a terminal: Rerun's SDK would hold the recording in memory
        source = log_records(log)
        stream = export_stream(rr)
        try:
            stream.stdout(default_blueprint=event_time_blueprint(rr))
            return _write_rerun(rr, source, stream)
        except RuntimeError:  # the SDK's, for a write that failed: EPIPE is said as the others say it
            if stdout_reader_gone():
                raise BrokenPipeError(errno.EPIPE, "the reader of standard output went away") from None
            raise
        finally:
            stream.disconnect()
    out = export_path(log.path if isinstance(log, LogHead) else log, out, overwrite)
    source = log_records(log)
    # written beside it, then renamed: an export that fails leaves no file that looks whole
    partial = out.with_name(f".{out.name}.{os.getpid()}.partial")
    stream = export_stream(rr)
    try:
        try:
            stream.save(partial, default_blueprint=event_time_blueprint(rr))
        except Exception as e:  # the SDK's own error for a path it cannot create
            raise LogError(f"cannot write {out}: {e}") from None
        written = _write_rerun(rr, source, stream)
        os.replace(partial, out)
    finally:
        stream.disconnect()
        partial.unlink(missing_ok=True)
    return written


def _write_rerun(rr, source: LogRecords, stream) -> RerunExport:
    """The log's records logged on ``stream`` (its sink set), flushed every FLUSH_BYTES handed
    and at the end, and disconnected."""
    head = source.head
    stream.send_recording_name(head.run.get("pipeline") or Path(head.path).stem)
    recording = RerunRecording(rr, stream)
    recording.reserve(source.step_nodes, [port for c in head.channels.values() if (port := parse_data_topic(c.topic))])
    handed = 0  # since the stream's last flush, in bytes (FLUSH_BYTES)
    for record in source.records():
        if type(record) is StepRecord:
            recording.log_step(record)
            handed += RECORD_BYTES
        else:
            recording.log_event(record.node, record.port, record.tag[0], record.publish_ns, record.seq,
                                head.value(record, keep_unregistered=True))
            handed += RECORD_BYTES + len(record.raw_value)
        if handed >= FLUSH_BYTES:
            stream.flush()
            handed = 0
    stream.flush()
    stream.disconnect()
    return RerunExport(recording.written, recording.renamed)
