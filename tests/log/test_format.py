"""The MCAP event log's format: a golden small log read with plain ``mcap``, exact value round
trips through a real log, and the logged trace equal to the live one."""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
import subprocess
import sys
import warnings
from itertools import count
from pathlib import Path

import msgpack
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from retriever import LogError, RetrieverWarning, RunEnd, read_log
from retriever.loading import load_pipeline
from retriever.codec import Encoder, packb
from retriever.replay import replay, resim
from retriever.log.format import decode_step
from tests.log import log_flows
from tests.test_codec import assert_same
from tests.log.helpers import CHUNK, GOLDEN, QUICKSTART, ROOT, cli, records
from tests.log.plain_mcap import decoded_records, digest, read_plain, unpack

GOLDEN_LOG = GOLDEN / "small_log.json"
SMALL_TOPICS = {"data/counter/k", "data/counter/level", "data/counter/pose", "data/accumulate/total",
                "data/accumulate/window", "data/tally/count", "steps"}


@pytest.fixture(scope="module")
def small(tmp_path_factory):
    """The golden pipeline run 0.5 s with ``log=``: ``(path, live trace)``."""
    path = tmp_path_factory.mktemp("small") / "small.mcap"
    trace = log_flows.build_small().run(duration=0.5, log=path)
    return path, trace


@pytest.fixture(scope="module")
def small_plain(small):
    return read_plain(small[0])


