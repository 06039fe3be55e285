"""A log opens in the MCAP readers users have (issue 41 §5): readers that seek find a chunk's
messages through its MessageIndex records, so every chunk of a log carries them.

Two independent readers: Foxglove's TypeScript ``McapIndexedReader`` (``@mcap/core`` from npm,
what the Foxglove app uses; it refuses a chunk without message indexes), and the records
themselves read with the ``mcap`` Python package (whose ``SeekingReader`` scans whole chunks and
does not need them, so the test reads the indexes and checks each entry against its message).
"""

from __future__ import annotations

import io
import json
import os
import random
import shutil
import subprocess
import zlib
from pathlib import Path

import pytest
import zstandard
from mcap.data_stream import ReadDataStream
from mcap.reader import make_reader
from mcap.records import Chunk, MessageIndex
from mcap.stream_reader import breakup_chunk

from retriever import read_log
from retriever.loading import load_pipeline
from retriever.log.mcap_writer import McapWriter
from retriever.log.ros2 import export_ros2
from tests.log.export_flows import camera_log
from tests.log.helpers import CHUNK, QUICKSTART, records

HERE = Path(__file__).resolve().parent
MCAP_JS = ("@mcap/core@2.2.2", "fzstd@0.1.1")  # the reader Foxglove's app uses, and a zstd decoder for it
NPM_TIMEOUT = 300.0


@pytest.fixture(scope="module")
def quickstart_log(tmp_path_factory) -> Path:
    path = tmp_path_factory.mktemp("indexed") / "quickstart.mcap"
    pipe = load_pipeline(str(QUICKSTART))  # the module's pipeline, which other tests may have run
    pipe.reset()
    try:
        pipe.run(duration=3.0, log=path)
    finally:
        pipe.reset()
    return path


def _small_chunks_log(path: Path) -> list[tuple]:
    """Three channels, out-of-order log times within chunks, many small chunks: the messages."""
    rng = random.Random(7)
    messages = [(rng.choice((1, 2, 3)), rng.randrange(10**9), rng.randrange(10**9), i, rng.randbytes(rng.randrange(40)))
                for i in range(3000)]
    with path.open("wb") as f:
        writer = McapWriter(f, profile="retriever", chunk_size=2000)
        for topic in ("a", "b", "c"):
            writer.add_channel(topic, "msgpack", {})
        for start in range(0, len(messages), 37):
            writer.add_messages(messages[start:start + 37])
        writer.finish()
    return messages


def _check_message_indexes(path: Path) -> int:
    """Every chunk's MessageIndex records, as its ChunkIndex places them, list each of its messages
    once, with its channel, log time and offset, in log-time order; the messages in all."""
    data = path.read_bytes()
    summary = make_reader(io.BytesIO(data)).get_summary()
    assert summary is not None and summary.chunk_indexes
    total = 0
    for chunk_index in summary.chunk_indexes:
        stream = ReadDataStream(io.BytesIO(data[chunk_index.chunk_start_offset + 9:]))
        chunk = Chunk.read(stream)
        records = zstandard.ZstdDecompressor().decompress(chunk.data, max_output_size=chunk.uncompressed_size)
        assert zlib.crc32(records) == chunk.uncompressed_crc
        starts, pos = [], 0
        while pos < len(records):
            starts.append(pos)
            pos += 9 + int.from_bytes(records[pos + 1:pos + 9], "little")
        offsets = dict(zip(starts, breakup_chunk(chunk, validate_crc=True), strict=True))
        assert chunk_index.message_index_offsets, "a chunk without message indexes: indexed readers skip it"
        assert set(chunk_index.message_index_offsets) == {m.channel_id for m in offsets.values()}
        listed = []
        index_end = chunk_index.chunk_start_offset + chunk_index.chunk_length
        for channel_id, offset in chunk_index.message_index_offsets.items():
            assert data[offset] == 0x07
            index = MessageIndex.read(ReadDataStream(io.BytesIO(data[offset + 9:])))
            assert index.channel_id == channel_id
            assert [t for t, _ in index.records] == sorted(t for t, _ in index.records)
            for log_time, at in index.records:
                message = offsets[at]
                assert (message.channel_id, message.log_time) == (channel_id, log_time)
                listed.append(at)
            index_end = max(index_end, offset + 9 + int.from_bytes(data[offset + 1:offset + 9], "little"))
        assert sorted(listed) == sorted(offsets), "each message of the chunk is listed exactly once"
        assert chunk_index.message_index_length == index_end - chunk_index.chunk_start_offset - chunk_index.chunk_length
        total += len(offsets)
    return total


def test_every_chunk_of_a_log_carries_message_indexes_that_find_its_messages(quickstart_log):
    count = _check_message_indexes(quickstart_log)
    log = read_log(quickstart_log)
    assert count == len(log.messages) > 1000
    with quickstart_log.open("rb") as f:
        reader = make_reader(f, validate_crcs=True)
        indexed = list(reader.iter_messages())
        assert len(indexed) == reader.get_summary().statistics.message_count == count


