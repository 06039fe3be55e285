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
bytes and the records' lengths: the hot path adds one ``extend`` per batch.

Crash safety comes from the layout: schemas, channels, attachments and metadata go straight into
the data section as they are added, and each :meth:`flush` closes the open chunk (zstd-compressed, with a
CRC of its contents) and flushes the file. Compression and file writes run, in call order, on one
I/O thread (zstd and file writes release the GIL), so they overlap the run instead of pausing it.
A big record (:meth:`McapWriter.add_large_record`, a big array's) is a chunk of its own, never
joined with others: joining bytes holds the GIL for as long as the copy takes. A killed writer leaves complete chunks followed by at
most one torn record, which ``mcap``'s non-seeking reader reads up to (``retriever log recover``).
"""

from __future__ import annotations

import struct
import threading
import time
import zlib
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from typing import BinaryIO

import numpy as np
import zstandard
from mcap.data_stream import RecordBuilder
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    AttachmentIndex,
    Channel,
    Chunk,
    ChunkIndex,
    DataEnd,
    Footer,
    Header,
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

MAGIC = b"\x89MCAP0\r\n"
#: Uncompressed chunk bytes queued for the I/O thread at most: past it, whoever adds messages
#: waits for the disk (a run faster than its disk would otherwise grow its memory without bound)
MAX_BYTES_QUEUED = 32 << 20
#: The head of a Message record: ``MESSAGE_HEAD.pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data),
#: channel_id, sequence & 0xFFFFFFFF, log_time, publish_time) + data`` is the whole record.
MESSAGE_HEAD = struct.Struct("<BQHIQQ")
MESSAGE_FIELDS = 2 + 4 + 8 + 8
_CHANNEL_AT, _LOG_TIME_AT = 9, 15  # where a Message record's channel id and log time begin
_LOG_TIME_BYTES = np.arange(_LOG_TIME_AT, _LOG_TIME_AT + 8)
#: The head of a Chunk record, up to its compression's name: opcode, record length, message start
#: and end time, uncompressed size and CRC, the name's length; then the name, and the records'
#: length (8 bytes) before them; CHUNK_FIELDS counts the fields' bytes but the name and records
CHUNK_HEAD = struct.Struct("<BQQQQII")
CHUNK_FIELDS = 8 + 8 + 8 + 4 + 4 + 8
_ZSTD = b"zstd"
MESSAGE_INDEX_HEAD = struct.Struct("<BQHI")  # opcode, record length, channel id, entries' length
_U32 = 0xFFFFFFFF


def _nothing() -> None:
    """A job for the I/O thread whose end tells that every job queued before it is done."""


class McapWriter:
    """Write one MCAP file: ``add_channel``, ``add_message``…, ``flush`` as often as data must
    survive a crash, ``finish`` once."""

    def __init__(self, stream: BinaryIO, *, profile: str = "", library: str = "", chunk_size: int = 1 << 20):
        self._stream = stream
        self._chunk_size = chunk_size
        self._compressor = zstandard.ZstdCompressor(level=1)
        self._channels: list[Channel] = []
        self._schemas: list[Schema] = []
        self._chunk = bytearray()
        self._lengths: list[int] = []  # of the open chunk's records, in order (for its message indexes)
        self._chunk_times: list[int] | None = None  # [earliest, latest] log time in the open chunk
        self._message_counts: Counter[int] = Counter()
        self._start_time: int | None = None
        self._end_time = 0
        self._finished = False
        # Owned by the I/O thread until finish() joins it:
        self._offset = 0
        self._data_crc = 0
        self._chunk_indexes: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._io = ThreadPoolExecutor(max_workers=1, thread_name_prefix="retriever-log-io")
        self._queued = 0  # chunk bytes handed to the I/O thread and not yet written
        self._written = threading.Condition()
        #: how often adding messages waited for the disk (MAX_BYTES_QUEUED), and for how long in all
        self.waits, self.waited_ns = 0, 0
        self._failure: BaseException | None = None
        self._submit(self._write, MAGIC)
        self._submit(self._write_record, Header(profile=profile, library=library))

    # -- the I/O thread -------------------------------------------------------------------
    def _submit(self, job, *args) -> None:
        if self._failure is not None:
            raise self._failure
        self._io.submit(self._run, job, args)

    def _run(self, job, args) -> None:
        if self._failure is None:
            try:
                job(*args)
            except BaseException as e:  # reported to the caller at its next call
                with self._written:  # a caller waiting for the disk stops waiting
                    self._failure = e
                    self._written.notify_all()

    def _write(self, data: bytes | bytearray) -> None:
        self._stream.write(data)
        self._data_crc = zlib.crc32(data, self._data_crc)
        self._offset += len(data)

    def _write_record(self, record: McapRecord) -> tuple[int, int]:
        builder = RecordBuilder()
        record.write(builder)
        data = builder.end()
        offset = self._offset
        self._write(data)
        return offset, len(data)

    def add_schema(self, name: str, encoding: str, data: bytes) -> int:
        """A schema for channels to name (Retriever's own channels have none: 0)."""
        schema = Schema(id=len(self._schemas) + 1, name=name, encoding=encoding, data=bytes(data))
        self._schemas.append(schema)
        self._submit(self._write_record, schema)
        return schema.id

    def add_channel(self, topic: str, message_encoding: str, metadata: dict[str, str], schema_id: int = 0) -> int:
        channel = Channel(id=len(self._channels) + 1, topic=topic, message_encoding=message_encoding,
                          metadata=dict(metadata), schema_id=schema_id)
        self._channels.append(channel)
        self._submit(self._write_record, channel)
        return channel.id

    def add_attachment(self, name: str, media_type: str, data: bytes, log_time: int = 0, create_time: int = 0) -> None:
        self._close_chunk()  # keep the file in call order: messages added before come first
        record = Attachment(log_time=log_time, create_time=create_time, name=name, media_type=media_type, data=data)
        self._submit(self._write_attachment, record)

    def _write_attachment(self, record: Attachment) -> None:
        offset, length = self._write_record(record)
        self._attachment_indexes.append(AttachmentIndex(
            offset=offset, length=length, log_time=record.log_time, create_time=record.create_time,
            data_size=len(record.data), name=record.name, media_type=record.media_type))

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self._close_chunk()  # keep the file in call order: messages added before come first
        self._submit(self._write_metadata, Metadata(name=name, metadata=dict(data)))

    def _write_metadata(self, record: Metadata) -> None:
        offset, length = self._write_record(record)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=record.name))

    # -- messages --------------------------------------------------------------------------
    def add_message(self, channel_id: int, log_time: int, publish_time: int, sequence: int, data: bytes) -> None:
        self.add_messages([(channel_id, log_time, publish_time, sequence, data)])

    def add_messages(self, messages: list[tuple[int, int, int, int, bytes]]) -> None:
        """Append ``(channel_id, log_time, publish_time, sequence, data)`` messages to the open chunk."""
        if not messages:
            return
        pack = MESSAGE_HEAD.pack
        records = [pack(Opcode.MESSAGE, MESSAGE_FIELDS + len(data), channel_id, sequence & _U32, log_time,
                        publish_time) + data for channel_id, log_time, publish_time, sequence, data in messages]
        times = [m[1] for m in messages]
        self.add_records(records, min(times), max(times), Counter(m[0] for m in messages))

    def add_records(self, records: list[bytes], start: int, end: int, counts: dict[int, int]) -> None:
        """Append whole Message records (built with :data:`MESSAGE_HEAD`), whose log times lie in
        ``[start, end]`` and which ``counts`` counts per channel: the hot path of the log writer."""
        if not records:
            return
        self._chunk += b"".join(records)
        self._lengths.extend(map(len, records))
        if self._chunk_times is None:
            self._chunk_times = [start, end]
        else:
            self._chunk_times[0] = min(self._chunk_times[0], start)
            self._chunk_times[1] = max(self._chunk_times[1], end)
        self._message_counts.update(counts)
        if len(self._chunk) >= self._chunk_size:
            self._close_chunk()

    def add_large_record(self, record: np.ndarray, log_time: int, channel_id: int) -> None:
        """Append one big Message record (its bytes, in a buffer nobody changes afterwards) in a
        chunk of its own: it is not copied on this thread, and the I/O thread compresses and
        writes it as it is."""
        self._close_chunk()
        self._start_time = log_time if self._start_time is None else min(self._start_time, log_time)
        self._end_time = max(self._end_time, log_time)
        self._message_counts[channel_id] += 1
        self._reserve(len(record))
        self._submit(self._write_large_chunk, record, log_time)

    def flush(self) -> None:
        """Close the open chunk and push everything to the OS (as soon as the I/O thread gets
        there): it then survives a kill."""
        self._close_chunk()
        self._submit(self._stream.flush)

    def wait(self) -> None:
        """Block until every queued write reached the OS; raise the first write that failed."""
        self._io.submit(_nothing).result()
        if self._failure is not None:
            raise self._failure

    def abandon(self) -> None:
        """Stop writing after a failure: let the I/O thread end; the file stays as it is."""
        self._finished = True
        self._io.shutdown(wait=True)

    def _close_chunk(self) -> None:
        if not self._chunk:
            return
        data, lengths, (start, end) = self._chunk, self._lengths, self._chunk_times
        self._chunk, self._lengths, self._chunk_times = bytearray(), [], None
        self._start_time = start if self._start_time is None else min(self._start_time, start)
        self._end_time = max(self._end_time, end)
        self._reserve(len(data))
        self._submit(self._write_chunk, data, lengths, start, end)

    def _reserve(self, size: int) -> None:
        """Count ``size`` chunk bytes as queued, once the queue is short enough (MAX_BYTES_QUEUED)."""
        with self._written:
            if self._queued > MAX_BYTES_QUEUED and self._failure is None:
                began = time.monotonic_ns()
                self.waits += 1
                self._written.wait_for(lambda: self._queued <= MAX_BYTES_QUEUED or self._failure is not None)
                self.waited_ns += time.monotonic_ns() - began
            self._queued += size

    def _written_out(self, size: int) -> None:
        with self._written:
            self._queued -= size
            self._written.notify_all()

    def _write_chunk(self, data: bytearray, lengths: list[int], start: int, end: int) -> None:
        try:
            self._compress_and_write(data, lengths, start, end)
        finally:
            self._written_out(len(data))

    def _write_large_chunk(self, record: np.ndarray, log_time: int) -> None:
        """The chunk of one big record, written without joining its parts (zstd, crc32 and file
        writes of big buffers let the run's other threads go on meanwhile)."""
        try:
            compressed = self._compressor.compress(record)
            fields = CHUNK_FIELDS + len(_ZSTD) + len(compressed)
            chunk_head = (CHUNK_HEAD.pack(Opcode.CHUNK, fields, log_time, log_time, len(record), zlib.crc32(record),
                                          len(_ZSTD)) + _ZSTD + len(compressed).to_bytes(8, "little"))
            chunk_offset = self._offset
            [(channel_id, index)] = message_indexes(record, [len(record)])
            self._write(chunk_head)
            self._write(compressed)
            self._write(index)
            self._chunk_indexes.append(ChunkIndex(
                message_start_time=log_time, message_end_time=log_time, chunk_start_offset=chunk_offset,
                chunk_length=1 + 8 + fields, message_index_offsets={channel_id: chunk_offset + 1 + 8 + fields},
                message_index_length=len(index), compression="zstd", compressed_size=len(compressed),
                uncompressed_size=len(record)))
        finally:
            self._written_out(len(record))

    def _compress_and_write(self, data: bytearray, lengths: list[int], start: int, end: int) -> None:
        compressed = self._compressor.compress(data)
        builder = RecordBuilder()
        Chunk(message_start_time=start, message_end_time=end, uncompressed_size=len(data),
              uncompressed_crc=zlib.crc32(data), compression="zstd", data=compressed).write(builder)
        chunk = builder.end()
        chunk_offset = self._offset
        indexes = message_indexes(data, lengths)
        offsets, at = {}, chunk_offset + len(chunk)
        for channel_id, record in indexes:
            offsets[channel_id] = at
            at += len(record)
        # one write: a kill leaves the chunk with its indexes, or a torn record at the end
        self._write(b"".join([chunk, *(record for _, record in indexes)]))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_offset,
            chunk_length=len(chunk), message_index_offsets=offsets,
            message_index_length=at - chunk_offset - len(chunk), compression="zstd", compressed_size=len(compressed), uncompressed_size=len(data)))

    # -- the end ---------------------------------------------------------------------------
    def finish(self) -> None:
        """Write the summary (channels, statistics, indexes) and the footer. Idempotent."""
        if self._finished:
            return
        self._finished = True
        self._close_chunk()
        self._io.shutdown(wait=True)  # every queued write is done: the thread's state is ours now
        if self._failure is not None:
            raise self._failure
        self._write_record(DataEnd(data_section_crc=self._data_crc))
        summary_start = self._offset
        summary = RecordBuilder()
        offsets: list[SummaryOffset] = []

        def group(opcode: int, records: list) -> None:
            if not records:
                return
            begin = summary.count
            for r in records:
                r.write(summary)
            offsets.append(SummaryOffset(group_opcode=opcode, group_start=summary_start + begin,
                                         group_length=summary.count - begin))

        group(Opcode.SCHEMA, self._schemas)
        group(Opcode.CHANNEL, self._channels)
        group(Opcode.STATISTICS, [Statistics(
            message_count=sum(self._message_counts.values()), schema_count=len(self._schemas),
            channel_count=len(self._channels), attachment_count=len(self._attachment_indexes),
            metadata_count=len(self._metadata_indexes), chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_time or 0, message_end_time=self._end_time,
            channel_message_counts=dict(self._message_counts))])
        group(Opcode.CHUNK_INDEX, self._chunk_indexes)
        group(Opcode.ATTACHMENT_INDEX, self._attachment_indexes)
        group(Opcode.METADATA_INDEX, self._metadata_indexes)
        summary_offset_start = summary_start + summary.count
        for offset in offsets:
            offset.write(summary)
        summary_data = summary.end()
        crc = zlib.crc32(summary_data)
        crc = zlib.crc32(struct.pack("<BQQQ", Opcode.FOOTER, 20, summary_start, summary_offset_start), crc)
        self._stream.write(summary_data)
        footer = RecordBuilder()
        Footer(summary_start=summary_start, summary_offset_start=summary_offset_start, summary_crc=crc).write(footer)
        self._stream.write(footer.end())
        self._stream.write(MAGIC)
        self._stream.flush()