# ---------------------------------------------------------------------------------------------
# The golden small log, read with mcap + msgpack only
# ---------------------------------------------------------------------------------------------
def test_a_logged_trace_has_read_only_values_as_the_run_had(small):
    """An emitted value is immutable (docs/semantics.md): a run's trace holds its arrays
    read-only, and so does the trace read back from its log (it held them writable)."""
    path, trace = small
    logged = read_log(path).trace()
    assert logged == trace

    def arrays(value):
        if isinstance(value, np.ndarray):
            yield value
        elif isinstance(value, dict):
            for item in value.values():
                yield from arrays(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                yield from arrays(item)

    for run in (trace, logged):
        found = [a for e in run.events for a in arrays(e.value)]
        assert found and not any(a.flags.writeable for a in found)


def test_small_log_is_a_valid_mcap_file_with_the_retriever_profile(small_plain):
    """Header profile, CRCs (chunks, data section, summary), one channel per port plus steps."""
    assert small_plain["profile"] == "retriever"
    assert small_plain["library"].startswith("retriever ")
    assert small_plain["summary_crc_ok"], "the footer's summary CRC does not match the summary section"
    channels = small_plain["channels"]
    assert {c.topic for c in channels.values()} == SMALL_TOPICS
    assert len(channels) == len(SMALL_TOPICS), "one channel per topic"
    for c in channels.values():
        assert c.message_encoding == "msgpack"
        assert c.schema_id == 0
        if c.topic != "steps":
            _, node, port = c.topic.split("/")
            assert (c.metadata["node"], c.metadata["port"]) == (node, port)
    types = {c.topic: c.metadata.get("type") for c in channels.values()}
    assert types["data/counter/pose"] == "Labelled"
    assert types["data/counter/k"] == "int"
    assert types["data/tally/count"] == ""  # an untyped port


def test_message_counts_and_statistics(small, small_plain):
    """5 readings (×3 ports), 3 summaries (×2 ports), 2 tallies, one step record per tick; the
    summary's statistics agree with what the data section holds."""
    _, trace = small
    by_topic: dict[str, int] = {}
    for topic, _ in small_plain["messages"]:
        by_topic[topic] = by_topic.get(topic, 0) + 1
    assert by_topic == {"data/counter/k": 5, "data/counter/level": 5, "data/counter/pose": 5,
                        "data/accumulate/total": 3, "data/accumulate/window": 3, "data/tally/count": 1,
                        "steps": 11}
    assert sum(by_topic.values()) - by_topic["steps"] == len(trace.events)
    assert by_topic["steps"] == len(trace.steps)
    stats = small_plain["statistics"]
    ids = {c.topic: c.id for c in small_plain["channels"].values()}
    assert stats.message_count == sum(by_topic.values())
    assert stats.channel_message_counts == {ids[t]: n for t, n in by_topic.items()}
    assert stats.channel_count == len(SMALL_TOPICS)
    assert (stats.attachment_count, stats.metadata_count) == (1, 2)
    assert stats.message_start_time == 0
    assert stats.message_end_time == max(m.log_time for _, m in small_plain["messages"])


def test_events_log_time_is_tag_time_sequence_is_seq_data_is_microstep_value(small, small_plain):
    """Each event message, in trace order: log_time = tag time, sequence = seq, publish_time =
    the wall clock it was published at, data = msgpack ``[microstep, value]`` with the value in
    the codec's encoding."""
    _, trace = small
    events = [(topic, m) for topic, m in small_plain["messages"] if topic != "steps"]
    assert len(events) == len(trace.events)
    for (topic, m), e in zip(events, trace.events):
        assert topic == f"data/{e.node}/{e.port}"
        assert (m.log_time, m.sequence, m.publish_time) == (e.tag[0], e.seq, e.publish_ns)
        assert m.data == b"\x92" + msgpack.packb(e.tag[1]) + packb(e.value), (e, m.data)
        microstep, _ = unpack(m.data)
        assert microstep == e.tag[1]


def test_step_records(small, small_plain):
    """Each step message: log_time = tick time, sequence = step index, publish_time = wall start,
    data = ``[node, microstep, consumed, produced, status, detail, wall_ns]``."""
    _, trace = small
    steps = [m for topic, m in small_plain["messages"] if topic == "steps"]
    assert [m.sequence for m in steps] == list(range(len(trace.steps)))
    for m, s in zip(steps, trace.steps):
        assert (m.log_time, m.publish_time) == (s.tag[0], s.wall_start_ns)
        node, microstep, consumed, produced, status, detail, wall_ns = unpack(m.data)
        assert (node, microstep, status, detail, wall_ns) == (s.node, s.tag[1], s.status, s.detail, s.wall_ns)
        assert consumed == {port: [list(i) for i in ids] for port, ids in s.consumed.items()}
        assert produced == [list(i) for i in s.produced]
    tally = [unpack(m.data) for m in steps if unpack(m.data)[0] == "tally"]
    assert [t[2] for t in tally] == [{"total": [["accumulate", "total", 0]]}, {"total": [["accumulate", "total", 1]]},
                                     {"total": [["accumulate", "total", 2]]}]


def test_ir_attachment_and_run_metadata(small, small_plain):
    """The IR attachment is the pipeline's IR JSON; retriever.run comes first, retriever.end last."""
    _, trace = small
    attachment = small_plain["attachments"]["pipeline.ir.json"]
    assert attachment.media_type == "application/json"
    ir = json.loads(bytes(attachment.data))
    assert [n["id"] for n in ir["nodes"]] == ["counter", "accumulate", "tally"]
    assert [n["type"] for n in ir["nodes"]] == ["tests.log.log_flows:Counter", "tests.log.log_flows:Accumulate",
                                                "tests.log.log_flows:Tally"]
    assert ir == json.loads(log_flows.build_small().build_ir().to_json())
    flows_file = Path(log_flows.__file__).read_bytes()
    assert ir["metadata"]["code_sha256"] == {"tests.log.log_flows": hashlib.sha256(flows_file).hexdigest()}

    names = [name for name, _ in small_plain["metadata"]]
    assert names == ["retriever.run", "retriever.end"]
    run, end = (data for _, data in small_plain["metadata"])
    assert (run["format"], run["pipeline"], run["backend"], run["seeds"]) == ("1", "small_log", "inproc", "{}")
    assert {"mcap", "msgpack", "numpy", "retriever"} <= set(json.loads(run["packages"]))
    assert str(ROOT) in json.loads(run["python_path"])  # where tests.log.log_flows was imported from
    assert int(run["pid"]) == os.getpid()
    assert isinstance(json.loads(run["command_line"]), list)
    assert int(run["started_unix_ns"]) <= int(end["finished_unix_ns"])
    assert (end["status"], end["end_ns"]) == ("finished", "500000000")
    assert (int(end["events"]), int(end["steps"])) == (len(trace.events), len(trace.steps))
    stats = json.loads(end["stats"])
    assert {n: (s["ticks"], s["steps"], s["skips"], s["errors"]) for n, s in stats.items()} == {
        "counter": (5, 5, 0, 0), "accumulate": (3, 3, 0, 0), "tally": (3, 3, 0, 0)}


def test_a_run_end_is_its_value_in_the_end_record():
    """RunEnd's values are the end record's ``status`` as logs hold it: the logs written before
    read the same, and a status read back compares equal to its member."""
    assert [str(s) for s in RunEnd] == ["finished", "interrupted", "error"]
    assert all(s == s.value and type(s.value) is str for s in RunEnd)


def test_small_log_matches_golden_file(small_plain):
    """Every deterministic field of every record, and a digest of them, against the golden file
    (regenerate with RETRIEVER_UPDATE_GOLDEN=1 and review the diff)."""
    found = decoded_records(small_plain)
    doc = {"digest": digest(found), "records": found}
    if os.environ.get("RETRIEVER_UPDATE_GOLDEN") == "1":
        GOLDEN_LOG.write_text(json.dumps(doc, indent=1, sort_keys=True) + "\n", encoding="utf-8")
    assert GOLDEN_LOG.exists(), f"{GOLDEN_LOG} is missing; run with RETRIEVER_UPDATE_GOLDEN=1 to create it"
    golden = json.loads(GOLDEN_LOG.read_text(encoding="utf-8"))
    assert golden["digest"] == digest(golden["records"]), "the golden file was edited by hand"
    for key in golden["records"]:
        assert found[key] == golden["records"][key], (
            f"{key} of the log changed; if on purpose, regenerate with RETRIEVER_UPDATE_GOLDEN=1 and review the diff")
    assert doc["digest"] == golden["digest"]


def test_a_second_run_writes_the_same_records(small_plain, tmp_path):
    """Two runs of the same pipeline differ only in wall-clock fields."""
    path = tmp_path / "again.mcap"
    log_flows.build_small().run(duration=0.5, log=path)
    assert decoded_records(read_plain(path)) == decoded_records(small_plain)


def test_readable_without_retriever(small):
    """The reading side needs only mcap and msgpack: it works where importing retriever fails."""
    code = ("import sys; sys.modules['retriever'] = None\n"
            "from tests.log.plain_mcap import read_plain, decoded_records, digest\n"
            f"print(digest(decoded_records(read_plain({str(small[0])!r}))))\n"
            "assert not any(m == 'retriever' or m.startswith('retriever.') for m in sys.modules if sys.modules[m])\n")
    done = subprocess.run([sys.executable, "-c", code], check=False, capture_output=True, text=True, cwd=ROOT, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == json.loads(GOLDEN_LOG.read_text(encoding="utf-8"))["digest"]


def test_end_record_is_written_after_every_message(small):
    """format.py: ``retriever.end`` is written last, so a file torn before its end holds none.
    The writer adds it in close() while the last chunk is still open, and finish() writes that
    chunk after it."""
    data = small[0].read_bytes()
    layout = records(data)
    end_offset = max(offset for opcode, offset, _ in layout if opcode == 0x0C)  # the last metadata record
    last_chunk = max(offset for opcode, offset, _ in layout if opcode == CHUNK)
    assert end_offset > last_chunk


# ---------------------------------------------------------------------------------------------
# Values round-trip exactly through a real log
# ---------------------------------------------------------------------------------------------
DTYPES = ["bool", "int8", "uint8", ">i2", "int32", "uint32", "int64", "uint64", "float16", "float32", ">f8",
          "float64", "complex128", "<U3", "S2", "datetime64[ms]"]
big_ints = st.integers(min_value=-(2**150), max_value=2**150)
ints = st.integers() | big_ints | st.sampled_from([2**63 - 1, 2**63, 2**64 - 1, 2**64, -(2**63), -(2**63) - 1])
floats = st.floats() | st.sampled_from([-0.0, math.nan, -math.nan, math.inf, -math.inf, 5e-324,
                                        struct.unpack("<d", struct.pack("<Q", 0x7FF8_0000_0000_0001))[0]])


@st.composite
def arrays(draw):
    dtype = np.dtype(draw(st.sampled_from(DTYPES)))
    arr = draw(hnp.arrays(dtype, hnp.array_shapes(min_dims=0, max_dims=3, min_side=0, max_side=3)))
    return arr.T if draw(st.booleans()) else arr  # transposed: not C-contiguous


leaves = (st.none() | st.booleans() | ints | floats | st.text(max_size=6) | st.binary(max_size=6) | arrays()
          | st.sampled_from([np.float32(-0.0), np.int64(-(2**63)), np.uint64(2**64 - 1), np.bool_(True)]))
keys = st.text(max_size=4) | st.integers(min_value=-(2**63), max_value=2**64 - 1) | st.binary(max_size=3)


def nested_io(children):
    points = st.builds(log_flows.Point, floats, floats, st.lists(children, max_size=2).map(tuple))
    return st.builds(log_flows.Labelled, st.text(max_size=4), points, st.dictionaries(keys, children, max_size=2))


values = st.recursive(leaves, lambda children: (st.lists(children, max_size=3)
                                                | st.lists(children, max_size=3).map(tuple)
                                                | st.dictionaries(keys, children, max_size=3)
                                                | nested_io(children)), max_leaves=12)
top_level = values.filter(lambda v: v is not None)  # None on an untyped port is "no event"
_file_number = count()


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(top_level, min_size=1, max_size=3))
def test_values_round_trip_exactly_through_a_log(tmp_path_factory, emitted):
    """Whatever a source emits comes back from the file equal bit for bit, with the bytes the
    writer's encoder gives and, once decoded, the codec's canonical bytes; resim agrees."""
    path = tmp_path_factory.getbasetemp() / f"roundtrip-{next(_file_number)}.mcap"
    trace = log_flows.build_emit(emitted).run(duration=len(emitted) / 10, log=path)
    assert len(trace.events) == len(emitted)
    log = read_log(path)
    events = list(log.iter_events())
    assert [(e.node, e.port, e.seq, e.tag) for e in events] == [("emit", "value", k, (k * 100_000_000, 1))
                                                               for k in range(len(emitted))]
    encode = Encoder().pack
    for value, event in zip(emitted, events):
        back = log.value(event)
        assert_same(value, back)
        assert event.raw_value == encode(value)
        assert packb(back) == packb(value)
    assert log.trace() == trace
    assert resim(log).identical
    path.unlink()


def test_special_values_round_trip(tmp_path):
    """The corner cases named in the codec's promise, each through a real log."""
    nan_with_payload = struct.unpack("<d", struct.pack("<Q", 0x7FF8_0000_0000_0001))[0]
    emitted = [
        -0.0, math.nan, nan_with_payload, -math.inf, 2**200, -(2**64) - 1,
        np.zeros((0, 3), dtype=">i4"), np.array(7, dtype=np.uint16), np.zeros((2, 0)),
        {b"k": [1, (2, 3)], 2**70: {"deep": [None, True]}},
        log_flows.Labelled("l", log_flows.Point(-0.0, math.inf, (np.arange(3), 2**65)), {1: b"\x00"}),
        [log_flows.Reading(k=1, level=0.5, pose=log_flows.Labelled("p", log_flows.Point(1.0, 2.0)))],
    ]
    path = tmp_path / "special.mcap"
    log_flows.build_emit(emitted).run(duration=len(emitted) / 10, log=path)
    log = read_log(path)
    events = list(log.iter_events())
    assert len(events) == len(emitted)
    for value, event in zip(emitted, events):
        assert_same(value, log.value(event))


@pytest.mark.parametrize("value", [np.array(1.5), np.zeros(7, dtype=np.uint8), np.array(-1, dtype=np.int64)],
                         ids=["0-d float64", "uint8[7]", "0-d int64"])
def test_logged_bytes_are_the_codec_encoding(tmp_path, value):
    """format.py: an event's value is msgpack 'in retriever.codec'; for arrays whose payload is
    16 bytes the log holds ``c7 10 01 …`` while ``codec.packb`` gives ``d8 01 …``."""
    path = tmp_path / "array.mcap"
    log_flows.build_emit([value]).run(duration=0.1, log=path)
    (event,) = read_log(path).iter_events()
    assert event.raw_value == packb(value)


def test_replay_of_deep_microsteps_with_arrays_is_identical(tmp_path):
    """At microstep >= 128 the writer packs ``[microstep, value]`` with msgpack's own packer
    (fixext16 for a 0-d float64 array), while replay re-encodes the value with ``Encoder.pack``
    (ext8): the same array compares unequal ("logged: array(24.)  replayed: array(24.)")."""
    path = tmp_path / "deep.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        trace = log_flows.build_deep(hops=150).run(duration=1, log=path)
    assert max(e.tag[1] for e in trace.events) > 128
    log = read_log(path)
    assert log.trace() == trace
    report = replay(log)
    assert report.identical, "\n".join(map(str, report.divergences[:1]))


def test_deep_microsteps_below_128_replay_identically(tmp_path):
    """The same graph kept under microstep 128 replays identically (the control for the test above)."""
    path = tmp_path / "shallow.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        trace = log_flows.build_deep(hops=100).run(duration=1, log=path)
    assert 100 <= max(e.tag[1] for e in trace.events) < 128
    log = read_log(path)
    assert log.trace() == trace
    assert replay(log).identical
    assert resim(log).identical


def test_event_at_microstep_beyond_127_is_read_back(tmp_path):
    """Microsteps >= 128 take the writer's general ``[microstep, value]`` path; the reader splits it."""
    path = tmp_path / "deep.mcap"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RetrieverWarning)
        trace = log_flows.build_deep(hops=300).run(duration=1, log=path)
    log = read_log(path)
    deepest = max(log.iter_events(), key=lambda e: e.tag[1])
    assert deepest.tag[1] == max(e.tag[1] for e in trace.events) > 255  # a uint16 microstep
    assert log.trace() == trace


