"""The replay's first pass over a log: what it must know of the whole log before its first step."""

from __future__ import annotations

import bisect
from pathlib import Path
from typing import Any

import msgpack
import numpy as np

from ..errors import LogError
from ..log import format as fmt
from ..log.reader import ChunkMessages
from ..time import format_tag
from ..trace import DETAIL_KEYS


#: the hint of a LogError for a log whose records do not add up (an event twice, one a record cannot have produced)
DAMAGED = "the file is damaged or was edited: retriever replay reads logs as a run wrote them"
#: why a step record cannot have produced an event it names (:func:`not_its_event`)
NOT_IN_LOG = "which the log does not have"
NAMED_BEFORE = "which an earlier step record said it produced too (a record logged twice?)"


def not_its_event(path: Path, step: tuple, event_id: tuple, which: str) -> LogError:
    """A source's step record (a StepRecord, or the plain tuple of its fields) names an event it
    cannot have produced (``which``: NOT_IN_LOG, NAMED_BEFORE): the log is refused."""
    node, port, seq = event_id
    return LogError(f"{path}: the step record of {step[0]} at {format_tag(step[1])} says it produced event "
                    f"{node}.{port} #{seq}, {which}", DAMAGED)


def no_record_of(path: Path, event_id: tuple) -> LogError:
    """An event of the log that no step record of its node says it produced (a source's, which a
    replay takes from the log as its records name them): the log is refused."""
    node, port, seq = event_id
    return LogError(f"{path}: event {node}.{port} #{seq} is in the log, but no step record of {node} says it "
                    "produced it", DAMAGED)


