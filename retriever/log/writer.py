"""``LogWriter``: stream a run's trace into an MCAP file as the run goes.

A session calls :meth:`LogWriter.write` with its trace about every 20 ms of wall time (at most
every 4096 steps, see ``Session.write_log``); each call encodes the records appended since the last. The chunk is closed and the file flushed at
least every ``flush_interval`` seconds of wall time, which bounds what a ``kill -9`` can take.
From its first write on, the trace's tape expanders make the records they can
(``Trace.log_records``: a compiled in-process tick's step record, in two ``struct.pack``s, and
its event's if the value is a float or an int of up to 32 bits, in two more); the writer makes
the others, a generic tick's step record of the common shape the same way (step_record_maker),
the rest with msgpack; and the other events, an array of a dtype and shape seen before on its
port in one ``struct.pack`` with its bytes (benchmarks/reports/logging_overhead.md).
"""

from __future__ import annotations

import errno
import functools
import json
import os
import stat
import struct
import time
from contextlib import contextmanager
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Iterable, Iterator

import msgpack
import numpy as np
from mcap.opcode import Opcode

from ..codec import Encoder, array_encoding_head
from ..errors import CodecError, LogError, LogWriteError
from ..ir import port_name_problem
from ..trace import StepStatus
from . import format as fmt
from .mcap_records import MESSAGE_FIELDS, MESSAGE_HEAD
from .mcap_writer import McapWriter

if TYPE_CHECKING:
    from ..graph import Graph
    from ..trace import Trace


#: an event's data is msgpack ``[microstep, value]``: a fixarray of 2 (this byte), then, almost always,
#: a fixint microstep (< 128), which _EVENT_HEAD packs with the Message record's head in one call
_FIXARRAY_2 = 0x92
#: a Message record's sequence is 32 bits: an index or a seq past them is logged as its low 32 bits
_U32 = 0xFFFFFFFF
_EVENT_HEAD = struct.Struct(MESSAGE_HEAD.format + "BB")
_HEAD_FIXED = 1 + 8 + 2  # a Message record's opcode, record length and channel id: the head's first bytes
#: a Message record's head as those first bytes (fixed for a kind of record on a channel), then its
#: sequence, log time and publish time
_FIXED_HEAD = struct.Struct(f"<{_HEAD_FIXED}sIQQ")
#: the most bytes of an event's data the tape's expanders make (``[microstep, value]`` of a float: a
#: fixarray, a fixint, a float 64's head and 8 bytes)
_EVENT_DATA_MAX = 1 + 1 + 1 + 8
# what became of the run when its log could not be written
RUN_NOT_STARTED = "the run did not start"
RUN_STOPPED = "the run was stopped, and the file holds only what was written before"
RUN_UNFINISHED_LOG = "the run ended, but its log is incomplete"
#: an array value at least this big is logged without joining its bytes (LogWriter._add_large_event)
LARGE_VALUE_BYTES = 1 << 20
#: the most (port, shape) of array values whose record's struct the writer keeps
MAX_ARRAY_HEADS = 1024
#: a port's last array (LogWriter._last_array) before it had one: no dtype is None
_NO_ARRAY = (None, None, None, None, None)


def describe_os_error(e: OSError) -> str:
    """``No space left on device (ENOSPC)``: what the OS said, and the name to search for."""
    name = errno.errorcode.get(e.errno or 0)
    return f"{e.strerror or e}" + (f" ({name})" if name else "")


def _folder(path: Path) -> tuple[str, str]:
    return (f"cannot create the log {path}: it is a folder",
            f"pass --log / log= a file path, e.g. {path / 'run.mcap'}")


