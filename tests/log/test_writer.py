"""Where a run's log goes: an existing file is kept unless asked; a path that cannot be a log is
refused before the run starts; a write the OS refuses during the run stops it with the path and
the OS error; no message claims a run is in a file that does not hold it."""

from __future__ import annotations

import re
import resource
import runpy
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader

from retriever import Burst, Flow, Latest, LogError, Pipeline, Rate, Trigger, io, read_log
from retriever.codec import packb
from retriever.errors import LogWriteError
from retriever.log import format as fmt
from retriever.log import recover
from retriever.log.writer import LARGE_VALUE_BYTES, LogFile, LogWriter, sequences
from retriever.replay import replay
from retriever.trace import StepStatus, Trace
from tests.log import log_flows
from tests.backends.test_inproc_ticks import mixed
from tests.log.helpers import QUICKSTART, RETRIEVER, assert_cli_error, cli, cli_env

NOTES = "my notes, not a log\n"
EXISTS = r"the log .*notes\.mcap already exists; a run does not overwrite a file"
EXISTS_HINT = r"pass --force \(retriever run\) or overwrite=True \(pipe\.run\) to replace it, or log to another path"
#: file sizes the OS refuses to go past (RLIMIT_FSIZE): a disk that fills up during the run,
#: after a few chunks (in-process chunks reach the writer's 1 MiB limit; a real-time quickstart
#: log grows about 10 kB/s, its IR and metadata take 4 kB)
FULL_AFTER_BYTES = {"inproc": 3_000_000, "zenoh": 20_000}


@pytest.fixture
def notes(tmp_path: Path) -> Path:
    path = tmp_path / "notes.mcap"
    path.write_text(NOTES, encoding="utf-8")
    return path


# ---------------------------------------------------------------------------------------------
# An existing file
# ---------------------------------------------------------------------------------------------
def test_a_run_does_not_overwrite_an_existing_file(notes: Path):
    pipe = log_flows.build_small()
    with pytest.raises(LogError, match=EXISTS + r"\n    hint: " + EXISTS_HINT):
        pipe.run(duration=0.5, log=notes)
    assert notes.read_text(encoding="utf-8") == NOTES
    assert pipe.trace.steps == [], "the refused run must not have started"
    trace = pipe.run(duration=0.5, log=notes, overwrite=True)
    assert read_log(notes).trace() == trace


def test_cli_run_refuses_an_existing_log_unless_forced(notes: Path):
    assert_cli_error(cli("run", QUICKSTART, "--duration", "1", "--log", notes), "^error: " + EXISTS, hint=EXISTS_HINT)
    assert notes.read_text(encoding="utf-8") == NOTES
    forced = cli("run", QUICKSTART, "--duration", "1", "--log", notes, "--force")
    assert forced.returncode == 0, forced.stderr
    assert replay(read_log(notes)).identical


def test_a_refused_zenoh_run_starts_no_hub_and_no_worker(notes: Path):
    """The check comes before the backend opens: no hub endpoint is printed, no worker started."""
    result = cli("run", QUICKSTART, "--backend", "zenoh", "--duration", "1", "--log", notes)
    assert_cli_error(result, "^error: " + EXISTS, hint=EXISTS_HINT)
    assert "Zenoh hub listening" not in result.stdout + result.stderr
    assert notes.read_text(encoding="utf-8") == NOTES


def test_a_run_refused_after_the_file_was_created_removes_it(tmp_path: Path):
    """A run refused once the log file exists (a second run= of a pipeline with log=) leaves no
    empty file that would claim to hold it."""
    pipe = log_flows.build_small()
    pipe.run(duration=0.5)
    with pytest.raises(Exception, match="log= records a run from T0"):
        pipe.run(duration=0.5, log=tmp_path / "late.mcap")
    assert not (tmp_path / "late.mcap").exists()


