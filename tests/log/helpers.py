"""Shared helpers of the event-log tests: the ``retriever`` command as a subprocess, MCAP record
scanning for damage tests, and comparing logged records."""

from __future__ import annotations

import os
import re
import struct
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
QUICKSTART = ROOT / "examples" / "quickstart.py"
RETRIEVER = Path(sys.executable).parent / "retriever"
GOLDEN = ROOT / "tests" / "golden"

CHUNK = 0x06
MAGIC_LEN = 8


def cli_env(pythonpath: Path | None = None) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k not in ("FORCE_COLOR", "PYTHONPATH")}
    # no .pyc: tests rewrite a flow module within the same second, same size or not
    env.update(NO_COLOR="1", TERM="dumb", COLUMNS="200", PYTHONIOENCODING="utf-8", PYTHONDONTWRITEBYTECODE="1")
    # this checkout's retriever, not whichever one the venv's editable install points at
    env["PYTHONPATH"] = os.pathsep.join(str(p) for p in (pythonpath, ROOT) if p is not None)
    return env


def cli(*args: str, cwd: Path | None = None, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    """``retriever ARGS`` as users run it; ``subprocess.run`` waits for (and on timeout kills) it."""
    return subprocess.run([str(RETRIEVER), *map(str, args)], check=False, capture_output=True, text=True, cwd=cwd or ROOT,
                          env=cli_env(pythonpath), timeout=120)


def assert_cli_error(result: subprocess.CompletedProcess, message: str, hint: str | None = None) -> None:
    """Exit status 1, ``error: …`` first on stderr, the ``hint: …`` line if given, no traceback."""
    assert result.returncode == 1, (result.returncode, result.stdout, result.stderr)
    assert result.stderr.startswith("error: "), result.stderr
    assert re.search(message, result.stderr, re.MULTILINE), result.stderr
    if hint is not None:
        assert re.search(r"^(    )?hint: " + hint, result.stderr, re.MULTILINE), result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    assert "run with --debug" not in result.stderr, "a LogError must not look like an unexpected exception"


def records(data: bytes) -> list[tuple[int, int, int]]:
    """``(opcode, offset, length)`` of every top-level MCAP record, read from the raw bytes."""
    found, pos = [], MAGIC_LEN
    while pos + 9 <= len(data):
        opcode, length = data[pos], struct.unpack_from("<Q", data, pos + 1)[0]
        found.append((opcode, pos, length))
        pos += 9 + length
        if opcode == 0x02:  # footer
            break
    return found


def chunks(data: bytes) -> list[tuple[int, int]]:
    """``(offset, length)`` of every chunk record."""
    return [(offset, length) for opcode, offset, length in records(data) if opcode == CHUNK]


def chunk_payload_offset(data: bytes, chunk_offset: int) -> int:
    """Where a chunk's compressed records start (after start/end time, sizes, CRC, compression)."""
    pos = chunk_offset + 9 + 8 + 8 + 8 + 4
    compression_len = struct.unpack_from("<I", data, pos)[0]
    return pos + 4 + compression_len + 8


def flip(path: Path, offset: int, out: Path) -> Path:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0xFF
    out.write_bytes(bytes(data))
    return out


def cut(path: Path, size: int, out: Path) -> Path:
    out.write_bytes(path.read_bytes()[:size])
    return out


def rewrite(src: Path, dst: Path, *, metadata=None, keep=None, add: dict | None = None, topic=None,
            writer_options: dict | None = None, order=None) -> Path:
    """A copy of the log ``src`` made with the ``mcap`` writer, as a forger would: ``metadata(name,
    dict)`` changes a metadata record in place, ``keep(topic, message)`` drops messages it says no
    to, ``add`` holds metadata records to add ({name: {key: value}}), ``topic(topic)`` renames a
    channel; ``writer_options``: the ``mcap`` Writer's (``chunk_size``, ``index_types``...);
    ``order(messages)``: the ``(schema, channel, message)`` triples in the order to write them."""
    from mcap.reader import make_reader
    from mcap.writer import Writer

    with open(src, "rb") as f:
        reader = make_reader(f)
        header = reader.get_header()
        messages = list(reader.iter_messages())
        if order is not None:
            messages = list(order(messages))
        attachments = list(reader.iter_attachments())
        metas = list(reader.iter_metadata())
    with open(dst, "wb") as out:
        writer = Writer(out, **(writer_options or {}))
        writer.start(profile=header.profile, library=header.library)
        channels: dict[int, int] = {}
        for _, channel, message in messages:
            if keep is not None and not keep(channel.topic, message):
                continue
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic if topic is None else topic(channel.topic),
                                                               channel.message_encoding, 0,
                                                               dict(channel.metadata))
            writer.add_message(channels[channel.id], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time, sequence=message.sequence)
        for a in attachments:
            writer.add_attachment(create_time=a.create_time, log_time=a.log_time, name=a.name,
                                  media_type=a.media_type, data=a.data)
        for record in metas:
            values = dict(record.metadata)
            if metadata is not None:
                metadata(record.name, values)
            writer.add_metadata(record.name, values)
        for name, values in (add or {}).items():
            writer.add_metadata(name, values)
        writer.finish()
    return dst
