"""Bad logs: not MCAP, missing, truncated, corrupted, or written by code that has since changed.
Each is a ``LogError`` with a hint through the API, and ``error: …`` with exit status 1 and no
traceback through the CLI; ``retriever log recover`` salvages what can be salvaged."""

from __future__ import annotations

import importlib
import io
import re
import secrets
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.stream_reader import StreamReader, breakup_chunk

from retriever import LogError, RetrieverWarning, read_log
from retriever.log.reader import scan_log
from retriever.loading import load_pipeline
from retriever.backends.inproc import InprocSession
from retriever.log import LogWriter, recover
from retriever.replay import Divergence, replay, replay_file, resim
from retriever.replay.resimulation import TRACES
from retriever.log.format import RECOVERED_METADATA
from tests.log.helpers import (
    CHUNK,
    MAGIC_LEN,
    QUICKSTART,
    assert_cli_error,
    chunk_payload_offset,
    chunks,
    cli,
    cli_env,
    cut,
    records,
    flip,
    rewrite,
)

RECOVER_HINT = (r"(`retriever log recover .*` writes a readable copy of everything before the damage|no message comes "
                r"before the damage: `retriever log recover .*` can keep only the run's metadata)")
DAMAGED = r"cannot be read: (it ends in the middle of|it ends \d+ bytes short of its closing magic|it is corrupt)"


def _quickstart_log(path: Path, duration: float):
    pipe = load_pipeline(str(QUICKSTART))
    pipe.reset()
    try:
        return pipe.run(duration=duration, log=path)
    finally:
        pipe.reset()


@pytest.fixture(scope="module")
def one_chunk(tmp_path_factory) -> Path:
    """A complete 5 s quickstart log: its messages are one chunk, then indexes and summary (the
    writer flushes at the end only, however long the run takes on a loaded machine)."""
    path = tmp_path_factory.mktemp("one") / "quickstart.mcap"
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(LogWriter.__init__.__kwdefaults__, "flush_interval", float("inf"))
        _quickstart_log(path, 5.0)
    assert len(chunks(path.read_bytes())) == 1
    return path


@pytest.fixture(scope="module")
def many_chunks(tmp_path_factory) -> Path:
    """A complete 20 s quickstart log cut into many chunks: the writer gets the trace every 500
    steps and flushes (closes the chunk) on every hand-over."""
    path = tmp_path_factory.mktemp("many") / "quickstart.mcap"
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(InprocSession, "LOG_BATCH", 500)
        mp.setitem(LogWriter.__init__.__kwdefaults__, "flush_interval", 0.0)
        _quickstart_log(path, 20.0)
    assert len(chunks(path.read_bytes())) >= 8
    return path


# ---------------------------------------------------------------------------------------------
# Not a log at all
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def text_file(tmp_path: Path) -> Path:
    path = tmp_path / "notes.mcap"
    path.write_text("these are my notes about the run, not a log\n", encoding="utf-8")
    return path


def test_a_text_file_is_not_an_mcap_file(text_file: Path):
    with pytest.raises(LogError, match=r"notes\.mcap is not an MCAP file \(it does not start with the MCAP magic "
                                       r"bytes\)\n    hint: retriever reads the \.mcap files written by "):
        read_log(text_file)
    with pytest.raises(LogError, match="is not an MCAP file"):
        read_log(text_file, salvage=True)  # salvaging cannot make a log out of it either
    with pytest.raises(LogError, match="is not an MCAP file"):
        recover(text_file)


@pytest.mark.parametrize("command", [["replay"], ["replay", "--resim"], ["log", "info"], ["log", "cat"],
                                     ["log", "recover"]], ids=" ".join)
def test_cli_on_a_text_file(text_file: Path, command):
    result = cli(*command, text_file)
    assert_cli_error(result, r"^error: .*notes\.mcap is not an MCAP file", hint=r"retriever reads the \.mcap files")


def test_a_short_text_file_is_not_an_mcap_file(tmp_path: Path):
    path = tmp_path / "short.mcap"
    path.write_text("hello\n", encoding="utf-8")
    with pytest.raises(LogError, match="is not an MCAP file"):
        read_log(path)


def test_a_missing_file(tmp_path: Path):
    missing = tmp_path / "nope.mcap"
    with pytest.raises(LogError, match=r"^no such log file: .*nope\.mcap\n    hint: give the path of a \.mcap file"):
        read_log(missing)
    with pytest.raises(LogError, match="no such log file"):
        recover(missing)
    for command in (["replay"], ["log", "recover"]):
        assert_cli_error(cli(*command, missing), r"^error: no such log file: .*nope\.mcap$", "give the path")


def test_a_directory_is_not_a_log(tmp_path: Path):
    with pytest.raises(LogError, match=r"cannot open the log .*: Is a directory"):
        read_log(tmp_path)


