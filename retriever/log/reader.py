"""Read a Retriever log back: validate it, and present its IR, metadata, events and steps.

One sequential pass with ``mcap``'s stream reader, CRCs checked (chunk contents and the data
section), so a flipped byte is an error and not silently wrong data. A file whose writer was
killed ends mid-record: :func:`read_log` refuses it with a hint, ``read_log(...,
salvage=True)`` (what ``retriever log recover`` uses) keeps every record before the damage.

A log is read a chunk at a time: a chunk's Message records are found by the MessageIndex
records after it, every record's head read at once with numpy (checked to tile the chunk
exactly; else walked with one ``unpack_from`` each: :func:`chunk_messages`), and handed on,
where a reader takes them in bulk (:func:`scan_log`, or as numpy arrays, :class:`ChunkMessages`;
``ScannedLog.time_ordered``, or as batches of columns ``ScannedLog.in_order``: the replay's two
passes), as **message tuples**
``(log_time, position, channel_id, sequence, publish_time, data)`` rather than ``mcap``
``Message`` objects (making those was most of a log's reading). ``position`` says where the
record is (its chunk's offset in the file times 2**32, plus its own in the chunk's records):
unique and increasing in file order, so message tuples sort by log time, ties in file order,
and no further field is compared. :func:`read_log` keeps ``Message`` objects.
"""

from __future__ import annotations

import json
import os
import struct
import sys
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator

import numpy as np
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.exceptions import EndOfFile
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, Chunk, ChunkIndex, Footer, Header, Message, Metadata, Schema
from mcap.stream_reader import CRCValidationError, StreamReader, get_chunk_data_stream

from ..codec import unpackb
from ..errors import ChunkTooLargeError, CodecError, IRError, LogError, UnregisteredTypeError
from ..flow.read_only import make_read_only
from ..ir import IR
from ..trace import Event, StepRecord, Trace
from . import format as fmt
from .deployment import LoggedDeployment, read_deployment
from .mcap_records import MAGIC, MESSAGE_FIELDS, MESSAGE_HEAD


@dataclass(frozen=True)
class LogChannel:
    id: int
    topic: str
    message_encoding: str
    metadata: dict[str, str]
    schema_id: int = 0  # 0: none (Retriever's own channels are msgpack without a schema)


@dataclass(frozen=True)
class LoggedEvent:
    """An event as logged: the value stays msgpack bytes until asked for (``RunLog.value``)."""

    tag: tuple[int, int]
    node: str
    port: str
    seq: int
    raw_value: bytes
    publish_ns: int

    @property
    def id(self) -> tuple[str, str, int]:
        return (self.node, self.port, self.seq)


@dataclass
class LogHead:
    """What one log file says of its run, but its messages: header, channels, attachments (the
    IR), metadata, and whether it was finished. :class:`RunLog` adds the messages;
    :class:`ScannedLog`, read by :func:`scan_log`, keeps none."""

    path: Path
    profile: str = ""  # the header's: "retriever" for a Retriever log
    channels: dict[int, LogChannel] = field(default_factory=dict)
    schemas: dict[int, Schema] = field(default_factory=dict)
    attachments: dict[str, Attachment] = field(default_factory=dict)
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    complete: bool = False  # the writer finished the file (footer read)
    damage: str | None = None  # why reading stopped early, when salvaging

    # -- what the run was --------------------------------------------------------------------
    @property
    def run(self) -> dict[str, str]:
        return self.metadata.get(fmt.RUN_METADATA, {})

    @property
    def end(self) -> dict[str, str] | None:
        """The ``retriever.end`` record, its counts checked (a changed file's text is not a count)."""
        end = self.metadata.get(fmt.END_METADATA)
        for field in ("end_ns", "events", "steps", "finished_unix_ns"):
            value = end.get(field) if end is not None else None
            if value is not None and not (value.isascii() and value.isdigit() and len(value) <= 20):
                raise LogError(f"{self.path}: the end record {fmt.END_METADATA} is malformed: its {field} is "
                               f"{value!r:.40}, not a count", "the file was changed after it was written")
        return end

    @property
    def ir(self) -> IR:
        attachment = self.attachments.get(fmt.IR_ATTACHMENT)
        if attachment is None:
            raise LogError(f"{self.path} holds no pipeline IR (attachment {fmt.IR_ATTACHMENT!r})",
                           "was it written by Retriever? (retriever replay can be given the pipeline: "
                           "--pipeline FILE:ATTR)")
        try:
            return IR.from_json(bytes(attachment.data).decode())
        except (IRError, UnicodeDecodeError, ValueError) as e:
            raise LogError(f"the IR stored in {self.path} is invalid: {e}",
                           "retriever replay can be given the pipeline: --pipeline FILE:ATTR") from None

    @property
    def faults(self) -> list[dict[str, Any]]:
        """The run's lost processes (``retriever.fault.N`` records), in order, JSON fields decoded."""
        faults = []
        for name in sorted((n for n in self.metadata if n.startswith(fmt.FAULT_METADATA)),
                           key=lambda n: (len(n), n)):
            record = self.metadata[name]
            try:
                lost = list(fmt.event_ids(json.loads(record.get("lost_events", "[]"))))
                seqs = json.loads(record.get("seqs", "{}"))
            except (ValueError, RecursionError):  # not JSON, not event ids, nested past the limit
                lost = seqs = None
            node = record.get("node")
            if (type(node) is not str or lost is None or type(seqs) is not dict
                    or any(event_id[0] != node for event_id in lost)
                    or not all(type(n) is int and n >= 0 for n in seqs.values())
                    or not (record.get("at_ns", "0").isdigit() and len(record.get("at_ns", "0")) <= 20)):
                raise LogError(f"{self.path}: the fault record {name} is malformed",
                               "the file was changed after it was written")
            faults.append({**record, "seqs": seqs, "lost_events": lost})
        return faults

    @property
    def deployment(self) -> LoggedDeployment | None:
        """Where the nodes of a deployment's run ran, and their moves after a worker was lost
        (None: the run was not a deployment)."""
        return read_deployment(self.path, self.run.get("deployment"), self.faults)

    @property
    def starved(self) -> list[dict[str, Any]]:
        """The inputs that had no event while their producers made some (``retriever.starved.N``
        records, starved.StarvationWatch), in order: ``node``, ``port``, ``producers``,
        ``since_ns``, ``until_ns`` (None: to the run's end), ``ticks``, ``produced``."""
        found = []
        for name in sorted((n for n in self.metadata if n.startswith(fmt.STARVED_METADATA)),
                           key=lambda n: (len(n), n)):
            record = self.metadata[name]
            try:
                fields = {key: json.loads(record.get(key, "null"))
                          for key in ("producers", "since_ns", "until_ns", "ticks", "produced")}
            except (ValueError, RecursionError):
                fields = None
            counts = (fields or {}).get("since_ns"), (fields or {}).get("ticks"), (fields or {}).get("produced")
            if (fields is None or type(record.get("node")) is not str or type(record.get("port")) is not str
                    or not all(type(n) is int and n >= 0 for n in counts)
                    or not (fields["until_ns"] is None or type(fields["until_ns"]) is int)
                    or type(fields["producers"]) is not list
                    or not all(type(p) is str for p in fields["producers"])):
                raise LogError(f"{self.path}: the starved record {name} is malformed",
                               "the file was changed after it was written")
            found.append({"node": record["node"], "port": record["port"], **fields})
        return found

    def add_import_paths(self) -> None:
        """Put the folders the run imported its flows from on ``sys.path`` (those that exist
        here), so its classes can be imported again from any working directory."""
        try:
            roots = json.loads(self.run.get("python_path", "[]") or "[]")
        except ValueError:
            roots = None
        if type(roots) is not list or not all(type(root) is str for root in roots):
            raise LogError(f"{self.path}: the run record's python_path is not a JSON list of folders",
                           "the file was changed after it was written; give the pipeline yourself: "
                           "retriever replay LOG --pipeline FILE")
        for root in reversed(roots):
            if root not in sys.path and os.path.isdir(root):
                sys.path.insert(0, root)

    def value(self, event: LoggedEvent, *, keep_unregistered: bool = False) -> Any:
        """The event's value. Decoding imports and calls nothing: a dataclass comes back as the
        value type this process registered (``@io``) under its path, else it is an error, or with
        ``keep_unregistered=True`` an inert :class:`retriever.codec.UnregisteredValue`."""
        try:
            return unpackb(event.raw_value, keep_unregistered=keep_unregistered)
        except UnregisteredTypeError as e:
            raise LogError(f"{self.path}: cannot decode event {event.node}.{event.port} #{event.seq}: "
                           f"{str(e).partition(chr(10))[0]}",
                           "import the modules that define the run's @io types before reading its values "
                           "(retriever replay imports the flows' modules the IR names)") from None
        except CodecError as e:
            raise LogError(f"{self.path}: event {event.node}.{event.port} #{event.seq} is damaged: "
                           f"{str(e).partition(chr(10))[0]}", "the file was changed after it was written") from None
        except Exception as e:  # msgpack's own errors on a damaged value
            raise LogError(f"{self.path}: event {event.node}.{event.port} #{event.seq} is not valid msgpack "
                           f"({type(e).__name__})", "the file is damaged: retriever log recover") from None


