"""The protocol module (issue 37): every control and status message a typed record, its bytes
today's, its decoder exact; and signed control (issue 40: an insider's forged ``ctl/run``)."""

from __future__ import annotations

import json
import math
import queue
import sys

import msgpack
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from retriever.backends.zenoh import protocol as p
from retriever.backends.zenoh.origin import KEY_BYTES, MAC_BYTES, new_key
from retriever.backends.zenoh.protocol.run_spec import MAX_SPEC_BYTES, Seconds, ZenohId
from retriever.backends.zenoh.protocol.schema import (ABSENT, Bool, Document, Float, HexKey, Int, ListOf, MapOf, Name,
                                                      Nested, Nullable, OneOf, Plain, Row, Text)
from retriever.backends.zenoh.protocol.seal import COUNTER_BYTES, REPLAY_WINDOW
from retriever.backends.zenoh.protocol.to_coordinator import STATUSES
from retriever.backends.zenoh.wire import KeySpace, WireEncoder, WireError

KEYS = KeySpace("proto")
PID = 4242


def today(*fields) -> bytes:
    """A message as its senders packed it before the records (control, status and report all are this)."""
    return msgpack.packb(list(fields), use_bin_type=True)


def control(op, args) -> bytes:
    """A control message (``[2, op, args]``) as its senders packed it before the records."""
    return today(2, op, args)


def worker_status(node: str, state: str, **info) -> bytes:
    """A status as the worker put it before its records (``status(state, **info)``): its pid appended last."""
    info["pid"] = PID
    return today(2, node, state, info)


# ---------------------------------------------------------------------------------------------
# Today's bytes: each message as its sender builds it today, and its record
# ---------------------------------------------------------------------------------------------
T0, END = 1_780_000_000_123_456_789, 30_000_000_000
HEX = "ab" * KEY_BYTES
#: a run's spec as a deployment's coordinator sends it (its fields at their default left out)
SPEC_FIELDS = {"ir": {"nodes": [{"id": "cam"}, {"id": "sink"}]}, "namespace": "proto", "hub": "tcp/10.0.0.2:7447",
               "plan": {"nodes": []}, "argv": ["deploy.py", "--fast"], "startup_timeout": 60.0,
               "zids": {"cam": "1a2b", "sink": "3c4d"}, "hub_zid": "ef01", "virtual_time": False}
SPEC = p.RunSpec(ir=SPEC_FIELDS["ir"], namespace="proto", hub="tcp/10.0.0.2:7447", plan={"nodes": []},
                 argv=("deploy.py", "--fast"), startup_timeout=60.0, zids={"cam": "1a2b", "sink": "3c4d"},
                 hub_zid="ef01", virtual_time=False)