#: a pipeline whose policy's setup() raises (its weights are missing), for ``retriever run``
UNSTARTABLE = """
from retriever import Latest, Pipeline, Rate, Trigger
from tests.backends.setup_flows import Camera, Policy

with Pipeline("unstartable") as pipe:
    (Camera("{journal}") @ Rate(hz=10)).then(Policy("{journal}", fail_setup=True) @ Trigger(), sync=Latest())
"""
UNSTARTED = r"policy\.setup\(\) raised FileNotFoundError: weights\.pt, before its first tick: the run did not start"


@pytest.mark.parametrize("backend", ["inproc", "zenoh"])
def test_a_run_whose_setup_fails_leaves_no_log_and_says_so(tmp_path: Path, backend):
    """A flow's setup() raised before the first tick: a log would hold no step of the run (only
    its metadata), so the run removes it, an overwritten file too (it was emptied), and its
    error says so on a line of its own."""
    from retriever import SetupError
    from tests.backends.setup_flows import Camera, Policy

    journal, log = tmp_path / "journal", tmp_path / "run.mcap"
    with Pipeline("unstartable") as pipe:
        (Camera(str(journal)) @ Rate(hz=10)).then(Policy(str(journal), fail_setup=True) @ Trigger(), sync=Latest())
    options = {"quiet": True} if backend == "zenoh" else {}
    with pytest.raises(SetupError, match=UNSTARTED) as raised:
        pipe.run(duration=1.0, backend=backend, log=log, **options)
    assert not log.exists()
    assert raised.value.__notes__ == [f"no log is left: the run did not start, so {log} was removed"]
    pipe.reset()

    script = tmp_path / "unstartable.py"
    script.write_text(UNSTARTABLE.format(journal=journal))
    log.write_text("an older run's log")
    result = cli("run", script, "--backend", backend, "--duration", "1", "--log", log, "--force")
    assert result.returncode == 1 and re.search("^error: " + UNSTARTED, result.stderr, re.MULTILINE), result.stderr
    assert f"\nno log is left: the run did not start, so {log} was removed\n" in result.stderr, result.stderr
    assert "the run up to the error is in" not in result.stderr and not log.exists()


def test_recover_does_not_overwrite_an_existing_file(notes: Path, tmp_path: Path):
    log = tmp_path / "run.mcap"
    log_flows.build_small().run(duration=0.5, log=log)
    torn = tmp_path / "torn.mcap"
    torn.write_bytes(log.read_bytes()[:-100])
    with pytest.raises(LogError, match=r"notes\.mcap already exists; recover does not overwrite a file\n    hint: "
                                       r"pass --force \(retriever log recover\) or overwrite=True"):
        recover(torn, notes)
    assert notes.read_text(encoding="utf-8") == NOTES
    assert_cli_error(cli("log", "recover", torn, "-o", notes), "recover does not overwrite a file",
                     hint=r"pass --force \(retriever log recover\)")
    done = cli("log", "recover", torn, "-o", notes, "--force")
    assert done.returncode == 0, done.stderr
    assert read_log(notes).complete


# ---------------------------------------------------------------------------------------------
# A path that cannot be a log
# ---------------------------------------------------------------------------------------------
def test_a_folder_is_not_a_log(tmp_path: Path):
    for overwrite in (False, True):
        with pytest.raises(LogError, match=r"cannot create the log .*: it is a folder\n    hint: pass --log / log= a "
                                           r"file path, e.g. .*run\.mcap"):
            log_flows.build_small().run(duration=0.5, log=tmp_path, overwrite=overwrite)


def test_a_log_that_takes_no_bytes_fails_before_the_run(tmp_path: Path):
    """/dev/full opens, and refuses every write with ENOSPC: the first write, made before the
    run starts, says so with the path."""
    pipe = log_flows.build_small()
    with pytest.raises(LogError, match=r"the log /dev/full already exists"):
        pipe.run(duration=0.5, log="/dev/full")
    with pytest.raises(LogWriteError, match=r"cannot write the log /dev/full: No space left on device \(ENOSPC\); "
                                            r"the run did not start\n    hint: log to a disk with room"):
        pipe.run(duration=0.5, log="/dev/full", overwrite=True)
    assert pipe.trace.steps == []