def step_record_maker(graph: "Graph", node: str, channel: int | None, otherwise: Callable[[tuple, int], Any],
                      wall_bytes: int = 8) -> Callable[[tuple, int], Any]:
    """``make(step, sequence)``: the Message record of ``step``, a step record of ``node`` (a
    generic tick's, which no tape expander made), the log's step record ``sequence`` (its low 32
    bits), on ``channel``; with ``channel`` None, the record's data alone (``sequence`` unused).
    One of the common shape: ``ok``, no detail, a microstep below 128, one event on the node's one
    output, and one event consumed on each input port that one edge of ``graph`` feeds, no more,
    is made here; any other by ``otherwise(step, sequence)`` (msgpack, in the writer).
    ``otherwise`` itself for a node that has no such shape (other than one output, an input fed
    by two edges, or more than two fed). As the tape expanders do (Trace.log_records): the
    msgpack data in one ``struct.pack`` of the bytes fixed here and the ints that change, each in
    a fixed width (uint32 seqs, uint64 wall time: read back the same). With ``wall_bytes=4``, a
    wall time below 2**32 ns only (the uint64's first 4 bytes fixed zeros: a uint32's pack costs
    ~100 instructions less), any other step to ``otherwise``. (The writer's comprehension calls it
    with the step tuple whole: unpacked here, its fields are fast locals of one frame, not
    arguments passed one by one, benchmarks/reports/logging_overhead.md.) Also ``--resim``'s way
    of telling a logged record the same as the session's (replay/resimulation.py: the data alone,
    ``otherwise`` giving None): one maker of the layout, written and compared."""
    spec = graph.nodes[node]
    fed = []  # the ports in the order a tick consumes them, each with its edge's source node and port
    for port in spec.inputs:
        edges = [(edge.src, edge.src_port) for edge in graph.edges if edge.dst == node and edge.dst_port == port]
        if len(edges) > 1:
            return otherwise
        fed += [(port, *edge) for edge in edges]
    if len(spec.outputs) != 1 or len(fed) > 2:
        return otherwise
    output, = spec.outputs
    pack = functools.partial(msgpack.packb, use_bin_type=True)
    consts = [b"\x97" + pack(node), bytes((0x80 | len(fed),))]  # then the microstep, a fixint
    for port, src, src_port in fed:
        consts[-1] += pack(port) + b"\x91\x93" + pack(src) + pack(src_port) + b"\xce"
        consts.append(b"")  # then the seq of the event consumed, a uint32
    consts[-1] += b"\x91\x93" + pack(node) + pack(output) + b"\xce"
    consts.append(pack(StepStatus.OK.value) + b"\xc0\xcf" + bytes(8 - wall_bytes))  # then the wall time, a uint64
    wall_format = {8: "Q", 4: "I"}[wall_bytes]
    data = struct.Struct(">" + "".join(f"{len(c)}s{i}" for c, i in zip(consts, ["B", *"I" * len(fed), "I", wall_format])))
    # the Message record's head: its opcode, length and channel id fixed here, then the ints that change
    fixed = None if channel is None else _fixed_head(MESSAGE_FIELDS + data.size, channel)
    head_pack = _FIXED_HEAD.pack
    ok, errors = StepStatus.OK, (ValueError, TypeError, KeyError, struct.error)
    data_pack = data.pack
    # (an int out of its field's range is a struct.error; a consumed or produced of another length, or
    # a step of another length, a ValueError; a consumed without the port a KeyError)
    if not fed:
        c0, c1, c2 = consts

        def make(step, sequence):
            try:
                _, tag, consumed, produced, status, detail, start, wall = step
                if status is ok and detail is None and not consumed and tag[1] < 128:
                    (n, p, s), = produced
                    if n == node and p == output:
                        if fixed is not None:
                            return head_pack(fixed, sequence, tag[0], start) + data_pack(c0, tag[1], c1, s, c2, wall)
                        return data_pack(c0, tag[1], c1, s, c2, wall)
            except errors:
                pass
            return otherwise(step, sequence)
    elif len(fed) == 1:
        (port0, src0, src_port0), = fed
        c0, c1, c2, c3 = consts

        def make(step, sequence):
            try:
                _, tag, consumed, produced, status, detail, start, wall = step
                if status is ok and detail is None and tag[1] < 128 and len(consumed) == 1:
                    (a0, b0, s0), = consumed[port0]
                    (n, p, s), = produced
                    if a0 == src0 and b0 == src_port0 and n == node and p == output:
                        if fixed is not None:
                            return head_pack(fixed, sequence, tag[0], start) + data_pack(
                                c0, tag[1], c1, s0, c2, s, c3, wall)
                        return data_pack(c0, tag[1], c1, s0, c2, s, c3, wall)
            except errors:
                pass
            return otherwise(step, sequence)
    else:
        (port0, src0, src_port0), (port1, src1, src_port1) = fed
        c0, c1, c2, c3, c4 = consts

        def make(step, sequence):
            try:
                _, tag, consumed, produced, status, detail, start, wall = step
                if status is ok and detail is None and tag[1] < 128:
                    p0, p1 = consumed
                    (a0, b0, s0), = consumed[p0]
                    (a1, b1, s1), = consumed[p1]
                    (n, p, s), = produced
                    if (p0 == port0 and a0 == src0 and b0 == src_port0 and p1 == port1 and a1 == src1
                            and b1 == src_port1 and n == node and p == output):
                        if fixed is not None:
                            return head_pack(fixed, sequence, tag[0], start) + data_pack(
                                c0, tag[1], c1, s0, c2, s1, c3, s, c4, wall)
                        return data_pack(c0, tag[1], c1, s0, c2, s1, c3, s, c4, wall)
            except errors:
                pass
            return otherwise(step, sequence)
    return make