TODAY = [
    # coordinator.advance, _lockstep, _handle, _end_by_exit, _tell_have, _start_afresh, _stop_workers
    (control("start", {"t0": T0, "end": END, "values": True}), p.Start(t0=T0, end=END, values=True)),
    (control("start", {"t0": T0, "end": END, "values": False, "grant": 50_000_000}),
     p.Start(t0=T0, end=END, values=False, grant=50_000_000)),
    (control("grant", {"until": 100_000_000}), p.Grant(until=100_000_000)),
    (control("redeclare", {"nodes": ["cam", "src"]}), p.Redeclare(nodes=("cam", "src"))),
    (control("restarted", {"node": "src", "seqs": {"out": 1 << 20, "aux": (1 << 20) + 7},
                                          "values": True}),
     p.Restarted(node="src", seqs={"out": 1 << 20, "aux": (1 << 20) + 7}, values=True)),
    (control("handover", {"node": "ctl"}), p.Handover(node="ctl")),
    (control("resume", {"node": "ctl"}), p.Resume(node="ctl")),
    (control("end", {"at": 5_800_000_000}), p.End(at=5_800_000_000)),
    (control("have", {"streams": [["src", "out", 41], ["cam", "rgb", -1]]}),
     p.Have(streams=(("src", "out", 41), ("cam", "rgb", -1)))),
    (control("lost", {"node": "src"}), p.Lost(node="src")),
    (control("stop", {}), p.Stop()),
    # coordinator._answer_finished, _answer_start
    (control("finished", {"nodes": ["a", "b"], "complete": ["a"], "restarting": [], "handed_over": []}),
     p.Finished(nodes=("a", "b"), complete=("a",), restarting=(), handed_over=())),
    # the worker's status(...) calls (worker/'s phases), in their order
    (worker_status("cam", "failed", error="cannot build node 'cam': ImportError: x", traceback="Traceback..."),
     p.Failed(node="cam", pid=PID, error="cannot build node 'cam': ImportError: x", traceback="Traceback...")),
    (worker_status("cam", "failed", error="RuntimeError: no GPU", setup=True, traceback="Traceback..."),
     p.Failed(node="cam", pid=PID, error="RuntimeError: no GPU", setup=True, traceback="Traceback...")),
    (worker_status("cam", "restart", tag=[20_000_000, 0], error="ValueError: bad"),
     p.Restart(node="cam", pid=PID, tag=(20_000_000, 0), error="ValueError: bad")),
    (worker_status("cam", "exit", tag=[5_800_000_000, 0]), p.Exit(node="cam", pid=PID, tag=(5_800_000_000, 0))),
    (worker_status("cam", "reached", until=50_000_000), p.Reached(node="cam", pid=PID, until=50_000_000)),
    (worker_status("cam", "ready"), p.Ready(node="cam", pid=PID)),
    (worker_status("cam", "done", counts={"garbage": 1}), p.Done(node="cam", pid=PID, counts={"garbage": 1})),
    (worker_status("cam", "unanswered", nodes=["src"]), p.Unanswered(node="cam", pid=PID, nodes=("src",))),
    (worker_status("cam", "ready", linked=False, unlinked=["src", "the coordinator"], peers=2),
     p.Ready(node="cam", pid=PID, linked=False, unlinked=("src", "the coordinator"), peers=2)),
    (worker_status("cam", "failed", error="cam.step() raised X", tag=None, counts={}, traceback=None, zeno=False),
     p.Failed(node="cam", pid=PID, error="cam.step() raised X", tag=None, counts={}, traceback=None, zeno=False)),
    (worker_status("cam", "failed", error="cam.step() raised X", tag=[3, 1], counts={"late": 2}, traceback="T",
                   zeno=True),
     p.Failed(node="cam", pid=PID, error="cam.step() raised X", tag=(3, 1), counts={"late": 2}, traceback="T",
              zeno=True)),
    # a restart in place past the budget (worker/ending.tell_failed, node/in_place.py)
    (worker_status("cam", "failed", error="flow 'cam' failed again", tag=[3, 1], counts={"restarts": 1},
                   traceback="T", zeno=False, raised="ValueError: bad", out_of_restarts=True),
     p.Failed(node="cam", pid=PID, error="flow 'cam' failed again", tag=(3, 1), counts={"restarts": 1},
              traceback="T", zeno=False, raised="ValueError: bad", out_of_restarts=True)),
    (worker_status("cam", "handed_over", counts={}, reports=12),
     p.HandedOver(node="cam", pid=PID, counts={}, reports=12)),
    (worker_status("cam", "done", counts={"late": 3}, reports=7, started_ns=-250_000_000, ticks=1500, stopped=False,
                   sent={"rgb": 1499}),
     p.Done(node="cam", pid=PID, counts={"late": 3}, reports=7, started_ns=-250_000_000, ticks=1500, stopped=False,
            sent={"rgb": 1499})),
    (worker_status("cam", "done", counts={}, reports=0, started_ns=None, ticks=0, stopped=True, sent={}),
     p.Done(node="cam", pid=PID, counts={}, reports=0, started_ns=None, ticks=0, stopped=True, sent={})),
    # remote.RemoteHost.request ({"run": run, **args}), the deployment's discovery (deploy/discovery.py), daemon.ask
    (control("info", {}), p.InfoRequest()),
    (control("prepare", {"run": "5f3a9c0d1e2b", "spec": SPEC_FIELDS, "nodes": ["cam"]}),
     p.PrepareRequest(run="5f3a9c0d1e2b", spec=SPEC, nodes=("cam",))),
    (control("spawn", {"run": "r", "node": "cam", "mode": []}),
     p.SpawnRequest(run="r", node="cam", mode=())),
    (control("spawn", {"run": "r", "node": "cam", "mode": ["--fresh", str(T0), str(END)]}),
     p.SpawnRequest(run="r", node="cam", mode=(p.SpawnMode.FRESH, str(T0), str(END)))),
    (control("signal", {"run": "r", "pid": PID, "signal": 10}),
     p.SignalRequest(run="r", pid=PID, signal=10)),
    (control("usage", {"run": "r"}), p.UsageRequest(run="r")),
    (control("end", {"run": "r"}), p.EndRequest(run="r")),
    # daemon/core.py WorkerDaemon.info, daemon/runs.py DaemonRuns.prepare/spawn/signal/usage/end, daemon.answer's errors
    (control("info", {"protocol": 2, "name": "w1", "labels": ["gpu"], "host": "robot", "pid": PID,
                                    "python": "3.11.7", "packages": {"retriever": "0.1.0"}, "clock_ns": T0,
                                    "nodes": [], "counts": {"refused": 1}}),
     p.InfoReply(protocol=2, name="w1", labels=("gpu",), host="robot", pid=PID, python="3.11.7",
                 packages={"retriever": "0.1.0"}, clock_ns=T0, nodes=(), counts={"refused": 1})),
    (control("prepare", {"nodes": ["cam"], "warnings": [], "key": HEX}),
     p.PrepareReply(nodes=("cam",), warnings=(), key=bytes.fromhex(HEX))),
    (control("spawn", {"pid": PID, "key": HEX}), p.SpawnReply(pid=PID, key=bytes.fromhex(HEX))),
    (control("signal", {}), p.SignalReply()),
    (control("usage", {"cpu_s": {"cam": 1.25}}), p.UsageReply(cpu_s={"cam": 1.25})),
    (control("end", {}), p.EndReply()),
    (control("error", {"message": "worker 'w' knows no op 'x'"}),
     p.ErrorReply(message="worker 'w' knows no op 'x'")),
    # runs.forward_output, DaemonRuns._await_exit
    (control("output", {"run": "r", "node": "cam", "stream": "stderr", "lines": ["a", "b"]}),
     p.ProcessOutput(run="r", node="cam", stream=p.Stream.STDERR, lines=("a", "b"))),
    (control("exit", {"run": "r", "node": "cam", "pid": PID, "code": -9}),
     p.ProcessExit(run="r", node="cam", pid=PID, code=-9)),
    # deploy.ask_deployment, DeploymentQueryable.answer, Deployment.status
    (control("status", {}), p.StatusQuery()),
    (control("stop", {}), p.StopQuery()),
    (control("stop", {"pipeline": "demo"}), p.StopReply(pipeline="demo")),
    (control("status", {"pipeline": "demo", "run": "5f3a9c0d1e2b", "t_ns": 1000, "end_ns": 30_000,
                                      "started": True, "nodes": {
                                          "cam": {"worker": "w1", "state": "ready", "ticks": 3, "steps": 3, "skips": 0,
                                                  "errors": 0, "counts": {}, "cpu_s": 0.5},
                                          "src": {"worker": None, "state": None, "ticks": 0, "steps": 0, "skips": 0,
                                                  "errors": 0, "counts": {"late": 1}}}}),
     p.StatusReply(pipeline="demo", run="5f3a9c0d1e2b", t_ns=1000, end_ns=30_000, started=True, nodes={
         "cam": p.NodeStatus(worker="w1", state="ready", ticks=3, steps=3, skips=0, errors=0, counts={}, cpu_s=0.5),
         "src": p.NodeStatus(worker=None, state=None, ticks=0, steps=0, skips=0, errors=0, counts={"late": 1})})),
]

#: which channel each message of TODAY is decoded from (a name may be on several)
DECODERS = {
    p.InfoRequest: p.REQUEST, p.PrepareRequest: p.REQUEST, p.SpawnRequest: p.REQUEST, p.SignalRequest: p.REQUEST,
    p.UsageRequest: p.REQUEST, p.EndRequest: p.REQUEST, p.ErrorReply: p.ERROR_REPLY,
    p.ProcessOutput: p.DAEMON_EVENT, p.ProcessExit: p.DAEMON_EVENT, p.StatusQuery: p.DEPLOYMENT_QUERY,
    p.StopQuery: p.DEPLOYMENT_QUERY, p.StopReply: p.DEPLOYMENT_REPLY, p.StatusReply: p.DEPLOYMENT_REPLY,
    p.Finished: p.FINISHED_REPLY,
}


def decode_as_received(data: bytes, record: p.Record) -> p.Record:
    """``data`` decoded by its receiver's channel (not by the record's own class)."""
    if isinstance(record, p.Status):
        return p.STATUS.decode(data, node=record.node)
    if type(record) in (p.InfoReply, p.PrepareReply, p.SpawnReply, p.SignalReply, p.UsageReply, p.EndReply):
        return p.decode_reply(data, record.NAME)
    return DECODERS.get(type(record), p.RUN_CONTROL).decode(data)


@pytest.mark.parametrize("data, record", TODAY, ids=[f"{type(r).__name__}-{i}" for i, (_, r) in enumerate(TODAY)])
def test_a_record_encodes_to_todays_bytes_and_todays_bytes_decode_to_it(data, record):
    assert record.encode() == data
    assert decode_as_received(data, record) == record
    assert type(record).decode(data) == record


def test_every_message_kind_is_covered_by_todays_bytes():
    covered = {type(record) for _, record in TODAY}
    assert covered >= {*p.RUN_CONTROL.records.values(), *STATUSES.values(), *p.REQUEST.records.values(),
                       *p.DAEMON_EVENT.records.values(), *p.DEPLOYMENT_QUERY.records.values(),
                       *p.DEPLOYMENT_REPLY.records.values(), p.Finished, p.ErrorReply, p.InfoReply, p.PrepareReply,
                       p.SpawnReply, p.SignalReply, p.UsageReply, p.EndReply}


