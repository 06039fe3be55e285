"""``LogWriter``: stream a run's trace into an MCAP file as the run goes.

A session calls :meth:`LogWriter.write` with its trace about every 20 ms of wall time (at most
every 4096 steps, see ``Session.write_log``); each call encodes the records appended since the last. The chunk is closed and the file flushed at
least every ``flush_interval`` seconds of wall time, which bounds what a ``kill -9`` can take.
"""

from __future__ import annotations

import json
import time
from collections import Counter
from operator import itemgetter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgpack
from mcap.opcode import Opcode

from ..codec import Encoder
from ..errors import CodecError, LogError
from . import format as fmt
from .mcap_writer import MESSAGE_FIELDS, MESSAGE_HEAD, McapWriter

if TYPE_CHECKING:
    from ..graph import Graph
    from ..trace import Trace


_first, _second, _node_port = itemgetter(0), itemgetter(1), itemgetter(1, 2)
_HEADS = [bytes((0x92, m)) for m in range(128)]  # msgpack: fixarray of 2, fixint microstep


class LogWriter:
    """Writes one run to ``path``: the IR and run metadata first, then events and steps."""

    def __init__(self, path: str | Path, graph: "Graph", *, backend: str, seeds: dict[str, Any] | None = None,
                 flush_interval: float = 0.1):
        self.path = Path(path)
        try:
            self._file = open(self.path, "wb")
        except OSError as e:
            raise LogError(f"cannot create the log {self.path}: {e.strerror}",
                           "pass log= a path in a directory that exists and is writable") from None
        version = fmt.package_versions().get("retriever", "dev")
        self._mcap = McapWriter(self._file, profile=fmt.PROFILE, library=f"retriever {version}")
        self._mcap.add_attachment(fmt.IR_ATTACHMENT, "application/json", graph.to_ir().to_json().encode())
        modules = sorted({type(node.flow).__module__ for node in graph.nodes.values()})
        self._mcap.add_metadata(fmt.RUN_METADATA, fmt.run_metadata(graph.name, backend, seeds or {}, time.time_ns(),
                                                                    modules))
        self._channels: dict[tuple[str, str], int] = {}
        for node in sorted(graph.nodes.values(), key=lambda n: n.id):
            for port, spec in node.outputs.items():
                self._add_channel(node.id, port, spec.type)
        self._steps_channel = self._mcap.add_channel(fmt.STEPS_TOPIC, fmt.MESSAGE_ENCODING, {})
        self._mcap.flush()
        self._events_done = 0
        self._steps_done = 0
        self._encode = Encoder().pack
        self._pack_step = msgpack.Packer(use_bin_type=True).pack
        self._flush_interval = flush_interval
        self._last_flush = time.monotonic()
        self.closed = False

    def _add_channel(self, node: str, port: str, port_type: Any = None) -> int:
        type_name = "" if port_type is None else getattr(port_type, "__qualname__", str(port_type))
        channel = self._mcap.add_channel(fmt.data_topic(node, port), fmt.MESSAGE_ENCODING,
                                         {"node": node, "port": port, "type": type_name})
        self._channels[(node, port)] = channel
        return channel

    def write(self, trace: "Trace") -> None:
        """Encode the records appended to ``trace`` since the last call; flush if it is time.

        One comprehension per kind builds whole MCAP message records: this runs for every event
        and step of a logged run, so it avoids every intermediate object it can.
        """
        events, steps = trace.raw_events, trace.raw_steps
        head, op, fields, u32 = MESSAGE_HEAD.pack, Opcode.MESSAGE, MESSAGE_FIELDS, 0xFFFFFFFF
        if len(events) > self._events_done:
            new = events[self._events_done:]
            channels, encode = self._channels, self._encode
            try:
                # data = [microstep, value]: a fixarray of 2 and, almost always, a fixint microstep
                records = [head(op, fields + len(data := _HEADS[tag[1]] + encode(value) if tag[1] < 128
                                                 else encode([tag[1], value])),
                                channels.get((node, port)) or self._add_channel(node, port), seq & u32, tag[0],
                                published) + data
                           for tag, node, port, seq, value, published in new]
            except CodecError:
                raise self._unencodable(new) from None
            tags = list(map(_first, new))
            counts = Counter(map(_node_port, new))
            self._mcap.add_records(records, min(tags)[0], max(tags)[0],
                                   {channels[key]: n for key, n in counts.items()})
            self._events_done = len(events)
        if len(steps) > self._steps_done:
            pack, channel = self._pack_step, self._steps_channel
            new = steps[self._steps_done:]
            records = [head(op, fields + len(data := pack((node, tag[1], consumed, produced, status, detail, wall))),
                            channel, index & u32, tag[0], start) + data
                       for index, (node, tag, consumed, produced, status, detail, start, wall)
                       in enumerate(new, self._steps_done)]
            tags = list(map(_second, new))
            self._mcap.add_records(records, min(tags)[0], max(tags)[0], {channel: len(new)})
            self._steps_done = len(steps)
        now = time.monotonic()
        if now - self._last_flush >= self._flush_interval:
            self._mcap.flush()
            self._last_flush = now

    def _unencodable(self, events: list[tuple]) -> LogError:
        for tag, node, port, seq, value, _ in events:
            try:
                self._encode(value)
            except CodecError as e:
                return LogError(f"event {node}.{port} #{seq} (at t={tag[0] / 1e9:g} s) cannot be logged: {e}",
                                f"make {node}.{port} carry numbers, str, bytes, lists, dicts, numpy arrays "
                                "or @io dataclasses")
        return LogError("an event cannot be logged (the codec refused a value it later accepted)")

    def close(self, trace: "Trace", end_ns: int, *, status: str = "finished", error: str = "",
              stats: dict | None = None, counts: dict | None = None) -> None:
        """Write what is left and the ``retriever.end`` record, then finish the file."""
        if self.closed:
            return
        self.closed = True
        try:
            self.write(trace)
        finally:
            end = {"status": status, "end_ns": str(end_ns), "events": str(self._events_done),
                   "steps": str(self._steps_done), "finished_unix_ns": str(time.time_ns())}
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
            self._file.close()