# ---------------------------------------------------------------------------------------------
# The logged trace is the live trace
# ---------------------------------------------------------------------------------------------
def _assert_log_is_the_run(path: Path, live) -> None:
    log = read_log(path)
    assert log.complete and log.damage is None
    logged = log.trace()
    assert logged.first_difference(live) is None
    assert logged == live
    assert logged.digest() == live.digest()
    assert replay(log).identical
    assert resim(log).identical


def test_quickstart_log_trace_equals_live_trace(tmp_path):
    pipe = load_pipeline(str(QUICKSTART))
    pipe.reset()
    live = pipe.run(duration=3.0, log=tmp_path / "quickstart.mcap")
    assert len(live.events) > 500
    _assert_log_is_the_run(tmp_path / "quickstart.mcap", live)
    pipe.reset()
    assert pipe.run(duration=3.0).digest() == live.digest(), "logging changed the run"


@pytest.mark.filterwarnings("ignore::retriever.RetrieverWarning")  # the ping ⇄ pong cycle is instantaneous on purpose
def test_delay_latency_trigger_and_cycles_log_trace_equals_live_trace(tmp_path):
    """Edge delay, LET latency (events tagged at a later time, microstep 0), Trigger clocks, a
    cycle broken by the delay and an instantaneous cycle running several microsteps."""
    live = log_flows.build_timing().run(duration=3.0, log=tmp_path / "timing.mcap")
    tags = {(e.node, e.tag[1]) for e in live.events}
    assert ("mixer", 0) in tags  # latency: published at (t + 0.05 s, 0)
    assert max(m for node, m in tags if node in ("ping", "pong")) >= 4
    assert any(s.node == "mixer" and "feedback" in s.consumed for s in live.steps)
    _assert_log_is_the_run(tmp_path / "timing.mcap", live)
    log = read_log(tmp_path / "timing.mcap")
    mixer = [e for e in log.iter_events() if e.node == "mixer"]
    assert all(e.tag[0] % 50_000_000 == 0 and e.tag[1] == 0 for e in mixer)