def test_the_one_status_whose_map_order_differs_from_todays_decodes_the_same():
    """The worker's crash `failed` (worker.run, ending.say_failed) puts counts after the traceback; every other failed puts
    tag and counts before it, which is the record's order: same keys, same values."""
    data = worker_status("cam", "failed", error="worker 'cam' crashed: OSError: x", traceback="T", counts={"late": 1})
    record = p.STATUS.decode(data, node="cam")
    assert record == p.Failed(node="cam", pid=PID, error="worker 'cam' crashed: OSError: x", traceback="T",
                              counts={"late": 1})
    assert msgpack.unpackb(record.encode()) == msgpack.unpackb(data)


def test_a_report_encodes_to_the_reporters_bytes_and_decodes_as_wire_did():
    """node/reporter.py: ``[2, node, records, events]`` as packed before Report, the loop's records of tuples."""
    message = WireEncoder().data((20_000_000, 0), 3, (40_000_000, 0), "cam", "rgb", [1, 2])
    raw_records = [((20_000_000, 0), {"img": (("src", "out", 4), ("src", "out", 5))}, (("cam", "rgb", 3),), "ok",
                    None, T0, 1500),
                   ((40_000_000, 0), {}, (), "error", {"error": "ValueError: x", "on_error": "skip",
                                                       "late": {"img": [("src", "out", 6)]}}, T0 + 5, -3)]
    data = today(2, "cam", raw_records, [(T0, message), (T0 + 1, "cam.77.1.msg")])
    report = p.Report.decode(data, node="cam")
    assert report.records[0] == ((20_000_000, 0), {"img": (("src", "out", 4), ("src", "out", 5))},
                                 (("cam", "rgb", 3),), "ok", None, T0, 1500)
    assert report.records[1].detail["late"] == {"img": [["src", "out", 6]]}
    assert report.events == (p.ReportedEvent(T0, message), p.ReportedEvent(T0 + 1, "cam.77.1.msg"))
    assert report.encode() == data
    assert p.Report(node="cam", records=tuple(raw_records), events=((T0, message), (T0 + 1, "cam.77.1.msg"))).encode() \
        == data


def test_the_enums_name_every_state_and_op_today_spells():
    assert [str(s) for s in p.State] == ["ready", "done", "failed", "restart", "handed_over", "reached", "unanswered",
                                         "exit"]
    assert set(p.REQUEST.records) == {"info", "prepare", "spawn", "signal", "end", "usage"}
    # in the order a daemon's unknown-op error lists them
    assert list(p.DaemonOp) == ["info", "prepare", "spawn", "signal", "end", "usage"]


# ---------------------------------------------------------------------------------------------
# Round trips: a strategy for every record, made from its fields' kinds
# ---------------------------------------------------------------------------------------------
NAMES = st.from_regex(r"[A-Za-z0-9_][A-Za-z0-9_.\-]{0,11}", fullmatch=True)


def values(kind) -> st.SearchStrategy:
    """Values a field of ``kind`` may hold (as the record holds them)."""
    if isinstance(kind, Int):
        return st.integers(kind.low, kind.high)
    if isinstance(kind, Float):
        return st.floats(kind.low, kind.high, allow_nan=False, allow_infinity=False)
    if isinstance(kind, Bool):
        return st.booleans()
    if isinstance(kind, Name):
        return NAMES
    if isinstance(kind, Text):
        return st.text(min_size=kind.min_chars, max_size=min(kind.max_chars, 20))
    if isinstance(kind, OneOf):
        return st.sampled_from(list(kind.enum))
    if isinstance(kind, Nullable):
        return st.none() | values(kind.inner)
    if isinstance(kind, ListOf):
        return st.lists(values(kind.item), min_size=kind.min_items, max_size=4).map(tuple)
    if isinstance(kind, Row):
        return st.tuples(*(values(item) for item in kind.items))
    if isinstance(kind, MapOf):
        return st.dictionaries(values(kind.key), values(kind.value), max_size=4)
    if isinstance(kind, (Document, Plain)):
        leaves = st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.text(max_size=8) | st.floats(
            allow_nan=False, allow_infinity=False)
        return st.dictionaries(st.text(max_size=6), st.recursive(leaves, lambda inner: st.lists(inner, max_size=3)
                                                                 | st.dictionaries(st.text(max_size=4), inner,
                                                                                   max_size=3), max_leaves=8),
                               max_size=4)
    if isinstance(kind, HexKey):
        return st.binary(min_size=kind.size, max_size=kind.size)
    if isinstance(kind, Nested):
        return records(kind.record)
    if isinstance(kind, ZenohId):
        return st.from_regex(r"[1-9a-f][0-9a-f]{0,31}", fullmatch=True)
    if isinstance(kind, Seconds):
        return st.floats(kind.low, kind.high, allow_nan=False, allow_infinity=False)
    if type(kind).__name__ == "Mode":
        digits = st.integers(0, 10**19 - 1).map(str)
        return st.just(()) | st.tuples(st.sampled_from(list(p.SpawnMode)), digits, digits)
    raise AssertionError(f"no strategy for {kind!r}")


def records(cls) -> st.SearchStrategy:
    fields, defaults = {}, cls.defaults()
    for name, kind, optional in cls.schema():
        left_out = st.just(defaults.get(name, ABSENT))
        fields[name] = left_out | values(kind) if optional else values(kind)
    if issubclass(cls, p.Status):
        fields["node"] = NAMES
    if cls is p.RunSpec:  # one Zenoh id per node of its IR, or none; no groups (spec_ids checks those)
        fields["groups"] = st.just({})
        fields["zids"] = st.dictionaries(NAMES, values(ZenohId()), max_size=4).filter(
            lambda zids: len(set(zids.values())) == len(zids))
        return st.fixed_dictionaries(fields).map(lambda kwargs: cls(**{
            **kwargs, "ir": {**kwargs["ir"], "nodes": [{"id": node} for node in kwargs["zids"]]}}))
    return st.fixed_dictionaries(fields).map(lambda kwargs: cls(**kwargs))


ALL_RECORDS = sorted({type(record) for _, record in TODAY}, key=lambda cls: cls.__name__)


@settings(max_examples=40, deadline=None)
@given(records(p.RunSpec))
def test_a_run_spec_round_trips_through_its_file_and_a_prepare_request(spec):
    assert p.RunSpec.from_fields(json.loads(spec.to_json()), "the spec") == spec
    request = p.PrepareRequest(run="r", spec=spec, nodes=())
    assert p.PrepareRequest.decode(request.encode()) == request


@settings(max_examples=40, deadline=None)
@given(st.data())
@pytest.mark.parametrize("cls", ALL_RECORDS, ids=lambda cls: cls.__name__)
def test_every_record_round_trips(cls, data):
    record = data.draw(records(cls))
    encoded = record.encode()
    assert decode_as_received(encoded, record) == record
    assert decode_as_received(encoded, record).encode() == encoded