def test_cli_on_a_log_that_takes_no_bytes():
    result = cli("run", QUICKSTART, "--duration", "1", "--log", "/dev/full", "--force")
    assert_cli_error(result, r"^error: cannot write the log /dev/full: No space left on device \(ENOSPC\); "
                             r"the run did not start", hint="log to a disk with room")
    assert "is in /dev/full" not in result.stderr


# ---------------------------------------------------------------------------------------------
# The disk fills up during the run
# ---------------------------------------------------------------------------------------------
def _run_on_a_small_disk(log: Path, size: int, *args: str) -> subprocess.CompletedProcess:
    """``retriever run quickstart --log LOG ARGS`` in a process whose files cannot grow past
    ``size`` bytes (Python ignores SIGXFSZ, so a write past it fails with EFBIG)."""
    def limit() -> None:
        resource.setrlimit(resource.RLIMIT_FSIZE, (size, size))

    result = subprocess.run([str(RETRIEVER), "run", str(QUICKSTART), "--log", str(log), *args], capture_output=True,
                            text=True, env=cli_env(), preexec_fn=limit, timeout=120)
    result.stderr = "".join(line for line in result.stderr.splitlines(keepends=True)
                            if not line.startswith("retriever: Zenoh hub listening"))  # zenoh's endpoint line
    return result


@pytest.mark.parametrize("backend", ["inproc", "zenoh"])
def test_a_disk_that_fills_during_the_run_stops_it(tmp_path: Path, backend):
    """A run of 1e6 s (in-process) or 60 s (real time) whose log stops growing: the run stops
    within a flush interval, with the path and the OS error, and what reached the file is
    salvaged by recover."""
    log = tmp_path / "run.mcap"
    size = FULL_AFTER_BYTES[backend]
    result = _run_on_a_small_disk(log, size, "--backend", backend, "--duration", "1e6" if backend == "inproc" else "60")
    assert_cli_error(result, r"^error: cannot write the log .*run\.mcap: File too large \(EFBIG\); the run was "
                             r"stopped, and the file holds only what was written before",
                     hint=r"log to a disk with room, or to a path that takes files \(`retriever log recover .*run"
                          r"\.mcap` salvages what reached it\)")
    assert "the run up to the error is in" not in result.stderr
    assert log.stat().st_size <= size
    salvaged = recover(log, tmp_path / "saved.mcap")
    assert salvaged.steps > 0 and read_log(salvaged.output).complete
    if backend == "inproc":  # a real-time log cut mid-run may hold a step whose output event was not written yet
        assert replay(read_log(salvaged.output)).identical


def test_a_writer_faster_than_its_disk_waits_for_it_instead_of_queueing_without_bound(tmp_path, monkeypatch):
    """Chunks go to the I/O thread; past MAX_BYTES_QUEUED of them not yet written, adding messages
    waits for the disk. A disk that takes nothing until the test opens it: 40 chunks of 1 MiB, 4 MiB
    allowed in flight; the writer must stop and wait, holding no more than that."""
    import io
    import threading

    from mcap.reader import make_reader

    from retriever.log import mcap_writer

    class ShutDisk(io.BytesIO):
        def __init__(self):
            super().__init__()
            self.open = threading.Event()

        def write(self, data):
            self.open.wait()
            return super().write(data)

    monkeypatch.setattr(mcap_writer, "MAX_BYTES_QUEUED", 4 << 20)
    stream = ShutDisk()
    writer = mcap_writer.McapWriter(stream, profile="retriever")
    channel = writer.add_channel("data/camera/image", "msgpack", {})
    frame, most = bytes(1 << 20), [0]

    def produce():
        for k in range(40):
            writer.add_message(channel, k, k, k, frame)
            writer.flush()
            most[0] = max(most[0], writer.queued_bytes)
    producer = threading.Thread(target=produce)
    producer.start()
    while writer.waits == 0 and producer.is_alive():  # it stops at the bound: nothing is written yet
        producer.join(0.01)
    assert writer.waits == 1 and producer.is_alive() and writer.queued_bytes <= (4 << 20) + (1 << 20) + 1024
    stream.open.set()
    producer.join()
    writer.finish()
    assert most[0] <= (4 << 20) + (1 << 20) + 1024, most
    stream.seek(0)
    assert sum(1 for _ in make_reader(stream).iter_messages()) == 40


