"""A chunked MCAP writer for many small messages, laid out to survive ``kill -9``.

Why not ``mcap.writer.Writer``: it builds a dataclass and updates statistics per message, a cost
of the order of a whole in-process step, so a logged run would be several times slower
(benchmarks/logging_overhead.py measures what logging costs). Here a
batch of messages is one list comprehension of ``struct.pack`` joined into the open chunk; every other record (header, channels,
chunks, indexes, attachments, metadata, summary, footer) is written with the ``mcap`` package's
own record classes, and the result is read back by the plain ``mcap`` reader in the tests.

Each chunk is followed by its MessageIndex records (one per channel: log time and offset of every
message), which MCAP's indexed readers (Foxglove's ``McapIndexedReader``, Rerun's import) need to
find a chunk's messages. They are built on the I/O thread, vectorised with numpy, from the chunk's
bytes and the records' lengths, and so are the summary's statistics (messages per channel, first
and last log time): the hot path adds one ``join`` and one ``extend`` per batch.

Crash safety comes from the layout: schemas, channels, attachments and metadata go straight into
the data section as they are added, and each :meth:`flush` closes the open chunk (zstd-compressed, with a
CRC of its contents) and flushes the file. Compression and file writes run, in call order, on one
I/O thread (zstd and file writes release the GIL), so they overlap the run instead of pausing it.

The writer is split by concern: ``McapWriter`` takes the calls in order, keeps the channels and
schemas (``Registry``) and the open chunk (``OpenChunk``); mcap_records.py builds the records'
bytes, mcap_io.py runs the I/O thread and its back-pressure, mcap_file.py lays the file out.
A big record (:meth:`McapWriter.add_large_record`, a big array's) is a chunk of its own, never
joined with others: joining bytes holds the GIL for as long as the copy takes. A killed writer leaves complete chunks followed by at
most one torn record, which ``mcap``'s non-seeking reader reads up to (``retriever log recover``).
"""

from __future__ import annotations

from typing import BinaryIO

import numpy as np
from mcap.records import Attachment, Channel, Header, Metadata, Schema

from .mcap_file import McapFile
from .mcap_io import WriteQueue
from .mcap_records import MAGIC, message_records

#: Uncompressed chunk bytes queued for the I/O thread at most: past it, whoever adds messages
#: waits for the disk (a run faster than its disk would otherwise grow its memory without bound)
MAX_BYTES_QUEUED = 32 << 20


class Registry:
    """The file's schemas and channels, numbered from 1 in the order they were added."""

    def __init__(self) -> None:
        self.schemas: list[Schema] = []
        self.channels: list[Channel] = []

    def schema(self, name: str, encoding: str, data: bytes) -> Schema:
        schema = Schema(id=len(self.schemas) + 1, name=name, encoding=encoding, data=bytes(data))
        self.schemas.append(schema)
        return schema

    def channel(self, topic: str, message_encoding: str, metadata: dict[str, str], schema_id: int) -> Channel:
        channel = Channel(id=len(self.channels) + 1, topic=topic, message_encoding=message_encoding,
                          metadata=dict(metadata), schema_id=schema_id)
        self.channels.append(channel)
        return channel


class OpenChunk:
    """Message records joined into the chunk not yet closed, and their lengths (what the I/O
    thread reads the chunk's indexes and statistics by, mcap_records.ChunkIndexes)."""

    def __init__(self) -> None:
        self.data = bytearray()
        self._lengths: list[int] = []  # of the open chunk's records, in order

    def add(self, records: list[bytes]) -> int:
        """Join ``records`` into the chunk; return how many bytes they are."""
        joined = b"".join(records)
        self.data += joined
        self._lengths.extend(map(len, records))
        return len(joined)

    def take(self) -> tuple[bytearray, list[int]] | None:
        """Close the chunk: its bytes and its records' lengths; None when it is empty. The next
        records start a new one."""
        if not self.data:
            return None
        data, lengths = self.data, self._lengths
        self.data, self._lengths = bytearray(), []
        return data, lengths