def test_log_of_the_ir_flows_pipeline_replays(tmp_path):
    """The IR tests' small pipeline (Window, ActionChunking, Queue, delay, latency, Trigger)."""
    from tests import ir_flows

    live = ir_flows.build().run(duration=2.0, log=tmp_path / "ir.mcap")
    _assert_log_is_the_run(tmp_path / "ir.mcap", live)


@pytest.mark.parametrize("pythonpath", [ROOT, None])
def test_log_cat_prints_decoded_events_in_tag_order_without_importing_anything(small, pythonpath):
    """``retriever log cat`` shows @io values by their type's path and fields: it imports and calls
    nothing a log names, whether the value's module could be imported or not."""
    result = cli("log", "cat", small[0], "--node", "counter", "--port", "pose", "--limit", "2", pythonpath=pythonpath)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len(lines) == 2
    pose = "<tests.log.log_flows:Labelled>(label='p{}', point=<tests.log.log_flows:Point>(x="
    assert lines[0].startswith("t=0.000000000s m=1  counter.pose #0  " + pose.format(1)), lines[0]
    assert lines[1].startswith("t=0.100000000s m=1  counter.pose #1  " + pose.format(2)), lines[1]


def test_log_info_on_the_small_log(small):
    result = cli("log", "info", small[0])
    assert result.returncode == 0, result.stderr
    assert "complete" in result.stdout and "small_log" in result.stdout and "finished" in result.stdout
    assert "data/counter/pose" in result.stdout


