"""``McapFile``: the bytes of one MCAP file, in order, as the I/O thread writes them (mcap_io.py).

It knows where each record lands, keeps the data section's CRC and the index records the summary
lists, compresses chunks, and at the end writes the summary and the footer. Only the I/O thread
calls it until the writer has shut that thread down; then the writer's thread finishes the file.
"""

from __future__ import annotations

import struct
import zlib
from collections import Counter
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
    McapRecord,
    Metadata,
    MetadataIndex,
    Schema,
    Statistics,
    SummaryOffset,
)

from .mcap_records import MAGIC, ZSTD, ChunkIndexes, chunk_fields, chunk_head, record_bytes


class McapFile:
    """Writes records to ``stream`` and remembers what the summary indexes and counts."""

    def __init__(self, stream: BinaryIO):
        self._stream = stream
        self._compressor = zstandard.ZstdCompressor(level=1)
        self._offset = 0
        self._data_crc = 0
        self._chunk_indexes: list[ChunkIndex] = []
        self._attachment_indexes: list[AttachmentIndex] = []
        self._metadata_indexes: list[MetadataIndex] = []
        self._message_counts: Counter[int] = Counter()
        self._start_time: int | None = None  # of the messages written so far
        self._end_time = 0
        #: each channel's latest log time among the messages written so far (another thread reads
        #: it only once the I/O thread is idle: McapWriter.channel_end_time waits for it)
        self.channel_end_times: dict[int, int] = {}

    def write(self, data: bytes | bytearray) -> None:
        """Bytes of the data section, as they are."""
        self._stream.write(data)
        self._data_crc = zlib.crc32(data, self._data_crc)
        self._offset += len(data)

    def write_record(self, record: McapRecord) -> tuple[int, int]:
        """One record of ``mcap``'s classes; where it begins, and its length."""
        data = record_bytes(record)
        offset = self._offset
        self.write(data)
        return offset, len(data)

    def write_attachment(self, record: Attachment) -> None:
        offset, length = self.write_record(record)
        self._attachment_indexes.append(AttachmentIndex(
            offset=offset, length=length, log_time=record.log_time, create_time=record.create_time,
            data_size=len(record.data), name=record.name, media_type=record.media_type))

    def write_metadata(self, record: Metadata) -> None:
        offset, length = self.write_record(record)
        self._metadata_indexes.append(MetadataIndex(offset=offset, length=length, name=record.name))

    def flush(self) -> None:
        """Push what is written to the OS: it then survives a kill."""
        self._stream.flush()

    def write_chunk(self, data: bytearray, lengths: list[int]) -> None:
        """A chunk of Message records whose lengths are ``lengths``, compressed, with its
        MessageIndex records after it."""
        compressed = self._compressor.compress(data)
        read = ChunkIndexes(data, lengths)
        start, end = read.start_time, read.end_time
        builder = RecordBuilder()
        Chunk(message_start_time=start, message_end_time=end, uncompressed_size=len(data),
              uncompressed_crc=zlib.crc32(data), compression=ZSTD, data=compressed).write(builder)
        chunk = builder.end()
        chunk_offset = self._offset
        offsets, at = {}, chunk_offset + len(chunk)
        for channel_id, record in read.records:
            offsets[channel_id] = at
            at += len(record)
        # one write: a kill leaves the chunk with its indexes, or a torn record at the end
        self.write(b"".join([chunk, *(record for _, record in read.records)]))
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=start, message_end_time=end, chunk_start_offset=chunk_offset,
            chunk_length=len(chunk), message_index_offsets=offsets,
            message_index_length=at - chunk_offset - len(chunk), compression=ZSTD, compressed_size=len(compressed),
            uncompressed_size=len(data)))
        self._tally(read)

    def write_large_chunk(self, record: np.ndarray) -> None:
        """The chunk of one big record, written without joining its parts (zstd, crc32 and file
        writes of big buffers let the run's other threads go on meanwhile)."""
        compressed = self._compressor.compress(record)
        read = ChunkIndexes(record, [len(record)])
        log_time = read.start_time
        fields = chunk_fields(len(compressed))
        head = chunk_head(log_time, len(record), zlib.crc32(record), len(compressed))
        chunk_offset = self._offset
        [(channel_id, index)] = read.records
        self.write(head)
        self.write(compressed)
        self.write(index)
        self._chunk_indexes.append(ChunkIndex(
            message_start_time=log_time, message_end_time=log_time, chunk_start_offset=chunk_offset,
            chunk_length=1 + 8 + fields, message_index_offsets={channel_id: chunk_offset + 1 + 8 + fields},
            message_index_length=len(index), compression=ZSTD, compressed_size=len(compressed),
            uncompressed_size=len(record)))
        self._tally(read)

    def _tally(self, read: ChunkIndexes) -> None:
        """Count a chunk's messages into the summary's statistics."""
        self._message_counts.update(read.counts)
        self._start_time = read.start_time if self._start_time is None else min(self._start_time, read.start_time)
        self._end_time = max(self._end_time, read.end_time)
        ends = self.channel_end_times
        for channel_id, end in read.channel_end_times.items():
            ends[channel_id] = max(ends.get(channel_id, 0), end)

    def finish(self, schemas: list[Schema], channels: list[Channel]) -> None:
        """End the data section, then write the summary (schemas, channels, statistics, indexes),
        the footer and the closing magic."""
        self.write_record(DataEnd(data_section_crc=self._data_crc))
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

        group(Opcode.SCHEMA, schemas)
        group(Opcode.CHANNEL, channels)
        counts = self._message_counts
        group(Opcode.STATISTICS, [Statistics(
            message_count=sum(counts.values()), schema_count=len(schemas),
            channel_count=len(channels), attachment_count=len(self._attachment_indexes),
            metadata_count=len(self._metadata_indexes), chunk_count=len(self._chunk_indexes),
            message_start_time=self._start_time or 0, message_end_time=self._end_time,
            channel_message_counts=dict(sorted(counts.items())))])
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