@dataclass
class RunLog(LogHead):
    """Everything one log file holds, in file order."""

    messages: list[Message] = field(default_factory=list)
    _steps: list[StepRecord] | None = field(default=None, repr=False)

    # -- its records -------------------------------------------------------------------------
    def iter_events(self) -> Iterator[LoggedEvent]:
        """Every event, in file order, value undecoded."""
        ports = {c.id: parsed for c in self.channels.values() if (parsed := fmt.parse_data_topic(c.topic))}
        for m in self.messages:
            port = ports.get(m.channel_id)
            if port is not None:
                yield logged_event(self.path, port, m.log_time, m.sequence, m.publish_time, m.data)

    def iter_steps(self) -> Iterator[StepRecord]:
        """Every step record, in file order (decoded once, then kept)."""
        if self._steps is None:
            self._steps = list(self._decode_steps())
        return iter(self._steps)

    def _decode_steps(self) -> Iterator[StepRecord]:
        steps = {c.id for c in self.channels.values() if c.topic == fmt.STEPS_TOPIC}
        for m in self.messages:
            if m.channel_id in steps:
                yield step_record(self.path, m.log_time, m.sequence, m.publish_time, m.data)

    def trace(self) -> Trace:
        """The logged run as a :class:`Trace` (values decoded), comparable with a live one: its
        values read-only, as a run's are (an emitted value is immutable)."""
        events = [Event(e.tag, e.node, e.port, e.seq, self.value(e), e.publish_ns) for e in self.iter_events()]
        for event in events:
            make_read_only(event.value)
        return Trace(events, list(self.iter_steps()))



def logged_event(path: Path, port: tuple[str, str], log_time: int, sequence: int, publish_time: int,
                 data: bytes) -> LoggedEvent:
    """The event a message on the channel of ``port`` (``(node, port)``) holds, value undecoded."""
    try:
        microstep, raw = fmt.split_event(data)
    except ValueError as e:
        raise LogError(f"{path}: event {port[0]}.{port[1]} #{sequence} is malformed ({e})") from None
    return LoggedEvent((log_time, microstep), port[0], port[1], sequence, raw, publish_time)


def step_record(path: Path, log_time: int, sequence: int, publish_time: int, data: bytes) -> StepRecord:
    """The step record a message on the steps channel holds."""
    try:
        node, microstep, consumed, produced, status, detail, wall_ns = fmt.decode_step(data)
    except Exception as e:
        raise LogError(f"{path}: step record #{sequence} is malformed ({e})") from None
    return StepRecord(node, (log_time, microstep), consumed, produced, status, detail, publish_time, wall_ns)


def read_log(path: str | Path, *, salvage: bool = False) -> RunLog:
    """Read and validate a log. ``salvage=True`` keeps the records before a tear or corruption
    instead of raising (``log.complete`` and ``log.damage`` then say what happened)."""
    log = RunLog(Path(path))
    messages = log.messages

    def add(read: list[tuple]) -> None:
        messages.extend([Message(channel_id=channel_id, log_time=log_time, data=data, publish_time=publish_time,
                                 sequence=sequence)
                         for log_time, _, channel_id, sequence, publish_time, data in read])

    _read(log, add, salvage)
    return log