def test_log_to_a_missing_folder_is_a_log_error(tmp_path):
    """log= on a folder that does not exist is a LogError at the start, not a traceback at the end."""
    with pytest.raises(LogError, match=r"cannot create the log .*missing.*: No such file or directory \(ENOENT\)\n    hint: pass --log / log= a path"):
        log_flows.build_small().run(duration=0.1, log=tmp_path / "missing" / "x.mcap")


@pytest.mark.parametrize("had_below", [
    [["prod", "value", 7]],
    {"x": [["prod", "value", -1]]},
    {"x": [["prod", 7, 7]]},
    {"x": ["prod", "value", 7]},
])
def test_a_malformed_had_below_in_a_step_record_is_refused(had_below):
    """What an incomplete tick had (replay withholds later events by it): from a hostile log, checked."""
    record = msgpack.packb(["probe", 0, {}, [], "incomplete", {"incomplete": ["x"], "had_below": had_below}, 0])
    with pytest.raises(ValueError, match="what its incomplete inputs had|its event ids"):
        decode_step(record)


def _decode_step_read_as_lists(data: bytes) -> tuple:
    """What decode_step did before it read records without detail as tuples (the reference)."""
    from retriever.log.format import event_ids
    from retriever.trace import STEP_STATUSES

    node, microstep, consumed, produced, status, detail, wall_ns = msgpack.unpackb(data, raw=False)
    if (type(node) is not str or type(microstep) is not int or microstep < 0 or type(consumed) is not dict
            or not all(type(p) is str for p in consumed) or status not in STEP_STATUSES or type(wall_ns) is not int
            or not (detail is None or (type(detail) is dict and all(type(k) is str for k in detail)))
            or (detail is None and status in ("late", "error"))):
        raise ValueError("it is not [node, microstep, consumed, produced, status, detail, wall_ns] of a step")
    if consumed:
        consumed = {port: event_ids(ids) for port, ids in consumed.items()}
    return node, microstep, consumed, event_ids(produced), status, detail, wall_ns