IDS = st.lists(st.tuples(NAMES, NAMES, st.integers(0, 2**63 - 1)), max_size=3).map(tuple)
STEPS = st.builds(p.ReportedStep, st.tuples(st.integers(0, 2**63 - 1), st.integers(0, 2**63 - 1)),
                  st.dictionaries(NAMES, IDS, max_size=3), IDS, st.sampled_from(["ok", "skipped", "error", "late"]),
                  st.none() | st.dictionaries(st.text(max_size=5), st.integers(-2**63, 2**64 - 1) | st.text(max_size=5),
                                              max_size=3),
                  st.integers(-2**63, 2**63 - 1), st.integers(-2**63, 2**63 - 1))


@settings(max_examples=100, deadline=None)
@given(NAMES, st.lists(STEPS, max_size=4), st.lists(st.builds(
    p.ReportedEvent, st.integers(-2**63, 2**63 - 1), st.binary(max_size=16) | NAMES), max_size=4))
def test_reports_round_trip(node, steps, events):
    report = p.Report(node=node, records=tuple(steps), events=tuple(events))
    assert p.Report.decode(report.encode(), node=node) == report


# ---------------------------------------------------------------------------------------------
# Exact: every kind of malformed input refused, with a WireError that names what is wrong
# ---------------------------------------------------------------------------------------------
MALFORMED = [
    ("not bytes", p.RUN_CONTROL, "grant", "must be bytes"),
    ("garbage", p.RUN_CONTROL, b"\xc1 garbage", "not valid msgpack"),
    ("trailing bytes", p.RUN_CONTROL, control("stop", {}) + b"\x00", r"not valid msgpack \(ExtraData"),
    ("invalid utf-8", p.RUN_CONTROL, b"\x93\x02\xa4st\xffp\x80", "not valid msgpack"),
    ("array of 4", p.RUN_CONTROL, today(2, "stop", {}, 1), "array of 3"),
    ("a map, not an array", p.RUN_CONTROL, msgpack.packb({"op": "stop"}), "array of 3"),
    ("wire format 1", p.RUN_CONTROL, today(1, "stop", {}), "wire format 1; this process speaks 2"),
    ("unknown op", p.RUN_CONTROL, control("frobnicate", {}), "knows no op 'frobnicate' .it knows start, grant"),
    ("op not a string", p.RUN_CONTROL, control(7, {}), "knows no op 7"),
    ("args a list", p.RUN_CONTROL, control("stop", []), "'stop' message on ctl/run must carry a map"),
    ("missing field", p.RUN_CONTROL, control("grant", {}), "lacks its field 'until'"),
    ("extra field", p.RUN_CONTROL, control("stop", {"now": True}), "field it does not take: 'now'"),
    ("wrong type", p.RUN_CONTROL, control("grant", {"until": "5"}), "field 'until' must be an integer"),
    ("bool for an int", p.RUN_CONTROL, control("end", {"at": True}), "field 'at' must be an integer"),
    ("negative", p.RUN_CONTROL, control("grant", {"until": -1}), "field 'until' must be an integer from 0"),
    ("past the range", p.RUN_CONTROL, control("end", {"at": 2**63}), "field 'at' must be an integer from 0 to"),
    ("a name that is no key chunk", p.RUN_CONTROL, control("lost", {"node": "a/*"}), "field 'node' must be a name"),
    ("an oversize name", p.RUN_CONTROL, control("lost", {"node": "n" * 1025}), "field 'node' must be a name"),
    ("nested, named by path", p.RUN_CONTROL, control("have", {"streams": [["a", "b", 1], ["a", "b", "x"]]}),
     r"field 'streams'\[1\]\[2\] must be an integer from -1"),
    ("a row too short", p.RUN_CONTROL, control("have", {"streams": [["a", "b"]]}),
     r"field 'streams'\[0\] must be \[producer, port, last seq\]"),
    ("a map key of the wrong kind", p.RUN_CONTROL, control("restarted", {"node": "a", "seqs": {7: 1}, "values": True}),
     "field 'seqs' key 7 must be a string of 1 to 1024"),
    ("a key twice", p.RUN_CONTROL, b"\x93\x02\xa5grant\x82\xa5until\x01\xa5until\x02", "names a key twice"),
    ("an empty list where one is needed", p.RUN_CONTROL, control("redeclare", {"nodes": []}),
     "field 'nodes' must be a list of 1 to"),
    ("an extension type", p.RUN_CONTROL,
     control("lost", {"node": msgpack.ExtType(4, msgpack.packb(["os:system", {"command": "touch /tmp/x"}]))}),
     "field 'node' must be a name.*got ExtType"),
    ("too big", p.REQUEST, control("prepare", {"run": "r", "spec": {"pad": "x" * (9 << 20)}, "nodes": []}),
     r"of \d+ bytes, past 8388608: refused"),
    ("non-finite float", p.REPLY, control("usage", {"cpu_s": {"cam": math.inf}}), "field 'cpu_s'.*must be a finite"),
    ("NaN", p.REPLY, control("usage", {"cpu_s": {"cam": math.nan}}), "must be a finite float"),
    ("an int where a float is", p.REPLY, control("usage", {"cpu_s": {"cam": 1}}), "must be a finite float"),
    ("oversize text", p.ERROR_REPLY, control("error", {"message": "x" * ((1 << 20) + 1)}),
     "field 'message' must be a string of 0 to 1048576"),
    ("a spawn mode", p.REQUEST, control("spawn", {"run": "r", "node": "c", "mode": ["--join", "1; rm -rf /", "2"]}),
     "spawn mode"),
    ("a spawn mode of unicode digits", p.REQUEST,
     control("spawn", {"run": "r", "node": "c", "mode": ["--fresh", "²", "1"]}),
     "spawn mode"),
    ("a spawn's group flag that is an int", p.REQUEST,
     control("spawn", {"run": "r", "node": "g", "mode": [], "group": 1}), "field 'group' must be true or false"),
    ("a spawn's group flag that is text", p.REQUEST,
     control("spawn", {"run": "r", "node": "g", "mode": [], "group": "true"}), "field 'group' must be true or false"),
    ("a key in a spawn request", p.REQUEST, control("spawn", {"run": "r", "node": "c", "mode": [], "key": HEX}),
     "carries no key"),
    ("a key that is not hex", p.REPLY, control("spawn", {"pid": 7, "key": "zz" * KEY_BYTES}),
     "field 'key' must be 64 hexadecimal digits"),
    ("a stream that is neither", p.DAEMON_EVENT, control("output", {"run": "r", "node": "c", "stream": "stdin",
                                                                    "lines": []}),
     "field 'stream' must be one of 'stdout', 'stderr'"),
    ("a nested record's field", p.DEPLOYMENT_REPLY, control("status", {
        "pipeline": "d", "run": "r", "t_ns": 0, "end_ns": 0, "started": False,
        "nodes": {"a": {"worker": None, "state": None, "ticks": -1, "steps": 0, "skips": 0, "errors": 0,
                        "counts": {}}}}),
     r"field 'nodes'\['a'\]: field 'ticks' must be an integer from 0"),
    ("a node state that is none", p.DEPLOYMENT_REPLY, control("status", {
        "pipeline": "d", "run": "r", "t_ns": 0, "end_ns": 0, "started": False,
        "nodes": {"a": {"worker": None, "state": "running", "ticks": 0, "steps": 0, "skips": 0, "errors": 0,
                        "counts": {}}}}),
     r"field 'nodes'\['a'\]: field 'state' must be one of 'starting', 'ready', 'failed', 'done', got str 'running'"),
]