@dataclass
class ScannedLog(LogHead):
    """A log read through once by :func:`scan_log`: what it says of its run, and where its
    messages are, without them; :meth:`time_ordered` reads them again, chunk by chunk."""

    messages_read: int = 0
    size: int = 0  # bytes
    #: ``[first log_time, offset]`` of every chunk that holds messages: the chunk's own word on its
    #: times is not taken, its messages' are (a chunk says when it starts; a changed file may lie)
    chunks: list[list[int]] = field(default_factory=list, repr=False)
    loose: int = 0  # messages outside any chunk (MCAP allows them; Retriever's writer makes none)
    _identity: tuple = field(default=(), repr=False)

    def time_ordered(self) -> Iterator[tuple]:
        """Every message as a message tuple (the module docstring), in log-time order, ties in file order
        (what a stable sort of the file's messages by ``log_time`` gives: the tuples sort so),
        read again from the file a chunk at a time: chunks are taken in the order of their first
        message's time, and a message is handed on once no chunk still to be read can hold an
        earlier one. What is held at a time is the chunks whose times overlap: for a log as a run
        writes it, a few chunks (its LET latencies and late reports make them overlap), however
        long the log."""
        for held, data in self._ordered():
            ats, offsets = held["at"], held["offset"]
            if int(ats.max()) < 1 << 30:
                positions = ((ats.astype(np.int64) << 32) + offsets).tolist()
            else:
                positions = [(at << 32) + offset for at, offset in zip(ats.tolist(), offsets.tolist())]
            yield from zip(held["log_time"].tolist(), positions, held["channel_id"].tolist(),
                           held["sequence"].tolist(), held["publish_time"].tolist(), data)

    def in_order(self) -> Iterator[tuple[list, list, list, list, list]]:
        """The messages of :meth:`time_ordered`, in its order, in batches of columns: each batch
        ``(log_times, channel_ids, sequences, publish_times, data)``, lists of the same length
        (no position, no tuple a message: what the replay reads)."""
        for held, data in self._ordered():
            yield (held["log_time"].tolist(), held["channel_id"].tolist(), held["sequence"].tolist(),
                   held["publish_time"].tolist(), data)

    def _ordered(self) -> Iterator[tuple[dict[str, np.ndarray], list[bytes]]]:
        """:meth:`time_ordered`'s reading: the messages in batches, each the messages' fields
        (:data:`_HELD`, an array each) and their data. The messages held are kept as arrays (sorted
        with numpy: by log time, then chunk, then place in it) and their data in their chunks'
        bytes, sliced once a message is handed on."""
        if self.loose:
            raise LogError(f"{self.path} holds {self.loose} messages outside its chunks, which time_ordered() "
                           "does not read", "read it whole: read_log(path)")
        order = sorted(self.chunks)
        held: dict[str, np.ndarray] | None = None  # sorted: by log time, then chunk, then offset in it (unique)
        raws: dict[int, bytes] = {}  # the bytes of the chunks that held messages are in, by piece
        try:
            stream = open(self.path, "rb")
        except OSError as e:
            raise LogError(f"cannot open the log {self.path} again: {e.strerror}") from None
        with stream:
            if _identity(stream) != self._identity:
                raise LogError(f"{self.path} changed since it was read", "read it again, once nothing writes it")
            for k, (_, offset) in enumerate(order):
                try:
                    stream.seek(offset)
                    chunk = next(_StreamReader(stream, skip_magic=True, emit_chunks=True).records)
                    # (its CRC was checked as the file was read through, and the file is the same:
                    # _identity; a CRC of the decompressed bytes costs 4 instructions a byte)
                    messages, rest = chunk_messages(chunk, offset, self.channels,
                                                   _indexes_after(stream, _index_room(chunk, self.channels)),
                                                   arrays=True, check_crc=False)
                except Exception as e:  # the file was read whole before: it changed since
                    raise LogError(f"{self.path} changed since it was read: the chunk at byte {offset} no longer "
                                   f"reads ({type(e).__name__}: {e})",
                                   "read it again, once nothing writes it") from None
                if _identity(stream) != self._identity:  # written to in place as this reading went: what
                    # was read may be the change (the CRC, not checked again, would have said so)
                    raise LogError(f"{self.path} changed as it was read", "read it again, once nothing writes it")
                found, raws[k] = _held(messages, rest, offset, k)
                if found is not None:
                    if held is not None:
                        found = {name: np.concatenate((held[name], found[name])) for name in _HELD}
                    order_by = np.lexsort((found["offset"], found["at"], found["log_time"]))
                    held = {name: column[order_by] for name, column in found.items()}
                if held is None:
                    continue
                if k + 1 < len(order):  # hand on what no chunk still to be read can come before
                    cut = int(np.searchsorted(held["log_time"], np.uint64(order[k + 1][0])))
                else:
                    cut = len(held["log_time"])
                if cut:
                    yield {name: column[:cut] for name, column in held.items()}, _data(held, cut, raws)
                if cut == len(held["log_time"]):
                    held, raws = None, {}
                else:
                    held = {name: column[cut:] for name, column in held.items()}
                    raws = _kept(held, raws)

    def records(self) -> Iterator[LoggedEvent | StepRecord]:
        """Every event (value undecoded) and step record, in log-time order (:meth:`time_ordered`),
        read again from the file: what is held at a time is a few chunks, however long the log."""
        kinds: dict[int, tuple[str, str] | None] = {
            c.id: fmt.parse_data_topic(c.topic) for c in self.channels.values() if c.topic != fmt.STEPS_TOPIC}
        path = self.path
        for log_time, _, channel_id, sequence, publish_time, data in self.time_ordered():
            port = kinds.get(channel_id, _STEPS)
            if port is _STEPS:
                yield step_record(path, log_time, sequence, publish_time, data)
            elif port is not None:
                yield logged_event(path, port, log_time, sequence, publish_time, data)


_STEPS = ("steps",)  # ScannedLog.records: a channel of step records (a port is a pair)

#: the fields of a message :meth:`ScannedLog._ordered` holds: its head's, where its record is
#: (``at`` its chunk's offset in the file, ``offset`` its own in the chunk's records) and where its
#: data is (``piece``: which chunk's bytes, ``start``, ``end`` in them)
_HELD = ("log_time", "at", "offset", "channel_id", "sequence", "publish_time", "piece", "start", "end")


def _held(messages: list[tuple] | ChunkMessages, rest: list, at: int,
          piece: int) -> tuple[dict[str, np.ndarray] | None, bytes]:
    """A chunk's messages (:func:`chunk_messages` with ``arrays=True``, at byte ``at``) as
    :data:`_HELD` columns (None if it has none), and the bytes their data is in: a chunk walked by
    its indexes as its arrays; one walked otherwise (its message tuples, and those among its
    other records) as the data joined."""
    if type(messages) is ChunkMessages:
        heads, offsets, n = messages.heads, messages.offsets, len(messages)
        return {"log_time": heads["log_time"], "at": np.full(n, at, dtype=np.uint64), "offset": offsets,
                "channel_id": heads["channel_id"], "sequence": heads["sequence"], "publish_time": heads["publish_time"],
                "piece": np.full(n, piece, dtype=np.int64), "start": offsets + (_RECORD_HEAD + MESSAGE_FIELDS),
                "end": messages.ends}, messages.raw
    tuples = messages + [record for record in rest if type(record) is tuple]
    if not tuples:
        return None, b""
    log_times, positions, channel_ids, sequences, publish_times, data = zip(*tuples)
    base, n = at << 32, len(tuples)
    lengths = np.fromiter(map(len, data), dtype=np.int64, count=n)
    ends = np.cumsum(lengths)
    return {"log_time": np.array(log_times, dtype=np.uint64), "at": np.full(n, at, dtype=np.uint64),
            "offset": np.array([position - base for position in positions], dtype=np.int64),
            "channel_id": np.array(channel_ids, dtype=np.uint16), "sequence": np.array(sequences, dtype=np.uint32),
            "publish_time": np.array(publish_times, dtype=np.uint64), "piece": np.full(n, piece, dtype=np.int64),
            "start": ends - lengths, "end": ends}, b"".join(data)


def _data(held: dict[str, np.ndarray], cut: int, raws: dict[int, bytes]) -> list[bytes]:
    """The data of the first ``cut`` messages ``held`` (:data:`_HELD` columns), in their order,
    sliced from ``raws`` (the chunks' bytes they are in, those joined when more than one)."""
    pieces, starts, ends = held["piece"][:cut], held["start"][:cut], held["end"][:cut]
    used = np.unique(pieces).tolist()
    if len(used) > 1:
        firsts = np.cumsum([0] + [len(raws[piece]) for piece in used[:-1]])  # where each begins, joined
        shift = firsts[np.searchsorted(used, pieces)]
        raw = b"".join(raws[piece] for piece in used)
        starts, ends = starts + shift, ends + shift
    else:
        raw = raws[used[0]]
    return list(map(raw.__getitem__, map(slice, starts.tolist(), ends.tolist())))