def message_indexes(chunk: bytes | bytearray, lengths: list[int]) -> list[tuple[int, bytes]]:
    """The MessageIndex records of a chunk of Message records whose lengths are ``lengths``:
    ``(channel_id, record)`` by channel id, each listing ``(log_time, offset in the chunk)`` in
    log-time order (ties in file order)."""
    sizes = np.array(lengths, dtype=np.int64)
    offsets = np.cumsum(sizes) - sizes
    raw = np.frombuffer(chunk, dtype=np.uint8)
    channels = raw[offsets + _CHANNEL_AT].astype(np.uint16) | (raw[offsets + _CHANNEL_AT + 1].astype(np.uint16) << 8)
    times = np.ascontiguousarray(raw[offsets[:, None] + _LOG_TIME_BYTES]).view("<u8").ravel()
    order = np.lexsort((times, channels))  # by channel, then log time; stable
    channels, entries = channels[order], np.empty((len(order), 2), dtype="<u8")
    entries[:, 0], entries[:, 1] = times[order], offsets[order]
    firsts = np.flatnonzero(np.r_[True, channels[1:] != channels[:-1]])
    records = []
    for first, last in zip(firsts, [*firsts[1:], len(order)]):
        body = entries[first:last].tobytes()
        channel_id = int(channels[first])
        records.append((channel_id, MESSAGE_INDEX_HEAD.pack(Opcode.MESSAGE_INDEX, 2 + 4 + len(body), channel_id,
                                                             len(body)) + body))
    return records
