"""``retriever replay`` streams the log (issue 42), and so does ``retriever replay --resim``: its
memory stays flat however long the log, it reads the messages in log-time order a few chunks at a
time, it says the same as a replay (a re-simulation) of the log read whole, and it shows its
progress on a terminal (and nothing on a pipe)."""

from __future__ import annotations

import os
import pty
import re
import select
import subprocess
import sys
from pathlib import Path

import msgpack
import pytest
from mcap.opcode import Opcode

from retriever import Latest, LogError, Pipeline, Rate, read_log
from retriever.backends.inproc import InprocSession
from retriever.log import LogWriter
from retriever.log.reader import scan_log
from retriever.replay import replay, replay_file, resim, resim_file
from retriever.log.format import RECOVERED_METADATA
from tests.log.helpers import RETRIEVER, chunks, cli, cli_env, rewrite
from tests.log.helpers import records as file_records
from tests.log.log_flows import Brightness, Frames, build_frames


def _frames_log(path: Path, seconds: float, batch: int = 16) -> Path:
    """A log of ``build_frames()`` (64 KiB of noise a frame at 30 Hz: about 2 MB a second), a
    chunk every ``batch`` steps: a chunk is read whole, so the chunks' size, which the writer
    otherwise sets by the wall clock, bounds what a replay holds."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(InprocSession, "LOG_BATCH", batch)
        mp.setitem(LogWriter.__init__.__kwdefaults__, "flush_interval", 0.0)
        build_frames().run(duration=seconds, log=path, keep="counters")
    return path


_PEAK = ("import resource, subprocess, sys\n"
         "done = subprocess.run(sys.argv[1:], capture_output=True, text=True)\n"
         "print(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss)\n"
         "sys.stdout.write(done.stdout + done.stderr)\n"
         "sys.exit(done.returncode)\n")


def _replay_peak_rss_kib(log: Path, *flags: str) -> int:
    """The peak RSS of ``retriever replay [FLAGS] LOG``, in KiB: measured by a process of its own,
    whose only child is the replay (RUSAGE_CHILDREN is the largest child a process waited for)."""
    done = subprocess.run([sys.executable, "-c", _PEAK, str(RETRIEVER), "replay", *flags, str(log)],
                          capture_output=True, text=True, env=cli_env(), timeout=240)
    peak, _, output = done.stdout.partition("\n")
    assert done.returncode == 0 and "identical:" in output, output
    return int(peak)


@pytest.fixture(scope="module")
def frames_logs(tmp_path_factory) -> tuple[Path, Path]:
    """A log and one 8 times as long: 4 MB and 32 MB of frames."""
    folder = tmp_path_factory.mktemp("lengths")
    short = _frames_log(folder / "short.mcap", 2.0)
    long = _frames_log(folder / "long.mcap", 16.0)
    assert long.stat().st_size > 7.5 * short.stat().st_size > 7.5 * 3e6
    return short, long


@pytest.mark.parametrize("flags", [(), ("--resim",)], ids=["replay", "resim"])
def test_replay_memory_is_flat_however_long_the_log(frames_logs, flags):
    """A log 8 times as long (4 MB and 32 MB of frames) replays, and re-simulates, in the same
    memory, within a few MB: before the replay streamed, every message was held, and every frame
    decoded (+83 MB); before the re-simulation streamed, it grew by 27 MB."""
    short, long = frames_logs
    one, eight = _replay_peak_rss_kib(short, *flags), _replay_peak_rss_kib(long, *flags)
    assert eight - one < 16 * 1024, f"peak RSS {one} KiB for the 1x log, {eight} KiB for the 8x log"


def test_a_message_that_waits_past_its_chunk_does_not_keep_the_chunk(tmp_path):
    """Reading in log-time order (``time_ordered``, what the replay reads) holds a message until no
    chunk still to be read can come before it: a LET output 2 s late waits 60 frames. It keeps its
    own data, not its chunk's 64 KiB frames: 1.4 MB at most here (before: every chunk with a
    waiting output, 8.8 MB; a forged far-future message in every chunk kept the whole log)."""
    import tracemalloc

    with Pipeline("late_outputs") as pipe:
        camera = Frames(1 << 16).named("camera") @ Rate(hz=30)
        camera.then(Brightness().named("brightness").configure(latency=2.0) @ Rate(hz=30, offset=0.01), sync=Latest())
    path = tmp_path / "late.mcap"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(InprocSession, "LOG_BATCH", 8)
        mp.setitem(LogWriter.__init__.__kwdefaults__, "flush_interval", 0.0)
        pipe.run(duration=4.0, log=path, keep="counters")
    log = scan_log(path, lambda channels, messages: None)
    assert len(log.chunks) > 30
    tracemalloc.start()
    try:
        count = sum(1 for _ in log.time_ordered())
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert count > 300
    assert peak < 2_000_000, f"{peak} bytes held at most while reading in log-time order"


def test_message_indexes_that_cannot_tile_their_chunk_are_not_kept(small_chunks, tmp_path):
    """A forged log with 4.8 MB of MessageIndex records after its first chunk (more than could
    tile it) reads the same messages, both ways, holding none of them: before, every one was kept
    and joined (17 MB at most, 3.5 times their size)."""
    import struct
    import tracemalloc

    from mcap.writer import IndexType

    # no summary and no chunk indexes: nothing points past the forged records, so the file reads whole
    plain = rewrite(small_chunks, tmp_path / "plain.mcap", writer_options={
        "index_types": IndexType.MESSAGE, "use_summary_offsets": False, "use_statistics": False,
        "repeat_channels": False, "repeat_schemas": False, "chunk_size": 1 << 18})
    data = plain.read_bytes()
    found = file_records(data)
    first = next(i for i, (opcode, _, _) in enumerate(found) if opcode == Opcode.CHUNK)
    after = next(offset for opcode, offset, _ in found[first + 1:] if opcode != Opcode.MESSAGE_INDEX)
    body = struct.pack("<HI", 1, 16 * 1000) + b"".join(struct.pack("<QQ", 0, 8 * k) for k in range(1000))
    extra = (bytes([Opcode.MESSAGE_INDEX]) + struct.pack("<Q", len(body)) + body) * 300
    forged = tmp_path / "forged.mcap"
    forged.write_bytes(data[:after] + extra + data[after:])

    def read(path):
        """The messages in log-time order (their data by its hash), and the peaks of memory of
        the two readings."""
        tracemalloc.start()
        try:
            log = scan_log(path, lambda channels, messages: None)
            in_file_order = tracemalloc.get_traced_memory()[1]
            tracemalloc.reset_peak()
            messages = [(m[0], m[2], m[3], hash(m[5])) for m in log.time_ordered()]
            return messages, in_file_order, tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()

    messages, scan_plain, ordered_plain = read(plain)
    forged_messages, scan_forged, ordered_forged = read(forged)
    assert forged_messages == messages and len(messages) > 300
    assert scan_forged < scan_plain + 1_000_000 and ordered_forged < ordered_plain + 1_000_000, \
        (scan_plain, scan_forged, ordered_plain, ordered_forged)


# ---------------------------------------------------------------------------------------------
# Read in log-time order, a few chunks at a time; the same report as the log read whole
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def small_chunks(tmp_path_factory) -> Path:
    """A frames log cut into a chunk every 8 steps: the LET outputs of one chunk's ticks are in the
    next ones, so chunks overlap in time."""
    path = _frames_log(tmp_path_factory.mktemp("frames") / "frames.mcap", 3.0, batch=8)
    assert len(chunks(path.read_bytes())) > 20
    return path


def _fields(m) -> tuple:
    """A message's fields, of an ``mcap`` Message or of a message tuple (log/reader.py)."""
    if type(m) is tuple:
        log_time, _, channel_id, sequence, publish_time, data = m
        return (log_time, channel_id, sequence, publish_time, data)
    return (m.log_time, m.channel_id, m.sequence, m.publish_time, m.data)