@pytest.mark.parametrize("what, channel, data, error", MALFORMED, ids=[m[0] for m in MALFORMED])
def test_malformed_messages_are_refused_with_an_error_naming_what(what, channel, data, error):
    with pytest.raises(WireError, match=error):
        channel.decode(data)


DROP = object()


def spec_with(**changes) -> dict:
    """SPEC_FIELDS with ``changes`` (DROP: the field left out)."""
    return {k: v for k, v in {**SPEC_FIELDS, **changes}.items() if v is not DROP}


SPEC_ATTACKS = [
    ("a field missing", spec_with(plan=DROP), "lacks its field 'plan'"),
    ("another field missing", spec_with(zids=DROP), "lacks its field 'zids'"),
    ("a field it does not take", spec_with(shell="touch /tmp/x"), "has a field it does not take: 'shell'"),
    ("the IR not a map", spec_with(ir=["x"]), "field 'ir' must be a map with string keys"),
    ("the plan with a key that is no string", spec_with(plan={1: 2}), "field 'plan' must be a map with string keys"),
    ("a namespace that is no key chunk", spec_with(namespace="a/**"), "field 'namespace' must be a name"),
    ("a hub that is a number", spec_with(hub=7447), "field 'hub' must be a string"),
    ("a timeout that is text", spec_with(startup_timeout="60"), "field 'startup_timeout' must be seconds"),
    ("a timeout that is infinite", spec_with(startup_timeout=math.inf), "field 'startup_timeout' must be seconds"),
    ("a timeout that is true", spec_with(startup_timeout=True), "field 'startup_timeout' must be seconds"),
    ("a lease below zero", spec_with(lease=-1), "field 'lease' must be seconds"),
    ("virtual time that is text", spec_with(virtual_time="yes"), "field 'virtual_time' must be true or false"),
    ("argv of numbers", spec_with(argv=[1]), r"field 'argv'\[0\] must be a string"),
    ("a python path that is one string", spec_with(python_path="/tmp"), "field 'python_path' must be a list"),
    ("a zid with a leading zero", spec_with(zids={"cam": "0bad", "sink": "3c4d"}),
     r"field 'zids'\['cam'\] must be a Zenoh id"),
    ("a zid too long", spec_with(zids={"cam": "a" * 33, "sink": "3c4d"}), r"field 'zids'\['cam'\] must be a Zenoh id"),
    ("a zid in capitals", spec_with(zids={"cam": "ABC", "sink": "3c4d"}), r"field 'zids'\['cam'\] must be a Zenoh id"),
    ("zids as a list", spec_with(zids=["1a2b"]), "field 'zids' must be a map"),
    ("a zid of a node not in the IR", spec_with(zids={"cam": "1a2b", "sink": "3c4d", "ghost": "5e"}),
     "field 'zids' must name one Zenoh id for each node of its IR, or none"),
    ("zids of some nodes only", spec_with(zids={"cam": "1a2b"}),
     r"field 'zids' must name one Zenoh id for each node of its IR, or none \(amiss: 'sink'\)"),
    ("an IR whose node ids are no names", spec_with(ir={"nodes": [{"id": ["cam"]}, {"id": {}}, "sink"]}),
     "field 'zids' must name one Zenoh id for each node of its IR, or none"),
    ("two nodes of no group with one zid", spec_with(zids={"cam": "1a2b", "sink": "1a2b"}),
     "field 'zids' gives nodes 'cam' and 'sink' one Zenoh id, and they are no group's"),
    ("a hub zid that is a path", spec_with(hub_zid="../etc"), "field 'hub_zid' must be a Zenoh id"),
    ("a group of no node", spec_with(groups={"g": []}), r"field 'groups'\['g'\] must be a list of 1"),
    # a node in two groups' processes, or twice in one, would run twice at once
    ("a node in two groups", spec_with(groups={"g": ["cam", "sink"], "h": ["cam"]}),
     "field 'groups' puts node 'cam' in groups 'g' and 'h': a node runs in one process"),
    ("a node twice in a group", spec_with(groups={"g": ["cam", "sink", "cam"]}),
     "field 'groups' puts node 'cam' in group 'g' twice: a node runs in one process"),
    ("a group of a node not in the IR", spec_with(groups={"g": ["cam", "ghost"]}),
     "field 'groups' names node 'ghost' in group 'g', which its IR does not have"),
    ("access that is a string", spec_with(access="secret"), "field 'access' must be a map"),
    ("an extension type", spec_with(main_file=msgpack.ExtType(4, b"os:system")), "field 'main_file' must be a string.*ExtType"),
]


@pytest.mark.parametrize("what, fields, error", SPEC_ATTACKS, ids=[a[0] for a in SPEC_ATTACKS])
def test_a_malformed_run_spec_is_refused_naming_the_field_in_a_prepare_request_and_in_a_file(
        what, fields, error, tmp_path):
    with pytest.raises(WireError, match=r"a 'prepare' message on ctl/<name>: field 'spec'.*" + error):
        p.REQUEST.decode(control("prepare", {"run": "r", "spec": fields, "nodes": []}))
    try:
        text = json.dumps(fields)
    except TypeError:
        return  # (no JSON file holds an extension type)
    if json.loads(text) != fields:
        return  # (nor a key that is no string)
    path = tmp_path / "spec.json"
    path.write_text(text)
    with pytest.raises(WireError, match=r"the run's spec .*spec.json.*" + error):
        p.RunSpec.read_file(path)


def test_a_run_spec_takes_one_zid_for_a_groups_members_and_its_defaults_when_left_out(tmp_path):
    grouped = p.RunSpec.from_fields(spec_with(zids={"cam": "1a2b", "sink": "1a2b"}, groups={"g": ["cam", "sink"]}),
                                    "the spec")
    assert grouped.groups == {"g": ("cam", "sink")} and grouped.zids == {"cam": "1a2b", "sink": "1a2b"}
    assert (SPEC.python_path, SPEC.main_file, SPEC.spill_dir, SPEC.router, SPEC.listen, SPEC.lease) == (
        (), None, None, (), (), None)
    assert p.RunSpec.from_fields(spec_with(startup_timeout=60), "the spec").startup_timeout == 60.0
    path = tmp_path / "spec.json"
    path.write_text("{not json")
    with pytest.raises(WireError, match="is not JSON"):
        p.RunSpec.read_file(path)
    path.write_bytes(b" " * (MAX_SPEC_BYTES + 1))
    with pytest.raises(WireError, match=rf"of {MAX_SPEC_BYTES + 1} bytes, past {MAX_SPEC_BYTES}: refused"):
        p.RunSpec.read_file(path)