def _kept(held: dict[str, np.ndarray], raws: dict[int, bytes]) -> dict[int, bytes]:
    """The bytes that the messages still ``held`` have their data in, by piece: a chunk's whole
    bytes while they are most of it; else only their data, copied out (and ``held``'s start and
    end set to where it is now), so that a message that waits long (a LET output, or a forged
    far-future one in every chunk) does not keep its whole chunk."""
    kept = {}
    pieces = held["piece"]
    for piece in np.unique(pieces).tolist():
        raw = raws[piece]
        rows = np.flatnonzero(pieces == piece)
        starts, ends = held["start"][rows], held["end"][rows]
        waiting = int((ends - starts).sum())
        if 4 * waiting >= len(raw):
            kept[piece] = raw
            continue
        kept[piece] = b"".join(map(raw.__getitem__, map(slice, starts.tolist(), ends.tolist())))
        moved_ends = np.cumsum(ends - starts)
        held["start"] = held["start"].copy()  # (a view of the batch's columns until now)
        held["end"] = held["end"].copy()
        held["start"][rows], held["end"][rows] = moved_ends - (ends - starts), moved_ends
    return kept


def scan_log(path: str | Path, take: Callable[[dict[int, LogChannel], list[tuple]], None], *,
             progress: Callable[[int, int], None] | None = None,
             take_chunk: Callable[[dict[int, LogChannel], ChunkMessages], None] | None = None) -> ScannedLog:
    """Read and validate a log as :func:`read_log` does (the same errors, for a log torn or
    damaged), handing its messages to ``take(channels, messages)`` in file order instead of
    keeping them: ``messages`` is a list of message tuples (the module docstring) (a chunk's at a time,
    nearly always), ``channels`` the log's by id (each message's is there). What is kept is the
    log's head and where its chunks are (``log.time_ordered()`` reads them again).
    ``progress(bytes read, file size)`` is called as the file is read. ``take_chunk``, if given,
    takes instead each chunk whose MessageIndex records tile it (every chunk of a log Retriever
    wrote) as a :class:`ChunkMessages`, without a Python object per message."""
    log = ScannedLog(Path(path))
    channels, chunks = log.channels, log.chunks
    chunk: list[int] | None = None

    def at_chunk(offset: int | None) -> None:
        nonlocal chunk
        if offset is None:  # a message outside any chunk
            chunk = None
        else:
            chunk = [2 ** 64, offset]  # past any log time until its first message
            chunks.append(chunk)

    def add(messages: list[tuple] | ChunkMessages) -> None:
        if chunk is None:
            log.loose += len(messages)
            take(channels, messages)
            return
        if type(messages) is ChunkMessages:
            first = int(messages.heads["log_time"].min())
            take_chunk(channels, messages)
        else:
            first = min(messages)[0]
            take(channels, messages)
        if first < chunk[0]:
            chunk[0] = first

    _read(log, add, False, progress=progress, at_chunk=at_chunk, arrays=take_chunk is not None)
    chunks[:] = [c for c in chunks if c[0] < 2 ** 64]
    if progress is not None:
        progress(log.size, log.size)
    return log


@dataclass
class LogRecords:
    """A log as an export to a viewer reads it: what it says of its run (``head``: its IR, run
    record, ``value()``), what a first reading found (the nodes with step records, the wall time
    of the run's tag 0), and ``records()``, its events and step records read again."""

    head: LogHead
    step_nodes: set[str]
    #: the earliest publish time less its event's tag (an event is published at or after its
    #: tag), None when no event has a publish time
    wall_start_ns: int | None
    records: Callable[[], Iterator[LoggedEvent | StepRecord]]


def log_records(log: RunLog | str | Path) -> LogRecords:
    """``log`` for an export: a log read whole (its events in file order, then its step records),
    or the path of one, which is read twice and never held (scan_log; its records in log-time
    order, a few chunks at a time), so that an export's memory does not grow with the log's
    length (a log with messages outside its chunks, which Retriever's writer never makes, is
    read whole)."""
    if isinstance(log, RunLog):
        starts = [e.publish_ns - e.tag[0] for e in log.iter_events() if e.publish_ns]
        return LogRecords(log, {step.node for step in log.iter_steps()}, min(starts, default=None),
                          lambda: _whole_records(log))
    path = Path(log)
    nodes: set[str] = set()
    start: list[int | None] = [None]
    kinds: dict[int, Any] = {}

    def take(channels: dict[int, LogChannel], messages: list[tuple]) -> None:
        for log_time, _, channel_id, sequence, publish_time, data in messages:
            kind = kinds.get(channel_id, _UNSEEN)
            if kind is _UNSEEN:
                topic = channels[channel_id].topic
                kind = kinds[channel_id] = _STEPS if topic == fmt.STEPS_TOPIC else fmt.parse_data_topic(topic)
            if kind is _STEPS:
                nodes.add(step_record(path, log_time, sequence, publish_time, data).node)
            elif kind is not None and publish_time and (start[0] is None or publish_time - log_time < start[0]):
                start[0] = publish_time - log_time

    scanned = scan_log(path, take)
    if scanned.loose:
        return log_records(read_log(path))
    return LogRecords(scanned, nodes, start[0], scanned.records)


def _whole_records(log: RunLog) -> Iterator[LoggedEvent | StepRecord]:
    yield from log.iter_events()
    yield from log.iter_steps()


_UNSEEN = ("unseen",)


def _identity(stream) -> tuple:
    """What tells a file that was changed (rewritten, appended to) from the one read before."""
    stat = os.fstat(stream.fileno())
    return (stat.st_dev, stat.st_ino, stat.st_size, stat.st_mtime_ns)


def _read(log: LogHead, add: Callable[[list[tuple]], None], salvage: bool, *,
          progress: Callable[[int, int], None] | None = None,
          at_chunk: Callable[[int | None], None] | None = None, arrays: bool = False) -> None:
    """Read and validate the log at ``log.path`` into ``log``, its messages handed to ``add`` as
    lists of message tuples, in file order: a chunk's Message records up to its first other
    record at once, any other message alone; with ``arrays``, a chunk its indexes tile as one
    :class:`ChunkMessages`."""
    path = log.path
    try:
        stream = open(path, "rb")
    except FileNotFoundError:
        raise LogError(f"no such log file: {path}", "give the path of a .mcap file written by --log / log=") from None
    except OSError as e:
        raise LogError(f"cannot open the log {path}: {e.strerror}",
                       "give the path of a .mcap file written by --log / log=") from None
    with stream:
        if stream.read(len(MAGIC)) != MAGIC:
            raise LogError(f"{path} is not an MCAP file (it does not start with the MCAP magic bytes)",
                           "retriever reads the .mcap files written by pipe.run(log=...) or --log")
        stream.seek(0)
        size = os.fstat(stream.fileno()).st_size
        if isinstance(log, ScannedLog):
            log.size, log._identity = size, _identity(stream)
        tracked = _Tracked(stream, size, progress)
        # chunks as they are, broken up here (chunk_messages: what mcap's breakup_chunk does, faster)
        reader = _StreamReader(tracked, validate_crcs=True, emit_chunks=True)
        dropped: list[str] = []  # salvaging: damaged attachments left out, and why
        bad_attachment = bad_channel = None
        footer, chunk_indexes = None, []
        read = 0  # messages
        channels = log.channels
        try:
            for record in _records_in_chunks(reader, tracked, channels, at_chunk, arrays):
                if type(record) is list or type(record) is ChunkMessages:  # a chunk's, each on a channel read before
                    add(record)
                    read += len(record)
                    continue
                if type(record) is tuple:
                    if record[2] not in channels:
                        raise ValueError(f"message on unknown channel {record[2]}")
                    add([record])
                    read += 1
                    continue
                if isinstance(record, ChunkIndex):
                    chunk_indexes.append(record)
                elif isinstance(record, Footer):
                    footer = record
                elif isinstance(record, Channel) and log.profile == fmt.PROFILE:
                    bad_channel = fmt.data_topic_problem(record.topic)
                    if bad_channel is not None:
                        break
                if isinstance(record, Attachment):
                    error = _attachment_crc_error(record, tracked.last_data)
                    if error is not None:
                        at = stream.tell()
                        why = _diagnose(stream, size, tracked.last_read_at, error)
                        stream.seek(at)
                        if not salvage:
                            bad_attachment = why
                            break
                        dropped.append(f"{why}; the attachment {record.name!r} was left out")
                        continue
                _take(log, record)
        except Exception as e:  # EndOfFile, CRCs, struct.error, zstd errors, bad UTF-8: a tear or a bad byte
            _damaged(log, salvage, _diagnose(stream, size, tracked.last_read_at, e), read)
        else:
            closing = None if footer is None else _closing_damage(stream, size, tracked.position, footer,
                                                                   chunk_indexes)
            if closing is not None:  # every record read; what indexed readers go by is wrong
                log.damage = (f"{closing}; its records read whole, but readers that seek by its summary (Foxglove's) "
                              "refuse it")
        if dropped:
            log.damage = "; ".join([*dropped, *([log.damage] if log.damage else [])])
        if isinstance(log, ScannedLog):
            log.messages_read = read
    if bad_channel is not None:
        raise LogError(f"{path} cannot be read: {bad_channel}",
                       "the log was changed after it was written, or written by a Retriever that let a port name "
                       "hold '/' (its events were lost from every view)")
    if bad_attachment is not None:
        raise LogError(f"{path} cannot be read: {bad_attachment}",
                       f"`retriever log recover {path}` writes a readable copy without the damaged attachment "
                       "(replay that one with --pipeline FILE:ATTR)")