def test_time_ordered_is_the_files_messages_sorted_by_log_time(small_chunks):
    seen = []
    scanned = scan_log(small_chunks, lambda channels, messages: seen.extend(messages))
    whole = read_log(small_chunks).messages
    assert [m[0] for m in seen] == [m.log_time for m in whole] != sorted(m.log_time for m in whole)
    assert list(map(_fields, seen)) == list(map(_fields, whole))
    assert all(a[1] < b[1] for a, b in zip(seen, seen[1:])), "positions increase in file order"
    ordered = list(scanned.time_ordered())
    # ties in file order: the sort is stable
    assert list(map(_fields, ordered)) == list(map(_fields, sorted(whole, key=lambda m: m.log_time)))


def test_in_order_is_time_ordered_in_columns_read_by_the_indexes_or_not(small_chunks, tmp_path):
    """``in_order``'s batches are ``time_ordered``'s messages, positions left out; both read a
    log the same whether its chunks are walked by their MessageIndex records (as written) or
    not (a copy without them, in small chunks: walked one record at a time), and the replay of
    either says what the replay of the log read whole says."""
    from mcap.writer import IndexType

    unindexed = rewrite(small_chunks, tmp_path / "unindexed.mcap",
                        writer_options={"index_types": IndexType.CHUNK, "chunk_size": 100_000})
    opcodes = [opcode for opcode, _, _ in file_records(unindexed.read_bytes())]
    assert opcodes.count(Opcode.CHUNK) > 20 and Opcode.MESSAGE_INDEX not in opcodes
    for path in (small_chunks, unindexed):
        scanned = scan_log(path, lambda channels, messages: None)
        ordered = list(scanned.time_ordered())
        whole = read_log(path).messages
        assert list(map(_fields, ordered)) == list(map(_fields, sorted(whole, key=lambda m: m.log_time)))
        assert sorted(m[1] for m in ordered) == sorted(set(m[1] for m in ordered)), "positions unique"
        batches = list(scanned.in_order())
        assert len(batches) > 1
        columns = [sum((list(batch[k]) for batch in batches), []) for k in range(5)]
        assert list(zip(*columns)) == list(map(_fields, ordered))
        _same(replay(read_log(path)), replay_file(path))


def _same(a, b) -> None:
    assert a.nodes == b.nodes
    assert (a.divergent_steps, list(map(str, a.divergences))) == (b.divergent_steps, list(map(str, b.divergences)))
    assert a.code_changes == b.code_changes