def test_nothing_decoded_is_imported_or_called():
    """A dataclass extension naming a module: refused, and the module is never imported."""
    name = "retriever_protocol_test_never_imported"
    data = control("lost", {"node": msgpack.ExtType(4, msgpack.packb([f"{name}:Evil", {}]))})
    with pytest.raises(WireError):
        p.RUN_CONTROL.decode(data)
    detail = {"x": msgpack.ExtType(4, msgpack.packb([f"{name}:Evil", {}]))}
    with pytest.raises(WireError, match="field 'detail'"):
        p.Report.decode(today(2, "cam", [[[0, 0], {}, [], "ok", detail, 0, 0]], []))
    assert name not in sys.modules


@pytest.mark.parametrize("data, error", [
    (worker_status("cam", "bogus"), "state 'bogus'; a worker's states are ready, done"),
    (worker_status("cam", "ready", linked="yes"), "'ready' status of cam: field 'linked' must be true or false"),
    (worker_status("other", "ready"), "a status of other arrived on the key of cam"),
    (today(2, "cam", "ready", {}), "lacks its field 'pid'"),
    (worker_status("cam", "exit", tag=[1]), r"field 'tag' must be \[t_ns, microstep\]"),
    (today(2, "cam", "exit", {"tag": [1, 0], "pid": PID, "node": "x"}), "field it does not take: 'node'"),
    (worker_status("cam", "done", counts={"late": -1}), r"field 'counts'\['late'\] must be an integer from 0"),
    (worker_status("cam", "unanswered", nodes=[]), "field 'nodes' must be a list of 1 to"),
    (worker_status("cam", "reached"), "lacks its field 'until'"),
    (worker_status("cam", "failed", error="x", traceback=None, out_of_restarts=1),
     "'failed' status of cam: field 'out_of_restarts' must be true or false"),
    (today(2, "cam", "ready"), "array of 4"),
])
def test_malformed_statuses_are_refused_with_an_error_naming_what(data, error):
    with pytest.raises(WireError, match=error):
        p.STATUS.decode(data, node="cam")


@pytest.mark.parametrize("record, error", [
    ([[0, 0], {}, [], "bogus", None, 0, 0], "field 'status' must be one of ok, skipped"),
    ([[0, 0], {}, [], "ok", None, 0], r"^a report of cam: record 0 must be \[tag, consumed, produced"),
    ([[0, -1], {}, [], "ok", None, 0, 0], r"field 'tag'\[1\] must be an integer from 0"),
    ([[0, 0], {"in": [["a", "b", -1]]}, [], "ok", None, 0, 0], "field 'consumed' must hold event ids"),
    ([[0, 0], {}, [["a", "b"]], "ok", None, 0, 0], "field 'produced' must hold event ids"),
    ([[0, 0], [], [], "ok", None, 0, 0], "field 'consumed' must be a map"),
    ([[0, 0], {}, [], "ok", [1], 0, 0], "field 'detail' must be nil or a map"),
    ([[0, 0], {}, [], "ok", {"x": math.nan}, 0, 0], r"field 'detail'\['x'\] must be plain data.*got float nan"),
    ([[0, 0], {}, [], "ok", None, 2**63, 0], "field 'wall_start_ns' must be an integer"),
])
def test_malformed_report_records_are_refused_naming_the_field(record, error):
    with pytest.raises(WireError, match=error if error.startswith("^") else f"^a report of cam: record 0: {error}"):
        p.Report.decode(today(2, "cam", [record], []), node="cam")


def test_malformed_report_envelopes_are_refused():
    with pytest.raises(WireError, match="a report of other arrived on the key of cam"):
        p.Report.decode(today(2, "other", [], []), node="cam")
    with pytest.raises(WireError, match=r"event 0 must be \[wall_ns, data message or file name\]"):
        p.Report.decode(today(2, "cam", [], [[0, 5]]), node="cam")
    with pytest.raises(WireError, match="must carry a list of records"):
        p.Report.decode(today(2, "cam", {}, []), node="cam")


def test_a_reply_must_answer_the_op_asked_and_a_daemon_of_another_protocol_says_so():
    with pytest.raises(WireError, match="a 'end' reply to a 'spawn' request"):
        p.decode_reply(control("end", {}), p.DaemonOp.SPAWN)
    with pytest.raises(WireError, match="the worker speaks protocol 3, this process 2"):
        p.decode_reply(control("info", {"protocol": 3, "anything": "new"}), p.DaemonOp.INFO)
    with pytest.raises(WireError, match="a 'grant' message where 'start' was expected"):
        p.Start.decode(p.Grant(until=1).encode())


def test_unknown_ops_name_their_receiver_as_the_daemon_and_the_deployment_say_it():
    with pytest.raises(WireError, match=r"^worker 'w' knows no op 'frobnicate' \(it knows info, prepare, spawn, "
                                        r"signal, end, usage\)$"):
        p.REQUEST.decode(control("frobnicate", {}), who="worker 'w'")
    with pytest.raises(WireError, match=r"^the deployment knows no op 'x' \(it knows status, stop\)$"):
        p.DEPLOYMENT_QUERY.decode(control("x", {}), who="the deployment")


def test_error_replies_say_their_message_and_nothing_else_is_one():
    assert p.error_message(control("error", {"message": "no"})) == "no"
    assert p.error_message(b"Timeout") is None
    assert p.error_message(control("error", {})) is None


CHANNELS = [p.RUN_CONTROL, p.FINISHED_REPLY, p.REQUEST, p.REPLY, p.ERROR_REPLY, p.DAEMON_EVENT,
            p.DEPLOYMENT_QUERY, p.DEPLOYMENT_REPLY]
ANY = st.recursive(st.none() | st.booleans() | st.integers(-2**63, 2**64 - 1) | st.floats() | st.text(max_size=6)
                   | st.binary(max_size=6), lambda inner: st.lists(inner, max_size=3)
                   | st.dictionaries(st.text(max_size=6) | st.integers(-5, 5), inner, max_size=3), max_leaves=10)


@settings(max_examples=400, deadline=None)
@given(st.binary(max_size=64) | st.builds(lambda version, op, args: today(version, op, args),
                                          st.sampled_from([2, 2, 2, 1]),
                                          st.sampled_from(sorted({n for c in CHANNELS for n in c.records})) | ANY,
                                          st.dictionaries(st.sampled_from(["node", "until", "t0", "end", "values",
                                                                           "nodes", "streams", "run", "pid", "key",
                                                                           "message", "mode", "seqs", "lines"]),
                                                          ANY, max_size=4) | ANY))
def test_any_bytes_decode_to_a_record_or_raise_wire_error(data):
    for channel in CHANNELS:
        try:
            assert isinstance(channel.decode(data), p.Record)
        except WireError:
            pass
    for decode in (lambda d: p.STATUS.decode(d), lambda d: p.Report.decode(d)):
        try:
            decode(data)
        except WireError:
            pass