class McapWriter:
    """Write one MCAP file: ``add_channel``, ``add_message``…, ``flush`` as often as data must
    survive a crash, ``finish`` once."""

    def __init__(self, stream: BinaryIO, *, profile: str = "", library: str = "", chunk_size: int = 1 << 20):
        self._chunk_size = chunk_size
        self._registry = Registry()
        self._chunk = OpenChunk()
        self._finished = False
        self._file = McapFile(stream)  # the I/O thread's until finish() shuts it down
        self._queue = WriteQueue(MAX_BYTES_QUEUED)
        self._queue.submit(self._file.write, MAGIC)
        self._queue.submit(self._file.write_record, Header(profile=profile, library=library))

    @property
    def queued_bytes(self) -> int:
        """Chunk bytes handed to the I/O thread and not yet written (past ``MAX_BYTES_QUEUED``, writes wait)."""
        return self._queue.queued_bytes

    @property
    def waits(self) -> int:
        """How often adding messages waited for the disk (MAX_BYTES_QUEUED)."""
        return self._queue.waits

    @property
    def waited_ns(self) -> int:
        """How long adding messages waited for the disk, in all."""
        return self._queue.waited_ns

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """A schema for channels to name (Retriever's own channels have none: 0)."""
        schema = self._registry.schema(name, encoding, data)
        self._queue.submit(self._file.write_record, schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, metadata: dict[str, str], schema_id: int = 0) -> int:
        channel = self._registry.channel(topic, message_encoding, metadata, schema_id)
        self._queue.submit(self._file.write_record, channel)
        return channel.id

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time: int = 0, create_time: int = 0) -> None:
        self._close_chunk()  # keep the file in call order: messages added before come first
        record = Attachment(log_time=log_time, create_time=create_time, name=name, media_type=media_type, data=data)
        self._queue.submit(self._file.write_attachment, record)

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._close_chunk()  # keep the file in call order: messages added before come first
        self._queue.submit(self._file.write_metadata, Metadata(name=name, metadata=dict(data)))

    # -- messages --------------------------------------------------------------------------
    def add_message(self, channel_id: int, log_time: int, publish_time: int, sequence: int, data: bytes) -> None:
        self.add_messages([(channel_id, log_time, publish_time, sequence, data)])

    def add_messages(self, messages: list[tuple[int, int, int, int, bytes]]) -> None:
        """Append ``(channel_id, log_time, publish_time, sequence, data)`` messages to the open chunk."""
        if messages:
            self.add_records(message_records(messages))

    def add_records(self, records: list[bytes]) -> int:
        """Append whole Message records (built with :data:`MESSAGE_HEAD`): the hot path of the
        log writer. What the summary counts of them is read on the I/O thread. Returns their
        bytes."""
        if not records:
            return 0
        added = self._chunk.add(records)
        if len(self._chunk.data) >= self._chunk_size:
            self._close_chunk()
        return added

    def add_large_record(self, record: np.ndarray) -> None:
        """Append one big Message record (its bytes, in a buffer nobody changes afterwards) in a
        chunk of its own: it is not copied on this thread, and the I/O thread compresses and
        writes it as it is."""
        self._close_chunk()
        self._queue.submit(self._file.write_large_chunk, record, size=len(record))

    def flush(self) -> None:
        """Close the open chunk and push everything to the OS (as soon as the I/O thread gets
        there): it then survives a kill."""
        self._close_chunk()
        self._queue.submit(self._file.flush)

    def wait(self) -> None:
        """Block until every queued write reached the OS; raise the first write that failed."""
        self._queue.wait()

    def channel_end_time(self, channel_id: int) -> int:
        """The latest log time among the messages of a channel added so far (0: none). Closes
        the open chunk and waits for the I/O thread, which reads the times from the chunks."""
        self._close_chunk()
        self.wait()
        return self._file.channel_end_times.get(channel_id, 0)

    def abandon(self) -> None:
        """Stop writing after a failure: let the I/O thread end; the file stays as it is."""
        self._finished = True
        self._queue.close()

    def _close_chunk(self) -> None:
        closed = self._chunk.take()
        if closed is not None:
            self._queue.submit(self._file.write_chunk, *closed, size=len(closed[0]))

    # -- the end ---------------------------------------------------------------------------
    def finish(self) -> None:
        """Write the summary (channels, statistics, indexes) and the footer. Idempotent."""
        if self._finished:
            return
        self._finished = True
        self._close_chunk()
        self._queue.close()  # every queued write is done: the file is this thread's now
        self._queue.check()
        self._file.finish(self._registry.schemas, self._registry.channels)