# ---------------------------------------------------------------------------------------------
# Channels the graph did not name
# ---------------------------------------------------------------------------------------------
def test_ports_an_untyped_flow_returns_at_run_time_get_channels_in_the_order_their_events_came(tmp_path: Path):
    """An untyped flow's step may return ports no edge reads and the graph did not know: each
    gets its channel when its first event is written (the writer looks channels up by node, then
    port, and adds the missing ones of a batch before it encodes it), and the log reads back as
    the trace."""

    class Camera(Flow):
        def __init__(self):
            self.k = 0

        def step(self):
            self.k += 1
            return {"ok": self.k, **({"late": -self.k} if self.k > 3 else {}), **({"later": 0.5} if self.k > 6 else {})}

    class Policy(Flow):
        def step(self, ok):
            return {"done": ok}

    with Pipeline("late_ports") as pipe:
        (Camera().named("camera") @ Rate(hz=10)).then(Policy().named("policy") @ Rate(hz=10))
    path = tmp_path / "run.mcap"
    trace = pipe.run(duration=2.0, log=path)
    log = read_log(path)
    assert log.trace() == trace
    topics = [channel.topic for channel in sorted(log.channels.values(), key=lambda c: c.id)]
    assert [t for t in topics if "late" in t] == [fmt.data_topic("camera", "late"), fmt.data_topic("camera", "later")]
    assert {e.port for e in trace.events_of("camera")} == {"ok", "late", "later"}