def nested(depth: int) -> bytes:
    """A list nested ``depth`` deep, packed by hand (msgpack's packer refuses past 511 levels;
    its unpacker takes up to about 1,024)."""
    return b"\x91" * depth + b"\x90"


@pytest.mark.parametrize("place", ["version", "op", "fields"])
def test_a_field_nested_deeper_than_repr_goes_is_refused_with_a_short_error(place):
    """The fuzz campaign found it: a message whose first field was a list nested ~1000 deep made
    the error's repr raise RecursionError (a crash, not a refusal). Errors show decoded values
    through wire.shown: bounded, whatever they hold."""
    deep = nested(1000)
    data = {"version": b"\x93" + deep + msgpack.packb("stop") + b"\x80",
            "op": b"\x93\x02" + deep + b"\x80",
            "fields": b"\x93\x02" + msgpack.packb("grant") + b"\x81" + msgpack.packb("until") + deep}[place]
    decoders = [channel.decode for channel in CHANNELS] + [p.STATUS.decode, p.Report.decode]
    for decode in decoders:
        with pytest.raises(WireError) as refused:
            decode(data)
        assert len(str(refused.value)) < 400


# ---------------------------------------------------------------------------------------------
# Signed control (seal.py): forged, altered, replayed, another run's, a wrong key
# ---------------------------------------------------------------------------------------------
class Process:
    """A worker process as the coordinator holds it (only its identity matters to the signer)."""


def run_of(n: int = 3) -> tuple[p.ControlSigner, list[bytes]]:
    """A coordinator's signer with ``n`` processes started, and their keys."""
    signer, keys = p.ControlSigner(), [new_key() for _ in range(n)]
    for key in keys:
        signer.add(Process(), key)
    return signer, keys


def test_every_live_process_opens_what_the_coordinator_sealed_once():
    signer, keys = run_of(3)
    key_expr, payload = KEYS.run_control(), p.Lost(node="src").encode()
    seal = signer.seal(key_expr, payload)
    assert len(seal) == COUNTER_BYTES + 3 * MAC_BYTES
    for key in keys:
        assert p.ControlOpener(key).control(key_expr, payload, seal) == p.Lost(node="src")


@pytest.mark.parametrize("attachment, error", [
    (None, "without the coordinator's seal"),
    (b"", "without the coordinator's seal"),
    (b"\x00" * COUNTER_BYTES, "without the coordinator's seal"),
    (b"\x00" * (COUNTER_BYTES + MAC_BYTES + 1), "without the coordinator's seal"),
    (b"\x00" * COUNTER_BYTES + b"\x01" * MAC_BYTES, "did not seal for this process"),
])
def test_an_unsealed_or_forged_control_message_is_refused(attachment, error):
    """An insider's `lost` (issue 40): it holds the run's password, not a process's key."""
    _, keys = run_of(1)
    with pytest.raises(WireError, match=error):
        p.ControlOpener(keys[0]).control(KEYS.run_control(), p.Lost(node="src").encode(), attachment)


def test_a_seal_made_with_another_key_is_refused():
    """An insider that seals with a key of its own (or a process's key of another run)."""
    signer, _ = run_of(2)  # another run's coordinator, with its processes
    _, ours = run_of(1)
    key_expr, payload = KEYS.run_control(), p.Stop().encode()
    with pytest.raises(WireError, match="did not seal for this process .forged, altered, or another run's"):
        p.ControlOpener(ours[0]).control(key_expr, payload, signer.seal(key_expr, payload))


def test_a_message_replayed_from_another_run_is_refused():
    """A `stop` recorded from one run, put on another's key (or the same namespace's next run)."""
    first, _ = run_of(2)
    payload = p.Stop().encode()
    sealed = first.seal(KEYS.run_control(), payload)
    _, keys = run_of(2)
    for key in keys:
        with pytest.raises(WireError, match="did not seal for this process"):
            p.ControlOpener(key).control(KEYS.run_control(), payload, sealed)
    # a run's own process, its message moved to another namespace's key: the key expression is signed
    signer, keys = run_of(1)
    sealed = signer.seal(KeySpace("other").run_control(), payload)
    with pytest.raises(WireError, match="did not seal for this process"):
        p.ControlOpener(keys[0]).control(KEYS.run_control(), payload, sealed)


def test_an_altered_payload_or_counter_is_refused():
    signer, keys = run_of(1)
    key_expr, payload = KEYS.run_control(), p.End(at=5_000).encode()
    seal = signer.seal(key_expr, payload)
    opener = p.ControlOpener(keys[0])
    with pytest.raises(WireError, match="did not seal"):
        opener.control(key_expr, p.End(at=1).encode(), seal)
    with pytest.raises(WireError, match="did not seal"):
        opener.control(key_expr, payload, (2).to_bytes(COUNTER_BYTES, "big") + seal[COUNTER_BYTES:])
    assert opener.control(key_expr, payload, seal) == p.End(at=5_000)


def test_a_replay_within_the_run_is_refused_and_a_reordering_is_forgiven():
    """A process takes each sealed put once: an insider that puts again a `lost` or a `handover`
    it saw earlier in the run (sealed for this very process) gets nowhere."""
    signer, keys = run_of(1)
    key_expr = KEYS.run_control()
    sealed = [(payload, signer.seal(key_expr, payload))
              for payload in (p.Handover(node="ctl").encode(), p.Grant(until=1).encode(), p.Grant(until=2).encode())]
    opener = p.ControlOpener(keys[0])
    opener.control(key_expr, *sealed[0])
    opener.control(key_expr, *sealed[2])
    assert opener.control(key_expr, *sealed[1]) == p.Grant(until=1)  # late, not seen before: taken
    for payload, seal in sealed:
        with pytest.raises(WireError, match=r"taken before \(counter \d\): a replay"):
            opener.control(key_expr, payload, seal)


def test_a_message_older_than_the_window_is_refused():
    signer, keys = run_of(1)
    key_expr, payload = KEYS.run_control(), p.Stop().encode()
    old = signer.seal(key_expr, payload)
    opener = p.ControlOpener(keys[0])
    for _ in range(REPLAY_WINDOW):
        opener.control(key_expr, payload, signer.seal(key_expr, payload))
    with pytest.raises(WireError, match="a replay"):
        opener.control(key_expr, payload, old)


def test_a_process_opens_nothing_sealed_before_it_started_nor_after_it_ended():
    """A `lost` sealed for a node's old process does not reach the new one (a replay of it
    would stop the very process that replaced it); a process the coordinator dropped gets none."""
    signer, keys = run_of(1)
    key_expr, payload = KEYS.run_control(), p.Lost(node="src").encode()
    before = signer.seal(key_expr, payload)
    newer, key = Process(), new_key()
    signer.add(newer, key)
    with pytest.raises(WireError, match="did not seal"):
        p.ControlOpener(key).control(key_expr, payload, before)
    p.ControlOpener(key).control(key_expr, payload, signer.seal(key_expr, payload))
    signer.drop(newer)
    with pytest.raises(WireError, match="did not seal"):
        p.ControlOpener(key).control(key_expr, payload, signer.seal(key_expr, payload))