_ID = ["prod", "value", 7]


@pytest.mark.parametrize("record", [
    ["c", 0, {}, [], "ok", None, 5], ["c", 3, {"x": [_ID], "y": [_ID, ["p", "q", 0]]}, [_ID], "ok", None, 5],
    ["c", 0, {}, [], "skipped", None, 5], ["c", 0, {}, [], "late", None, 5], ["c", 0, {}, [], "error", None, 5],
    ["c", 0, {}, [], "exploded", None, 5], [7, 0, {}, [], "ok", None, 5], ["c", -1, {}, [], "ok", None, 5],
    ["c", 1.5, {}, [], "ok", None, 5], ["c", 0, [], [], "ok", None, 5], ["c", 0, {"x": [_ID]}, [], "ok", None, 1.0],
    ["c", 0, {b"x": [_ID]}, [], "ok", None, 5], ["c", 0, {"x": _ID}, [], "ok", None, 5],
    ["c", 0, {"x": [["p", "q"]]}, [], "ok", None, 5], ["c", 0, {"x": [["p", "q", -1]]}, [], "ok", None, 5],
    ["c", 0, {"x": [["p", 2, 1]]}, [], "ok", None, 5], ["c", 0, {"x": {"a": 1}}, [], "ok", None, 5],
    ["c", 0, {}, [["p", "q", 1.0]], "ok", None, 5], ["c", 0, {}, [[b"p", "q", 1]], "ok", None, 5],
    ["c", 0, {}, "p", "ok", None, 5], ["c", 0, {}, [], "ok", None], ["c", 0, {}, [], "ok", None, 5, 6], "c", 5,
    {"c": 0}, ["c", 0, {"x": [_ID], 5: [_ID]}, [], "ok", None, 5], ["c", 0, {"x": [[_ID]]}, [], "ok", None, 5],
    # two things wrong: the error of the one checked first
    ["c", 0, {b"x": [_ID]}, [], {"a": 1}, None, 5], ["c", 0, {"x": [["p", "q"]]}, [], "ok", None, 1.0],
    ["c", 0, {5: [["p", "q"]]}, [], "exploded", None, 5], ["c", 0, {"x": [["p", "q"]]}, [], "exploded", None, 5],
])
def test_a_step_record_without_detail_reads_as_read_as_lists(record):
    """decode_step reads a record without detail as tuples, checked in place (faster: a replay
    reads every step record twice): the same record, or the same error, as reading it as lists."""
    data = msgpack.packb(record, use_bin_type=True)

    def outcome(decode):
        try:
            return decode(data)
        except Exception as e:
            return type(e).__name__, str(e)

    assert outcome(decode_step) == outcome(_decode_step_read_as_lists)


