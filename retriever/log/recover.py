"""``recover``: rewrite the readable part of a torn or damaged log as a complete MCAP file."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

from ..errors import LogError
from . import format as fmt
from .mcap_writer import McapWriter
from .reader import RunLog, read_log
from .writer import LogFile, describe_os_error


@dataclass
class Recovered:
    source: Path
    output: Path | None  # None when the source was already complete
    messages: int
    events: int
    steps: int
    damage: str | None


def recover(source: str | Path, output: str | Path | None = None, *, overwrite: bool = False) -> Recovered:
    """Copy every record before the damage in ``source`` into ``output`` (default
    ``<name>.recovered.mcap``; an existing file only with ``overwrite=True``), finished with
    indexes and a ``retriever.recovered`` record."""
    log = read_log(source, salvage=True)
    steps_channels = {c.id for c in log.channels.values() if c.topic == fmt.STEPS_TOPIC}
    steps = sum(1 for m in log.messages if m.channel_id in steps_channels)
    if log.complete and log.damage is None:
        return Recovered(log.path, None, len(log.messages), len(log.messages) - steps, steps, None)
    if not log.channels:
        raise LogError(f"nothing in {log.path} can be recovered: {log.damage}")
    out = Path(output) if output is not None else log.path.with_name(log.path.stem + ".recovered.mcap")
    if out.resolve() == log.path.resolve():
        raise LogError(f"recover would overwrite its input {log.path}", "pass another path with -o")
    if out.exists() and not overwrite:
        raise LogError(f"{out} already exists; recover does not overwrite a file",
                       "pass --force (retriever log recover) or overwrite=True (recover) to replace it, "
                       "or another path with -o")
    file = LogFile(out, overwrite=True)
    file.start()
    try:
        _copy(log, file.stream)
        file.stream.close()
    except OSError as e:
        file.discard()
        raise LogError(f"cannot write {out}: {describe_os_error(e)}", "recover into a folder on a disk with room") from None
    return Recovered(log.path, out, len(log.messages), len(log.messages) - steps, steps, log.damage)


def _copy(log: RunLog, stream: BinaryIO) -> None:
    """Write the records ``log`` holds, and a ``retriever.recovered`` record, as one complete MCAP file."""
    writer = McapWriter(stream, profile=log.profile, library="retriever log recover")
    schema_ids = {s.id: writer.add_schema(s.name, s.encoding, s.data) for s in log.schemas.values()}
    channel_ids = {c.id: writer.add_channel(c.topic, c.message_encoding, c.metadata, schema_ids.get(c.schema_id, 0))
                   for c in log.channels.values()}
    for attachment in log.attachments.values():
        writer.add_attachment(attachment.name, attachment.media_type, bytes(attachment.data),
                              attachment.log_time, attachment.create_time)
    for name, data in log.metadata.items():
        writer.add_metadata(name, data)
    writer.add_metadata(fmt.RECOVERED_METADATA, {
        "source": str(log.path), "damage": log.damage or "", "messages": str(len(log.messages)),
        "recovered_unix_ns": str(time.time_ns())})
    for m in log.messages:
        writer.add_message(channel_ids[m.channel_id], m.log_time, m.publish_time, m.sequence, m.data)
    writer.finish()