def sequences(first: int, count: int) -> Iterable[int]:
    """The sequences of the Message records of ``count`` step records from the log's ``first``:
    each index's low 32 bits (a record's sequence is a uint32). A range while they do not wrap,
    with no ``&`` a record (~150 instructions each, benchmarks/reports/logging_overhead.md)."""
    start = first & _U32
    if start + count <= _U32 + 1:
        return range(start, start + count)
    return map(_U32.__and__, range(first, first + count))


def _fixed_head(length: int, channel: int) -> bytes:
    """The first bytes of a Message record's head (_FIXED_HEAD): opcode, record length, channel."""
    return MESSAGE_HEAD.pack(Opcode.MESSAGE, length, channel, 0, 0, 0)[:_HEAD_FIXED]


@functools.cache
def _event_heads(channel: int) -> tuple[bytes, ...]:
    """The fixed first bytes of the heads of event records on ``channel``, by their data's size
    (asked for at each hand-over of the trace to the writer, by each node's expander)."""
    return tuple(_fixed_head(MESSAGE_FIELDS + size, channel) for size in range(_EVENT_DATA_MAX + 1))


@functools.cache
def _step_fixed_head(size: int, channel: int) -> bytes:
    return _fixed_head(MESSAGE_FIELDS + size, channel)


@functools.cache
def _record_pack(data_format: str) -> Callable[..., bytes]:
    """``pack(fixed, sequence, log time, publish time, *data)``: a whole Message record, its data of
    ``data_format`` (little-endian: a format of bytes only, which have no byte order)."""
    return struct.Struct(_FIXED_HEAD.format + data_format).pack


class LogFile:
    """The file a run's log goes to, opened before the run starts, so that a path that cannot be
    a log (it exists, it is a folder, its folder is missing or read-only) is refused before any
    worker starts and before anything is written.

    An existing file is kept unless ``overwrite``; even then it is emptied only when the writer
    starts (:meth:`start`), so a run refused before its start leaves it untouched.
    """

    def __init__(self, path: str | Path, *, overwrite: bool = False):
        self.path = Path(path)
        existed = os.path.lexists(self.path)
        flags = os.O_WRONLY | os.O_CREAT | os.O_CLOEXEC | (0 if overwrite else os.O_EXCL)
        try:
            fd = os.open(self.path, flags, 0o666)
        except FileExistsError:
            if self.path.is_dir():
                raise LogError(*_folder(self.path)) from None
            raise LogError(f"the log {self.path} already exists; a run does not overwrite a file",
                           "pass --force (retriever run) or overwrite=True (pipe.run) to replace it, "
                           "or log to another path") from None
        except IsADirectoryError:
            raise LogError(*_folder(self.path)) from None
        except OSError as e:
            raise LogError(f"cannot create the log {self.path}: {describe_os_error(e)}",
                           "pass --log / log= a path in a folder that exists and is writable") from None
        self.stream = os.fdopen(fd, "wb")
        self.regular = stat.S_ISREG(os.fstat(fd).st_mode)
        self._remove_on_discard = self.regular and not existed

    def start(self) -> None:
        """The writer takes the file: empty it (a file being overwritten)."""
        if self.regular:
            self.stream.truncate(0)
            self._remove_on_discard = True

    def discard(self) -> None:
        """The run did not start, or its log could not be begun: close the file and remove what
        this run created or emptied, so that no file claims to hold the run."""
        try:
            self.stream.close()
        except OSError:  # the buffered bytes the OS refused (ENOSPC, EIO): nothing is kept anyway
            pass
        if self._remove_on_discard:
            self.path.unlink(missing_ok=True)