def _attachment_crc_error(record: Attachment, crc_bytes: bytes) -> CRCValidationError | None:
    """The mcap library reads an attachment's CRC and drops it: check it here (it covers the
    record's fields before it). ``crc_bytes`` is the last read, the CRC field; 0 means none."""
    if len(crc_bytes) != 4:
        return None
    expected = int.from_bytes(crc_bytes, "little")
    if expected == 0:
        return None
    name, media_type = record.name.encode(), record.media_type.encode()
    crc = zlib.crc32(struct.pack("<QQI", record.log_time, record.create_time, len(name)) + name
                     + struct.pack("<I", len(media_type)) + media_type + struct.pack("<Q", len(record.data)))
    actual = zlib.crc32(record.data, crc)
    return None if actual == expected else CRCValidationError(expected, actual, record)


#: the most bytes one chunk may hold uncompressed: a chunk is decompressed whole, and a small
#: file whose chunk says it holds many gigabytes (a decompression bomb) would take that much memory
#: (Retriever's writer closes a chunk past 1 MiB; only one value of this size makes a bigger one)
MAX_CHUNK_BYTES = 1 << 30


class _StreamReader(StreamReader):
    """``mcap``'s stream reader, handing on MessageIndex records unparsed (:class:`_Index`: their
    entries, parsed field by field in Python, were a third of a read; :func:`chunk_messages` reads
    them with numpy). A chunk that says it holds more than MAX_CHUNK_BYTES is refused before it
    is decompressed. ``record_at`` is where the last Chunk or Message record read begins."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        self.record_at = 0

    def _read_record(self, opcode: int, length: int):
        if opcode == Opcode.MESSAGE_INDEX:
            return _Index(self._stream.read(length))
        if opcode == Opcode.CHUNK or opcode == Opcode.MESSAGE:  # where its messages come from
            self.record_at = self._stream.count - _RECORD_HEAD
        record = super()._read_record(opcode, length)
        if isinstance(record, Chunk):
            size = _uncompressed_size(record)
            if size > MAX_CHUNK_BYTES:
                raise ChunkTooLargeError(f"a chunk holds {size:,} bytes uncompressed, more than a log is read with "
                                         f"({MAX_CHUNK_BYTES:,})")
        return record


class _Index:
    """A MessageIndex record's fields, unparsed (channel id, entries' length, entries)."""

    __slots__ = ("body",)

    def __init__(self, body: bytes) -> None:
        self.body = body


def _records_in_chunks(reader: _StreamReader, tracked: _Tracked, channels: dict[int, LogChannel],
                       at_chunk: Callable[[int | None], None] | None = None, arrays: bool = False) -> Iterator:
    """The records of a stream read with ``emit_chunks=True``, each chunk's in its place (as a
    stream reader without it yields them), a chunk's records all read before the first is handed
    on; messages as message tuples, the Message records that begin a chunk on a channel of
    ``channels`` as one list. A chunk is broken up once the MessageIndex records after it are read
    (:func:`chunk_messages` walks it by them), as if where it was read: a chunk that does not
    read is blamed where it is (``tracked``'s last read is set back to it), and before a damaged
    record after it. ``at_chunk(offset)`` is told where each chunk starts before its messages are
    handed on (None for a message outside any chunk). ``arrays``: as :func:`chunk_messages`."""
    records = reader.records
    held = None  # (chunk, its offset, the file's last read in it), its MessageIndex records being read
    indexes: list[bytes] = []
    room = 0  # what more of them could still tile the held chunk (_index_room)

    def broken_up(chunk: Chunk, at: int, read_at: int, indexes: list[bytes]) -> Iterator:
        now, tracked.last_read_at = tracked.last_read_at, read_at
        messages, rest = chunk_messages(chunk, at, channels, indexes, arrays=arrays)
        tracked.last_read_at = now
        if at_chunk is not None:
            at_chunk(at)
        if messages:
            yield messages
        yield from rest

    while True:
        try:
            record = next(records, None)
        except Exception:
            if held is not None:  # the chunk first, as if read alone
                yield from broken_up(*held, [])
            raise
        if type(record) is _Index:
            if held is not None:
                room -= len(record.body)
                if room >= 0:
                    indexes.append(record.body)
                else:  # more than could tile it: not kept, the chunk is walked
                    indexes.clear()
            continue  # one after no chunk: skipped (mcap's readers read it for nothing)
        if held is not None:
            yield from broken_up(*held, indexes)
            held, indexes = None, []
        if record is None:
            return
        if type(record) is Chunk:
            held = (record, reader.record_at, tracked.last_read_at)
            room = _index_room(record, channels)
        elif type(record) is Message:  # outside any chunk
            if at_chunk is not None:
                at_chunk(None)
            yield (record.log_time, reader.record_at << 32, record.channel_id, record.sequence, record.publish_time,
                   record.data)
        else:
            yield record


def _indexes_after(stream, room: int) -> list[bytes]:
    """The MessageIndex records' fields from where ``stream`` is (after a chunk), unparsed; none
    if they take more than ``room`` bytes (:func:`_index_room`: then they cannot tile the chunk)."""
    bodies = []
    while True:
        head = stream.read(_RECORD_HEAD)
        if len(head) < _RECORD_HEAD or head[0] != Opcode.MESSAGE_INDEX:
            return bodies
        length = int.from_bytes(head[1:], "little")
        room -= length
        if room < 0:
            return []
        bodies.append(stream.read(length))


def _index_room(chunk: Chunk, channels) -> int:
    """How many bytes of MessageIndex fields can tile ``chunk``: 16 for each record it may hold (a
    record is at least a Message's head long), and an index's own 6 for each channel. Indexes past
    that are not kept (the chunk is walked record by record): a forged log's indexes take no more
    memory than its chunks' own size."""
    return 16 * (_uncompressed_size(chunk) // MESSAGE_HEAD.size) + 6 * len(channels)


def chunk_messages(chunk: Chunk, at: int, channels, indexes: list[bytes] = (), *, by_time: bool = False,
                   arrays: bool = False, check_crc: bool = True) -> tuple[list[tuple] | ChunkMessages, list]:
    """The records in ``chunk`` (at byte ``at`` of its file), its CRC checked (unless not
    ``check_crc``: a chunk read again, checked the first time), as ``mcap``'s
    ``breakup_chunk(chunk, validate_crc=True)`` reads them, record for record, with the same
    errors, but each Message record as a message tuple (the module docstring): the Message
    records before the first other record, or the first on a channel not in ``channels``, and
    then the records from there on (none, in a log Retriever wrote). ``mcap`` decompresses and
    checks the chunk. ``indexes``, the fields of the MessageIndex records after it, say where its
    records are: when they tile it exactly with whole Message records on channels of
    ``channels`` (:func:`_indexed_heads`), numpy reads every record's head at once, and with
    ``by_time`` the messages come in log-time order (ties in file order); with ``arrays``, as one
    :class:`ChunkMessages` (its ``tuples()`` are the message tuples). Else the chunk is
    walked: a whole Message record is read with the layout the writer writes it with
    (``MESSAGE_HEAD``, one ``unpack_from``, into one tuple); from the first other record on (a
    Channel, a Schema, another type's, a Message that is cut short or shorter than its fields),
    the library's own record readers read the rest, from :class:`_ChunkBytes` (the decompressed
    bytes, without a file-like object's call per field)."""
    stream, length = get_chunk_data_stream(chunk, validate_crc=check_crc)
    raw = stream.read(length) if length else b""
    base = at << 32  # a chunk holds less than 2**32 bytes (MAX_CHUNK_BYTES)
    if indexes:
        heads = _indexed_heads(raw, indexes, channels)
        if heads is not None:
            found = ChunkMessages(raw, base, *heads)
            return (found if arrays else found.tuples(by_time)), []
    messages: list[tuple] = []
    append = messages.append
    # (constants as locals: this loop runs once a message, twice a replay)
    pos, head, message, least, record_head = 0, MESSAGE_HEAD.unpack_from, Opcode.MESSAGE, MESSAGE_FIELDS, _RECORD_HEAD
    fields = record_head + least
    last = length - fields  # the last offset a Message record's head fits at
    while pos <= last:
        opcode, size, channel_id, sequence, log_time, publish_time = head(raw, pos)
        end = pos + record_head + size
        if opcode != message or size < least or end > length or channel_id not in channels:
            break
        append((log_time, base + pos, channel_id, sequence, publish_time, raw[pos + fields:end]))
        pos = end
    rest: list = []
    if pos == length:
        return messages, rest
    data = _ChunkBytes(raw, pos)
    read1, read8 = data.read1, data.read8
    while data.count < length:
        start = data.count
        opcode = read1()
        size = read8()
        if opcode == Opcode.MESSAGE:
            m = Message.read(data, size)
            rest.append((m.log_time, base + start, m.channel_id, m.sequence, m.publish_time, m.data))
        elif opcode == Opcode.CHANNEL:
            rest.append(Channel.read(data))
        elif opcode == Opcode.SCHEMA:
            rest.append(Schema.read(data))
        else:  # a record of another type: skipped, as mcap's breakup_chunk does
            data.read(size)
    return messages, rest


#: a Message record's head as numpy reads it (``MESSAGE_HEAD``'s layout)
_HEAD = np.dtype([("opcode", "u1"), ("length", "<u8"), ("channel_id", "<u2"), ("sequence", "<u4"),
                  ("log_time", "<u8"), ("publish_time", "<u8")])


def _indexed_heads(raw: bytes, indexes: list[bytes], channels) -> tuple | None:
    """Where the records of a chunk's bytes ``raw`` are, by its MessageIndex records' fields
    ``indexes``, and their heads: ``(offsets, heads, ends)`` in file order, when the offsets the
    indexes give tile ``raw`` exactly with whole Message records (each ends where the next
    begins, the last where ``raw`` does; none shorter than its fields) on channels of
    ``channels``; else None (an index missing, damaged, or naming no record: the chunk is walked).
    Every field is the record's own: the index gives only where it is."""
    length = len(raw)
    entries = []
    for body in indexes:
        size = int.from_bytes(body[2:6], "little") if len(body) >= 6 else -1
        if size < 0 or size % 16 or len(body) != 6 + size:
            return None
        entries.append(body[6:])
    offsets = np.sort(np.frombuffer(b"".join(entries), dtype="<u8")[1::2])
    if not len(offsets) or offsets[0] != 0 or length < MESSAGE_HEAD.size or offsets[-1] > length - MESSAGE_HEAD.size \
            or (offsets[1:] == offsets[:-1]).any():
        return None
    offsets = offsets.astype(np.int64)
    # each record's head, 31 bytes from its offset: rows of a sliding view, copied whole
    heads = np.lib.stride_tricks.sliding_window_view(np.frombuffer(raw, dtype=np.uint8), MESSAGE_HEAD.size)[offsets]
    heads = heads.view(_HEAD).ravel()
    lengths = heads["length"]
    if (heads["opcode"] != Opcode.MESSAGE).any() or (lengths < MESSAGE_FIELDS).any() or (lengths > length).any():
        return None
    ends = offsets + _RECORD_HEAD + lengths.astype(np.int64)
    if ends[-1] != length or (ends[:-1] != offsets[1:]).any():
        return None
    if not all(channel_id in channels for channel_id in np.flatnonzero(np.bincount(heads["channel_id"])).tolist()):
        return None
    return offsets, heads, ends


@dataclass
class ChunkMessages:
    """A chunk's Message records, all of it, as numpy found them (:func:`_indexed_heads`):
    ``raw`` the chunk's bytes, ``offsets`` where each record is in them (file order), ``heads``
    their fields (``opcode``, ``length``, ``channel_id``, ``sequence``, ``log_time``,
    ``publish_time``), ``ends`` where each ends; a record's data is ``raw[offset + 31:end]``
    (:meth:`data`); ``base``: its chunk's offset in the file times 2**32 (for positions)."""

    raw: bytes
    base: int
    offsets: np.ndarray
    heads: np.ndarray
    ends: np.ndarray

    def __len__(self) -> int:
        return len(self.offsets)

    def data(self, which: np.ndarray) -> list[bytes]:
        """The data of the records at indexes ``which``, in their order."""
        starts = (self.offsets[which] + (_RECORD_HEAD + MESSAGE_FIELDS)).tolist()
        return list(map(self.raw.__getitem__, map(slice, starts, self.ends[which].tolist())))

    def tuples(self, by_time: bool = False) -> list[tuple]:
        """The message tuples (the module docstring), in file order or by log time (ties in file order)."""
        offsets, heads, ends = self.offsets, self.heads, self.ends
        if by_time:
            order = np.lexsort((offsets, heads["log_time"]))
            offsets, heads, ends = offsets[order], heads[order], ends[order]
        starts = (offsets + (_RECORD_HEAD + MESSAGE_FIELDS)).tolist()
        data = list(map(self.raw.__getitem__, map(slice, starts, ends.tolist())))
        base = self.base
        positions = (offsets + base).tolist() if base < 1 << 62 else [base + offset for offset in offsets.tolist()]
        return list(zip(heads["log_time"].tolist(), positions, heads["channel_id"].tolist(),
                        heads["sequence"].tolist(), heads["publish_time"].tolist(), data))


class _ChunkBytes(ReadDataStream):
    """``mcap``'s ReadDataStream over bytes in memory: the same values and errors (a field that
    runs past the end takes the library's own path), each field one ``unpack_from``."""

    def __init__(self, data: bytes, start: int = 0) -> None:
        super().__init__(None)
        self._data, self._size = data, len(data)
        self._count = start  # where the next record begins

    def read(self, length: int) -> bytes:
        if length == 0:
            return b""
        if length > sys.maxsize:  # (a damaged length: BytesIO's error)
            raise OverflowError("cannot fit 'int' into an index-sized integer")
        start = self._count
        # a negative length (a record shorter than its fields) reads to the end, as BytesIO does
        data = self._data[start:start + length] if length > 0 else self._data[start:]
        self._count = start + len(data)
        if not data:
            raise EndOfFile()
        return data

    def read1(self) -> int:
        pos = self._count
        if pos < self._size:
            self._count = pos + 1
            return self._data[pos]
        return super().read1()

    def read2(self) -> int:
        pos = self._count
        if pos + 2 <= self._size:
            self._count = pos + 2
            return _U16.unpack_from(self._data, pos)[0]
        return super().read2()

    def read4(self) -> int:
        pos = self._count
        if pos + 4 <= self._size:
            self._count = pos + 4
            return _U32.unpack_from(self._data, pos)[0]
        return super().read4()

    def read8(self) -> int:
        pos = self._count
        if pos + 8 <= self._size:
            self._count = pos + 8
            return _U64.unpack_from(self._data, pos)[0]
        return super().read8()


_U16, _U32, _U64 = struct.Struct("<H"), struct.Struct("<I"), struct.Struct("<Q")


def _uncompressed_size(chunk: Chunk) -> int:
    """What decompressing ``chunk`` would make, as far as can be told before: a zstd frame's own
    content size wins over the chunk's (zstandard allocates what the frame says)."""
    if chunk.compression == "zstd":
        try:
            said = zstandard.frame_content_size(chunk.data)
        except zstandard.ZstdError:
            return chunk.uncompressed_size  # not a frame: decompressing it fails on its own
        return said if said >= 0 else chunk.uncompressed_size
    return chunk.uncompressed_size


def _closing_damage(stream, size: int, end: int, footer: Footer, chunk_indexes: list) -> str | None:
    """What is wrong with the end of a file read whole to its closing magic (at ``end``), for
    readers that seek by its footer and summary rather than read it through: bytes after the
    magic, a summary outside the file or whose CRC does not match, a chunk index naming no chunk."""
    if end != size:
        return f"{size - end:,} bytes follow its closing magic bytes (at byte {end})"
    footer_at = end - len(MAGIC) - _RECORD_HEAD - 20  # a footer's fields: two offsets and a CRC
    start, offsets = footer.summary_start, footer.summary_offset_start
    if start > footer_at or offsets > footer_at or (offsets and offsets < start):
        return f"its footer puts the summary at bytes {start:,} (offsets {offsets:,}), not before the footer"
    if footer.summary_crc:
        stream.seek(start or footer_at)
        crc = zlib.crc32(stream.read(footer_at - (start or footer_at)))
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, start, offsets), crc)
        if crc != footer.summary_crc:
            return "its summary does not match its CRC"
    for index in chunk_indexes:
        stream.seek(index.chunk_start_offset)
        head = stream.read(_RECORD_HEAD)
        if len(head) != _RECORD_HEAD or head[0] != Opcode.CHUNK \
                or int.from_bytes(head[1:], "little") != index.chunk_length - _RECORD_HEAD:
            return f"its chunk index names a chunk at byte {index.chunk_start_offset:,} where there is none"
    return None


class _Tracked:
    """A file as the MCAP reader reads it, remembering where its last read began: a read that
    fails begins inside the record that is damaged (a damaged length may make it end far past);
    ``progress(bytes read, size)``, if given, is told every ``size / 1000`` bytes (1 MiB at least)."""

    def __init__(self, stream, size: int = 0, progress: Callable[[int, int], None] | None = None):
        self._stream = stream
        self._pos = 0
        self.last_read_at = 0
        self.last_data = b""
        self._size, self._progress = size, progress
        self._every = max(size // 1000, 1 << 20)  # bytes between two calls of progress
        self._next = 0 if progress is not None else float("inf")

    @property
    def position(self) -> int:
        """How many bytes were read."""
        return self._pos

    def read(self, n: int = -1) -> bytes:
        self.last_read_at = self._pos
        data = self._stream.read(n)
        self._pos += len(data)
        self.last_data = data if len(data) <= 8 else b""  # only small reads are kept (a CRC field)
        if self._pos >= self._next:
            self._next = self._pos + self._every
            self._progress(self._pos, self._size)
        return data


# -- telling a torn file from a corrupt one ---------------------------------------------------
#: Every MCAP record's fields after its opcode and length: a number is a fixed-size field, "4" /
#: "8" a field prefixed with its length in 4 / 8 bytes (strings, maps, data). None: a Message,
#: whose data runs to the record's end. A record whose fields run past its own length was damaged:
#: a writer stopped mid-record leaves a consistent record that is cut short. Fields may end before
#: the record does (MCAP lets later versions append fields), and a record of another opcode (a
#: later version's, or a private one, 0x80 and up) is skipped by its length, as readers must.
_LAYOUTS: dict[int, tuple[str, list | None]] = {
    0x01: ("Header", ["4", "4"]), 0x02: ("Footer", [20]), 0x03: ("Schema", [2, "4", "4", "4"]),
    0x04: ("Channel", [2, 2, "4", "4", "4"]), 0x05: ("Message", None), 0x06: ("Chunk", [8, 8, 8, 4, "4", "8"]),
    0x07: ("MessageIndex", [2, "4"]), 0x08: ("ChunkIndex", [8, 8, 8, 8, "4", 8, "4", 8, 8]),
    0x09: ("Attachment", [8, 8, "4", "4", "8", 4]), 0x0A: ("AttachmentIndex", [8, 8, 8, 8, 8, "4", "4"]),
    0x0B: ("Statistics", [8, 2, 4, 4, 4, 4, 8, 8, "4"]), 0x0C: ("Metadata", ["4", "4"]),
    0x0D: ("MetadataIndex", [8, 8, "4"]), 0x0E: ("SummaryOffset", [1, 8, 8]), 0x0F: ("DataEnd", [4]),
}
_RECORD_HEAD = 9  # opcode (1 byte) and length (8)
_RESERVED = 0x00  # no record has it: a zeroed or overwritten byte


def _fields_length(stream, start: int, length: int, present: int, layout: list) -> int | None:
    """What a record's fields add up to (as soon as they pass ``length``, the record's own), reading
    their length prefixes from the file; None when the record is cut before a prefix (then
    nothing can be told)."""
    offset = 0
    for field in layout:
        if offset > length:
            break
        if isinstance(field, int):
            offset += field
            continue
        width = int(field)
        if offset + width > present:
            return None
        stream.seek(start + offset)
        offset += width + int.from_bytes(stream.read(width), "little")
    return offset


def _walk(stream, size: int) -> tuple[list[tuple[int, str, int]], str | None, bool]:
    """The top-level records ``(offset, name, length)`` up to the first that is damaged or cut,
    and what is wrong with that one (None if none is), and whether it is cut short (a tear)
    rather than damaged. A file that ends with the MCAP magic was finished: nothing in it is a tear.
    Damage after a record longer than its fields is blamed on that record: its length is the
    likelier change than a later version's fields."""
    stream.seek(size - len(MAGIC))
    finished = size >= 2 * len(MAGIC) and stream.read(len(MAGIC)) == MAGIC
    records: list[tuple[int, str, int]] = []
    longer = None  # the first record longer than its fields, and what they add up to

    def damaged(problem: str) -> tuple[list[tuple[int, str, int]], str, bool]:
        if longer is not None:
            offset, name, length, fields = longer
            problem = (f"the {name} record at byte {offset} says it is {length} bytes long, but its fields add up "
                       f"to {fields}")
        return records, problem, False

    pos = len(MAGIC)
    while pos < size:
        if pos + _RECORD_HEAD > size:
            return records, f"it ends in the middle of the record at byte {pos}", not finished
        stream.seek(pos)
        opcode = stream.read(1)[0]
        length = int.from_bytes(stream.read(8), "little")
        if opcode == _RESERVED:
            return damaged(f"the record at byte {pos} is of no MCAP type (opcode 0x{opcode:02x})")
        name, layout = _LAYOUTS.get(opcode, (f"opcode 0x{opcode:02x}", None))
        present = min(length, size - pos - _RECORD_HEAD)
        fields = None if layout is None else _fields_length(stream, pos + _RECORD_HEAD, length, present, layout)
        if fields is not None and fields > length:
            return damaged(f"the {name} record at byte {pos} says it is {length} bytes long, but its fields add up "
                           "to more")
        if fields is not None and fields < length and longer is None:
            longer = (pos, name, length, fields)
        if pos + _RECORD_HEAD + length > size:
            problem = (f"it ends in the middle of the {name} record at byte {pos} ({present} of its {length} bytes "
                       "are there)")
            return (records, problem, True) if not finished else damaged(problem)
        records.append((pos, name, length))
        if opcode == 0x02:  # the footer: the magic follows, and the file ends
            after = size - (pos + _RECORD_HEAD + length)
            if not finished and after < len(MAGIC):
                return records, f"it ends {len(MAGIC) - after} bytes short of its closing magic bytes", True
            break
        pos += _RECORD_HEAD + length
    else:
        if not finished and records:  # whole records, then nothing: a writer stopped between two of them
            offset, name, _ = records[-1]
            return records, (f"it ends with the {name} record at byte {offset}, whole, without the summary "
                             "and closing magic bytes a finished log has"), True
        if finished and longer is not None:  # no footer where the records lead: one of them was changed
            return damaged("")
    return records, None, False


def _diagnose(stream, size: int, where: int, error: Exception) -> str:
    """Why reading stopped at byte ``where``: a tear (the writer was stopped) or damage (a byte
    changed after it was written), and at which record."""
    records, problem, torn = _walk(stream, size)
    if problem is not None and torn:
        return f"{problem}: its writer was stopped before finishing"
    if problem is not None:
        return f"it is corrupt: {problem}; the file was damaged after it was written (this is not a stopped writer)"
    at = next(((offset, name) for offset, name, length in reversed(records) if offset <= where), None)
    record = f"the {at[1]} record at byte {at[0]}" if at else f"byte {where}"
    what = (f"a CRC check failed ({error})" if isinstance(error, CRCValidationError)
            else f"a record cannot be parsed ({type(error).__name__}: {error})")
    return f"it is corrupt at {record}: {what}; the file was damaged after it was written"


def _take(log: LogHead, record: Any) -> None:
    """Keep a record other than a message (``_read`` hands those on)."""
    if isinstance(record, Channel):
        log.channels[record.id] = LogChannel(record.id, record.topic, record.message_encoding, dict(record.metadata),
                                             record.schema_id)
    elif isinstance(record, Schema):
        log.schemas[record.id] = record
    elif isinstance(record, Attachment):
        log.attachments[record.name] = record
    elif isinstance(record, Metadata):
        log.metadata[record.name] = dict(record.metadata)
    elif isinstance(record, Header):
        log.profile = record.profile
    elif isinstance(record, Footer):
        log.complete = True


def _damaged(log: LogHead, salvage: bool, why: str, read: int) -> None:
    log.damage = f"{why} ({read} messages read before it)"
    if not salvage:
        raise LogError(f"{log.path} cannot be read: {log.damage}",
                       f"`retriever log recover {log.path}` writes a readable copy of everything before the damage"
                       if read else
                       f"no message comes before the damage: `retriever log recover {log.path}` can keep only "
                       "the run's metadata")


def run_info(log: RunLog) -> dict[str, Any]:
    """The figures ``retriever log info`` prints."""
    counts: dict[str, int] = {}
    span: dict[str, list[int]] = {}
    by_channel = log.channels
    for m in log.messages:
        topic = by_channel[m.channel_id].topic
        counts[topic] = counts.get(topic, 0) + 1
        lo_hi = span.setdefault(topic, [m.log_time, m.log_time])
        lo_hi[0], lo_hi[1] = min(lo_hi[0], m.log_time), max(lo_hi[1], m.log_time)
    statuses: dict[str, dict[str, int]] = {}
    for s in log.iter_steps():
        node = statuses.setdefault(s.node, {})
        node[s.status] = node.get(s.status, 0) + 1
    try:
        packages = json.loads(log.run.get("packages", "{}") or "{}")
    except ValueError:
        packages = None
    if type(packages) is not dict or not all(type(v) is str for v in packages.values()):
        raise LogError(f"{log.path}: the run record's packages are not a JSON object of versions",
                       "the file is damaged: retriever log recover")
    return {"counts": counts, "span": span, "statuses": statuses, "packages": packages}


class LoggedTrace(Trace):
    """The trace of a logged run that kept only counters (``keep="counters"``): read back from
    its log the first time anything asks for it, then held like any trace."""

    def __init__(self, path) -> None:  # noqa: D107 (no Trace.__init__: the records come from the log)
        self.log_path = path
        self._read: Trace | None = None

    def _load(self) -> Trace:
        if self._read is None:
            self._read = read_log(self.log_path).trace()
        return self._read

    def __getattr__(self, name: str) -> Any:
        # everything a Trace holds (raw_events, raw_steps, keep, values_kept, the caches) is the read one's
        if name.startswith("__") or name in ("log_path", "_read"):
            raise AttributeError(name)
        return getattr(self._load(), name)

    def __repr__(self) -> str:
        return f"<Trace read back from {self.log_path} (keep='counters')>"