def test_replay_file_says_what_replay_of_the_log_read_whole_says(small_chunks):
    whole, streamed = replay(read_log(small_chunks)), replay_file(small_chunks)
    _same(whole, streamed)
    assert streamed.identical and streamed.nodes["brightness"].identical == 90


def _same_resim(a, b) -> None:
    def said(report) -> tuple:  # (a re-simulated event's publish time is when the re-simulation made it)
        difference = None if report.difference is None else re.sub(r"publish_ns=\d+\)$", ")", report.difference)
        return report.horizon_ns, report.steps_compared, report.events_compared, difference, report.code_changes

    assert said(a) == said(b)


def test_resim_file_says_what_resim_of_the_log_read_whole_says(small_chunks):
    whole, streamed = resim(read_log(small_chunks)), resim_file(small_chunks)
    _same_resim(whole, streamed)
    assert streamed.identical and streamed.steps_compared == 180


class Dimmer(Brightness):
    """Half the brightness from its 10th frame on: a divergence at every later step."""

    def step(self, frame):
        out = super().step(frame)
        return {**out, "mean": out["mean"] / 2} if self.seen >= 10 else out


def _dimmed():
    from retriever import Latest, Pipeline, Rate

    with Pipeline("frames") as pipe:
        camera = Frames().named("camera") @ Rate(hz=30)
        brightness = Dimmer().named("brightness").configure(latency=0.1) @ Rate(hz=30, offset=0.01)
        camera.then(brightness, sync=Latest())
    return pipe


def test_a_divergence_is_reported_in_step_order_as_before(small_chunks):
    """Each LET step is compared when its outputs are read, 0.1 s of log later; the divergences
    are still reported in step order, the first first."""
    whole, streamed = replay(read_log(small_chunks), _dimmed()), replay_file(small_chunks, _dimmed)
    _same(whole, streamed)
    assert streamed.divergent_steps == 81
    assert str(streamed.divergences[0]).startswith("brightness.mean at tick t=0.310000000s m=0: value differs")


def test_a_divergence_is_resimulated_as_before(small_chunks):
    """The first difference of the two traces, an event's value 0.41 s in (a LET output whose tag
    is in the second after the tick's, when the window is 0.1 s), as the whole traces say it."""
    import retriever.replay.resimulation as resimulation

    whole = resim(read_log(small_chunks), _dimmed())
    assert whole.difference.startswith("record 31: Event(tag=(410000000, 0), node='brightness', port='mean', seq=9")
    with pytest.MonkeyPatch.context() as mp:
        for window in (10**9, 10**8, 7 * 10**6):
            mp.setattr(resimulation, "WINDOW_NS", window)
            _same_resim(whole, resim_file(small_chunks, _dimmed))


def test_a_log_without_an_output_replays_as_before(small_chunks, tmp_path):
    """The outputs of one LET step left out: a divergence (<not in the log>) in a log that says it
    is whole; a step not compared (``cut``) in one that says it was recovered."""
    def keep(topic, message) -> bool:
        return not (topic.startswith("data/brightness/") and message.sequence == 20)

    missing = rewrite(small_chunks, tmp_path / "missing.mcap", keep=keep)
    cut = rewrite(small_chunks, tmp_path / "cut.mcap", keep=keep, add={RECOVERED_METADATA: {"source": "x"}})
    reports = {}
    for path, divergent, not_compared in ((missing, 1, 0), (cut, 0, 1)):
        whole, reports[path] = replay(read_log(path)), replay_file(path)
        _same(whole, reports[path])
        _same_resim(resim(read_log(path)), resim_file(path))
        assert (reports[path].divergent_steps, reports[path].nodes["brightness"].cut) == (divergent, not_compared)
    first = str(reports[missing].divergences[0])
    assert "value differs\n      logged:   '<not in the log: the log ends here>'" in first


@pytest.mark.parametrize("field, value", [(4, "exploded"), (1, -1), (3, [["brightness", "mean"]]), (6, 1.5)])
def test_a_step_record_that_is_not_one_mid_log_is_refused_by_both(small_chunks, tmp_path, field, value):
    """A step record without detail that is not one, in the middle of the log: the survey reads only
    its node, the replay refuses the log where it reads it, with the error a replay of the log read
    whole gives, and no report."""
    import msgpack

    def keep(topic, message) -> bool:
        if topic == "steps" and message.sequence == 60:
            record = msgpack.unpackb(message.data)
            assert record[5] is None
            record[field] = value
            message.data = msgpack.packb(record)
        return True

    changed = rewrite(small_chunks, tmp_path / "changed.mcap", keep=keep)
    said = []
    for run in (lambda: replay(read_log(changed)), lambda: replay_file(changed), lambda: resim(read_log(changed)),
                lambda: resim_file(changed)):
        with pytest.raises(LogError, match=r"step record #60 is malformed") as raised:
            run()
        said.append(str(raised.value))
    assert said[0] == said[1] == said[2] == said[3]