def test_each_event_record_holds_its_microstep_and_value_as_the_codec_writes_them(tmp_path: Path):
    """Arrays take the writer's fast path (a record's struct cached by port and shape, for the
    dtype seen last in it: another dtype of the shape, an equal dtype of another object, take the
    slow one), the first time and after, on each port; a big array a chunk of its own, between the others;
    any value at a microstep past msgpack's fixint the general one: each Message record's data
    is the codec's ``[microstep, value]``, byte for byte, on its port's channel, in the order the
    events came."""
    class Source(Flow[None, Any]):
        def step(self, inp: None) -> Any:
            return 0

    with Pipeline("values") as pipe:
        Source().named("src") @ Rate(hz=10)
    graph = pipe.compile()
    big = np.arange(LARGE_VALUE_BYTES // 8 + 1, dtype=">f8")
    grid = np.arange(24, dtype=np.int16).reshape(4, 6)
    values = [np.eye(3), np.eye(3) * 2, grid[:, ::2], grid.T, np.float32(1.5), np.array(7, dtype=np.uint8),
              np.zeros((0, 3)), big, np.eye(3), 0.25, np.asfortranarray(grid), {"k": [np.ones(2)]},
              np.zeros(5, dtype=[("a", "<i4"), ("b", "S2")]), np.eye(3), np.ones((3, 3), dtype=np.int8), np.eye(3),
              np.ones(5, dtype=[("a", "<i4"), ("b", "S2")]), np.ones(5, dtype=[("a", "<i4"), ("b", "S2")]),
              np.ones(5, dtype=[("a", ">i4"), ("b", "S2")])]
    microsteps = [1] * len(values)
    microsteps[2] = microsteps[9] = 200
    trace = Trace()
    for seq, (value, microstep) in enumerate(zip(values, microsteps)):
        trace.raw_events.append(((seq * 1000, microstep), "src", "out", seq, value, seq))
        if seq % 4 == 0:  # the same arrays on a port the graph does not know, whose channel comes later
            trace.raw_events.append(((seq * 1000, microstep), "src", "more", seq, value, seq))
    path = tmp_path / "values.mcap"
    writer = LogWriter(LogFile(path), graph, backend="inproc")
    writer.write(trace)
    writer.close(trace, len(values) * 1000)
    with open(path, "rb") as f:
        messages = [(channel.topic, message.data)
                    for _, channel, message in make_reader(f).iter_messages(log_time_order=False)]
    assert messages == [(fmt.data_topic(node, port), packb([tag[1], value]))
                        for tag, node, port, _, value, _ in trace.raw_events]
    assert len(messages) == len(values) + len(values[::4])


@io
@dataclass
class _Pair:
    a: float
    b: float


def test_a_generic_ticks_step_record_reads_back_as_msgpack_of_it_whatever_its_shape(tmp_path: Path):
    """The writer makes a generic tick's step record of the common shape (ok, one event out, one
    consumed per input fed by one edge) in two struct.packs with fixed-width ints (a wall time
    past 32 bits too), for nodes of 0, 1 and 2 inputs; any other record it packs with msgpack (one of a node the graph does not
    have too): each reads back as msgpack of the record, in the order they came."""

    class Source(Flow[None, float]):
        def step(self, inp: None) -> float:
            return 1.0

    class Double(Flow[float, float]):
        def step(self, inp: float) -> float:
            return 2 * inp

    class Join(Flow[_Pair, float]):
        def step(self, inp: _Pair) -> float:
            return inp.a + inp.b

    with Pipeline("shapes") as pipe:
        src = Source().named("src") @ Rate(hz=10)
        double = Double().named("double") @ Rate(hz=10)
        join = Join().named("join") @ Rate(hz=10)
        src.then(double, sync=Latest())
        src.then(join, sync=Latest(), map={"float": "a"})
        double.then(join, sync=Latest(), map={"float": "b"})
    graph = pipe.compile()
    ok, u32 = StepStatus.OK, 0xFFFFFFFF
    ids = {"src": ("src", "float", 3), "double": ("double", "float", 4)}
    common = [("src", (1000, 0), {}, (ids["src"],), ok, None, 5, 70),
              ("double", (1000, 1), {"float": (ids["src"],)}, (ids["double"],), ok, None, 6, 80),
              ("join", (1000, 2), {"a": (ids["src"],), "b": (ids["double"],)}, (("join", "float", 2),), ok, None, 7,
               90),
              ("double", (1000, 1), {"float": (ids["src"],)}, (ids["double"],), ok, None, 6, u32),
              ("double", (1000, 1), {"float": (ids["src"],)}, (ids["double"],), ok, None, 6, u32 + 1)]  # 4.3 s
    other = [("double", (2000, 0), {}, (), StepStatus.SKIPPED, {"missing": ["float"]}, 0, 0),
             ("double", (2000, 200), {"float": (ids["src"],)}, (ids["double"],), ok, None, 6, 80),
             ("double", (2000, 1), {"float": (ids["src"],)}, (ids["double"],), ok, {"dropped": {"float": 1}}, 6, 80),
             ("double", (2000, 1), {"float": (ids["src"], ids["src"])}, (ids["double"],), ok, None, 6, 80),
             ("double", (2000, 1), {"float": (("src", "float", u32 + 1),)}, (ids["double"],), ok, None, 6, 80),
             ("double", (2000, 1), {"float": (ids["src"],)}, (ids["double"],), ok, None, 6, -1),
             ("double", (2000, 1), {"float": (ids["src"],)}, (), ok, None, 6, 80),
             ("double", (2000, 1), {"float": (("join", "float", 1),)}, (ids["double"],), ok, None, 6, 80),
             ("double", (2000, 1), {"other": (ids["src"],)}, (ids["double"],), ok, None, 6, 80),
             ("join", (2000, 2), {"b": (ids["double"],), "a": (ids["src"],)}, (("join", "float", 2),), ok, None, 7, 90),
             ("join", (2000, 2), {"a": (ids["src"],)}, (("join", "float", 2),), ok, None, 7, 90),
             ("src", (2000, 0), {}, (ids["src"],), StepStatus.ERROR, {"error": "ValueError: x"}, 5, 70),
             ("src", (2000, 0), {}, (ids["src"],), "ok", None, 5, 70),
             ("ghost", (2000, 3), {}, (("ghost", "float", 1),), ok, None, 8, 95)]  # no node of the graph
    trace = Trace()
    trace.raw_steps.extend([*common, *other])
    path = tmp_path / "shapes.mcap"
    writer = LogWriter(LogFile(path), graph, backend="inproc")
    writer.write(trace)
    writer.close(trace, 3000)
    with open(path, "rb") as f:
        datas = [message.data for _, channel, message in make_reader(f).iter_messages(log_time_order=False)
                 if channel.topic == fmt.STEPS_TOPIC]

    def unpack(data: bytes):
        return msgpack.unpackb(data, strict_map_key=False)

    expected = [unpack(msgpack.packb((node, tag[1], consumed, produced, status, detail, wall)))
                for node, tag, consumed, produced, status, detail, _, wall in [*common, *other]]
    assert [unpack(data) for data in datas] == expected
    # the common ones in fixed widths (their wall time a uint64), the others as msgpack packs them
    assert [data[-9] for data in datas[:len(common)]] == [0xCF] * len(common)
    assert not {packed for packed, (node, tag, consumed, produced, status, detail, _, wall) in zip(datas, common)
                if packed == msgpack.packb((node, tag[1], consumed, produced, status, detail, wall))}
    assert datas[len(common):] == [msgpack.packb((node, tag[1], consumed, produced, status, detail, wall))
                                   for node, tag, consumed, produced, status, detail, _, wall in other]


def test_a_records_sequence_is_the_low_32_bits_of_its_index_or_seq(tmp_path: Path):
    """A step record's sequence is its index in the log, an event's its seq, each as a uint32: the
    low 32 bits of one past them (or below 0), on every path that makes the record (a float's, a
    new array's, a cached array's); the data as the codec writes it."""
    u32 = 0xFFFFFFFF
    for first, count in ((0, 5), (5, 3), (u32 - 1, 4), (u32 + 1, 3), (2**33 + 3, 2), (2**40 - 2, 6)):
        assert list(sequences(first, count)) == [(first + i) & u32 for i in range(count)]
    class Source(Flow[None, float]):
        def step(self, inp: None) -> float:
            return 1.5

    class Ones(Flow[float, np.ndarray]):
        def step(self, inp: float) -> np.ndarray:
            return np.ones(2) * inp

    with Pipeline("wide") as pipe:
        src = Source().named("src") @ Rate(hz=10)
        src.then(Ones().named("double") @ Rate(hz=10), sync=Latest())
    graph = pipe.compile()
    (port,) = graph.nodes["src"].outputs
    (double_port,) = graph.nodes["double"].outputs
    seqs = [3, u32, u32 + 1, 2**32 + 5, 2**40 + 7, -1, 4]
    events = [((1000 * i, 0), "src", port, seq, 1.5, 7 + i) for i, seq in enumerate(seqs)]
    events += [((1000 * i, 1), "double", double_port, seq, np.ones(2) * i, 20 + i) for i, seq in enumerate(seqs)]
    for made_with in ("all", "each"):  # one batch, or a batch an event (the array cached from the first)
        trace = Trace()
        path = tmp_path / f"wide-{made_with}.mcap"
        writer = LogWriter(LogFile(path), graph, backend="inproc")
        for event in events if made_with == "each" else [None]:
            trace.raw_events.extend([event] if event else events)
            writer.write(trace)
        writer.close(trace, 10_000)
        with open(path, "rb") as f:
            messages = [(channel.topic, message.sequence, message.log_time, message.publish_time, message.data)
                        for _, channel, message in make_reader(f).iter_messages(log_time_order=False)
                        if channel.topic != fmt.STEPS_TOPIC]
        assert messages == [(fmt.data_topic(node, p), seq & u32, tag[0], published, packb([tag[1], value]))
                            for tag, node, p, seq, value, published in events]


class _Values(Flow[None, Any]):
    """Each tick the next of ``VALUES``: ints in every msgpack form, floats, others."""

    VALUES = [0, 127, 128, 255, 256, 65535, 65536, 2**32 - 1, 2**32, -1, -200, 1.5, float("nan"), True, "s",
              np.float64(2.5), [1, 2.0]]

    def __init__(self):
        self.k = -1

    def step(self, inp: None) -> Any:
        self.k += 1
        return self.VALUES[self.k % len(self.VALUES)]


class _Relay(Flow[Any, Any]):
    def step(self, inp: Any) -> Any:
        return inp


def test_the_records_compiled_ticks_make_are_the_writers_byte_for_byte(tmp_path: Path):
    """A logged run whose compiled ticks make the records of their steps and of their float and
    int events as the tape is expanded (Trace.log_records), the writer the others (other values,
    none made): the log holds the records the writer makes of the trace, in the order the events
    came, byte for byte (each event's data the codec's ``[microstep, value]``), reads back as the
    trace, and replays identically."""
    def build():
        with Pipeline("made_records") as pipe:
            prev = _Values().named("src") @ Rate(hz=1000)
            for i in range(3):
                prev = prev.then(_Relay().named(f"r{i}") @ (Trigger() if i == 1 else Rate(hz=1000)), sync=Latest())
        return pipe

    pipe = build()
    path = tmp_path / "made.mcap"
    trace = pipe.run(duration=0.5, log=path)
    assert len(pipe.session.generated_ticks()) == 4
    with open(path, "rb") as f:
        messages = [(channel.topic, message.sequence, message.log_time, message.publish_time, message.data)
                    for _, channel, message in make_reader(f).iter_messages(log_time_order=False)]
    events = [(fmt.data_topic(node, port), seq, tag[0], published, packb([tag[1], value]))
              for tag, node, port, seq, value, published in trace.raw_events]
    assert [m for m in messages if m[0] != fmt.STEPS_TOPIC] == events
    steps = [m for m in messages if m[0] == fmt.STEPS_TOPIC]
    assert [(sequence, log_time, publish) for _, sequence, log_time, publish, _ in steps] == [
        (index, tag[0], start) for index, (_, tag, *_, start, _) in enumerate(trace.raw_steps)]
    log = read_log(path)
    assert log.trace() == trace
    assert replay(log, build()).identical


class _ArraySource(Flow[None, Any]):
    """Each tick the next of ``values()``: arrays of a few dtypes and shapes (float64 in several
    shapes, a structured dtype's equal copy of another object, a big one), ints in every msgpack form, other values, Bursts."""

    def __init__(self):
        self.k = -1

    @staticmethod
    def values(k: int) -> list:
        record = np.dtype([("a", "<i4"), ("b", "S2")])  # a new dtype object, equal to the last
        return [np.full((8, 8), k % 256, dtype=np.uint8), np.linspace(0.0, k, 4), np.full(k % 3 + 2, float(k)),
                np.zeros(3, dtype=record),
                np.arange(6, dtype=">i2").reshape(2, 3), *_Values.VALUES, 2**64 - 1, -2**63, None, b"b",
                Burst([np.ones(2) * k, np.zeros(2)]), Burst(np.eye(3)), Burst([1, 2.5, "x"]), np.float32(k),
                *([np.zeros(LARGE_VALUE_BYTES // 8 + 1)] if k == 40 else [])]

    def step(self, inp: None) -> Any:
        self.k += 1
        values = self.values(self.k // 9)
        return values[self.k % len(values)]


class _ArrayRelay(Flow[Any, Any]):
    def step(self, inp: Any) -> Any:
        return inp


@io
@dataclass
class _Halves:
    left: Any
    right: Any = None


class _TwoArrays(Flow[Any, _Halves]):
    """Two outputs: a node with no step-record maker; its arrays' records are made all the same."""

    def __init__(self):
        self.k = 0

    def step(self, inp: Any) -> _Halves:
        self.k += 1
        return _Halves(left=np.ones(2) * self.k, right=inp if self.k % 3 else None)


class _Either(Flow[_Halves, Any]):
    """An array each tick, of one dtype and shape: ticked at microsteps below 128 and past it."""

    def step(self, inp: _Halves) -> Any:
        return np.ones(2) * (inp.left is None)


def _logged_and_rewritten(pipe: Pipeline, path: Path, duration: float, **options: Any) -> tuple[dict, dict]:
    """Run ``pipe`` logged to ``path``; write its trace again with a writer of its own, which makes
    every record itself from the trace's plain records: each log's messages by channel (``(channel,
    sequence, log time, publish time, data)``, in the order they are in the file)."""
    pipe.reset()
    pipe.step(0.0, **options)
    trace = pipe.session.trace
    pipe.run(duration, log=path)
    again = Trace()
    again.raw_events.extend(trace.raw_events)
    again.raw_steps.extend(trace.raw_steps)
    writer = LogWriter(LogFile(path.with_suffix(".again.mcap")), pipe.compile(), backend="inproc")
    writer.write(again)
    writer.close(again, 0)

    def by_channel(log: Path) -> dict:
        found: dict = {}
        with open(log, "rb") as f:
            for _, channel, message in make_reader(f).iter_messages(log_time_order=False):
                found.setdefault(channel.topic, []).append(
                    (message.channel_id, message.sequence, message.log_time, message.publish_time, message.data))
        return found
    return by_channel(path), by_channel(path.with_suffix(".again.mcap"))


def test_a_logged_run_holds_the_records_the_writer_makes_of_its_trace_byte_for_byte(tmp_path: Path):
    """Whoever makes a record (the writer, from the trace's records, split from the tape by a
    Python loop or, a tape of plain records only, in C; a compiled tick's expander), every message
    of a run's log is byte for byte the one a writer makes by itself of the run's trace, on each
    channel, in order. The quickstart, whose tape holds plain records only; arrays of several
    dtypes and shapes, an equal dtype of another object, a big array, Bursts, ints of every msgpack
    width and other values, a node of two outputs, one ticked at microsteps below 128 and past it
    (a chain of 140 Trigger flows); the mixed graph's skips, errors and fan-ins, all generic, and
    with its compiled ticks, whose compact records the tape then holds too. Each event's data is
    also the codec's ``[microstep, value]`` of the trace's event."""
    def quickstart():
        return runpy.run_path(str(QUICKSTART), run_name="quickstart")["pipe"]

    def arrays():
        with Pipeline("arrays") as pipe:
            src = _ArraySource().named("src") @ Rate(hz=200)
            two = _TwoArrays().named("two") @ Rate(hz=200)
            src.then(two, sync=Latest())
            prev = two.then(_ArrayRelay().named("t000") @ Trigger(), sync=Latest(), map={"left": "any"})
            for i in range(1, 140):
                prev = prev.then(_ArrayRelay().named(f"t{i:03}") @ Trigger(), sync=Latest())
            either = _Either().named("either") @ Trigger()
            prev.then(either, sync=Latest(), map={"any": "left"})
            src.then(either, sync=Latest(), map={"any": "right"})
        return pipe

    for build, duration, options in ((quickstart, 20.0, {}), (arrays, 1.0, {"generate_ticks": False}),
                                     (mixed, 1.0, {"generate_ticks": False}), (mixed, 1.0, {})):
        path = tmp_path / f"{build.__name__}{len(options)}.mcap"
        pipe = build()
        logged, again = _logged_and_rewritten(pipe, path, duration, **options)
        assert logged.keys() == again.keys()
        for topic in logged:
            assert logged[topic] == again[topic], topic
        trace = pipe.session.trace
        # and each event's record is the codec's [microstep, value], whatever cached struct made it
        # (a port's arrays of one dtype in several shapes, the one last made found first)
        expected: dict = {}
        for tag, node, port, seq, value, published in trace.raw_events:
            expected.setdefault(fmt.data_topic(node, port), []).append((seq, tag[0], published,
                                                                        packb([tag[1], value])))
        assert {topic: [message[1:] for message in messages] for topic, messages in logged.items()
                if topic != fmt.STEPS_TOPIC} == expected
        # compact records in the tape (the compiled mixed graph's) or none (the quickstart's
        # camera, though compiled, emits arrays, which its tick records as a generic one does)
        assert bool(pipe.session.generated_ticks()) == (build is quickstart or not options)
        if build is arrays:
            assert {tag[1] >= 128 for tag, node, *_ in trace.raw_events if node == "either"} == {True, False}
        if build is quickstart:
            log = read_log(path)
            assert log.trace() == trace
            assert replay(log, build()).identical