def test_message_indexes_of_many_small_chunks_with_unordered_times(tmp_path):
    path = tmp_path / "small_chunks.mcap"
    messages = _small_chunks_log(path)
    assert len(make_reader(io.BytesIO(path.read_bytes())).get_summary().chunk_indexes) > 20
    assert _check_message_indexes(path) == len(messages)


# ---------------------------------------------------------------------------------------------
# Foxglove's TypeScript reader
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def mcap_js() -> Path:
    """``node_modules`` holding @mcap/core and fzstd, installed from npm once per machine."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("node and npm are not installed: Foxglove's TypeScript MCAP reader cannot run here")
    cache = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "retriever-tests" / "mcap-js"
    modules = cache / "node_modules"
    if not all((modules / name.rpartition("@")[0] / "package.json").exists() for name in MCAP_JS):
        cache.mkdir(parents=True, exist_ok=True)
        try:
            done = subprocess.run([npm, "install", "--prefix", str(cache), "--no-audit", "--no-fund", "--no-save",
                                   "--fetch-retries=1", "--fetch-timeout=30000", *MCAP_JS],
                                  capture_output=True, text=True, timeout=NPM_TIMEOUT)
        except subprocess.TimeoutExpired:
            pytest.skip(f"npm install {' '.join(MCAP_JS)} took over {NPM_TIMEOUT:g} s (is the npm registry reachable?)")
        if done.returncode != 0:
            pytest.skip(f"npm install {' '.join(MCAP_JS)} failed (is the npm registry reachable?): "
                        f"{(done.stderr.strip().splitlines() or ['no output'])[0]}")
    return modules


def _read_with_mcap_js(modules: Path, path: Path) -> dict:
    done = subprocess.run(["node", str(HERE / "mcap_indexed_read.mjs"), str(path)], capture_output=True, text=True,
                          timeout=120, env={**os.environ, "MCAP_JS_MODULES": str(modules)})
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_foxglove_s_typescript_indexed_reader_reads_every_message(mcap_js, quickstart_log):
    read = _read_with_mcap_js(mcap_js, quickstart_log)
    log = read_log(quickstart_log)
    topics: dict[str, int] = {}
    for m in log.messages:
        topic = log.channels[m.channel_id].topic
        topics[topic] = topics.get(topic, 0) + 1
    assert read["topics"] == topics and read["statistics"] == len(log.messages)
    assert read["times"] == sorted(m.log_time for m in log.messages), "in log-time order, as the app shows them"


def test_foxglove_s_typescript_reader_reads_many_small_chunks(mcap_js, tmp_path):
    path = tmp_path / "small_chunks.mcap"
    messages = _small_chunks_log(path)
    read = _read_with_mcap_js(mcap_js, path)
    assert read["topics"] == {topic: sum(1 for m in messages if m[0] == channel)
                              for channel, topic in ((1, "a"), (2, "b"), (3, "c"))}
    assert read["times"] == sorted(m[1] for m in messages)


def test_in_a_killed_log_each_whole_chunk_is_followed_by_its_message_indexes(tmp_path):
    """What a recovering importer (Rerun's ``mcap convert --recover``) reads of a log whose writer
    was killed: no summary, so each chunk's own MessageIndex records, right after it."""
    path = tmp_path / "small_chunks.mcap"
    _small_chunks_log(path)
    data = path.read_bytes()[:path.stat().st_size // 2]
    whole = [(opcode, offset, length) for opcode, offset, length in records(data) if offset + 9 + length <= len(data)]
    chunks = [i for i, (opcode, _, _) in enumerate(whole) if opcode == CHUNK]
    assert len(chunks) > 5
    for i in chunks[:-1]:
        chunk = Chunk.read(ReadDataStream(io.BytesIO(data[whole[i][1] + 9:])))
        channels = {m.channel_id for m in breakup_chunk(chunk)}
        following = []
        for opcode, offset, _ in whole[i + 1:]:
            if opcode != 0x07:
                break
            following.append(MessageIndex.read(ReadDataStream(io.BytesIO(data[offset + 9:]))))
        assert {index.channel_id for index in following} == channels
        assert sum(len(index.records) for index in following) == len(breakup_chunk(chunk))


def test_foxglove_s_typescript_reader_reads_the_ros2_export(mcap_js, tmp_path):
    """The ROS 2 export (log/ros2.py), read by a reader nobody here wrote: the ROS 2 profile,
    ros2msg schemas, CDR channels, and every message at the time the export gave it."""
    out = tmp_path / "run_ros2.mcap"
    done = export_ros2(read_log(camera_log(tmp_path)), out)
    read = _read_with_mcap_js(mcap_js, out)
    assert read["profile"] == "ros2" and read["schemaEncodings"] == ["ros2msg"] and read["messageEncodings"] == ["cdr"]
    assert read["topics"] == dict(done.written) and read["statistics"] == sum(done.written.values())
    with open(out, "rb") as f:
        times = sorted(message.log_time for _, _, message in make_reader(f).iter_messages())
    assert read["times"] == times