# ---------------------------------------------------------------------------------------------
# Progress: a bar on a terminal, nothing on a pipe
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("flags", [(), ("--resim",)], ids=["replay", "resim"])
def test_replay_shows_its_progress_on_a_terminal(small_chunks, flags):
    main, tty = pty.openpty()
    env = {**cli_env(), "TERM": "xterm-256color"}
    with subprocess.Popen([str(RETRIEVER), "replay", *flags, str(small_chunks)], stdout=subprocess.PIPE, stderr=tty,
                          env=env) as proc:
        os.close(tty)
        shown = b""
        while True:  # read the terminal while the replay writes to it (its buffer is small)
            ready, _, _ = select.select([main], [], [], 60)
            try:
                data = os.read(main, 65536) if ready else b""
            except OSError:  # EIO: the replay closed its end
                data = b""
            if not data:
                break
            shown += data
        out = proc.stdout.read().decode()
        assert proc.wait(timeout=60) == 0, out
    os.close(main)
    text = re.sub(r"\x1b\[[0-9;?]*[A-Za-z]", "", shown.decode(errors="replace"))
    assert "identical:" in out
    assert re.search(r"reading .*100%.* MB", text), text
    assert re.search(r"replaying .*100%.*180 of 180 steps", text), text


@pytest.mark.parametrize("flags", [(), ("--resim",)], ids=["replay", "resim"])
def test_replay_prints_no_progress_on_a_pipe(small_chunks, flags):
    done = cli("replay", *flags, small_chunks)
    assert done.returncode == 0 and "identical:" in done.stdout, done.stdout + done.stderr
    assert done.stderr == ""


def test_a_log_changed_between_the_two_readings_is_refused(small_chunks, tmp_path):
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(small_chunks.read_bytes())
    scanned = scan_log(copy, lambda channels, messages: None)
    with open(copy, "ab") as f:
        f.write(b"\0")
    with pytest.raises(LogError, match=r"copy\.mcap changed since it was read\n    hint: read it again"):
        next(scanned.time_ordered())