class LogWriter:
    """Writes one run to ``file``: the IR and run metadata first, then events and steps.

    The first records reach the OS before the constructor returns, so a file that takes no data
    (a full disk, ``/dev/full``) fails here, before the run starts. A write that fails later
    raises :class:`LogWriteError` from :meth:`write` (at most ``flush_interval`` after it), which
    stops the run.
    """

    def __init__(self, file: LogFile, graph: "Graph", *, backend: str, seeds: dict[str, Any] | None = None,
                 flush_interval: float = 0.1, extra: dict[str, str] | None = None):
        self.path = file.path
        file.start()
        self._file = file.stream
        version = fmt.package_versions().get("retriever", "dev")
        self._mcap = McapWriter(self._file, profile=fmt.PROFILE, library=f"retriever {version}")
        self.closed = False
        self.failed = False
        # the trace whose expanders make records (Trace.log_records), once the first write began it
        self._step_log: "Trace | None" = None
        with self._refused_writes(RUN_NOT_STARTED):
            self._mcap.add_attachment(fmt.IR_ATTACHMENT, "application/json", graph.to_ir().to_json().encode())
            modules = sorted({type(node.flow).__module__ for node in graph.nodes.values()})
            self._mcap.add_metadata(fmt.RUN_METADATA, {**fmt.run_metadata(graph.name, backend, seeds or {},
                                                                           time.time_ns(), modules), **(extra or {})})
            # by node, then port, then shape of an array value: (its dtype, the struct.pack of its event's
            # whole record, the bytes fixed in its head, its encoding's head, the shape), the latest dtype
            # seen in that shape; at most MAX_ARRAY_HEADS in all
            self._array_heads: dict[str, dict[str, dict[tuple, tuple[Any, Callable[..., bytes], bytes, bytes, tuple]]]] = {}
            self._array_heads_kept = 0
            # by node, then port: the one of those last made (_NO_ARRAY: none yet), which an array of
            # its dtype and shape finds with no dict lookup by its shape, which costs
            self._last_array: dict[str, dict[str, tuple]] = {}
            self._channels: dict[tuple[str, str], int] = {}
            self._channel_of: dict[str, dict[str, int]] = {}  # the same, by node then port (no tuple to make)
            for node in sorted(graph.nodes.values(), key=lambda n: n.id):
                for port, spec in node.outputs.items():
                    self._add_channel(node.id, port, spec.type)
            self._steps_channel = self._mcap.add_channel(fmt.STEPS_TOPIC, fmt.MESSAGE_ENCODING, {})
            self._mcap.flush()
            self._mcap.wait()
        self._events_done = 0  # of the trace's events (in recording order), how many are written
        self._steps_done = 0
        # records written and then dropped from the trace (keep="counters": release()), before those
        self._events_released = 0
        self._steps_released = 0
        self.last_bytes = 0  # the events' bytes of the last write() that had events
        self._faults = 0
        self._starved = 0
        self._encode = Encoder().pack
        self._pack_step = msgpack.Packer(use_bin_type=True).pack
        self._flush_interval = flush_interval
        self._last_flush = time.monotonic()
        # by node: what makes the step records of its generic ticks (those of the common shape in
        # two struct.packs, step_record_maker; the others with msgpack, _packed_step_record)
        self._step_makers = {node.id: self._step_maker(graph, node.id) for node in graph.nodes.values()}

    def _step_maker(self, graph: "Graph", node: str) -> Callable[[tuple, int], bytes]:
        """step_record_maker for ``node``: a wall time below 2**32 ns (4.3 s) in a uint32's pack,
        else the uint64's, else (and for a node of another shape) _packed_step_record."""
        wide = step_record_maker(graph, node, self._steps_channel, self._packed_step_record)
        return step_record_maker(graph, node, self._steps_channel, wide, wall_bytes=4)

    @contextmanager
    def _refused_writes(self, outcome: str) -> Iterator[None]:
        """Turn the OS refusing a write (ENOSPC, EIO, EFBIG, ...) into a LogWriteError that names
        the file and says what became of the run; the writer then writes nothing more."""
        try:
            yield
        except OSError as e:
            self.failed = True
            self._stop_step_log()
            self._mcap.abandon()
            raise LogWriteError(f"cannot write the log {self.path}: {describe_os_error(e)}; {outcome}",
                                "log to a disk with room, or to a path that takes files"
                                + ("" if outcome == RUN_NOT_STARTED else
                                   f" (`retriever log recover {self.path}` salvages what reached it)")) from None

    def _add_channel(self, node: str, port: str, port_type: Any = None) -> int:
        # an untyped flow's step() may return a key compile_graph could not see: a channel the log's
        # readers would not take (format.data_topic_problem) is refused, not written
        problem = port_name_problem(port)
        if problem is not None:
            raise LogError(f"an event of {node} cannot be logged: the output port {problem}",
                           f"rename the key {node}'s step() returns, e.g. to letters, digits and _")
        type_name = "" if port_type is None else getattr(port_type, "__qualname__", str(port_type))
        channel = self._mcap.add_channel(fmt.data_topic(node, port), fmt.MESSAGE_ENCODING,
                                         {"node": node, "port": port, "type": type_name})
        self._channels[(node, port)] = channel
        self._channel_of.setdefault(node, {})[port] = channel
        self._array_heads.setdefault(node, {})[port] = {}
        self._last_array.setdefault(node, {})[port] = _NO_ARRAY
        return channel

    @property
    def events_written(self) -> int:
        """How many of the trace's events are in the log so far (in recording order)."""
        return self._events_done

    @property
    def disk_waits(self) -> tuple[int, int]:
        """How often adding records waited for the disk, and how long in all (ns)."""
        return self._mcap.waits, self._mcap.waited_ns

    @property
    def steps_total(self) -> int:
        """How many step records the log has so far."""
        return self._steps_released + self._steps_done

    def release(self, trace: "Trace") -> None:
        """Drop from ``trace`` what is written (``keep="counters"``): the log holds it now."""
        trace.discard(self._events_done, self._steps_done)
        self._events_released += self._events_done
        self._steps_released += self._steps_done
        self._events_done = self._steps_done = 0

    def write(self, trace: "Trace") -> None:
        """Encode the records appended to ``trace`` since the last call; flush if it is time.
        Raises :class:`LogWriteError` when the OS refused a write (the run must stop)."""
        with self._refused_writes(RUN_STOPPED):
            self._write(trace)

    def _write(self, trace: "Trace") -> None:
        """One comprehension per kind builds whole MCAP message records: this runs for every event
        and step of a logged run, so it avoids every intermediate object it can.
        """
        if self._step_log is not trace:  # the first hand-over: from here on, expanders make records
            self._stop_step_log()
            trace.log_records(_FIXED_HEAD.pack, self._step_fixed_head, self._event_heads, _record_pack)
            self._step_log = trace
        made, made_from, n_steps, made_events, made_events_from, n_events = trace.take_log(
            self._events_released, self._steps_released)
        events, steps = trace.raw_events, trace.raw_steps
        if n_events > self._events_done:
            self.last_bytes = 0
            new_events = events[self._events_done:n_events]
            if (made_events_from != self._events_released + self._events_done or len(made_events) != len(new_events)
                    or made_events.count(None) == len(made_events)):
                made_events = None  # none made (as for step records below)
            self._add_events(new_events, made_events)
            self._events_done = n_events
        if n_steps > self._steps_done:
            new = steps[self._steps_done:n_steps]
            first = self._steps_released + self._steps_done
            if made_from != first or len(made) != len(new) or made.count(None) == len(made):
                # none made: a trace expanded before the log began, or not through a tape (another
                # backend's), or records of other shapes
                records = self._step_records(new, first)
            elif None in made:
                records = self._step_records(new, first, made)
            else:
                records = made
            self._mcap.add_records(records)
            self._steps_done = n_steps
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval:
            self._mcap.flush()
            self._last_flush = now

    def _step_records(self, steps: list[tuple], first: int, made: list[bytes | None] | None = None) -> list[bytes]:
        """The Message records of ``steps``, the first the log's step record ``first``; with
        ``made``, those of them that are not None as they are (Trace.take_log)."""
        makers = self._step_makers  # by node: a record of its common shape in two packs, else msgpack
        try:
            if made is None:
                return [makers[step[0]](step, sequence) for sequence, step in zip(sequences(first, len(steps)), steps)]
            return [record or makers[step[0]](step, sequence)
                    for sequence, record, step in zip(sequences(first, len(steps)), made, steps)]
        except KeyError:  # a node the graph did not have when the writer began (none does): msgpack
            missing = {step[0] for step in steps} - makers.keys()
            if not missing:
                raise
            makers.update(dict.fromkeys(missing, self._packed_step_record))
            return self._step_records(steps, first, made)

    def _packed_step_record(self, step: tuple, sequence: int) -> bytes:
        """The Message record of ``step``, the log's step record ``sequence``, its data packed by msgpack."""
        node, tag, consumed, produced, status, detail, start, wall = step
        data = self._pack_step((node, tag[1], consumed, produced, status, detail, wall))
        return MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data), self._steps_channel, sequence, tag[0],
                                 start) + data

    def _step_fixed_head(self, size: int) -> bytes:
        """The fixed first bytes of the head of a step record whose data is ``size`` bytes
        (Trace.log_records)."""
        return _step_fixed_head(size, self._steps_channel)

    def _event_heads(self, node: str, port: str) -> tuple[bytes, ...] | None:
        """The fixed first bytes of the heads of the records of events on ``node.port``, by the
        size of their data (up to _EVENT_DATA_MAX); None when the log has no channel for it yet
        (the writer makes those records, and the channel, in the order the events came)
        (Trace.log_records)."""
        channel = self._channel_of.get(node, {}).get(port)
        return None if channel is None else _event_heads(channel)

    def _stop_step_log(self) -> None:
        if self._step_log is not None:
            self._step_log.stop_log()
            self._step_log = None

    def _add_events(self, new: list[tuple], made: list[bytes | None] | None = None) -> None:
        """The Message records of ``new`` events, in recording order; with ``made``, those of
        them that are not None as they are (Trace.take_log); a big array's in a chunk of its own
        (_add_large_event)."""
        if made is None:
            records = self._event_records(new)
        elif None in made:
            left = [i for i, record in enumerate(made) if record is None]
            records = made
            for i, record in zip(left, self._event_records([new[i] for i in left])):
                records[i] = record
        else:  # all made: no big array among them
            self._add_small_events(made)
            return
        if None in records:
            begin = 0
            for i in [i for i, record in enumerate(records) if record is None]:
                self._add_small_events(records[begin:i])
                self._add_large_event(new[i])
                begin = i + 1
            records = records[begin:]
        self._add_small_events(records)

    def _event_records(self, new: list[tuple]) -> list[bytes | None]:
        """The Message records of ``new`` events; None for a big array's (_add_large_event)."""
        head, op, fields, ndarray = _EVENT_HEAD.pack, Opcode.MESSAGE, MESSAGE_FIELDS + 2, np.ndarray
        channel_of, encode, array_heads, last_array = self._channel_of, self._encode, self._array_heads, self._last_array
        try:
            # an array of a dtype and shape seen before on its port: its record in one struct.pack
            # with its bytes; any value but an array: its head in one, then the value encoded
            # (its dtype the very one seen last in its shape: no hash of a dtype, which costs; the
            # port's last array's dtype and shape first: no hash of the shape either)
            # (a seq past 32 bits: struct.error, then again with the low 32 bits, the log's sequence)
            records = [array[1](array[2], seq, tag[0], published, _FIXARRAY_2, tag[1], array[3],
                                value.tobytes())
                       if type(value) is ndarray and tag[1] < 128
                       and ((array := last_array[node][port])[0] is value.dtype and array[4] == value.shape
                            or (array := array_heads[node][port].get(value.shape)) and array[0] is value.dtype)
                       else head(op, fields + len(value_data := encode(value)), channel_of[node][port], seq,
                                 tag[0], published, _FIXARRAY_2, tag[1]) + value_data
                       if type(value) is not ndarray and tag[1] < 128
                       else self._event_record(tag, node, port, seq, value, published)
                       for tag, node, port, seq, value, published in new]
        except CodecError:
            raise self._unencodable(new) from None
        except struct.error:
            if all(0 <= seq <= _U32 for _, _, _, seq, _, _ in new):
                raise
            return self._event_records([(tag, node, port, seq & _U32, value, published)
                                        for tag, node, port, seq, value, published in new])
        except KeyError:  # a port no event came from before (an untyped flow's): its channel, then again
            added = [self._add_channel(node, port) for _, node, port, *_ in new
                     if port not in channel_of.get(node, ())]
            if not added:
                raise
            return self._event_records(new)
        return records

    def _add_small_events(self, records: list[bytes]) -> None:
        self.last_bytes += self._mcap.add_records(records)

    def _event_record(self, tag: tuple[int, int], node: str, port: str, seq: int, value: Any,
                      published: int) -> bytes | None:
        """The Message record of an event the comprehension in _event_records does not make: an
        array of a shape not seen before on its port, or of another dtype object than the one
        seen last in that shape (which it makes from then on), or a big one
        (None: _add_large_event makes it), or any value at a microstep of 128 or more (not a
        msgpack fixint)."""
        channel = self._channels.get((node, port)) or self._add_channel(node, port)
        if type(value) is np.ndarray:
            if value.nbytes >= LARGE_VALUE_BYTES:
                return None
            if tag[1] < 128:
                heads = self._array_heads[node][port]
                array = heads.get(value.shape)
                if array is None or array[0] != value.dtype:
                    value_head = array_encoding_head(value)
                    array = (value.dtype, struct.Struct(f"{_FIXED_HEAD.format}BB{len(value_head)}s{value.nbytes}s").pack,
                             _fixed_head(MESSAGE_FIELDS + 2 + len(value_head) + value.nbytes, channel), value_head,
                             value.shape)
                else:  # an equal dtype, another object: this one is checked by identity from now on
                    array = (value.dtype, *array[1:])
                if value.shape in heads or self._array_heads_kept < MAX_ARRAY_HEADS:
                    self._array_heads_kept += value.shape not in heads
                    heads[value.shape] = array
                    self._last_array[node][port] = array
                return array[1](array[2], seq & _U32, tag[0], published, _FIXARRAY_2, tag[1], array[3],
                                value.tobytes())
        data = self._encode([tag[1], value])
        return MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data), channel, seq & _U32, tag[0],
                                 published) + data

    def _add_large_event(self, event: tuple) -> None:
        """An event whose value is a big array: its record is assembled in one buffer into which
        numpy copies the array once (joining bytes would hold the GIL for as long as the copy
        takes, and the run's other threads, a coordinator's answers among them, would wait)."""
        (log_time, microstep), node, port, seq, value, published = event
        try:
            value_head = array_encoding_head(value)
        except CodecError:
            raise self._unencodable([event]) from None
        data_head = bytes((_FIXARRAY_2,)) + self._encode(microstep) + value_head
        channel = self._channels.get((node, port)) or self._add_channel(node, port)
        head = MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data_head) + value.nbytes, channel,
                                 seq & _U32, log_time, published) + data_head
        record = np.empty(len(head) + value.nbytes, dtype=np.uint8)
        record[:len(head)] = np.frombuffer(head, dtype=np.uint8)
        np.copyto(record[len(head):].view(value.dtype).reshape(value.shape), value)
        self._mcap.add_large_record(record)
        self.last_bytes += len(record)

    def add_fault(self, fault: dict) -> None:
        """Log what went wrong with one of the run's processes (``retriever.fault.N``): its text
        fields as they are, the rest as JSON."""
        self._faults += 1
        record = {key: value if type(value) is str else json.dumps(value, sort_keys=True)
                  for key, value in fault.items()}
        with self._refused_writes(RUN_STOPPED):
            self._mcap.add_metadata(f"{fmt.FAULT_METADATA}{self._faults}", record)

    def add_starved(self, episode: dict) -> None:
        """Log a span in which an input of a flow had no event while its producers made some
        (``retriever.starved.N``, starved.StarvationWatch): its text fields as they are, the rest as JSON."""
        self._starved += 1
        record = {key: value if type(value) is str else json.dumps(value, sort_keys=True)
                  for key, value in episode.items()}
        with self._refused_writes(RUN_STOPPED):
            self._mcap.add_metadata(f"{fmt.STARVED_METADATA}{self._starved}", record)

    def _unencodable(self, events: list[tuple]) -> LogError:
        for tag, node, port, seq, value, _ in events:
            try:
                self._encode(value)
            except CodecError as e:
                return LogError(f"event {node}.{port} #{seq} (at t={tag[0] / 1e9:g} s) cannot be logged: {e}",
                                f"make {node}.{port} carry numbers, str, bytes, lists, dicts, numpy arrays "
                                "or @io dataclasses")
        return LogError("an event cannot be logged (the codec refused a value it later accepted)")

    def close(self, trace: "Trace", end_ns: int, *, status: fmt.RunEnd = fmt.RunEnd.FINISHED, error: str = "",
              stats: dict | None = None, counts: dict | None = None) -> None:
        """Write what is left and the ``retriever.end`` record, then finish the file. The run
        ends at ``end_ns`` or at its latest step record's tick, whichever is later (a stopped
        real-time run's records may come after the time it reached)."""
        if self.closed:
            return
        self.closed = True
        try:
            if not self.failed:
                with self._refused_writes(RUN_UNFINISHED_LOG):
                    self._finish(trace, end_ns, status, error, stats, counts)
                    self._file.close()
        finally:
            self._stop_step_log()
            if not self._file.closed:
                try:
                    self._file.close()
                except OSError:  # bytes the OS refused: the failure was already raised
                    pass

    def _finish(self, trace: "Trace", end_ns: int, status: fmt.RunEnd, error: str, stats: dict | None,
                counts: dict | None) -> None:
        try:
            self._write(trace)
        finally:  # a value the codec refused still leaves a finished log that says so
            end_ns = max(end_ns, self._mcap.channel_end_time(self._steps_channel))
            end = {"status": status, "end_ns": str(end_ns), "events": str(self._events_released + self._events_done),
                   "steps": str(self.steps_total), "finished_unix_ns": str(time.time_ns())}
            if error:
                end["error"] = error
            if stats:
                # a node's real-time counters only when it has some: in-process logs stay as they were
                end["stats"] = json.dumps({node: {k: v for k, v in vars(s).items() if v or k != "counts"}
                                           for node, s in sorted(stats.items())}, sort_keys=True)
            if counts:
                end["counts"] = json.dumps({name: n for name, n in sorted(counts.items()) if n})
            self._mcap.add_metadata(fmt.END_METADATA, end)
            self._mcap.finish()
