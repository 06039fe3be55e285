"""Read a Retriever log with nothing but the ``mcap`` and ``msgpack`` packages.

This module must not import ``retriever``: it is what "readable by any MCAP reader" means
(``test_format.py`` also runs it in a subprocess where importing ``retriever`` fails). It reads
the file twice, with ``mcap``'s seeking reader (summary, chunk indexes, chunk CRCs) and with its
non-seeking stream reader (data-section CRC), checks the two agree, checks the summary CRC by
hand, and returns every record as plain JSON-able Python.
"""

from __future__ import annotations

import hashlib
import io
import json
import struct
import zlib
from pathlib import Path

import msgpack
from mcap.reader import NonSeekingReader, make_reader
from mcap.records import Attachment, Channel, Header, Message, Metadata

MAGIC = b"\x89MCAP0\r\n"
FOOTER_OPCODE = 0x02


class _Unseekable(io.RawIOBase):
    """A pipe-like view of bytes, so ``make_reader`` picks the non-seeking stream reader."""

    def __init__(self, data: bytes):
        self._data = io.BytesIO(data)

    def readable(self) -> bool:
        return True

    def seekable(self) -> bool:
        return False

    def readinto(self, buffer) -> int:
        return self._data.readinto(buffer)


def summary_crc_ok(data: bytes) -> bool:
    """The footer's summary CRC: crc32 of the summary section and the footer up to the CRC."""
    assert data.endswith(MAGIC)
    footer = len(data) - len(MAGIC) - (1 + 8 + 8 + 8 + 4)
    opcode, length, summary_start, _, crc = struct.unpack_from("<BQQQI", data, footer)
    assert (opcode, length) == (FOOTER_OPCODE, 20)
    return crc == zlib.crc32(data[summary_start:footer + 1 + 8 + 8 + 8])


def plain(value):
    """A msgpack-decoded value as canonical JSON: bytes as hex, maps as [key, value] pairs,
    extension types as their code and their payload (itself msgpack, except big ints: text)."""
    if isinstance(value, msgpack.ExtType):
        if value.code == 3:
            return {"ext": 3, "text": value.data.decode("ascii")}
        return {"ext": value.code, "payload": plain(unpack(value.data))}
    if isinstance(value, bytes):
        return {"bin": value.hex()}
    if isinstance(value, dict):
        return {"map": [[plain(k), plain(v)] for k, v in value.items()]}
    if isinstance(value, (list, tuple)):
        return [plain(v) for v in value]
    if isinstance(value, float):
        return {"f64": struct.pack(">d", value).hex()}  # bit-exact, and JSON has no nan
    return value


def unpack(data: bytes):
    return msgpack.unpackb(data, raw=False, strict_map_key=False)


def read_plain(path: str | Path) -> dict:
    """Every record of the log at ``path``, validated, as plain Python (see the module docstring)."""
    data = Path(path).read_bytes()
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        header = reader.get_header()
        summary = reader.get_summary()
        indexed = [(channel.topic, m) for _, channel, m in reader.iter_messages(log_time_order=False)]
        attachments = {a.name: a for a in reader.iter_attachments()}
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]

    # The same file, read front to back as from a pipe: the data-section CRC is checked too.
    streamed = NonSeekingReader(io.BufferedReader(_Unseekable(data)), validate_crcs=True)
    records = list(streamed._stream_reader.records)
    stream_channels = {r.id: r for r in records if isinstance(r, Channel)}
    stream_messages = [(stream_channels[r.channel_id].topic, r) for r in records if isinstance(r, Message)]

    assert [(t, m.log_time, m.publish_time, m.sequence, m.data) for t, m in indexed] == \
           [(t, m.log_time, m.publish_time, m.sequence, m.data) for t, m in stream_messages], \
        "the chunk indexes and the data section disagree"
    assert [(r.name, dict(r.metadata)) for r in records if isinstance(r, Metadata)] == metadata
    assert sorted(r.name for r in records if isinstance(r, Attachment)) == sorted(attachments)
    assert isinstance(records[0], Header)

    return {
        "profile": header.profile,
        "library": header.library,
        "summary_crc_ok": summary_crc_ok(data),
        "statistics": summary.statistics,
        "chunk_count": len(summary.chunk_indexes),
        "channels": {c.id: c for c in summary.channels.values()},
        "stream_channel_order": [stream_channels[i].topic for i in stream_channels],
        "messages": indexed,
        "attachments": attachments,
        "metadata": metadata,
    }


def decoded_records(log: dict) -> dict:
    """The deterministic content of a log read by :func:`read_plain`: everything but wall-clock
    fields (publish_time, wall_ns, metadata timestamps, host, pid, paths, versions, the IR's hashes of
    source files)."""
    channels = [{"id": c.id, "topic": c.topic, "message_encoding": c.message_encoding,
                 "schema_id": c.schema_id, "metadata": dict(sorted(c.metadata.items()))}
                for c in sorted(log["channels"].values(), key=lambda c: c.id)]
    events, steps = [], []
    for topic, m in log["messages"]:
        if topic == "steps":
            node, microstep, consumed, produced, status, detail, _wall_ns = unpack(m.data)
            steps.append({"log_time": m.log_time, "sequence": m.sequence, "node": node, "microstep": microstep,
                          "consumed": plain(consumed), "produced": plain(produced), "status": status,
                          "detail": plain(detail)})
        else:
            microstep, value = unpack(m.data)
            events.append({"topic": topic, "log_time": m.log_time, "sequence": m.sequence, "microstep": microstep,
                           "value": plain(value), "data_sha256": hashlib.sha256(m.data).hexdigest()[:16]})
    meta = dict(log["metadata"])
    run = {k: meta["retriever.run"][k] for k in ("format", "pipeline", "backend", "seeds")}
    end = {k: v for k, v in meta["retriever.end"].items() if k != "finished_unix_ns"}
    end["stats"] = {node: {k: v for k, v in s.items() if k != "step_ns"}
                    for node, s in json.loads(end["stats"]).items()}
    return {
        "profile": log["profile"],
        "channels": channels,
        "events": events,
        "steps": steps,
        "ir": _without_code_hashes(json.loads(bytes(log["attachments"]["pipeline.ir.json"].data))),
        "attachments": sorted([a.name, a.media_type] for a in log["attachments"].values()),
        "metadata_order": [name for name, _ in log["metadata"]],
        "run": run,
        "end": end,
    }


def _without_code_hashes(ir: dict) -> dict:
    """The IR with each flow module's sha256 (which changes with every edit of that file) named
    rather than given: the golden log pins that it is recorded, tests/log check its value."""
    hashes = ir.get("metadata", {}).get("code_sha256")
    if isinstance(hashes, dict):
        ir["metadata"]["code_sha256"] = {module: f"<sha256 of {module}>" for module in hashes}
    return ir


def digest(records: dict) -> str:
    return hashlib.sha256(json.dumps(records, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