def test_a_process_without_a_key_takes_no_control():
    signer, _ = run_of(1)
    signer.add(Process(), None)  # as origin.Senders: a process started without a key is never trusted
    key_expr, payload = KEYS.run_control(), p.Stop().encode()
    with pytest.raises(WireError, match="this process has no key"):
        p.ControlOpener(None).control(key_expr, payload, signer.seal(key_expr, payload))


def test_a_reply_opens_only_for_the_question_it_answers():
    """ctl/start and status/finished: a reply covers the nonce of its question, so an old answer
    (a `finished` saying this node's reports are all in) replayed to a new question is refused."""
    signer, keys = run_of(2)
    key_expr, payload = KEYS.start(), p.Start(t0=T0, end=END, values=True).encode()
    opener, nonce = p.ControlOpener(keys[1]), p.new_nonce()
    seal = signer.seal_reply(key_expr, payload, nonce)
    assert opener.reply(p.Start, key_expr, payload, seal, nonce) == p.Start(t0=T0, end=END, values=True)
    assert opener.reply(p.Start, key_expr, payload, seal, nonce) == p.Start(t0=T0, end=END, values=True)
    with pytest.raises(WireError, match="did not seal"):
        opener.reply(p.Start, key_expr, payload, seal, p.new_nonce())
    with pytest.raises(WireError, match="without the coordinator's seal"):
        opener.reply(p.Start, key_expr, payload, signer.seal_reply(key_expr, payload, None), nonce)
    finished = p.Finished(nodes=("cam",), complete=("cam",), restarting=(), handed_over=()).encode()
    with pytest.raises(WireError, match="did not seal"):  # a reply on one key is no reply on another
        opener.reply(p.Finished, KEYS.finished(), finished, signer.seal_reply(key_expr, finished, nonce), nonce)
    with pytest.raises(WireError, match="status/finished knows no op 'start'"):
        opener.reply(p.Finished, key_expr, payload, seal, nonce)


def test_seals_travel_as_zenoh_attachments_of_puts_queries_and_replies(session):
    """The wiring's Zenoh side: a sealed put's attachment reaches the subscriber, a question's
    nonce reaches the queryable, and the sealed reply's attachment reaches the querier."""
    keys = KeySpace(f"seal-{id(session)}")
    signer, (key,) = run_of(1)
    opener, got = p.ControlOpener(key), queue.SimpleQueue()
    subscriber = session.declare_subscriber(keys.run_control(), lambda sample: got.put(
        opener.control(str(sample.key_expr), sample.payload.to_bytes(), sample.attachment)))
    start = p.Start(t0=T0, end=END, values=True).encode()
    queryable = session.declare_queryable(keys.start(), lambda query: query.reply(
        keys.start(), start, attachment=signer.seal_reply(keys.start(), start, query.attachment.to_bytes())))
    try:
        payload = p.Grant(until=7).encode()
        session.put(keys.run_control(), payload, attachment=signer.seal(keys.run_control(), payload))
        assert got.get(timeout=10) == p.Grant(until=7)
        nonce = p.new_nonce()
        replies = [r.ok for r in session.get(keys.start(), attachment=nonce, timeout=10) if r.ok is not None]
        assert [opener.reply(p.Start, str(r.key_expr), r.payload.to_bytes(), r.attachment, nonce) for r in replies] \
            == [p.Start(t0=T0, end=END, values=True)]
    finally:
        subscriber.undeclare()
        queryable.undeclare()


def test_the_info_of_a_daemon_of_another_protocol_says_which_and_the_retriever_it_runs():
    """What a coordinator tells its user of such a worker (deploy/discovery.py: the version to install alike)."""
    with pytest.raises(p.OtherProtocolReply) as refused:
        p.decode_reply(control("info", {"protocol": 3, "packages": {"retriever": "9.9"}, "anything": "new"}),
                       p.DaemonOp.INFO)
    assert (refused.value.protocol, refused.value.retriever) == (3, "9.9")
    assert isinstance(refused.value, WireError)
    for packages in ({}, {"retriever": 9}, "9.9"):  # it says no version of Retriever it runs
        with pytest.raises(p.OtherProtocolReply) as refused:
            p.decode_reply(control("info", {"protocol": 1, "packages": packages}), p.DaemonOp.INFO)
        assert (refused.value.protocol, refused.value.retriever) == (1, None)


# ---------------------------------------------------------------------------------------------
# Reports and statuses as the coordinator reads them (from test_wire.py, where their decoders were)
# ---------------------------------------------------------------------------------------------
def test_report_round_trip():
    enc = WireEncoder()
    event = enc.data((7, 0), 3, (8, 0), "cam", "frame", np.arange(4))
    record = ((7, 0), {"x": [["src", "out", 1]]}, [["cam", "frame", 3]], "ok", None, 11, 12)
    report = p.Report.decode(p.Report(node="cam", records=(record,), events=((123, event),)).encode(), node="cam")
    assert report.node == "cam"
    assert list(report.records) == [((7, 0), {"x": (("src", "out", 1),)}, (("cam", "frame", 3),), "ok", None, 11, 12)]
    assert list(report.events) == [(123, event)]
    with pytest.raises(WireError, match="a report of cam arrived on the key of other"):
        p.Report.decode(p.Report(node="cam", records=(record,), events=()).encode(), node="other")
    with pytest.raises(WireError, match="wall_ns, data message"):
        p.Report.decode(msgpack.packb([2, "cam", [], [[1, 2.5]]]), node="cam")


@pytest.mark.parametrize("record", [
    [[7, 0], {"x": [["a"]]}, [], "ok", None, 1, 2],  # an event id that is not [node, port, seq]
    [[7, 0], {"x": [["src", "out", -1]]}, [], "ok", None, 1, 2],
    [[7, 0], {}, [["cam", "frame", "3"]], "ok", None, 1, 2],
    [[7, 0], {}, [], "finished", None, 1, 2],  # not a status a loop writes
    [[7, 0], {}, [], "ok", [1], 1, 2],  # detail: a map or nil
    [[7, 0], {}, [], "ok", None, "notanint", 2],
    [[7, 0], {1: []}, [], "ok", None, 1, 2],  # ports are names
    [[7, 0], {}, [], "ok", None, 1],
], ids=["short-id", "negative-seq", "seq-as-text", "status", "detail", "start", "port", "six-fields"])
def test_a_malformed_step_record_is_a_wire_error(record):
    with pytest.raises(WireError, match="a report of cam: record 0"):
        p.Report.decode(msgpack.packb([2, "cam", [record], []]), node="cam")


def test_a_status_of_an_unknown_state_is_a_wire_error():
    assert p.STATUS.decode(p.Done(node="cam", pid=PID, counts={}).encode()).NAME == "done"
    with pytest.raises(WireError, match="state"):
        p.STATUS.decode(today(2, "cam", "bogus-state", {}))