def test_a_well_formed_had_below_is_read():
    detail = {"incomplete": ["x"], "had_below": {"x": [["prod", "value", 7]]}}
    assert decode_step(msgpack.packb(["probe", 0, {}, [], "incomplete", detail, 0]))[5] == detail


# ---------------------------------------------------------------------------------------------
# The run record's git revision
# ---------------------------------------------------------------------------------------------
def _git(repo: Path, *args: str) -> str:
    return subprocess.run(["git", "-c", "user.email=t@example.com", "-c", "user.name=t", *args], cwd=repo,
                          check=True, capture_output=True, text=True).stdout.strip()


@pytest.fixture
def checkout(tmp_path: Path) -> tuple[Path, Path]:
    """A git checkout holding a script whose source flow comes from a module outside any
    repository (an installed package, say) that sorts before it: ``(outside, checkout)``."""
    outside, repo = tmp_path / "installed", tmp_path / "checkout"
    outside.mkdir()
    repo.mkdir()
    (outside / "aa_flows.py").write_text("from retriever import Flow\n"
                                         "class Tick(Flow):\n    def step(self):\n        return {'x': 1.0}\n")
    (repo / "app.py").write_text("from retriever import Flow, Latest, Pipeline, Rate\nfrom aa_flows import Tick\n"
                                 "class Sink(Flow):\n    def step(self, x):\n        return None\n"
                                 "with Pipeline('app') as pipe:\n"
                                 "    (Tick() @ Rate(hz=10)).then(Sink() @ Rate(hz=10), sync=Latest())\n")
    _git(repo, "init", "-q")
    _git(repo, "add", "app.py")
    _git(repo, "commit", "-qm", "app")
    return outside, repo