class LogSurvey:
    """What a replay must know of the whole log before its first step, gathered from its
    messages in one pass in file order (as the file is checked, or from a read log's list), in
    memory that grows with what was unusual in the run, not with its length: the nodes that
    have steps and how many steps; which event ids the log holds (per port, ranges of seqs: one
    range for a port whose events all are there), so an event logged twice is found; the events
    that reached a consumer late, the incomplete ticks' views and the restart gaps (the step
    records' ``late``, ``had_below`` and ``restart_gap``). A record with detail that is not one
    is kept as the error the replay raises before its first step; one without detail (nearly
    all: only its node is read here) the replay refuses where it reads it, with the same error,
    checking it whole unless it was found plain here (``unchecked``). With ``check_steps`` (the
    re-simulation's survey), every step record is checked here, as ``format.decode_step`` checks
    it, and the first that is not one kept as the error."""

    def __init__(self, path: Path, max_unchecked: int = 65_536, *, check_steps: bool = False) -> None:
        self.path = path
        self.check_steps = check_steps
        self.nodes: set[str] = set()
        self.steps = 0
        self.seqs: dict[tuple[str, str], _Seqs] = {}
        #: ((consumer, port), event id) -> the tag of the consumer's record that names it late
        self.late: dict[tuple[tuple[str, str], tuple[str, str, int]], tuple[int, int]] = {}
        self._views: dict[tuple[tuple[str, str], str, str], list] = {}
        self.gaps: dict[tuple[str, str], list[tuple[str, str, int, int]]] = {}
        #: (node, detail key, what it names) -> (tag, sequence) of the first record of the node that names
        #: it: a key of no writer's (what: None), a stream into an input port ((port, producer, its
        #: port)) or an output port ((port,), ``restarted``'s seqs), which the pipeline must have
        #: (:meth:`check_details`)
        self._named: dict[tuple[str, str, tuple | None], tuple[tuple[int, int], int]] = {}
        self.step_error: LogError | None = None
        self.event_error: LogError | None = None
        self.twice: LogError | None = None
        self._kinds: dict[int, Any] = {}  # channel id -> _STEPS, (node, port, seqs), or None
        #: the sequences of the step records not found plain here (_plain_steps): the replay checks
        #: these whole as it reads the file again (format.decode_step), the others for their status
        #: alone (format.decode_plain_step); None: every one whole (a chunk was taken as message
        #: tuples, or more than ``max_unchecked`` records were not found plain: memory it would hold)
        self.unchecked: set[int] | None = set()
        self.max_unchecked = max_unchecked

    def take(self, channels: dict, messages: list[tuple]) -> None:
        """Take ``messages``, message tuples in file order (log/reader.py), ``channels`` the log's by id."""
        kinds = self._kinds
        for log_time, _, channel_id, sequence, _, data in messages:
            kind = kinds.get(channel_id, _UNSEEN)
            if kind is _UNSEEN:
                kind = kinds[channel_id] = self._kind(channels[channel_id])
            if kind is _STEPS:
                self.unchecked = None
                self._step(log_time, sequence, data)
            elif kind is not None:
                node, port, seqs = kind
                if self.event_error is None:
                    try:
                        fmt.split_event(data)
                    except ValueError as e:
                        self.event_error = LogError(f"{self.path}: event {node}.{port} #{sequence} is malformed ({e})")
                hi = seqs.hi
                if hi and hi[-1] == sequence:  # the next one: the common case (_Seqs.add's first)
                    hi[-1] = sequence + 1
                elif not seqs.add(sequence) and self.twice is None:
                    self.twice = LogError(f"{self.path}: event {node}.{port} #{sequence} is logged twice", DAMAGED)

    def take_chunk(self, channels: dict, chunk: ChunkMessages) -> None:
        """Take a chunk's messages, as :func:`scan_log` hands them with ``take_chunk``: its events
        checked at once with numpy where each port's are framed as ``[microstep < 128, value]``
        and its seqs follow on (nearly always; a chunk with anything else is taken as message
        tuples, :meth:`take`, so the same is found and said), its step records without detail as
        Retriever writes nearly all of them told by their bytes, a length at a time (:func:`_shapes`),
        the rest parsed at once for their nodes (:func:`_plain_steps`),
        the others read one by one, in file order, as :meth:`take` reads them."""
        kinds = self._kinds
        heads, raw = chunk.heads, chunk.raw
        channel_ids = heads["channel_id"]
        found = np.flatnonzero(np.bincount(channel_ids)).tolist()
        for channel_id in found:
            if channel_id not in kinds:
                kinds[channel_id] = self._kind(channels[channel_id])
        if len(found) > 1:
            at = {channel_id: np.flatnonzero(channel_ids == channel_id) for channel_id in found}
        else:
            at = {found[0]: np.arange(len(channel_ids))}
        steps, ranges = [], []
        bytes_ = np.frombuffer(raw, dtype=np.uint8)
        for channel_id, which in at.items():
            kind = kinds[channel_id]
            if kind is _STEPS:
                steps.append(which)
            elif kind is not None:
                seqs = heads["sequence"][which]
                starts = chunk.offsets[which] + _DATA_AT
                framed = ((chunk.ends[which] - starts >= 3).all()
                          and (bytes_[starts] == 0x92).all() and (bytes_[starts + 1] < 0x80).all())
                first, last = int(seqs[0]), int(seqs[-1])
                hi = kind[2].hi
                # (a port on two channels, an edited log: its seqs are put in one by one, by take)
                if not framed or (hi and hi[-1] != first) or last - first != len(seqs) - 1 \
                        or any(taken is kind[2] for taken, _, _ in ranges) \
                        or (len(seqs) > 1 and (np.diff(seqs.astype(np.int64)) != 1).any()):
                    self.take(channels, chunk.tuples())
                    return
                ranges.append((kind[2], first, last))
        for seqs, first, last in ranges:
            if not seqs.hi:
                seqs.add(first)
            seqs.hi[-1] = last + 1
        if steps and self.step_error is None:
            which = steps[0] if len(steps) == 1 else np.sort(np.concatenate(steps))
            starts = chunk.offsets[which] + _DATA_AT
            padded = np.concatenate((bytes_, np.zeros(_PAD, dtype=np.uint8)))
            ends = chunk.ends[which]
            # the records of a shape seen (nearly all: _shapes), then the others parsed a field at a time
            shape, shape_nodes = _shapes(padded, starts, ends - starts, self.check_steps)
            rest = np.flatnonzero(shape < 0)
            plain = shape >= 0
            node_at = np.zeros(0, dtype=starts.dtype)
            if len(rest):
                rest_plain, node_at, status_at = _plain_steps(padded, starts[rest], ends[rest])
                if self.check_steps:
                    rest_plain &= _plain_statuses(padded, status_at)
                plain[rest] = rest_plain
            others = np.flatnonzero(~plain)
            step = self._step
            for other, log_time, sequence, data in zip(others.tolist(), heads["log_time"][which[others]].tolist(),
                                                       heads["sequence"][which[others]].tolist(),
                                                       chunk.data(which[others])):
                step(log_time, sequence, data)
                if self.step_error is not None:  # the records after it are not taken (as by take)
                    plain[other:] = False
                    break
            self.steps += int(plain.sum())
            self.nodes.update(shape_nodes[k] for k in np.unique(shape[plain]).tolist() if k >= 0)
            if len(rest):
                self.nodes.update(_names(padded, node_at[plain[rest]]))
            if len(others) and self.unchecked is not None:
                self.unchecked.update(heads["sequence"][which[~plain]].tolist())
                if len(self.unchecked) > self.max_unchecked:
                    self.unchecked = None

    def _kind(self, channel) -> Any:
        if channel.topic == fmt.STEPS_TOPIC:
            return _STEPS
        port = fmt.parse_data_topic(channel.topic)
        return None if port is None else (*port, self.seqs.setdefault(port, _Seqs()))

    def _step(self, log_time: int, sequence: int, data: bytes) -> None:
        if self.step_error is not None:
            return
        if not self.check_steps:
            # a record without detail tells the survey only its node: read, not checked (the replay's
            # own reading of it checks it, and refuses the log with the same error there)
            try:
                record = msgpack.unpackb(data, use_list=False)
            except Exception:
                record = None
            if type(record) is tuple and len(record) == 7 and record[5] is None and type(record[0]) is str:
                self.steps += 1
                self.nodes.add(record[0])
                return
        try:
            node, microstep, _, _, _, detail, _ = fmt.decode_step(data)
        except Exception as e:
            self.step_error = LogError(f"{self.path}: step record #{sequence} is malformed ({e})")
            return
        self.steps += 1
        self.nodes.add(node)
        if not detail:
            return
        tag = (log_time, microstep)
        self._note_names(node, tag, sequence, detail)
        for port, ids in (detail.get("late") or {}).items():
            for event_id in ids:
                key = ((node, port), tuple(event_id))
                if self.late.get(key, tag) <= tag:  # named late twice: the record that sorts last
                    self.late[key] = tag
        for port, streams in (detail.get("had_below") or {}).items():
            for src, out, seq in streams:
                self._views.setdefault(((node, port), src, out), []).append((tag, seq))
        for port, ranges in (detail.get("restart_gap") or {}).items():
            self.gaps.setdefault((node, port), []).extend(tuple(r) for r in ranges)

    def _note_names(self, node: str, tag: tuple[int, int], sequence: int, detail: dict) -> None:
        """Note what a record's ``detail`` (checked by ``format.decode_step``) names that the
        pipeline replayed must have (:meth:`check_details`)."""
        named, where = self._named, (tag, sequence)
        for key in detail:
            if key not in DETAIL_KEYS:  # a Queue's drop count, if an input port of the node: else no writer's
                named.setdefault((node, key, None), where)
        for key in fmt.STREAM_DETAIL_KEYS:
            for port, streams in (detail.get(key) or {}).items():
                for stream in streams:
                    named.setdefault((node, key, (port, stream[0], stream[1])), where)
        restarted = detail.get("restarted")
        if restarted is not None:
            for port in restarted["seqs"]:
                named.setdefault((node, "restarted", (port,)), where)
            for port, streams in restarted["inputs"].items():
                for stream in streams:
                    named.setdefault((node, "restarted", (port, stream[0], stream[1])), where)

    def check_details(self, graph) -> None:
        """Refuse the log if a step record's detail has a key no Retriever writer writes (nor an
        input port of its node's, whose Queue drops it would count), or names a stream into its
        node (``late``, ``had_below``, ``restart_gap``, ``restarted``'s inputs) that is no edge of
        ``graph``, or an output its node does not have (``restarted``'s seqs): the first such
        record in the log's time order. A replay would withhold or put in events by what no
        run of this pipeline wrote."""
        edges = {(edge.src, edge.src_port, edge.dst, edge.dst_port) for edge in graph.edges}
        found = []
        for (node, key, what), where in self._named.items():
            spec = graph.nodes.get(node)
            if spec is None:  # (pipeline_for refuses a log with steps of a node the pipeline lacks)
                continue
            if what is None:
                if key not in spec.inputs:
                    found.append((where, node, f"has detail '{key}', which Retriever does not write (nor is it an "
                                              f"input port of {node}, whose Queue drops it would count)"))
            elif len(what) == 1:
                if what[0] not in spec.outputs:
                    found.append((where, node, f"gives in its detail '{key}' the first seq of output {node}.{what[0]}, "
                                              f"which pipeline '{graph.name}' does not have"))
            elif (what[1], what[2], node, what[0]) not in edges:
                found.append((where, node, f"names in its detail '{key}' the stream {what[1]}.{what[2]} -> "
                                          f"{node}.{what[0]}, which is no edge of pipeline '{graph.name}'"))
        if found:
            (tag, sequence), node, says = min(found, key=lambda f: f[0])
            raise LogError(f"{self.path}: step record #{sequence} (of {node} at {format_tag(tag)}) {says}",
                           f"replay with the pipeline that wrote the log; else {DAMAGED}")

    def logged_nodes(self) -> set[str]:
        """The nodes the log has steps of (or the error of its first step record that is not one)."""
        if self.step_error is not None:
            raise self.step_error
        return self.nodes

    def check_events(self) -> None:
        """Raise what is wrong with the log's events: one that is not one, one logged twice."""
        if self.event_error is not None:
            raise self.event_error
        if self.twice is not None:
            raise self.twice

    def views(self) -> dict[tuple[tuple[str, str], str, str], tuple[list, list]]:
        """Per ``((consumer node, port), producer, producer port)``, the tags of the consumer's ticks
        that ran incomplete on it and, at each, the seq that stream's next event would have had
        (their ``had_below`` detail): the two lists in tag order."""
        return {key: tuple(map(list, zip(*sorted(v)))) for key, v in self._views.items()}

    def in_log(self, event_id: tuple[str, str, int]) -> bool:
        seqs = self.seqs.get(event_id[:2])
        return seqs is not None and event_id[2] in seqs