def test_a_log_written_to_in_place_as_its_second_reading_goes_is_refused(small_chunks, tmp_path):
    """The second reading does not check a chunk's CRC again (the file is the same as the first
    read through): a byte of a later chunk overwritten in place once that reading has begun (the
    size kept) was read as the log's, and the replay of it said DIVERGED of a value no run made."""
    copy = tmp_path / "copy.mcap"
    copy.write_bytes(small_chunks.read_bytes())
    offset, length = chunks(copy.read_bytes())[-1]
    reading = scan_log(copy, lambda channels, messages: None).time_ordered()
    next(reading)
    with open(copy, "r+b") as f:
        f.seek(offset + length // 2)
        byte = f.read(1)
        f.seek(offset + length // 2)
        f.write(bytes([byte[0] ^ 1]))
    with pytest.raises(LogError, match=r"copy\.mcap changed as it was read\n    hint: read it again"):
        for _ in reading:
            pass


def test_a_log_with_messages_outside_chunks_is_replayed_read_whole(small_chunks, tmp_path):
    """MCAP allows messages outside chunks (Retriever's writer makes none): time_ordered() does
    not read those, and replay_file replays such a log as replay() does, read whole."""
    from mcap.writer import Writer

    log = read_log(small_chunks)
    loose = tmp_path / "loose.mcap"
    with open(loose, "wb") as out:
        writer = Writer(out, use_chunking=False)
        writer.start(profile=log.profile, library="test")
        ids = {c.id: writer.register_channel(c.topic, c.message_encoding, 0, dict(c.metadata))
               for c in log.channels.values()}
        for a in log.attachments.values():
            writer.add_attachment(a.create_time, a.log_time, a.name, a.media_type, a.data)
        for name, data in log.metadata.items():
            writer.add_metadata(name, data)
        for m in log.messages:
            writer.add_message(ids[m.channel_id], m.log_time, m.data, m.publish_time, m.sequence)
        writer.finish()
    scanned = scan_log(loose, lambda channels, messages: None)
    assert scanned.loose == len(log.messages) and not scanned.chunks
    with pytest.raises(LogError, match="messages outside its chunks"):
        next(scanned.time_ordered())
    _same(replay(read_log(loose)), replay_file(loose))
    assert replay_file(loose).identical


# ---------------------------------------------------------------------------------------------
# The reader's chunks: mcap's record readers over the bytes, as breakup_chunk reads them
# ---------------------------------------------------------------------------------------------
def _outcome(read, chunk):
    try:
        return read(chunk)
    except Exception as e:  # the same kind of error, from the same field
        return type(e).__name__, str(e)


def test_chunk_messages_are_breakup_chunks_record_for_record(small_chunks):
    """``chunk_messages`` (what the reader breaks chunks up with) gives what ``mcap``'s
    ``breakup_chunk(validate_crc=True)`` gives, its Messages as message tuples, for every chunk
    of a log and for chunks cut short, with a byte changed or records of another type in them
    (their CRC left out: the records are read as they are), with a channel it is not told of,
    down to the error a damaged one raises; and a message's position is where its record is."""
    from mcap.records import Channel, Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    from retriever.log.reader import chunk_messages

    def reference(chunk):
        return [_fields(r) if type(r) is Message else r for r in breakup_chunk(chunk, validate_crc=True)]

    def read(chunk, channels=range(1 << 16)):
        messages, rest = chunk_messages(chunk, 7, channels)
        return [_fields(r) if type(r) is tuple else r for r in messages + rest]

    chunks_read = [r for r in StreamReader(open(small_chunks, "rb"), emit_chunks=True).records if type(r) is Chunk]
    assert len(chunks_read) > 20
    for chunk in chunks_read:
        assert read(chunk) == reference(chunk)
        messages, rest = chunk_messages(chunk, 7, range(1 << 16))
        assert not rest and [m[1] >> 32 for m in messages] == [7] * len(messages)
        assert messages[0][1] == 7 << 32 and all(a[1] < b[1] for a, b in zip(messages, messages[1:]))
    plain = breakup_chunk(chunks_read[0])
    data = b"".join(_record_bytes(r) for r in plain)
    unknown = b"\x80" + (3).to_bytes(8, "little") + b"abc"  # another type's record: skipped
    first = _record_bytes(plain[0])
    assert first[0] == 0x05  # a Message record: then one shorter than its fields (its length changed)
    short = first[:1] + (10).to_bytes(8, "little") + first[9:]
    channel = _record_bytes(Channel(id=9, schema_id=0, topic="t", message_encoding="m", metadata={}))
    variants = [data, data + unknown, unknown + data, data[:-1], data[:40], data[:9], data[:3], b"", short + data,
                data + short, first + channel + data, first + channel[:-1], first + first[:30]]
    variants += [data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:] for i in (0, 1, 5, 9, 11, 20, 30, 31, len(data) - 1)]
    for body in variants:
        chunk = Chunk(compression="", data=body, message_start_time=0, message_end_time=0,
                      uncompressed_crc=0, uncompressed_size=len(body))
        assert _outcome(read, chunk) == _outcome(reference, chunk), body[:40]
    # a channel it is not told of: from its first message on, mcap's readers read the rest, the same records
    chunk = Chunk(compression="", data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                  uncompressed_size=len(data))
    left_out = plain[-1].channel_id
    cut = next(i for i, m in enumerate(plain) if m.channel_id == left_out)
    messages, rest = chunk_messages(chunk, 0, {m.channel_id for m in plain} - {left_out})
    assert (len(messages), len(rest)) == (cut, len(plain) - cut) and cut > 0
    assert list(map(_fields, messages + rest)) == reference(chunk)
    sizes = [len(_record_bytes(m)) for m in plain]
    assert [m[1] for m in messages + rest] == [sum(sizes[:i]) for i in range(len(plain))]


def _record_bytes(record) -> bytes:
    from mcap.data_stream import RecordBuilder

    builder = RecordBuilder()
    record.write(builder)
    return builder.end()


def _index_bodies(entries: dict[int, list[tuple[int, int]]]) -> list[bytes]:
    """MessageIndex records' fields (channel id, entries' length, ``(log_time, offset)`` entries)."""
    import struct

    return [struct.pack("<HI", channel_id, 16 * len(pairs)) + b"".join(struct.pack("<QQ", *p) for p in pairs)
            for channel_id, pairs in entries.items()]

def chunk_read_both_ways(records: list, channels) -> tuple:
    """A chunk of ``records`` (``mcap`` Messages) with MessageIndex records made for it, read by
    them (``chunk_messages(..., arrays=True)``) and walked record by record: the two readings."""
    from mcap.records import Chunk

    from retriever.log.reader import chunk_messages

    sizes = [len(_record_bytes(m)) for m in records]
    data = b"".join(_record_bytes(m) for m in records)
    entries: dict[int, list] = {}
    for m, size_before in zip(records, [sum(sizes[:i]) for i in range(len(records))]):
        entries.setdefault(m.channel_id, []).append((m.log_time, size_before))
    body = Chunk(compression="", data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                 uncompressed_size=len(data))
    return (chunk_messages(body, 0, channels, _index_bodies(entries), arrays=True)[0],
            chunk_messages(body, 0, channels)[0])


def test_chunk_messages_walked_by_their_indexes_are_breakup_chunks(small_chunks):
    """A chunk walked by the MessageIndex records after it (numpy reading every record's head)
    gives what ``breakup_chunk`` gives, in file order, or by log time (ties in file order) for
    ``time_ordered``; indexes that are missing, damaged or do not tile the chunk exactly with
    whole Message records make it walked as before, with the same records and errors."""
    from mcap.records import Channel, Chunk, Message, MessageIndex
    from mcap.stream_reader import StreamReader, breakup_chunk

    from retriever.log.reader import ChunkMessages, chunk_messages

    def reference(chunk):
        return [_fields(r) if type(r) is Message else r for r in breakup_chunk(chunk, validate_crc=True)]

    def read(indexes, by_time=False):
        def read(chunk):
            messages, rest = chunk_messages(chunk, 7, range(1 << 16), indexes, by_time=by_time)
            return [_fields(r) if type(r) is tuple else r for r in messages + rest]
        return read

    def indexed(chunk, indexes) -> bool:
        try:
            return type(chunk_messages(chunk, 7, range(1 << 16), indexes, arrays=True)[0]) is ChunkMessages
        except Exception:
            return False

    # every chunk of a log, with the indexes its writer wrote after it
    chunks_read, bodies = [], []
    for record in StreamReader(open(small_chunks, "rb"), emit_chunks=True).records:
        if type(record) is Chunk:
            chunks_read.append(record)
            bodies.append([])
        elif type(record) is MessageIndex and bodies:
            bodies[-1] += _index_bodies({record.channel_id: record.records})
    assert len(chunks_read) > 20
    for chunk, indexes in zip(chunks_read, bodies):
        assert indexed(chunk, indexes)
        assert read(indexes)(chunk) == reference(chunk)
        assert read(indexes, by_time=True)(chunk) == sorted(reference(chunk), key=lambda m: m[0])
        tuples = chunk_messages(chunk, 7, range(1 << 16), indexes)[0]
        assert tuples == chunk_messages(chunk, 7, range(1 << 16))[0]  # positions too
    # one chunk, its indexes made here: right, odd and damaged
    plain = max((breakup_chunk(chunk) for chunk in chunks_read), key=len)
    assert len(plain) > 4
    data = b"".join(_record_bytes(r) for r in plain)
    sizes = [len(_record_bytes(m)) for m in plain]
    offsets = [sum(sizes[:i]) for i in range(len(plain))]
    by_channel: dict[int, list] = {}
    for m, offset in zip(plain, offsets):
        by_channel.setdefault(m.channel_id, []).append((m.log_time, offset))
    good = _index_bodies(by_channel)
    one = list(by_channel)[0]
    every = [(0, offset) for offset in offsets]
    cases = {
        "as written": (good, True),
        "all in one index, times and channel wrong": (_index_bodies({one: every[::-1]}), True),
        "none": ([], False),
        "one entry left out": (_index_bodies({one: every[1:]}), False),
        "the last left out": (_index_bodies({one: every[:-1]}), False),
        "one twice": (_index_bodies({one: every + every[-1:]}), False),
        "one off by a byte": (_index_bodies({one: every[:3] + [(0, offsets[3] + 1)] + every[4:]}), False),
        "one past the end": (_index_bodies({one: every + [(0, len(data) + 100)]}), False),
        "one at 2**64 - 1": (_index_bodies({one: every + [(0, 2 ** 64 - 1)]}), False),
        "an entry cut short": ([good[0][:-3], *good[1:]], False),
        "its length wrong": ([good[0][:2] + (17).to_bytes(4, "little") + good[0][6:], *good[1:]], False),
        "its length not whole entries": ([good[0][:2] + (8).to_bytes(4, "little") + good[0][6:14], *good[1:]], False),
        "a record of 3 bytes": ([b"abc", *good], False),
    }
    for name, (indexes, walked_by_them) in cases.items():
        chunk = Chunk(compression="", data=data, message_start_time=0, message_end_time=0,
                      uncompressed_crc=0, uncompressed_size=len(data))
        assert indexed(chunk, indexes) is walked_by_them, name
        assert _outcome(read(indexes), chunk) == _outcome(reference, chunk), name
    # the chunk's bytes changed (its indexes as written): a record cut, a byte changed, another
    # type's record, a Channel: not tiled, walked as before, the same records and errors
    unknown = b"\x80" + (3).to_bytes(8, "little") + b"abc"
    first = _record_bytes(plain[0])
    channel = _record_bytes(Channel(id=9, schema_id=0, topic="t", message_encoding="m", metadata={}))
    variants = [data + unknown, data[:-1], data[:40], b"", first + channel + data[len(first):], data[:-len(first)]]
    variants += [data[:i] + bytes([data[i] ^ 0xFF]) + data[i + 1:] for i in (0, 1, 5, 9, 11, 20, 30, 31, len(data) - 1)]
    for body in variants:
        chunk = Chunk(compression="", data=body, message_start_time=0, message_end_time=0,
                      uncompressed_crc=0, uncompressed_size=len(body))
        assert _outcome(read(good), chunk) == _outcome(reference, chunk), body[:40]
    # every chunk of the log with a byte changed: a length changed may run past the chunk, or past
    # 2**63 (BytesIO's OverflowError in breakup_chunk: the walk raises it too)
    for each in chunks_read:
        records = breakup_chunk(each)
        whole = b"".join(_record_bytes(r) for r in records)
        at, entries = 0, {}
        for r in records:
            entries.setdefault(r.channel_id, []).append((r.log_time, at))
            at += len(_record_bytes(r))
        for i in (0, 1, 5, 9, 11, 20, 30, 31, len(whole) - 1):
            body = whole[:i] + bytes([whole[i] ^ 0xFF]) + whole[i + 1:]
            changed = Chunk(compression="", data=body, message_start_time=0, message_end_time=0,
                            uncompressed_crc=0, uncompressed_size=len(body))
            assert _outcome(read(_index_bodies(entries)), changed) == _outcome(reference, changed), i
    # a channel it is not told of: walked as before
    chunk = Chunk(compression="", data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                  uncompressed_size=len(data))
    left_out = plain[-1].channel_id
    messages, rest = chunk_messages(chunk, 0, {m.channel_id for m in plain} - {left_out}, good)
    assert type(messages) is list and rest and list(map(_fields, messages + rest)) == reference(chunk)


def test_the_survey_of_a_chunk_as_arrays_is_its_survey_as_message_tuples(small_chunks, tmp_path):
    """``LogSurvey.take_chunk`` (a chunk as numpy read it) finds what ``take`` finds of the same
    messages as tuples, on a log as written and on chunks whose events skip a seq, repeat one,
    or are framed otherwise."""
    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    from retriever.replay import LogSurvey

    def state(survey):
        return (survey.nodes, survey.steps, {k: (v.lo, v.hi) for k, v in survey.seqs.items()}, survey.late,
                survey.views(), survey.gaps, *(str(e) for e in (survey.step_error, survey.event_error, survey.twice)))

    by_arrays, by_tuples = LogSurvey(small_chunks), LogSurvey(small_chunks)
    scan_log(small_chunks, by_arrays.take, take_chunk=by_arrays.take_chunk)
    scan_log(small_chunks, by_tuples.take)
    assert state(by_arrays) == state(by_tuples) and by_arrays.steps > 100

    channels = scan_log(small_chunks, lambda c, m: None).channels
    chunk = next(r for r in StreamReader(open(small_chunks, "rb"), emit_chunks=True).records if type(r) is Chunk)
    plain = breakup_chunk(chunk)
    events = [i for i, m in enumerate(plain) if channels[m.channel_id].topic.startswith("data/")]

    def changed(i, **fields):
        m = plain[i]
        return [*plain[:i], Message(**{**{k: getattr(m, k) for k in ("channel_id", "sequence", "log_time",
                                                                      "publish_time", "data")}, **fields}),
                *plain[i + 1:]]

    last = events[-1]
    steps = [i for i, m in enumerate(plain) if channels[m.channel_id].topic == "steps"]
    one, two = steps[len(steps) // 2], steps[-1]
    written = msgpack.unpackb(plain[one].data)
    assert written[5] is None

    def record(*fields, **changes):
        fields = list(fields or written)
        for at, value in changes.items():
            fields["node microstep consumed produced status detail wall_ns".split().index(at)] = value
        return msgpack.packb(fields)

    ids = [["a", "b", 1], ["c", "d", 2 ** 40]]
    kinds_of_steps = [
        record(detail={"late": {"in": [["camera", "frame", 3]]}}, status="late"),
        record(detail={"had_below": {"in": [["camera", "frame", 3]]}}),
        record(detail={"restart_gap": {"in": [["camera", "frame", 3, 5]]}}),
        record(detail={"missing": ["in"]}, status="skipped"), record(detail=5), record(detail={"late": 5}),
        record(node="é"), record(node="x" * 40), record(node=""), record(consumed={"é": ids}),
        record(consumed={"in": [["a", "é", 1]]}), record(produced=[["a", "b", -1]]), record(produced=[["a", "b"]]),
        record(consumed={f"p{i}": ids for i in range(16)}), record(produced=ids * 8),
        record(wall_ns=-5), record(wall_ns=2 ** 63), record(wall_ns=1.5), record(microstep=-1), record(microstep=300),
        record(status="nonsense"), record(status="é"), record(consumed=[]), record(consumed={1: ids}),
        record()[:-1], record() + b"\x00", b"\xc1", b"", b"\x97", msgpack.packb([*written, 1]),
        msgpack.packb(written[:6]), b"\x97" + record()[1:].replace(b"\xc0", b"\xc2"),
    ]
    variants = [plain, changed(last, sequence=plain[last].sequence + 5), changed(last, sequence=0),
                changed(last, data=b"\x93\x00\x00"), changed(last, data=b"\x92\xcc\x80\x00"),
                changed(last, data=b"\x92")]
    variants += [changed(one, data=data) for data in kinds_of_steps]
    variants += [changed(two, data=data) for data in kinds_of_steps[:3]]
    for records in variants:
        arrays, tuples = chunk_read_both_ways(records, channels)
        a, b = LogSurvey(small_chunks), LogSurvey(small_chunks)
        for _ in range(2):  # a chunk, then another after it
            a.take_chunk(channels, arrays)
            b.take(channels, tuples)
            assert state(a) == state(b)
        _plain_ones_decode_as_checked(a, b, [m for m in records if channels[m.channel_id].topic == "steps"])


def _plain_ones_decode_as_checked(by_arrays, by_tuples, steps: list) -> None:
    """What the replay reads again of each step record the surveys took: whole (``decode_step``)
    those they did not find plain, all of them taken as tuples (``unchecked`` None); for the
    others ``decode_plain_step`` says what ``decode_step`` says, the same record or error."""
    from retriever.log.format import decode_plain_step, decode_step

    if by_arrays.step_error is not None:  # (the replay stops before its first step)
        return
    assert by_tuples.unchecked is None
    if by_arrays.unchecked is None:  # a chunk it took as message tuples (its events framed otherwise)
        return
    for m in steps:
        if m.sequence not in by_arrays.unchecked:
            assert _outcome(decode_plain_step, m.data) == _outcome(decode_step, m.data), m.data


def test_only_the_step_records_found_plain_are_read_for_their_status_alone(small_chunks):
    """The survey of a chunk as arrays leaves the replay to read whole (``decode_step``) only the
    step records it did not find plain (on a log as written: those with detail, here none), and of each it
    found plain ``decode_plain_step`` says what ``decode_step`` says, for 2,000 records with one
    to three bytes changed at random (a changed string, integer, header or length: what is then
    still found plain decodes the same, or fails the same)."""
    import random

    from mcap.records import Chunk, Message
    from mcap.stream_reader import StreamReader, breakup_chunk

    from retriever.log.format import decode_step
    from retriever.replay import LogSurvey

    channels = scan_log(small_chunks, lambda c, m: None).channels
    survey = LogSurvey(small_chunks)
    scan_log(small_chunks, survey.take, take_chunk=survey.take_chunk)
    detailed = {m.sequence for m in read_log(small_chunks).messages
                if channels[m.channel_id].topic == "steps" and decode_step(m.data)[5] is not None}
    assert survey.unchecked == detailed and survey.steps > 100

    chunk = next(r for r in StreamReader(open(small_chunks, "rb"), emit_chunks=True).records if type(r) is Chunk)
    plain = breakup_chunk(chunk)
    steps = [i for i, m in enumerate(plain) if channels[m.channel_id].topic == "steps"]
    rng = random.Random(42)
    found_plain = 0
    for _ in range(2000):
        i = rng.choice(steps)
        data = bytearray(plain[i].data)
        for _ in range(rng.randint(1, 3)):
            data[rng.randrange(len(data))] = rng.choice([rng.randrange(256), 0xA0, 0xA5, 0x93, 0x92, 0x81, 0xCC,
                                                         0xCB, 0xC2, 0xC0, 0xD0, 0x7F, 0xFF, 0x41])
        m = plain[i]
        records = [*plain[:i], Message(channel_id=m.channel_id, sequence=m.sequence, log_time=m.log_time,
                                       publish_time=m.publish_time, data=bytes(data)), *plain[i + 1:]]
        arrays, tuples = chunk_read_both_ways(records, channels)
        a, b = LogSurvey(small_chunks), LogSurvey(small_chunks)
        a.take_chunk(channels, arrays)
        b.take(channels, tuples)
        _plain_ones_decode_as_checked(a, b, [records[k] for k in steps])
        found_plain += m.sequence not in a.unchecked and a.step_error is None
    assert 100 < found_plain < 2000  # changes the survey takes as plain records, and others


@pytest.mark.parametrize("second", [range(10), range(5, 8)], ids=["same seqs", "seqs inside"])
def test_the_survey_of_a_chunk_as_arrays_finds_a_port_logged_twice_on_two_channels(second, tmp_path):
    """Two channels with one data topic (an edited log: the reader takes it) whose events repeat
    seqs in one chunk: ``take`` says an event is logged twice, and so must ``take_chunk`` (which
    put each channel's seqs in after all of them were checked against the port's seqs before)."""
    import struct

    from mcap.records import Chunk, Message

    from retriever.log.reader import LogChannel, chunk_messages
    from retriever.replay import LogSurvey

    channels = {c: LogChannel(c, "data/cam/frame", "msgpack", {}) for c in (1, 2)}
    messages = [Message(channel_id=c, sequence=s, log_time=s, publish_time=s, data=msgpack.packb([0, s]))
                for c, seqs in ((1, range(10)), (2, second)) for s in seqs]
    data, entries = b"", {}
    for m in messages:
        entries.setdefault(m.channel_id, []).append((m.log_time, len(data)))
        data += _record_bytes(m)
    body = Chunk(compression="", data=data, message_start_time=0, message_end_time=0, uncompressed_crc=0,
                 uncompressed_size=len(data))
    indexes = [struct.pack("<HI", c, 16 * len(p)) + b"".join(struct.pack("<QQ", *e) for e in p)
               for c, p in entries.items()]
    arrays = chunk_messages(body, 0, channels, indexes, arrays=True)[0]
    assert type(arrays).__name__ == "ChunkMessages"
    by_arrays, by_tuples = LogSurvey(tmp_path / "x.mcap"), LogSurvey(tmp_path / "x.mcap")
    by_arrays.take_chunk(channels, arrays)
    by_tuples.take(channels, chunk_messages(body, 0, channels)[0])
    assert "logged twice" in str(by_tuples.twice)
    assert str(by_arrays.twice) == str(by_tuples.twice)
    assert [by_arrays.in_log(("cam", "frame", s)) for s in range(12)] == \
        [by_tuples.in_log(("cam", "frame", s)) for s in range(12)]


def test_resim_file_reads_events_framed_otherwise_as_the_log_read_whole(small_chunks, tmp_path):
    """Events whose microstep is packed wider than a fixint (valid msgpack, not as Retriever writes
    it): ``resim_file``'s reading of nearly every event (``[microstep < 128, value]``) does not
    apply, the event is read as ``read_log`` reads it, and the re-simulation is identical."""
    def keep(topic, message) -> bool:
        if topic.startswith("data/"):
            assert message.data[0] == 0x92 and message.data[1] < 0x80
            message.data = b"\x92\xcc" + message.data[1:]  # the same microstep, as a uint 8
        return True

    wide = rewrite(small_chunks, tmp_path / "wide.mcap", keep=keep)
    whole, streamed = resim(read_log(wide)), resim_file(wide)
    _same_resim(whole, streamed)
    assert streamed.identical and streamed.steps_compared == 180 and streamed.events_compared > 100