def test_the_run_record_has_the_revision_of_the_checkout_the_flows_came_from_and_whether_it_was_dirty(checkout):
    outside, repo = checkout
    head = _git(repo, "rev-parse", "HEAD")
    for log, edit in (("clean.mcap", None), ("dirty.mcap", "# edited\n")):
        if edit:
            (repo / "app.py").write_text((repo / "app.py").read_text() + edit)
        done = cli("run", "app.py", "--duration", "0.3", "--log", log, cwd=repo, pythonpath=outside)
        assert done.returncode == 0, done.stderr
        assert read_log(repo / log).run["git_revision"] == head + ("-dirty" if edit else "")
    info = cli("log", "info", "dirty.mcap", cwd=repo).stdout
    assert f"git  {head}-dirty\n" in info
    aa, app = (hashlib.sha256(path.read_bytes()).hexdigest()[:16]
               for path in (outside / "aa_flows.py", repo / "app.py"))
    assert f"code  aa_flows sha256 {aa}…, app sha256 {app}…\n" in info


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() != 0, reason="needs root to give the checkout away")
def test_a_checkout_git_refuses_to_read_is_said_so_not_just_unknown(checkout):
    """A checkout of another user (a container's root running in a mounted checkout): git will
    not read it (safe.directory), which the run record and log info say."""
    outside, repo = checkout
    subprocess.run(["chown", "-R", "65534:65534", str(repo)], check=True)
    done = cli("run", "app.py", "--duration", "0.3", "--log", outside / "run.mcap", cwd=repo, pythonpath=outside)
    assert done.returncode == 0, done.stderr
    run = read_log(outside / "run.mcap").run
    assert (run["git_revision"], run["git_error"]) == ("", f"detected dubious ownership in repository at '{repo}'")
    assert (f"git  ? (detected dubious ownership in repository at '{repo}')\n"
            in cli("log", "info", outside / "run.mcap").stdout)


def test_a_run_whose_flow_module_is_not_tracked_in_the_checkout_is_dirty(checkout):
    """HEAD does not hold the code that ran when a flow's module is a file git does not track."""
    outside, repo = checkout
    (repo / "new_flows.py").write_text("from retriever import Flow\n"
                                       "class Tock(Flow):\n    def step(self):\n        return {'x': 2.0}\n")
    (repo / "app2.py").write_text("from retriever import Flow, Latest, Pipeline, Rate\nfrom new_flows import Tock\n"
                                  "from app import Sink\n"
                                  "with Pipeline('app2') as pipe:\n"
                                  "    (Tock() @ Rate(hz=10)).then(Sink() @ Rate(hz=10), sync=Latest())\n")
    (repo / "scratch.txt").write_text("an untracked file no flow comes from\n")
    head = _git(repo, "rev-parse", "HEAD")
    done = cli("run", "app.py", "--duration", "0.3", "--log", "tracked.mcap", cwd=repo, pythonpath=outside)
    assert done.returncode == 0, done.stderr
    assert read_log(repo / "tracked.mcap").run["git_revision"] == head  # untracked files elsewhere: clean
    done = cli("run", "app2.py", "--duration", "0.3", "--log", "untracked.mcap", cwd=repo, pythonpath=outside)
    assert done.returncode == 0, done.stderr
    assert read_log(repo / "untracked.mcap").run["git_revision"] == head + "-dirty"