_STEPS = "steps"
_UNSEEN = object()


def _plain_steps(data: np.ndarray, starts: np.ndarray, ends: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Which of the step records ``data[starts:ends]`` are, as Retriever writes nearly every one,
    ``[node, microstep, {port: [id, ...]}, [id, ...], status, nil, wall_ns]`` with ids ``[node,
    port, seq]``, every string an ASCII fixstr, arrays and maps of up to 15, integers of any
    msgpack width (msgpack.unpackb reads such a record as a 7-tuple whose node is a str and
    detail None: what LogSurvey._step takes for its node alone), parsed with numpy a field at a
    time for all of them at once; and where each one's node and status (their fixstrs) are.
    ``data``: the bytes, followed by ``_PAD`` zeros."""
    fields = _Fields(data, starts.copy(), ends, ends - starts >= 2)
    fields.moved(None, fields.at(fields.p) == 0x97, 1)
    node_at = fields.p.copy()
    fields.integer(fields.text(None))
    ports = fields.header(None, 0x80)
    # the rest read apart for the records of each count of ports (nearly all have one), so that
    # a record with more costs no array operation over all the others
    plain, status_at = np.zeros(len(starts), dtype=bool), np.zeros_like(starts)
    for count in np.unique(ports[fields.ok]).tolist():
        rows = np.flatnonzero(fields.ok & (ports == count))
        group = fields if len(rows) == len(starts) else _Fields(data, fields.p[rows], ends[rows],
                                                                 np.ones(len(rows), dtype=bool))
        for _ in range(count):
            group.ids(group.text(None))
        group.ids(None)
        status_at[rows] = group.p
        group.integer(group.moved(group.text(None), group.at(group.p) == 0xC0, 1), signed=True)
        plain[rows] = group.ok & (group.p == group.ends)
    return plain, node_at, status_at


def _shapes(data: np.ndarray, starts: np.ndarray, lengths: np.ndarray,
            statuses: bool) -> tuple[np.ndarray, list[str]]:
    """Which of the step records ``data[starts:starts + lengths]`` (followed by ``_PAD`` zeros)
    are of a shape :func:`_plain_steps` finds plain, told by their bytes: per record, the index
    of its shape (-1: not told here) and per shape its node. A shape is a record of a length
    taken as it is (``_shape``: one parsed in Python, plain, with ``statuses`` a status a record
    without detail has), but for the bits of its integers' values (its microstep, seqs and wall
    time: the writer packs seqs and wall times in fixed widths, so a node's records of one
    shape are one length): a record of that length whose other bits are the same is plain too
    (each head, count and string the same: it parses the same, its integers' values aside) and
    has that node. Told for all the records of a length at once, 8 bytes at a time (each record
    as many uint64 as its length takes, masked); up to ``_SHAPES_A_LENGTH`` shapes a length, each
    the first record of that length not of one before."""
    shape = np.full(len(starts), -1, dtype=np.intp)
    nodes: list[str] = []
    words = np.ndarray((len(data) - 7,), "<u8", data, 0, (1,))
    for length in np.unique(lengths).tolist():
        rows = np.flatnonzero(lengths == length)
        for _ in range(_SHAPES_A_LENGTH):
            first = int(starts[rows[0]])
            found = _shape(data[first:first + length].tobytes(), statuses)
            if found is None:
                break
            node, fixed, value = found
            got = words[starts[rows][:, None] + np.arange(0, 8 * len(fixed), 8)]
            same = ((got ^ value) & fixed == 0).all(axis=1)
            shape[rows[same]] = len(nodes)
            nodes.append(node)
            rows = rows[~same]
            if not len(rows):
                break
    return shape, nodes


#: how many shapes of one length :func:`_shapes` tries (records of other shapes are parsed a field at a time)
_SHAPES_A_LENGTH = 4
_UINT_HEADS = {0xCC: 1, 0xCD: 2, 0xCE: 4, 0xCF: 8}  # an unsigned integer's head: its value's bytes
_INT_HEADS = {**_UINT_HEADS, 0xD0: 1, 0xD1: 2, 0xD2: 4, 0xD3: 8}


def _shape(record: bytes, statuses: bool) -> tuple[str, np.ndarray, np.ndarray] | None:
    """A step record as a shape (:func:`_shapes`): its node, and as little-endian uint64s (its
    bytes then zeros) the bits that are not its integers' values, and its bits; None if
    :func:`_plain_steps` would not find it plain (or, with ``statuses``, its status is not one of
    a record without detail: ``_plain_statuses``)."""
    values = bytearray(len(record))  # per byte, the bits of an integer's value

    def text(p: int) -> tuple[int, str]:
        size = record[p] - 0xA0
        s = record[p + 1:p + 1 + size]
        if not 0 <= size < 32 or len(s) != size:
            raise ValueError
        return p + 1 + size, s.decode("ascii")  # (a UnicodeDecodeError, a ValueError, if not ASCII)

    def integer(p: int, signed: bool) -> int:
        head = record[p]
        if head < 0x80:  # a positive fixint: its 7 low bits
            values[p] = 0x7F
            return p + 1
        if signed and head >= 0xE0:  # a negative fixint: taken as it is
            return p + 1
        width = (_INT_HEADS if signed else _UINT_HEADS)[head]
        values[p + 1:p + 1 + width] = b"\xff" * width
        return p + 1 + width

    def ids(p: int) -> int:
        if record[p] & 0xF0 != 0x90:
            raise ValueError
        count, p = record[p] & 0x0F, p + 1
        for _ in range(count):
            if record[p] != 0x93:
                raise ValueError
            p = integer(text(text(p + 1)[0])[0], False)
        return p

    try:
        if record[0] != 0x97:
            return None
        p, node = text(1)
        p = integer(p, False)
        if record[p] & 0xF0 != 0x80:
            return None
        count, p = record[p] & 0x0F, p + 1
        for _ in range(count):
            p = ids(text(p)[0])
        p, status = text(ids(p))
        if record[p] != 0xC0 or integer(p + 1, True) != len(record):
            return None
    except (IndexError, KeyError, ValueError):
        return None
    if statuses and status not in fmt.PLAIN_STEP_STATUSES:
        return None
    room = -len(record) % 8
    fixed = bytes(~b & 0xFF for b in values) + bytes(room)
    return node, np.frombuffer(fixed, "<u8"), np.frombuffer(record + bytes(room), "<u8")


class _Fields:
    """The step records ``_plain_steps`` reads, a field at a time: where each one is (``p``), where
    it ends, and whether it is still found plain (``ok``). Each field is read where the one before
    it ended, for every record (``act`` None) or those that have it (``act``), each record moved
    on whether found plain or not (one not plain then reads what it reads: it stays not plain), not
    checked to be within the record's bytes: a record whose last field ends where it ends had each
    within them (each field moves on by a byte or more)."""

    __slots__ = ("data", "words", "end", "last", "p", "ends", "ok")

    def __init__(self, data: np.ndarray, p: np.ndarray, ends: np.ndarray, ok: np.ndarray) -> None:
        # the 8 bytes from each offset, as a little-endian uint64 (past the end: the zeros), which tell
        # a string of up to 8 bytes ASCII at once (no bit of 0x80 set among its bytes: _HIGH_BITS)
        self.data, self.words = data, np.ndarray((len(data) - 7,), "<u8", data, 0, (1,))
        self.end, self.last = len(data) - _PAD, len(data) - 1
        self.p, self.ends, self.ok = p, ends, ok

    def at(self, where: np.ndarray) -> np.ndarray:
        return self.data[np.minimum(where, self.last)]

    def moved(self, act: np.ndarray | None, valid: np.ndarray, width) -> np.ndarray | None:
        """The records ``act`` (None: all) past a field ``width`` bytes long, those where it is not
        ``valid`` not plain; returns ``act``."""
        if act is None:
            self.ok &= valid
            self.p += width
        else:
            self.ok &= valid | ~act
            self.p += np.where(act, width, 0)
        return act

    def text(self, act: np.ndarray | None) -> np.ndarray | None:
        p = self.p
        size = _FIXSTR_SIZE[self.at(p)]  # (-1: no fixstr, which moves on by 0 bytes)
        valid = size >= 0
        begin = np.minimum(p + 1, self.end)
        for k in range((int(size.max(initial=0)) + 7) // 8):  # (a fixstr has up to 31 bytes)
            valid &= (self.words[8 * k:][begin] & _ASCII_MASKS[k][size]) == 0
        return self.moved(act, valid, size + 1)

    def integer(self, act: np.ndarray | None, signed: bool = False) -> np.ndarray | None:
        width = (_INT_WIDTH if signed else _UINT_WIDTH)[self.at(self.p)]
        return self.moved(act, width > 0, width)

    def header(self, act: np.ndarray | None, low: int) -> np.ndarray:
        """A fixarray's or fixmap's count (``low``: 0x90, 0x80): 0 where the record has none or is not plain."""
        h = self.at(self.p)
        self.moved(act, (h & 0xF0) == low, 1)
        return np.where(self.ok if act is None else act & self.ok, h & 0x0F, 0)

    def ids(self, act: np.ndarray | None) -> None:
        count = self.header(act, 0x90)
        for k in range(int(count.max(initial=0))):
            one = k < count
            if one.all():  # (every record has it: read as for all, the cheaper way)
                one = None
            self.integer(self.text(self.text(self.moved(one, self.at(self.p) == 0x93, 1))))


#: per count of bytes (0 to 8), the bits of 0x80 of that many low bytes of a uint64: _plain_steps' ASCII check
_HIGH_BITS = np.array([0x8080808080808080 & ((1 << 8 * n) - 1) for n in range(9)], dtype=np.uint64)

#: per 8 bytes of a fixstr (the 0th to the 3rd) and per size (0 to 31), _HIGH_BITS of its bytes among them
_ASCII_MASKS = np.array([[_HIGH_BITS[min(max(size - 8 * k, 0), 8)] for size in range(32)] for k in range(4)],
                        dtype=np.uint64)

#: per first byte, _plain_steps' reading of it: a fixstr's size (-1: no fixstr); an unsigned, a
#: signed integer's width in bytes, its head's with it (0: none)
_FIXSTR_SIZE = np.array([b - 0xA0 if 0xA0 <= b <= 0xBF else -1 for b in range(256)], dtype=np.int64)
_UINT_WIDTH = np.array([1 if b < 0x80 else {0xCC: 2, 0xCD: 3, 0xCE: 5, 0xCF: 9}.get(b, 0) for b in range(256)],
                       dtype=np.int64)
_INT_WIDTH = np.array([1 if b < 0x80 or b >= 0xE0 else {0xCC: 2, 0xCD: 3, 0xCE: 5, 0xCF: 9, 0xD0: 2, 0xD1: 3,
                                                         0xD2: 5, 0xD3: 9}.get(b, 0) for b in range(256)],
                      dtype=np.int64)

#: the statuses of a step record without detail, as msgpack packs them (fixstrs): _plain_statuses'
_PLAIN_STATUS_BYTES = [msgpack.packb(str(status)) for status in sorted(fmt.PLAIN_STEP_STATUSES)]
#: each as its first 8 bytes and the 8 after (little-endian uint64s), and the bits of them it has
#: (a status has up to 15 bytes: "incomplete" 11)
_PLAIN_STATUS_WORDS = [tuple(np.uint64(n) for n in (int.from_bytes(b[:8], "little"), (1 << 8 * len(b[:8])) - 1,
                                                    int.from_bytes(b[8:16], "little"), (1 << 8 * len(b[8:16])) - 1))
                       for b in _PLAIN_STATUS_BYTES]


def _plain_statuses(data: np.ndarray, status_at: np.ndarray) -> np.ndarray:
    """Which of the fixstrs at ``status_at`` in ``data`` (followed by ``_PAD`` zeros) are a status
    a step record without detail has (``format.decode_step`` refuses any other)."""
    words = np.ndarray((len(data) - 7,), "<u8", data, 0, (1,))
    at = np.minimum(status_at, len(data) - 16)  # (a status found is within the bytes, before the zeros)
    first, second = words[at], words[at + 8]
    found = np.zeros(len(status_at), dtype=bool)
    for low, low_bits, high, high_bits in _PLAIN_STATUS_WORDS:
        same = (first & low_bits) == low
        if high_bits:
            same &= (second & high_bits) == high
        found |= same
    return found


def _names(data: np.ndarray, node_at: np.ndarray) -> set[str]:
    """The distinct ASCII fixstrs at ``node_at`` in ``data`` (followed by ``_PAD`` zeros)."""
    if not len(node_at):
        return set()
    # each one's head and bytes as up to 4 little-endian uint64 (the bytes after it: 0), a row
    words = np.ndarray((len(data) - 7,), "<u8", data, 0, (1,))
    size = data[node_at].astype(np.intp) - 0xA0 + 1
    keys = np.empty((len(node_at), (int(size.max()) + 7) // 8), dtype="<u8")
    for k in range(keys.shape[1]):
        keys[:, k] = words[8 * k:][node_at] & _LOW_BYTES[k][size]
    keys = keys[np.lexsort(keys.T[::-1])] if keys.shape[1] > 1 else np.sort(keys, axis=0)
    rows = keys[np.r_[True, (keys[1:] != keys[:-1]).any(axis=1)]]
    return {(b := row.tobytes())[1:b[0] - 0x9F].decode("ascii") for row in rows}


#: per 8 bytes of a fixstr (the 0th to the 3rd) and per count of its head and bytes (0 to 32), the bits
#: of those among them: _names'
_LOW_BYTES = np.array([[(1 << 8 * min(max(n - 8 * k, 0), 8)) - 1 for n in range(33)] for k in range(4)],
                      dtype=np.uint64)
_DATA_AT = 9 + 22  # a Message record's data, after its opcode, length and fields
_PAD = 32  # zeros after a chunk's bytes, for _plain_steps and _names: a fixstr's head and bytes fit


class _Seqs:
    """A set of seqs held as sorted ranges ``[lo, hi)``: as small as the gaps between them."""

    __slots__ = ("lo", "hi")

    def __init__(self) -> None:
        self.lo: list[int] = []
        self.hi: list[int] = []

    def add(self, seq: int) -> bool:
        """Put ``seq`` in; False if it was there."""
        lo, hi = self.lo, self.hi
        if hi and hi[-1] == seq:  # the next one: the common case
            hi[-1] = seq + 1
            return True
        i = bisect.bisect_right(lo, seq)
        if i and seq < hi[i - 1]:
            return False
        after, before = i and hi[i - 1] == seq, i < len(lo) and lo[i] == seq + 1
        if after and before:
            hi[i - 1] = hi[i]
            del lo[i], hi[i]
        elif after:
            hi[i - 1] = seq + 1
        elif before:
            lo[i] = seq
        else:
            lo.insert(i, seq)
            hi.insert(i, seq + 1)
        return True

    def __contains__(self, seq: int) -> bool:
        i = bisect.bisect_right(self.lo, seq)
        return bool(i) and seq < self.hi[i - 1]