# ---------------------------------------------------------------------------------------------
# Truncated
# ---------------------------------------------------------------------------------------------
CUTS = {"last byte": lambda n: n - 1, "final magic": lambda n: n - 8, "inside the summary": lambda n: n - 100,
        "halfway": lambda n: n // 2, "inside the header": lambda n: 20}


@pytest.mark.parametrize("where", CUTS)
def test_a_truncated_log_is_refused_with_a_recover_hint(one_chunk: Path, tmp_path: Path, where):
    torn = cut(one_chunk, CUTS[where](one_chunk.stat().st_size), tmp_path / "torn.mcap")
    with pytest.raises(LogError, match=DAMAGED + r".*\n    hint: " + RECOVER_HINT):
        read_log(torn)
    salvaged = read_log(torn, salvage=True)
    assert salvaged.damage and "messages read before it" in salvaged.damage
    assert salvaged.complete == (where in ("last byte", "final magic"))  # complete: the footer was read


@pytest.mark.parametrize("where", ["last byte", "halfway"])
def test_cli_on_a_truncated_log(one_chunk: Path, tmp_path: Path, where):
    torn = cut(one_chunk, CUTS[where](one_chunk.stat().st_size), tmp_path / "torn.mcap")
    assert_cli_error(cli("replay", torn), r"^error: .*torn\.mcap " + DAMAGED, hint=RECOVER_HINT)


def test_cli_log_info_on_a_truncated_log(one_chunk: Path, tmp_path: Path):
    torn = cut(one_chunk, one_chunk.stat().st_size - 100, tmp_path / "torn.mcap")
    assert_cli_error(cli("log", "info", torn), r"^error: .*torn\.mcap " + DAMAGED, hint=RECOVER_HINT)


# ---------------------------------------------------------------------------------------------
# Corrupted: one flipped byte inside a chunk
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("where", [0.1, 0.5, 0.9])
def test_a_flipped_byte_inside_a_chunk_is_detected(one_chunk: Path, tmp_path: Path, where):
    data = one_chunk.read_bytes()
    (offset, length), = chunks(data)
    start = chunk_payload_offset(data, offset)
    damaged = flip(one_chunk, start + int((offset + 9 + length - start) * where), tmp_path / "flipped.mcap")
    with pytest.raises(LogError, match=r"cannot be read: it is corrupt.*(a CRC check failed|a record cannot be parsed).*\n"
                                       r"    hint: " + RECOVER_HINT):
        read_log(damaged)
    assert read_log(damaged, salvage=True).messages == [], "nothing of the damaged chunk may be kept"


def test_cli_on_a_flipped_byte(one_chunk: Path, tmp_path: Path):
    data = one_chunk.read_bytes()
    (offset, length), = chunks(data)
    damaged = flip(one_chunk, offset + length // 2, tmp_path / "flipped.mcap")
    assert_cli_error(cli("replay", damaged), r"^error: .*flipped\.mcap cannot be read: "
                                             r"it is corrupt.*(a CRC check failed|a record cannot be parsed)", hint=RECOVER_HINT)


def test_salvaging_a_corrupt_chunk_keeps_the_chunks_before_it(many_chunks: Path, tmp_path: Path):
    """A flipped byte in the third chunk: the first two chunks' messages are kept, byte for byte,
    and recover writes them into a log that replays."""
    original = read_log(many_chunks)
    data = many_chunks.read_bytes()
    third, length = chunks(data)[2]
    damaged = flip(many_chunks, third + 9 + length // 2, tmp_path / "flipped.mcap")
    with pytest.raises(LogError, match=r"cannot be read: it is corrupt.*(a CRC check failed|a record cannot be parsed)"):
        read_log(damaged)
    salvaged = read_log(damaged, salvage=True)
    kept = len(salvaged.messages)
    assert 0 < kept < len(original.messages)
    assert [_fields(m) for m in salvaged.messages] == [_fields(m) for m in original.messages[:kept]]
    result = recover(damaged, tmp_path / "flipped.recovered.mcap")
    assert result.messages == kept
    assert replay(read_log(result.output)).identical


# ---------------------------------------------------------------------------------------------
# Recover
# ---------------------------------------------------------------------------------------------
def _fields(m):
    return (m.channel_id, m.log_time, m.publish_time, m.sequence, bytes(m.data))


def _by_topic(log) -> dict[str, list[tuple]]:
    """Each topic's messages in file order (log_time, publish_time, sequence, data)."""
    topics = {c.id: c.topic for c in log.channels.values()}
    found: dict[str, list[tuple]] = {}
    for m in log.messages:
        found.setdefault(topics[m.channel_id], []).append(_fields(m)[1:])
    return found


def test_recover_a_truncated_log_gives_a_consistent_prefix(many_chunks: Path, tmp_path: Path):
    """Cut halfway: the recovered file is complete and readable, holds the IR and metadata, and
    per channel the first messages of the original, identical; events match the original's."""
    original = read_log(many_chunks)
    torn = cut(many_chunks, many_chunks.stat().st_size // 2, tmp_path / "torn.mcap")
    result = recover(torn)
    assert result.output == tmp_path / "torn.recovered.mcap"
    assert 0 < result.events < len(list(original.iter_events()))
    assert 0 < result.steps < len(list(original.iter_steps()))
    assert result.damage.startswith("it ends in the middle of the ")

    recovered = read_log(result.output)
    assert recovered.complete and recovered.damage is None
    assert recovered.ir == original.ir
    assert recovered.run == original.run
    assert recovered.metadata["retriever.recovered"]["source"] == str(torn)
    assert {c.topic for c in recovered.channels.values()} == {c.topic for c in original.channels.values()}
    before, after = _by_topic(original), _by_topic(recovered)
    for topic, messages in after.items():
        assert messages == before[topic][:len(messages)], f"{topic} is not a prefix of the original"
    originals = {e.id: e for e in original.iter_events()}
    for e in recovered.iter_events():
        assert e == originals[e.id]
    assert list(recovered.iter_steps()) == list(original.iter_steps())[:result.steps]
    assert replay(recovered).identical
    assert resim(recovered).identical


def test_cli_recover_then_replay(many_chunks: Path, tmp_path: Path):
    torn = cut(many_chunks, many_chunks.stat().st_size * 2 // 3, tmp_path / "torn.mcap")
    result = cli("log", "recover", torn, "-o", tmp_path / "saved.mcap")
    assert result.returncode == 0, result.stderr
    assert "recovered " in result.stdout and f"into {tmp_path / 'saved.mcap'}" in result.stdout
    assert "next: retriever replay" in result.stdout
    replayed = cli("replay", tmp_path / "saved.mcap")
    assert replayed.returncode == 0, replayed.stdout + replayed.stderr
    assert "identical:" in replayed.stdout
    resimulated = cli("replay", "--resim", tmp_path / "saved.mcap")
    assert resimulated.returncode == 0, resimulated.stdout + resimulated.stderr
    info = cli("log", "info", tmp_path / "saved.mcap")
    assert info.returncode == 0, info.stderr
    assert "recovered from" in info.stdout


def _foreign_mcap(path: Path) -> Path:
    """An MCAP file another tool wrote (the ``mcap`` package's writer): two schemas, three
    channels (one without a schema), no Retriever records."""
    from mcap.writer import Writer

    with path.open("wb") as f:
        writer = Writer(f, chunk_size=512)
        writer.start(profile="robots", library="another tool")
        point = writer.register_schema("demo.Point", "jsonschema", b'{"type": "object"}')
        image = writer.register_schema("demo.Image", "protobuf", b"not really a descriptor set")
        channels = [writer.register_channel("/point", "json", point),
                    writer.register_channel("/image", "protobuf", image), writer.register_channel("/raw", "cbor", 0)]
        for i in range(300):
            writer.add_message(channels[i % 3], log_time=i, publish_time=i, data=b'{"x": %d}' % i, sequence=i)
        writer.finish()
    return path


def test_log_info_and_recover_agree_that_a_foreign_mcap_file_is_complete(tmp_path: Path):
    path = _foreign_mcap(tmp_path / "foreign.mcap")
    assert recover(path).output is None
    assert f"{path} is complete and undamaged" in cli("log", "recover", path).stdout
    info = cli("log", "info", path)
    assert info.returncode == 0, info.stderr
    assert "complete, not written by Retriever (no retriever.run record)" in info.stdout
    assert "incomplete" not in info.stdout


def test_recover_keeps_schema_records_and_the_profile(tmp_path: Path):
    path = _foreign_mcap(tmp_path / "foreign.mcap")
    torn = cut(path, path.stat().st_size * 2 // 3, tmp_path / "torn.mcap")
    result = recover(torn)
    original, recovered = read_log(path), read_log(result.output)
    assert 0 < len(recovered.messages) < len(original.messages)
    by_topic = {c.topic: c for c in recovered.channels.values()}
    schemas = {topic: recovered.schemas[c.schema_id] if c.schema_id else None for topic, c in by_topic.items()}
    assert {topic: (s.name, s.encoding, bytes(s.data)) if s else None for topic, s in schemas.items()} == {
        "/point": ("demo.Point", "jsonschema", b'{"type": "object"}'),
        "/image": ("demo.Image", "protobuf", b"not really a descriptor set"), "/raw": None}
    with result.output.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert reader.get_header().profile == "robots"
    assert summary.statistics.schema_count == 2
    assert {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values() if c.schema_id} == {
        "/point": "demo.Point", "/image": "demo.Image"}


@pytest.mark.parametrize("renamed", ["data/counter/k/x", "data/counter", "data//k", "data/counter/"])
def test_a_data_channel_that_is_no_node_and_port_is_refused_not_left_out(one_chunk: Path, tmp_path: Path, renamed):
    """A port named 'k/x' (which Retriever once let a flow return) made a topic data/counter/k/x
    that every reader skipped: its events were lost from read_log, replay, info and every export
    without a word (issue 39). It is said, by read_log, scan_log and the CLI alike."""
    topic = list(read_log(one_chunk).channels.values())[0].topic
    assert topic.startswith("data/")
    forged = rewrite(one_chunk, tmp_path / "forged.mcap", topic=lambda t: renamed if t == topic else t)
    says = re.escape(f"{forged} cannot be read: its channel topic {renamed!r} is under data/ but is not "
                     "data/<node>/<port>, a node and a port of one non-empty segment each")
    for read in (read_log, lambda p: scan_log(p, lambda channels, messages: None)):
        with pytest.raises(LogError, match=says + r".*\n    hint: the log was changed after it was written, or "
                                               r"written by a Retriever that let a port name hold '/'"):
            read(forged)
    for command in (("log", "info"), ("replay",), ("log", "export", "--format", "rerun", "-o", str(tmp_path / "x.rrd"))):
        assert_cli_error(cli(*command, forged), says)


def test_recover_a_complete_log_has_nothing_to_do(one_chunk: Path):
    result = recover(one_chunk)
    assert result.output is None and result.damage is None
    assert not (one_chunk.parent / "quickstart.recovered.mcap").exists()
    done = cli("log", "recover", one_chunk)
    assert done.returncode == 0, done.stderr
    assert "is complete and undamaged; nothing to recover" in done.stdout


def test_recover_refuses_to_overwrite_its_input(one_chunk: Path, tmp_path: Path):
    torn = cut(one_chunk, one_chunk.stat().st_size - 1, tmp_path / "torn.mcap")
    with pytest.raises(LogError, match=r"recover would overwrite its input .*\n    hint: pass another path with -o"):
        recover(torn, torn)
    assert_cli_error(cli("log", "recover", torn, "-o", torn), "recover would overwrite its input",
                     hint="pass another path with -o")


def test_recover_with_nothing_readable(one_chunk: Path, tmp_path: Path):
    torn = cut(one_chunk, 20, tmp_path / "torn.mcap")
    with pytest.raises(LogError, match=r"nothing in .*torn\.mcap can be recovered"):
        recover(torn)
    assert_cli_error(cli("log", "recover", torn), r"^error: nothing in .*torn\.mcap can be recovered")


def test_a_log_cut_inside_a_chunk_header_is_diagnosed_as_torn(one_chunk: Path, tmp_path: Path):
    """A cut in a chunk's compressed data says "it ends in the middle of a record: its writer was
    stopped before finishing"; the same tear a few bytes earlier, inside the chunk's length,
    times, sizes or CRC, claims the file holds a record that cannot be parsed."""
    data = one_chunk.read_bytes()
    (offset, length), = chunks(data)
    in_data = cut(one_chunk, offset + length // 2, tmp_path / "torn.mcap")
    with pytest.raises(LogError, match=r"it ends in the middle of the Chunk record at byte \d+ \(\d+ of its \d+ bytes "
                                       r"are there\): its writer was stopped before finishing"):
        read_log(in_data)
    misdiagnosed = []
    for size in range(offset + 1, chunk_payload_offset(data, offset)):
        torn = cut(one_chunk, size, tmp_path / "torn.mcap")
        with pytest.raises(LogError) as raised:
            read_log(torn)
        if "its writer was stopped before finishing" not in str(raised.value):
            misdiagnosed.append((size - offset, str(raised.value).split(": ", 2)[-1].split(" (near")[0]))
    assert misdiagnosed == []


def test_a_log_cut_between_two_records_is_diagnosed_as_torn(many_chunks: Path, tmp_path: Path):
    """A writer killed between two records (SIGKILL to a logging `retriever demo`) leaves a file
    that ends at a record's end, without summary or closing magic: that is a stopped writer, not
    a file "damaged after it was written" (what it said, naming the record before the cut)."""
    data = many_chunks.read_bytes()
    ends = [offset + 9 + length for offset, length in chunks(data)[:3]]
    for size in ends:
        torn = cut(many_chunks, size, tmp_path / "torn.mcap")
        with pytest.raises(LogError, match=r"its writer was stopped before finishing") as raised:
            read_log(torn)
        assert "damaged" not in str(raised.value), str(raised.value)


def test_a_flipped_byte_in_a_message_index_is_corruption(many_chunks: Path, tmp_path: Path):
    """read_log passes over message indexes unparsed; the data section's CRC still covers them."""
    data = many_chunks.read_bytes()
    offset, length = next((offset, length) for opcode, offset, length in records(data) if opcode == 0x07)
    damaged = flip(many_chunks, offset + 9 + length - 3, tmp_path / "flipped.mcap")
    with pytest.raises(LogError, match=r"it is corrupt at the DataEnd record at byte \d+: a CRC check failed"):
        read_log(damaged)


def _with_private_and_extended_records(path: Path, out: Path) -> Path:
    """``path``'s data section with what the MCAP specification lets other writers add: a private
    record (opcode 0x80 and up) before every chunk, and 5 more bytes (a later version's fields) at
    the end of every channel record; then cut in the middle of the fourth chunk, as a kill leaves it."""
    data = path.read_bytes()
    found = records(data)
    fourth = [offset for opcode, offset, _ in found if opcode == CHUNK][3]
    pieces = [data[:MAGIC_LEN]]
    for opcode, offset, length in found:
        if offset >= fourth:
            break
        body = data[offset + 9:offset + 9 + length]
        if opcode == CHUNK:
            private = b"vendor data, not MCAP's"
            pieces.append(bytes([0x80 + offset % 0x7F]) + struct.pack("<Q", len(private)) + private)
        if opcode == 0x04:  # a channel
            body += b"later"
        pieces.append(bytes([opcode]) + struct.pack("<Q", len(body)) + body)
    pieces.append(data[fourth:fourth + 9 + found[[o for _, o, _ in found].index(fourth)][2] // 2])
    out.write_bytes(b"".join(pieces))
    return out


def test_a_killed_log_with_private_and_extended_records_is_a_stopped_writer(many_chunks: Path, tmp_path: Path):
    """Records a reader must skip (private opcodes, fields it does not know at the end of a record)
    were diagnosed as "damaged after it was written (this is not a stopped writer)"."""
    torn = _with_private_and_extended_records(many_chunks, tmp_path / "vendor.mcap")
    with pytest.raises(LogError, match=r"it ends in the middle of the Chunk record at byte \d+ .*: its writer was "
                                       r"stopped before finishing") as raised:
        read_log(torn)
    assert "damaged" not in str(raised.value)
    result = recover(torn)
    assert result.damage.startswith("it ends in the middle of the Chunk record")
    original, recovered = read_log(many_chunks), read_log(result.output)
    assert len(recovered.messages) == len(_messages_of_chunks(many_chunks, 3)) > 0
    assert recovered.messages == original.messages[:len(recovered.messages)]
    assert {c.topic for c in recovered.channels.values()} == {c.topic for c in original.channels.values()}
    private = [offset for opcode, offset, _ in records(torn.read_bytes()) if opcode >= 0x80][-1]
    in_private = cut(torn, private + 12, tmp_path / "in_private.mcap")
    with pytest.raises(LogError, match=rf"it ends in the middle of the opcode 0x.. record at byte {private} "
                                       r"\(3 of its 23 bytes are there\): its writer was stopped before finishing"):
        read_log(in_private)


def _messages_of_chunks(path: Path, n: int) -> list[Message]:
    """The messages of the first ``n`` chunks of a log."""
    chunks_read = [r for r in StreamReader(io.BytesIO(path.read_bytes()), emit_chunks=True).records
                   if isinstance(r, Chunk)][:n]
    return [m for chunk in chunks_read for m in breakup_chunk(chunk) if isinstance(m, Message)]


@pytest.fixture(scope="module")
def size_chunks(tmp_path_factory) -> Path:
    """A complete 60 s quickstart log whose chunks close only when they reach the writer's size
    limit (no timed flushes): several chunks, the last one written by finish()."""
    path = tmp_path_factory.mktemp("size") / "quickstart.mcap"
    with pytest.MonkeyPatch.context() as mp:
        mp.setitem(LogWriter.__init__.__kwdefaults__, "flush_interval", 1e9)
        _quickstart_log(path, 60.0)
    assert len(chunks(path.read_bytes())) >= 2
    return path


def test_resim_of_a_log_torn_in_its_last_chunk(size_chunks: Path, tmp_path: Path):
    """A writer killed while finish() writes the last chunk leaves an end record that says the
    run finished at 60 s; the recovered file is a consistent prefix (replay agrees) but resim
    trusts end_ns: 'the re-simulation stopped: camera.step() raised StopIteration'."""
    last, length = chunks(size_chunks.read_bytes())[-1]
    torn = cut(size_chunks, last + length // 2, tmp_path / "torn.mcap")
    result = recover(torn)
    assert result.events > 0
    recovered = read_log(result.output)
    assert replay(recovered).identical
    report = resim(recovered)
    assert report.identical, report.difference


# ---------------------------------------------------------------------------------------------
# The code changed since the log was written
# ---------------------------------------------------------------------------------------------
FLOWS = '''
from retriever import Flow, Pipeline, Rate, Trigger, io


@io
class Num:
    x: int


class Source(Flow[None, Num]):
    def __init__(self):
        self.k = 0

    def step(self, inp):
        self.k += 1
        return Num(self.k)


class {cls}(Flow[Num, Num]):
    def step(self, inp):
        return Num({expr})


with Pipeline("drift") as pipe:
    src = Source() @ Rate(hz=10)
    dbl = {cls}().named("double") @ Trigger()
    src.then(dbl)
'''


#: what a DIVERGED line says of a flow module edited since the run (rich may wrap it at a space)
CODE_CHANGED = (r"the code of module {name} differs from the run's "
                r"\(run sha256 [0-9a-f]{{64}},\s+here\s+[0-9a-f]{{64}} in [^)]*\)")


@pytest.fixture
def drift(tmp_path: Path, monkeypatch):
    """A flow module in tmp_path (a unique module name), imported and run with a log, in this
    process; ``(module path, module name, log path)``. Modules and sys.path are restored after."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    name = f"drift_{secrets.token_hex(4)}"
    module = tmp_path / "flows" / f"{name}.py"
    module.parent.mkdir()
    module.write_text(FLOWS.format(cls="Double", expr="inp.x * 2"), encoding="utf-8")
    log = tmp_path / "drift.mcap"
    try:
        trace = load_pipeline(str(module)).run(duration=1.0, log=log)
        assert [e.value for e in trace.events_of("double", "x")][:3] == [2, 4, 6]
        yield module, name, log
    finally:
        sys.modules.pop(name, None)


def _rewrite(module: Path, name: str, text: str | None) -> None:
    """Change (or, with None, delete) the module, and forget the imported one."""
    if text is None:
        module.unlink()
    else:
        module.write_text(text, encoding="utf-8")
    sys.modules.pop(name, None)
    importlib.invalidate_caches()


IR_HINT = (r"pass the pipeline that wrote the log with --pipeline FILE\[:ATTR\] \(a class that moved or was renamed "
           r"too\)")


def test_replay_when_the_flow_class_was_renamed(drift):
    module, name, log = drift
    _rewrite(module, name, FLOWS.format(cls="Doubler", expr="inp.x * 2"))
    with pytest.raises(LogError, match=rf"cannot rebuild the pipeline from the IR in .*drift\.mcap: invalid IR.*\n"
                                       rf".*node 'double': cannot import {name}:Double \(module '{name}' has no "
                                       rf"attribute 'Double'\)\n    hint: {IR_HINT}"):
        replay(read_log(log))
    with pytest.raises(LogError, match="cannot rebuild the pipeline"):
        resim(read_log(log))
    assert_cli_error(cli("replay", log), r"^error: cannot rebuild the pipeline from the IR in .*drift\.mcap",
                     hint=IR_HINT)
    assert re.search(rf"node 'double': cannot import {name}:Double", cli("replay", "--resim", log).stderr)
    # the hint's remedy: the renamed class keeps the node id, so the current file replays the log
    fixed = cli("replay", log, "--pipeline", f"{module}:pipe")
    assert fixed.returncode == 0, fixed.stdout + fixed.stderr
    assert "identical:" in fixed.stdout


SCRIPT_RUN = """
from retriever import Flow, Pipeline, Rate


class Tick(Flow):
    def __init__(self):
        self.n = 0

    def step(self):
        self.n += 1
        return {"n": self.n}


with Pipeline("script") as pipe:
    Tick() @ Rate(hz=10)

if __name__ == "__main__":
    pipe.run(duration=0.5, log="run.mcap")
"""


def test_replay_of_a_scripts_log_names_the_script_to_pass(tmp_path):
    """A log of ``python script.py`` names flows of its ``__main__``, which no other process can
    import: the error's hint is the command that replays it, with the script the log's run
    metadata names (its command line and working directory)."""
    script = tmp_path / "script.py"
    script.write_text(SCRIPT_RUN, encoding="utf-8")
    subprocess.run([sys.executable, str(script.name)], check=True, cwd=tmp_path, env=cli_env(), timeout=120)
    log = tmp_path / "run.mcap"
    result = cli("replay", log)
    assert_cli_error(result, rf"^error: cannot rebuild the pipeline from the IR in {re.escape(str(log))}: its flows live "
                             rf"in the script that ran \({re.escape(str(script))}\), whose __main__ no other process "
                             rf"can import\n",
                     hint=rf"retriever replay {re.escape(str(log))} --pipeline {re.escape(str(script))} ")
    assert "retriever ir" not in result.stderr  # the advice for an IR, not for a replay
    fixed = cli("replay", log, "--pipeline", script)
    assert fixed.returncode == 0 and "identical:" in fixed.stdout, fixed.stdout + fixed.stderr


def test_replay_when_the_flow_module_is_gone(drift):
    module, name, log = drift
    _rewrite(module, name, None)
    with pytest.raises(LogError, match=rf"cannot import {name}:Source \(No module named '{name}'\)(.|\n)*"
                                       rf"cannot import {name}:Double(.|\n)*hint: {IR_HINT}"):
        replay(read_log(log))
    assert_cli_error(cli("replay", log), rf"node 'source': cannot import {name}:Source \(No module named '{name}'\)",
                     hint=IR_HINT)


def test_replay_with_a_pipeline_that_lacks_the_logged_nodes(drift):
    _, _, log = drift
    assert_cli_error(cli("replay", log, "--pipeline", f"{QUICKSTART}:pipe"),
                     r"has steps of node\(s\) double, source, which pipeline 'quickstart' does not have",
                     hint="replay with the pipeline that wrote the log")


def test_replay_when_a_step_changed_reports_the_divergence(drift):
    module, name, log = drift
    _rewrite(module, name, FLOWS.format(cls="Double", expr="inp.x * 2 + 1"))
    with pytest.warns(RetrieverWarning, match=CODE_CHANGED.format(name=name)):
        report = replay(read_log(log))
    change, = report.code_changes
    assert re.fullmatch(CODE_CHANGED.format(name=name), change), change
    assert not report.identical
    assert report.nodes["double"].divergent == report.nodes["double"].replayed == 10
    assert report.nodes["source"].replayed == 0
    first = report.divergences[0]
    assert (first.node, first.port, first.tag, first.what) == ("double", "x", (0, 1), "value")
    assert (first.logged, first.replayed) == (2, 3)
    with pytest.warns(RetrieverWarning, match=CODE_CHANGED.format(name=name)):
        again = resim(read_log(log))
    assert not again.identical and again.code_changes == [change]

    result = cli("replay", log)
    assert result.returncode == 1
    assert "Traceback" not in result.stdout + result.stderr
    assert re.search(rf"DIVERGED: 10 of 10 replayed steps differ; {CODE_CHANGED.format(name=name)}\. First:\n\s+"
                     r"double\.x at tick t=0\.000000000s m=1: value differs\n\s+logged:\s+2\n\s+replayed:\s+3",
                     result.stdout), result.stdout
    resimulated = cli("replay", "--resim", log)
    assert resimulated.returncode == 1
    assert "DIVERGED" in resimulated.stdout and "node='double'" in resimulated.stdout


# ---------------------------------------------------------------------------------------------
# Records that parse but are not what a run writes (found by benchmarks/fuzz.py): LogError, not
# TypeError, AttributeError or msgpack's OutOfData from `log info`, `.trace()` and `replay`
# ---------------------------------------------------------------------------------------------
def _rewritten(source: Path, out: Path, change) -> Path:
    """``source`` written again by the MCAP writer, its messages ``[channel topic, log_time,
    publish_time, sequence, data]`` and run record passed through ``change`` first."""
    import msgpack  # noqa: F401 - the changes use it

    from retriever.log.mcap_writer import McapWriter

    log = read_log(source)
    messages = [[log.channels[m.channel_id].topic, m.log_time, m.publish_time, m.sequence, bytes(m.data)]
                for m in log.messages]
    metadata = {name: dict(data) for name, data in log.metadata.items()}
    change(messages, metadata)
    with open(out, "wb") as f:
        writer = McapWriter(f, profile="retriever")
        ids = {c.topic: writer.add_channel(c.topic, c.message_encoding, c.metadata) for c in log.channels.values()}
        for a in log.attachments.values():
            writer.add_attachment(a.name, a.media_type, bytes(a.data), a.log_time, a.create_time)
        for name, data in metadata.items():
            writer.add_metadata(name, data)
        for topic, log_time, publish_time, sequence, data in messages:
            writer.add_message(ids[topic], log_time, publish_time, sequence, data)
        writer.finish()
    return out


def _first(messages: list, topic: str) -> list:
    return next(m for m in messages if m[0] == topic)


def _small_log(tmp_path: Path) -> Path:
    from tests.log.log_flows import build_small

    path = tmp_path / "small.mcap"
    build_small().run(duration=0.5, log=path)
    return path


def _step_field(index: int, value):
    def change(messages, metadata):
        import msgpack

        step = _first(messages, "steps")
        record = msgpack.unpackb(step[4])
        record[index] = value
        step[4] = msgpack.packb(record)
    return change


@pytest.mark.parametrize("change", [
    _step_field(0, ["counter"]),  # a node that is no name
    _step_field(1, 1.5),  # a microstep that is no integer
    _step_field(3, [["counter", "out"]]),  # an event id that is no triple
    _step_field(4, "exploded"),  # no status
    _step_field(5, {"late": 5}),
])
def test_a_step_record_that_is_not_one_is_a_log_error_everywhere(tmp_path, change):
    from retriever.log.reader import run_info
    from tests.log.log_flows import build_small

    log = read_log(_rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change))
    for read in (log.trace, lambda: run_info(log), lambda: replay(log, build_small())):
        with pytest.raises(LogError, match=r"step record #\d+ is malformed \(it is not|its event ids|its late"):
            read()


def test_a_step_record_with_a_byte_msgpack_never_uses_says_so(tmp_path):
    """msgpack's FormatError has no message: the error said "is malformed ()"."""
    from retriever.replay import replay_file, resim_file
    from tests.log.log_flows import build_small

    def change(messages, metadata):
        import msgpack

        step = _first(messages, "steps")
        fields = msgpack.unpackb(step[4])
        step[4] = b"\x97" + b"".join(map(msgpack.packb, fields[:5])) + b"\xc1" + msgpack.packb(fields[6])  # as detail

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change)
    error = r"step record #\d+ is malformed \(it is not valid msgpack \(FormatError\)\)"
    for read in (read_log(path).trace, lambda: replay_file(path, build_small), lambda: resim_file(path, build_small)):
        with pytest.raises(LogError, match=error):
            read()


def _accumulate_detail(detail: dict):
    """A change: accumulate's first step record (a flow fed by counter's k, level and pose) with
    ``detail``."""
    def change(messages, metadata):
        import msgpack

        for message in messages:
            if message[0] == "steps":
                record = msgpack.unpackb(message[4])
                if record[0] == "accumulate":
                    record[5] = detail
                    message[4] = msgpack.packb(record)
                    return
    return change


@pytest.mark.parametrize("detail, says", [
    ({"bogus": 1}, r"has detail 'bogus', which Retriever does not write \(nor is it an input port of accumulate"),
    ({"had_below": {"k": [["ghost", "k", 3]]}}, r"names in its detail 'had_below' the stream ghost\.k -> accumulate\.k, "
                                                r"which is no edge of pipeline 'small_log'"),
    ({"late": {"k": [["counter", "nope", 0]]}}, r"names in its detail 'late' the stream counter\.nope -> accumulate\.k, which is no edge"),
    ({"restart_gap": {"nope": [["counter", "k", 1, 3]]}}, r"names in its detail 'restart_gap' the stream counter\.k -> accumulate\.nope"),
    ({"restarted": {"seqs": {"nope": 0}, "inputs": {}}},
     r"gives in its detail 'restarted' the first seq of output accumulate\.nope, which pipeline 'small_log' does not "
     r"have"),
    ({"restarted": {"seqs": {"total": 0}, "inputs": {"k": [["ghost", "k", 0]]}}},
     r"names in its detail 'restarted' the stream ghost\.k -> accumulate\.k"),
])
def test_a_step_records_detail_naming_what_no_run_of_the_pipeline_writes_is_a_log_error(tmp_path, detail, says):
    """A key no backend writes, or a stream into the node that is no edge (a node or port the
    pipeline lacks), refuses the log before the first step: plain replay read its ``late``,
    ``had_below``, ``restart_gap`` and ``restarted`` as they came and replayed such a log
    identical (``--resim`` said the two traces differed, or, for ``late``, nothing)."""
    from retriever.replay import replay_file, resim_file
    from tests.log.log_flows import build_small

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", _accumulate_detail(detail))
    error = r"step record #\d+ \(of accumulate at t=0\.050000000s m=0\) " + says
    for read in (lambda: replay_file(path, build_small), lambda: replay(read_log(path), build_small()),
                 lambda: resim_file(path, build_small)):
        with pytest.raises(LogError, match=error) as refused:
            read()
        assert refused.value.hint.startswith("replay with the pipeline that wrote the log; else the file is damaged")


@pytest.mark.parametrize("detail", [
    {"level": 2},  # a Queue's drop count on an input port (tick.select_inputs)
    {"flow": {"said": [1, "x"]}, "exit": 0},
    {"late": {"k": [["counter", "k", 0]]}, "had_below": {"level": [["counter", "level", 1]]},
     "restart_gap": {"pose": [["counter", "pose", 0, 0]]}, "restarted": {"seqs": {"total": 0}, "inputs": {}}},
])
def test_a_step_records_detail_as_a_writer_writes_it_replays(tmp_path, detail):
    from retriever.replay import replay_file
    from tests.log.log_flows import build_small

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", _accumulate_detail(detail))
    assert replay_file(path, build_small).identical


def test_an_event_whose_microstep_is_cut_short_is_a_log_error(tmp_path):
    def change(messages, metadata):
        _first(messages, "data/counter/k")[4] = b"\x92\xcd\x01"  # a uint16 microstep missing a byte

    log = read_log(_rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change))
    with pytest.raises(LogError, match=r"event counter\.k #\d+ is malformed \(its microstep is not valid msgpack"):
        log.trace()


def test_an_event_logged_twice_is_a_log_error_in_replay(tmp_path):
    from tests.log.log_flows import build_small

    def change(messages, metadata):
        messages.append(list(_first(messages, "data/counter/k")))

    log = read_log(_rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change))
    with pytest.raises(LogError, match=r"event counter\.k #0 is logged twice"):
        replay(log, build_small())


def test_an_event_logged_twice_is_expected_twice_by_resim(tmp_path):
    """``--resim`` takes each copy of an event logged twice as an event the run made (a trace of
    the log has both): it reports what the log's trace and the re-run's say, read whole and
    streamed."""
    from retriever.replay import resim_file
    from tests.log.log_flows import build_small

    def change(messages, metadata):
        messages.append(list(_first(messages, "data/counter/k")))

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change)
    expected = read_log(path).trace().first_difference(build_small().run(duration=0.5), TRACES)
    assert expected is not None
    for report in (resim(read_log(path), build_small()), resim_file(path, build_small)):
        assert re.sub(r"publish_ns=\d+", "", report.difference) == re.sub(r"publish_ns=\d+", "", expected)


def _source_record_names(port: str | None):
    """A change: counter's (a source's) first step record that produced events names a port of
    its second event that the log has no event on (``port``), or (None) is logged twice."""
    def change(messages, metadata):
        import msgpack

        records = [m for m in messages if m[0] == "steps" and msgpack.unpackb(m[4])[0] == "counter"]
        if port is None:
            messages.append(list(records[1]))
            return
        fields = msgpack.unpackb(records[1][4])
        fields[3][0][1] = port
        records[1][4] = msgpack.packb(fields)
    return change


@pytest.mark.parametrize("port, says", [
    ("luvel", "says it produced event counter.luvel #1, which the log does not have"),
    (None, r"says it produced event counter.k #1, which an earlier step record said it produced too \(a record "
           r"logged twice\?\)"),
])
def test_a_source_step_record_naming_an_event_it_cannot_give_is_a_log_error_in_resim(tmp_path, port, says):
    """A replayed source's tick takes the events its step record names: one the log lacks was a
    KeyError raised in its step, reported as 'the re-simulation stopped: counter.step() raised
    KeyError: ...' with the hint to set on_error; it is the damaged log's LogError, as a value
    that does not decode is."""
    from retriever.replay import resim_file
    from tests.log.log_flows import build_small

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", _source_record_names(port))
    for run in (lambda: resim(read_log(path), build_small()), lambda: resim_file(path, build_small)):
        with pytest.raises(LogError, match=r"odd\.mcap: the step record of counter at t=0\.100000000s m=0 " + says):
            run()


def _source_record_changed(how: str):
    """A change: counter's (a source's) step records that produced events, ``how``: its second
    names a port the log has no event on (``"port"``), or is logged twice (``"twice"``); its
    third names the second's event in place of its own (``"other"``); its second names none
    (``"none"``: its event is no record's)."""
    def change(messages, metadata):
        import msgpack

        records = [m for m in messages if m[0] == "steps" and msgpack.unpackb(m[4])[0] == "counter"]
        second, third = (msgpack.unpackb(r[4]) for r in records[1:3])
        if how == "twice":
            messages.append(list(records[1]))
        elif how == "port":
            second[3][0][1] = "luvel"
        elif how == "other":
            third[3] = second[3]
        else:
            second[3] = []
        records[1][4], records[2][4] = msgpack.packb(second), msgpack.packb(third)
    return change


_TWICE = r"which an earlier step record said it produced too \(a record logged twice\?\)"


@pytest.mark.parametrize("how, says", [
    ("port", r"the step record of counter at t=0\.100000000s m=0 says it produced event counter\.luvel #1, "
             r"which the log does not have"),
    ("twice", r"the step record of counter at t=0\.100000000s m=0 says it produced event counter\.k #1, " + _TWICE),
    ("other", r"the step record of counter at t=0\.200000000s m=0 says it produced event counter\.k #1, " + _TWICE),
    ("none", r"event counter\.k #1 is in the log, but no step record of counter says it produced it"),
])
def test_a_source_step_record_that_does_not_match_the_logs_events_is_a_log_error_in_replay(tmp_path, how, says):
    """Replay takes a source's events from the log and does not run it: a record of it naming an
    event the log lacks, or one a record named already, and an event no record of it names, were
    taken as they were (the replay identical); the log is refused, as ``--resim`` refuses it, read
    whole and streamed, and by the CLI."""
    from retriever.replay import resim_file
    from tests.log.log_flows import build_small

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", _source_record_changed(how))
    hint = "the file is damaged or was edited: retriever replay reads logs as a run wrote them"
    for run in (lambda: replay(read_log(path), build_small()), lambda: replay_file(path, build_small),
                lambda: replay(read_log(path), build_small(), keep_trace=True)):
        with pytest.raises(LogError, match=r"odd\.mcap: " + says + r"\n    hint: " + hint):
            run()
    assert_cli_error(cli("replay", path), r"^error: .*odd\.mcap: " + says, hint=hint)
    for run in (lambda: resim(read_log(path), build_small()), lambda: resim_file(path, build_small)):
        with pytest.raises(LogError, match=r"odd\.mcap: " + says + r"\n    hint: " + hint):
            run()


def _step_record_left_out(node: str):
    """A change: ``node``'s second step record that produced events is not in the log (its events are)."""
    def change(messages, metadata):
        import msgpack

        records = [m for m in messages if m[0] == "steps" and msgpack.unpackb(m[4])[0] == node
                   and msgpack.unpackb(m[4])[3]]
        messages.remove(records[1])
    return change


def test_an_event_whose_step_record_the_log_lacks_is_not_left_out_of_resim(tmp_path):
    """An event no step record names: a replayed source's refuses the log, as plain replay refuses
    it (its ticks take the log's records in turn: without the record, the re-simulation ran out of
    them, 'counter.step() raised StopIteration'); a re-executed flow's is compared, as the two
    whole traces compare it (it was left out: 'event accumulate.total #1 is in the re-simulation,
    not in the log'). A log cut short may lose the record and keep its event (another chunk): there
    the source's event is let go, as before."""
    from retriever.replay import resim_file
    from tests.log.log_flows import build_small

    hint = "the file is damaged or was edited: retriever replay reads logs as a run wrote them"
    says = r"odd\.mcap: event counter\.k #1 is in the log, but no step record of counter says it produced it"
    small = _small_log(tmp_path)
    path = _rewritten(small, tmp_path / "odd.mcap", _step_record_left_out("counter"))
    for run in (lambda: resim(read_log(path), build_small()), lambda: resim_file(path, build_small),
                lambda: replay_file(path, build_small)):
        with pytest.raises(LogError, match=says + r"\n    hint: " + hint):
            run()

    path = _rewritten(small, tmp_path / "other.mcap", _step_record_left_out("accumulate"))
    expected = read_log(path).trace().first_difference(build_small().run(duration=0.5), TRACES)
    assert expected.startswith("record 27: StepRecord(node='tally', tag=(250000000, 1)"), expected
    for report in (resim(read_log(path), build_small()), resim_file(path, build_small)):
        assert re.sub(r"wall_\w+=\d+", "", report.difference) == re.sub(r"wall_\w+=\d+", "", expected)

    def recovered(messages, metadata):
        _step_record_left_out("counter")(messages, metadata)
        metadata[RECOVERED_METADATA] = {"from": "odd.mcap"}

    path = _rewritten(small, tmp_path / "recovered.mcap", recovered)
    for report in (resim(read_log(path), build_small()), resim_file(path, build_small)):
        assert report.difference.startswith("the re-simulation stopped: counter.step() raised StopIteration")


def test_an_event_of_a_replayed_flow_that_no_step_record_names_refuses_the_replay(tmp_path):
    """Plain replay re-executes a flow's steps from its records and compares their outputs with the
    log's: an event of that flow no record names was compared with nothing, and the replay said
    "identical" of a log holding an output no step made. It refuses the log, as it refuses a
    source's such event (read whole, streamed, and by the CLI)."""
    from tests.log.log_flows import build_small

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", _step_record_left_out("accumulate"))
    says = r"odd\.mcap: event accumulate\.total #1 is in the log, but no step record of accumulate says it produced it"
    hint = "the file is damaged or was edited: retriever replay reads logs as a run wrote them"
    for run in (lambda: replay(read_log(path), build_small()), lambda: replay_file(path, build_small),
                lambda: replay(read_log(path), build_small(), keep_trace=True)):
        with pytest.raises(LogError, match=says + r"\n    hint: " + hint):
            run()
    assert_cli_error(cli("replay", path), r"^error: .*" + says, hint=hint)


def test_a_logged_value_that_does_not_decode_is_a_divergence_in_replay(tmp_path):
    from tests.log.log_flows import build_small

    def change(messages, metadata):
        event = _first(messages, "data/tally/count")
        event[4] = event[4][:2] + b"\xc1"  # microstep, then a byte msgpack never uses

    report = replay(read_log(_rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change)), build_small())
    assert report.divergences[0].logged == "<1 bytes that do not decode: FormatError>"


@pytest.mark.parametrize("value, error", [
    (b"\xc1", r"event counter\.k #0 is not valid msgpack \(FormatError\)"),
    (b"\xc7\x03\x04\x92\x01\x02", r"event counter\.k #0 is damaged: a dataclass value must be"),
])
def test_a_routed_value_that_does_not_decode_refuses_the_replay_as_the_log_says_it(tmp_path, value, error):
    """A value a consumer is given is decoded as it is read (counter.k goes to acc): one that does
    not decode refuses the log, with the error its reading (``log.value``) gives, read whole or
    streamed; the replay does not build a LoggedEvent for every event to say it."""
    from tests.log.log_flows import build_small

    def change(messages, metadata):
        event = _first(messages, "data/counter/k")
        event[4] = event[4][:2] + value  # microstep, then the value

    path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change)
    log = read_log(path)
    with pytest.raises(LogError, match=error):
        log.value(next(e for e in log.iter_events() if e.id == ("counter", "k", 0)))
    with pytest.raises(LogError, match=error):
        replay(read_log(path), build_small())
    with pytest.raises(LogError, match=error):
        replay_file(path, build_small)


def test_log_info_of_a_run_record_whose_packages_are_not_json_is_a_log_error(tmp_path):
    from retriever.log.reader import run_info

    def change(messages, metadata):
        metadata["retriever.run"]["packages"] = "{"

    log = read_log(_rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change))
    with pytest.raises(LogError, match="the run record's packages are not a JSON object of versions"):
        run_info(log)

ARRAY_FLOWS = '''
import numpy as np
from retriever import Flow, Pipeline, Rate, Trigger


class Source(Flow):
    def step(self):
        return {{"x": np.linspace(0.0, 1.0, 12).reshape(3, 4)}}


class Scale(Flow):
    def step(self, x):
        y = x * 2.0
        y[1, 2] += {nudge}
        return {{"y": y, "total": float(y.sum())}}


with Pipeline("nudge") as pipe:
    src = Source() @ Rate(hz=10)
    scale = Scale().named("scale") @ Trigger()
    src.then(scale)
'''


def test_replay_shows_a_difference_of_1e_7(tmp_path: Path, monkeypatch):
    """A step that now adds 1e-7 to one element: the replay names the array's dtype and shape,
    how many elements differ, where the largest difference is and how large, with values that
    show it; a float output is printed in full."""
    monkeypatch.setattr(sys, "path", list(sys.path))
    monkeypatch.setattr(sys, "dont_write_bytecode", True)
    name = f"nudge_{secrets.token_hex(4)}"
    module = tmp_path / "flows" / f"{name}.py"
    module.parent.mkdir()
    module.write_text(ARRAY_FLOWS.format(nudge="0.0"), encoding="utf-8")
    log = tmp_path / "nudge.mcap"
    try:
        load_pipeline(str(module)).run(duration=0.1, log=log)
        _rewrite(module, name, ARRAY_FLOWS.format(nudge="1e-7"))
        with pytest.warns(RetrieverWarning, match=CODE_CHANGED.format(name=name)):
            first, = replay(read_log(log)).divergences
    finally:
        sys.modules.pop(name, None)
    text = str(first)
    assert re.search(r"^scale\.y at tick t=0\.000000000s m=1: value differs\n", text), text
    assert "1.0909090909090908" in text and "1.0909091909090909" in text, text  # each value in full
    assert re.search(r"\n      float64 \(3, 4\): 1 of 12 elements differ\n      largest difference at \[1, 2\]: "
                     r"logged 1\.0909090909090908, replayed 1\.0909091909090909 \(absolute 1\.0000000\d*e-07, "
                     r"relative 9\.16666\d*e-08\)$", text), text
    total = str(Divergence("scale", (0, 1), "value", "total", 12.0, 12.0000001))  # the step's float output
    assert re.search(r"^scale\.total at .*\n      logged:   12\.0\n      replayed: 12\.0000001\n      difference: "
                     r"absolute 9\.99999993922529e-08, relative 8\.333333282687741e-09$", total), total
    result = cli("replay", log)
    assert result.returncode == 1
    assert re.search(rf"DIVERGED: 1 of 1 replayed steps differ; {CODE_CHANGED.format(name=name)}\. First:\n\s+"
                     r"scale\.y at tick t=0\.000000000s m=1: value differs\n(.*\n){6,}\s+float64 \(3, 4\): "
                     r"1 of 12 elements differ\n\s+largest difference at "
                     r"\[1, 2\]", result.stdout), result.stdout


@pytest.mark.parametrize("where", ["header length", "channel length", "metadata text", "chunk length"])
def test_a_flipped_byte_early_in_a_log_is_corruption_not_a_stopped_writer(one_chunk: Path, tmp_path: Path, where):
    """A byte changed in a record's length or text, early in a finished log, used to be reported
    as "its writer was stopped": it says the file is corrupt, at which record, and that
    recover keeps what comes before."""
    data = one_chunk.read_bytes()
    first = {0x01: None, 0x04: None, 0x0C: None, 0x06: None}
    for opcode, offset, _ in records(data):
        if opcode in first and first[opcode] is None:
            first[opcode] = offset
    offset = {"header length": first[0x01] + 2, "channel length": first[0x04] + 2,
              "metadata text": first[0x0C] + 9 + 6, "chunk length": first[0x06] + 2}[where]
    damaged = flip(one_chunk, offset, tmp_path / "flipped.mcap")
    record = {"header length": ("Header", first[0x01]), "channel length": ("Channel", first[0x04]),
              "metadata text": ("Metadata", first[0x0C]), "chunk length": ("Chunk", first[0x06])}[where]
    corrupt = rf"cannot be read: it is corrupt(: the| at the) {record[0]} record at byte {record[1]}"
    with pytest.raises(LogError, match=corrupt) as raised:
        read_log(damaged)
    assert "writer was stopped" not in str(raised.value)
    for command in (["log", "info"], ["log", "cat"], ["replay"]):
        result = cli(*command, damaged)
        assert_cli_error(result, r"^error: .*flipped\.mcap " + corrupt)
        assert "writer was stopped" not in result.stderr


# ---------------------------------------------------------------------------------------------
# Forged strings in a log reach the terminal inert; a log cut short replays what it holds
# ---------------------------------------------------------------------------------------------
@pytest.fixture
def small_log(tmp_path: Path) -> Path:
    from tests.log.log_flows import build_small

    path = tmp_path / "small.mcap"
    build_small().run(duration=0.5, log=path)
    return path


def test_a_logs_strings_reach_the_terminal_as_text_not_escape_codes_or_markup(small_log, tmp_path):
    """``log info`` printed a log's host as Rich markup with its control characters: an escape
    sequence retitled the terminal, recoloured it, planted a hyperlink; a stray ``[/]`` crashed it."""
    host = "\x1b]0;TITLE\x07\x1b[31mRED[/] [link=http://evil]click[/link]"

    def forge(name, values):
        if name == "retriever.run":
            values["host"] = host

    result = cli("log", "info", rewrite(small_log, tmp_path / "forged.mcap", metadata=forge))
    assert result.returncode == 0, result.stderr
    assert "\x1b" not in result.stdout and "\x07" not in result.stdout
    assert r"\x1b]0;TITLE\x07\x1b[31mRED[/] [link=http://evil]click[/link]" in result.stdout, result.stdout


@pytest.mark.parametrize("key, value, message", [
    ("command_line", "not json", r"its metadata 'command_line' is not a JSON list \('not json'\)"),
    ("packages", "[1, 2]", r"the run record's packages are not a JSON object of versions"),
])
def test_log_info_on_forged_metadata_is_an_error_not_a_traceback(small_log, tmp_path, key, value, message):
    def forge(name, values):
        if name == "retriever.run":
            values[key] = value

    result = cli("log", "info", rewrite(small_log, tmp_path / "forged.mcap", metadata=forge))
    assert_cli_error(result, r"^error: .*" + message)


def test_an_error_keeps_its_bracketed_text(small_log, tmp_path):
    """The first line of an error was printed as markup: ``[node, microstep, …]`` vanished."""
    import msgpack

    def keep(topic, message):
        if topic == "steps":
            message.data = msgpack.packb(["counter", 0, {}, [], "ok", None, 1.5])  # wall_ns a float
        return True

    result = cli("log", "cat", "--steps", rewrite(small_log, tmp_path / "forged.mcap", keep=keep))
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    assert "(it is not [node, microstep, consumed, produced, status, detail, wall_ns] of a step)" in \
        result.stderr.splitlines()[0], result.stderr


def test_a_log_cut_short_replays_the_steps_it_holds(small_log, tmp_path):
    """A step record can outlive the events it produced when a log is cut (its writer killed, or
    damage, then ``recover``): replay re-executes it but cannot compare it, and says so; before, it
    reported the honest run as DIVERGED (``<not in the log: the log ends here>``). A complete log
    that lacks an event is no record of the run: that stays a divergence."""
    log = read_log(small_log)
    last = max((s for s in log.iter_steps() if s.produced and s.node == "accumulate"), key=lambda s: s.tag)
    lost = set(last.produced)

    def keep(topic, message) -> bool:
        return not (topic.startswith("data/") and (*topic[len("data/"):].split("/"), message.sequence) in lost)

    assert not replay(read_log(rewrite(small_log, tmp_path / "missing.mcap", keep=keep))).identical
    cut = rewrite(small_log, tmp_path / "cut.mcap", keep=keep,
                  add={RECOVERED_METADATA: {"source": str(small_log)}})  # as `retriever log recover` marks it
    report = replay(read_log(cut))
    assert report.identical, report.divergences
    # the step that produced the lost event, and the one that consumed it
    assert (report.nodes["accumulate"].cut, report.nodes["tally"].cut) == (1, 1)
    result = cli("replay", cut)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "(2 at the end not compared: the log was cut short and lost events they consumed or produced)" in \
        result.stdout.replace("\n", " ")


def test_a_flipped_byte_in_the_ir_attachment_is_caught_by_its_crc(one_chunk: Path, tmp_path: Path):
    """The mcap library drops an attachment's CRC unread: a byte changed in the stored IR was
    reported at the DataEnd record, and `recover` copied the damaged IR into its "readable" copy
    (a replay then rebuilt the pipeline from it). Now: corrupt at the Attachment record, and
    recover leaves that attachment out, keeping every message."""
    data = one_chunk.read_bytes()
    offset = next(offset for opcode, offset, _ in records(data) if opcode == 0x09)
    body = data.index(b"{", offset)  # the IR's JSON text
    damaged = flip(one_chunk, body + 40, tmp_path / "flipped.mcap")
    corrupt = rf"cannot be read: it is corrupt at the Attachment record at byte {offset}: a CRC check failed"
    with pytest.raises(LogError, match=corrupt) as raised:
        read_log(damaged)
    assert "without the damaged attachment" in raised.value.hint
    result = cli("replay", damaged)
    assert_cli_error(result, r"^error: .*flipped\.mcap " + corrupt)
    salvaged = read_log(damaged, salvage=True)
    assert "pipeline.ir.json" not in salvaged.attachments
    assert len(salvaged.messages) == len(read_log(one_chunk).messages)
    assert re.search(rf"Attachment record at byte {offset}.*the attachment 'pipeline.ir.json' was left out", salvaged.damage)
    out = recover(damaged, tmp_path / "fixed.mcap").output
    fixed = read_log(out)
    assert "pipeline.ir.json" not in fixed.attachments and len(fixed.messages) == len(salvaged.messages)
    with pytest.raises(LogError, match="holds no pipeline IR"):
        fixed.ir


@pytest.mark.parametrize("field, value", [("end_ns", "NaN"), ("end_ns", "-1"), ("events", "x" * 200_000),
                                          ("steps", ""), ("finished_unix_ns", "1e4")])
def test_an_end_record_whose_counts_are_not_counts_is_named(tmp_path, field, value):
    """`log info` said `error: ValueError: invalid literal for int() with base 10: 'NaN'`."""
    def change(messages, metadata):
        metadata["retriever.end"][field] = value

    log_path = _rewritten(_small_log(tmp_path), tmp_path / "odd.mcap", change)
    with pytest.raises(LogError, match=rf"the end record retriever.end is malformed: its {field} is '.*, not a count"):
        read_log(log_path).end
    assert_cli_error(cli("log", "info", log_path), rf"the end record retriever.end is malformed: its {field} is",
                     hint="the file was changed after it was written")


def test_a_chunk_that_would_decompress_past_the_limit_is_refused_before_it_is(tmp_path, monkeypatch):
    """A decompression bomb: a 98 KB file whose one chunk expands to 3 GiB took 16 s and 6.3 GB.
    Here a real 2 MiB frame of zeros (4 KB on disk) against a limit lowered to 1 MiB."""
    import numpy as np

    import retriever.log.reader as reader
    from retriever import Flow, Pipeline, Rate

    class Zeros(Flow):
        def step(self):
            return {"frame": np.zeros(2 << 20, np.uint8)}

    class Sink(Flow):
        def step(self, frame):
            return None

    with Pipeline("bomb") as pipe:
        (Zeros() @ Rate(hz=1)).then(Sink() @ Rate(hz=1))
    path = tmp_path / "zeros.mcap"
    pipe.run(duration=1.0, log=path)
    assert path.stat().st_size < 64 << 10 and read_log(path).trace().values_of("zeros", "frame")[0].size == 2 << 20
    monkeypatch.setattr(reader, "MAX_CHUNK_BYTES", 1 << 20)
    with pytest.raises(LogError, match=r"a chunk holds 2,09\d,\d{3} bytes uncompressed, more than a log is read with "
                                       r"\(1,048,576\)"):
        read_log(path)


def _closing_variants(path: Path, tmp_path: Path) -> dict[str, Path]:
    """Copies of a whole log whose records all read, but whose end is not what indexed readers
    seek by: bytes after the magic, the file twice, a changed summary byte, a footer pointing
    past itself, a chunk index naming no chunk."""
    data = path.read_bytes()
    footer_at = len(data) - 8 - 29
    summary_start = int.from_bytes(data[footer_at + 9:footer_at + 17], "little")
    variants = {"trailing": data + b"JUNKJUNK", "twice": data + data}
    flipped = bytearray(data)
    flipped[footer_at - 1] ^= 0xFF  # the summary's last byte: a summary offset's length, a value no one parses
    variants["summary byte"] = bytes(flipped)
    past = bytearray(data)
    past[footer_at + 9:footer_at + 17] = (1 << 62).to_bytes(8, "little")
    variants["footer"] = bytes(past)
    with path.open("rb") as f:
        index = next(iter(make_reader(f).get_summary().chunk_indexes))
    # the chunk index's chunk_start_offset is its first field: find it in the summary by value
    at = data.index(index.chunk_start_offset.to_bytes(8, "little") + index.chunk_length.to_bytes(8, "little"),
                    summary_start)
    moved = bytearray(data)
    moved[at:at + 8] = (index.chunk_start_offset + 1).to_bytes(8, "little")
    offsets = int.from_bytes(data[footer_at + 17:footer_at + 25], "little")
    crc = zlib.crc32(bytes(moved[summary_start:footer_at]))  # its summary CRC made to match: only the index is wrong
    moved[footer_at + 25:footer_at + 29] = zlib.crc32(struct.pack("<BQQQ", 0x02, 20, summary_start, offsets),
                                                      crc).to_bytes(4, "little")
    variants["chunk index"] = bytes(moved)
    out = {}
    for name, content in variants.items():
        out[name] = tmp_path / f"{name.replace(' ', '_')}.mcap"
        out[name].write_bytes(content)
    return out


@pytest.mark.parametrize("variant, damage", [
    ("trailing", r"8 bytes follow its closing magic bytes"),
    ("twice", r"[\d,]+ bytes follow its closing magic bytes"),
    ("summary byte", r"its summary does not match its CRC"),
    ("footer", r"its footer puts the summary at bytes 4,611,686,018,427,387,904"),
    ("chunk index", r"its chunk index names a chunk at byte [\d,]+ where there is none"),
])
def test_a_log_whose_end_indexed_readers_refuse_is_called_damaged_and_recovered(tmp_path, variant, damage):
    """`log info` called such files complete, and `log recover` had nothing to do, while Foxglove's
    reader and mcap's refused them."""
    path = _small_log(tmp_path)
    changed = _closing_variants(path, tmp_path)[variant]
    log = read_log(changed)  # its records read whole: it still replays
    assert re.match(damage, log.damage) and log.trace() == read_log(path).trace()
    info = cli("log", "info", changed)
    assert info.returncode == 0 and re.search(r"damaged: " + damage, " ".join(info.stdout.split())), info.stdout
    result = recover(changed, tmp_path / "whole.mcap")
    assert result.output is not None and re.match(damage, result.damage)
    again = read_log(result.output)
    assert again.damage is None and again.complete and again.trace() == log.trace()
    with result.output.open("rb") as f:  # what an indexed reader seeks by is whole again
        assert len(list(make_reader(f).iter_messages())) == len(again.messages)


def test_an_event_no_step_record_names_is_let_go_only_for_a_flow_whose_process_died(tmp_path):
    """A process that died may leave its flow's event without a record (the log's fault record
    says whose): that flow's is let go, but another flow's still refuses the log (any fault in the
    log let every flow's go, and the replay said "identical" of an output no step made)."""
    import json

    from tests.log.log_flows import build_small

    def died(node: str):
        def change(messages, metadata):
            _step_record_left_out("accumulate")(messages, metadata)
            metadata["retriever.fault.1"] = {"kind": "process_lost", "node": node, "at_ns": "300000000",
                                             "pid": "7", "exit": "exited with code 3", "restarted": "false",
                                             "seqs": json.dumps({}), "lost_events": json.dumps([])}
        return change

    small = _small_log(tmp_path)
    says = r"event accumulate\.total #1 is in the log, but no step record of accumulate says it produced it"
    other = _rewritten(small, tmp_path / "other.mcap", died("tally"))
    for run in (lambda: replay(read_log(other), build_small()), lambda: replay_file(other, build_small)):
        with pytest.raises(LogError, match=says):
            run()
    its = _rewritten(small, tmp_path / "its.mcap", died("accumulate"))
    assert replay_file(its, build_small).steps_replayed > 0  # let go: a report, not that error


def _let_go_or_refused(path: Path, let_go: bool) -> None:
    """``path``'s added event accumulate.total #9, which no step record names, is let go (the log
    replays: a report) or refused, by replay and replay_file both."""
    from tests.log.log_flows import build_small

    says = r"event accumulate\.total #9 is in the log, but no step record of accumulate says it produced it"
    for run in (lambda: replay(read_log(path), build_small()), lambda: replay_file(path, build_small)):
        if let_go:
            assert run().steps_replayed > 0  # a report, not that error
        else:
            with pytest.raises(LogError, match=says):
                run()


@pytest.mark.parametrize("at_s, let_go", [
    (0.1, False),  # before accumulate's record at 0.25 s, the last before its death at 0.3 s: no record was lost
    (0.5, False),  # after its death: no process of it made it
    (0.27, True),  # after that record, before the death: its record may have gone with the process
])
def test_an_added_event_of_a_flow_whose_process_died_is_let_go_only_after_its_last_record_before_the_death(
        tmp_path, at_s, let_go):
    """On zenoh a consumer logs an event it took whose producer's record a kill lost, with every
    later record of that process (docs/log.md): an event of the dead flow that no record names is
    let go only if it is later than the flow's last record before the death, and not after the
    death. Any event of that flow was let go (session 13's cold review: one added to the log, dated
    before the crash, replayed without a word)."""
    import json

    def added(messages, metadata):
        total = [m for m in messages if m[0] == "data/accumulate/total"]
        assert [m[1] for m in total] == [50_000_000, 250_000_000, 450_000_000]  # accumulate's ticks
        messages.append(["data/accumulate/total", int(at_s * 1e9), total[0][2], 9, total[0][4]])
        metadata["retriever.fault.1"] = {"kind": "process_lost", "node": "accumulate", "at_ns": "300000000",
                                         "pid": "7", "exit": "was killed by SIGKILL", "restarted": "false",
                                         "seqs": json.dumps({}), "lost_events": json.dumps([])}

    path = _rewritten(_small_log(tmp_path), tmp_path / "added.mcap", added)
    _let_go_or_refused(path, let_go)


@pytest.mark.parametrize("ahead_ms, at_s, let_go", [
    (300, 0.5, True),  # its worker's clock ran 300 ms ahead: the event at 0.5 s is before its death at 0.6 s on it
    (100, 0.5, False),  # 100 ms: after its death at 0.4 s on that clock
    (-300, 0.5, False),  # behind: a stamp is never taken for earlier than the coordinator's clock says (HLC)
    (2**42, 0.5, True),  # a log claiming more is bounded by Zenoh's HLC tolerance, 500 ms: 0.5 s let go,
    (2**42, 0.85, False),  # but not past 0.3 + 0.5 s (a forged offset does not let every event go)
])
def test_an_orphan_event_of_a_deployments_flow_is_judged_by_the_clock_of_the_workers(tmp_path, ahead_ms, at_s,
                                                                                    let_go):
    """A deployment's node stamps by its worker's HLC, whose clock the worker said (``offset_ns``,
    in the run record's ``deployment``) was ahead of the coordinator's, which dates the death: an
    event stamped on it just before the death (after the coordinator's time of it) is let go, not
    refused as no step's output (session 14's note: the dead-flow rule against node clock skew)."""
    import json

    def added(messages, metadata):
        total = [m for m in messages if m[0] == "data/accumulate/total"]
        messages.append(["data/accumulate/total", int(at_s * 1e9), total[0][2], 9, total[0][4]])
        metadata["retriever.run"]["deployment"] = json.dumps({
            "namespace": "lab", "placed": {"accumulate": "w1", "tally": "w0"}, "ran_other_code": {},
            "workers": {"w0": {"host": "a", "offset_ns": 0}, "w1": {"host": "b", "offset_ns": ahead_ms * 1_000_000}}})
        metadata["retriever.fault.1"] = {"kind": "process_lost", "node": "accumulate", "at_ns": "300000000",
                                         "pid": "7", "exit": "was killed by SIGKILL", "restarted": "false",
                                         "seqs": json.dumps({}), "lost_events": json.dumps([])}

    path = _rewritten(_small_log(tmp_path), tmp_path / "deployed.mcap", added)
    assert read_log(path).deployment.workers["w1"]["offset_ns"] == ahead_ms * 1_000_000
    _let_go_or_refused(path, let_go)


def test_an_orphan_event_of_a_flow_whose_process_died_in_virtual_time_is_let_go_after_its_last_record(tmp_path):
    """A fault's ``at_ns`` is the coordinator's wall clock since T0 (book.run_time), which in a
    virtual-time log (run record ``time: virtual``) says nothing of the tags: the run goes as fast
    as its steps do. A process killed 10 ms into the run, its virtual time at 0.45 s, left an event
    after its last record that the replay must let go; _died_with_its_record compared its tag
    with the wall-clock death and refused the log (review14)."""
    import json

    from tests.log.log_flows import build_small

    def added(messages, metadata):
        total = [m for m in messages if m[0] == "data/accumulate/total"]
        messages.append(["data/accumulate/total", 470_000_000, total[0][2], 9, total[0][4]])
        metadata["retriever.run"]["time"] = "virtual"
        metadata["retriever.fault.1"] = {"kind": "process_lost", "node": "accumulate", "at_ns": "10000000",
                                         "pid": "7", "exit": "was killed by SIGKILL", "restarted": "false",
                                         "seqs": json.dumps({}), "lost_events": json.dumps([])}

    path = _rewritten(_small_log(tmp_path), tmp_path / "virtual.mcap", added)
    assert read_log(path).run["time"] == "virtual"
    for run in (lambda: replay(read_log(path), build_small()), lambda: replay_file(path, build_small)):
        assert run().steps_replayed > 0  # a report, not 'no step record of accumulate says it produced it'


def test_an_orphan_event_of_a_restarted_flow_is_let_go_when_another_worker_ran_ahead(tmp_path):
    """(review16a) The death is taken later by the furthest ahead any worker said its clock ran
    (``clock_ahead_ns``), here 200 ms (a worker of tally's; accumulate's worker runs at the
    coordinator's clock): accumulate, killed at 0.3 s and restarted, stepped again at 0.45 s,
    before the death so taken (0.5 s). That record of its fresh process is then taken for the last
    of the dead one, and the event the dead process stamped at 0.27 s, after its last record
    (0.25 s) and before its death, is refused as no step's output: the same log without the
    deployment lets it go (test above, at 0.27 s), and so should this one, a legitimate log of a
    deployment with a worker 200 ms ahead (``--max-clock-offset 0.5``)."""
    import json

    import msgpack

    from tests.log.log_flows import build_small

    def added(messages, metadata):
        total = [m for m in messages if m[0] == "data/accumulate/total"]
        assert [m[1] for m in total] == [50_000_000, 250_000_000, 450_000_000]  # accumulate's ticks
        messages.append(["data/accumulate/total", 270_000_000, total[0][2], 9, total[0][4]])
        # its record at 0.45 s is its fresh process's first (detail.restarted), as a restart writes it
        step = next(m for m in messages if m[0] == "steps" and m[1] == 450_000_000
                    and msgpack.unpackb(m[4])[0] == "accumulate")
        record = msgpack.unpackb(step[4])
        record[5] = {"restarted": {"seqs": {"total": 2, "window": 2},
                                   "inputs": {port: ids for port, ids in record[2].items()}}}
        step[4] = msgpack.packb(record)
        metadata["retriever.run"]["deployment"] = json.dumps({
            "namespace": "lab", "placed": {"counter": "w1", "accumulate": "w1", "tally": "w0"}, "ran_other_code": {},
            "workers": {"w0": {"host": "a", "offset_ns": 200_000_000}, "w1": {"host": "b", "offset_ns": 0}}})
        metadata["retriever.fault.1"] = {"kind": "process_lost", "node": "accumulate", "at_ns": "300000000",
                                         "pid": "7", "exit": "was killed by SIGKILL", "restarted": "true",
                                         "seqs": json.dumps({"total": 2, "window": 2}), "lost_events": json.dumps([])}

    path = _rewritten(_small_log(tmp_path), tmp_path / "restarted.mcap", added)
    assert read_log(path).deployment.clock_ahead_ns() == 200_000_000
    for run in (lambda: replay(read_log(path), build_small()), lambda: replay_file(path, build_small)):
        assert run().steps_replayed > 0  # a report, not "no step record of accumulate says it produced it"
