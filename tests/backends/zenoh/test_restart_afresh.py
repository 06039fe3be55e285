"""A flow started afresh after its process died (on_error="restart"; node/handover.py), piece by
piece: a real NodeLoop driven by hand (the test thread plays Zenoh's receiving thread and the
coordinator), and the log records a replay reads, attacked. The whole
story with real processes killed by SIGKILL is in test_lifecycle.py. No test here waits on time.
"""

from __future__ import annotations

import msgpack
import pytest

from retriever import LogError, Pipeline, Queue, Rate, Trigger, read_log
from retriever.backends.zenoh.node import CONTROL, DATA, EARLY_SEQS_MAX, NEVER
from retriever.backends.zenoh.protocol import RESTART_SEQ_GAP
from retriever.backends.zenoh.node import handover
from retriever.backends.zenoh.protocol import RUN_CONTROL
from retriever.backends.zenoh.wire import WIRE_VERSION, Progress, WireEncoder, WireError
from retriever.backends.zenoh.worker.build import build_loop
from retriever.log import format as fmt
from retriever.log.writer import LogFile, LogWriter

from .semantics_flows import Ticker, WhereRun
from .specs import run_spec

MS = 1_000_000
STREAM = ("counter", "value")
FIRST = RESTART_SEQ_GAP + 7  # the seq a restarted counter's stream goes on from, in these tests


@pytest.fixture
def loop(session):
    """The loop of ``where`` (Trigger on x, a Queue of counter's values), as run() leaves it."""
    with Pipeline("afresh_by_hand") as pipe:
        src = Ticker().configure(name="counter") @ Rate(hz=20)
        src.then(WhereRun().configure(name="where", on_error="restart") @ Trigger("x"), sync=Queue(maxsize=100))
    loop = build_loop(run_spec(pipe.compile().to_ir().doc, "afresh-test"), "where", session)
    loop.declare()
    loop.run_clock.t0, loop.run_clock.end, loop.run_clock.started = 0, 1 << 62, True  # as run() sets them
    yield loop
    loop.undeclare()


def data(seq: int, t_ms: int) -> tuple:
    message = WireEncoder().data((t_ms * MS, 0), seq, (t_ms * MS + 1, 0), "counter", "value", seq)
    return (DATA, STREAM, message)


def control(op: str, args: dict) -> tuple:
    """A control message as the loop's subscriber queues it: decoded, or the WireError refusing it."""
    try:
        return (CONTROL, None, RUN_CONTROL.decode(msgpack.packb([WIRE_VERSION, op, args])))
    except WireError as e:
        return (CONTROL, None, e)


def tick_all(loop) -> None:
    """Run every tick that is ready (the inputs here are complete up to their tags)."""
    while loop.try_tick(1 << 61) == "ticked":
        pass


def consumed(record) -> list[int]:
    return [eid[2] for ids in record[1].values() for eid in ids]


# ---------------------------------------------------------------------------------------------
# A consumer of a producer that died and was restarted
# ---------------------------------------------------------------------------------------------
def test_a_consumer_gives_up_the_dead_producers_missing_seqs_and_takes_the_new_stream_on(loop):
    for seq, t in ((0, 50), (1, 100)):
        loop.handle(data(seq, t))
    loop.handle(control("lost", {"node": "counter"}))
    loop.handle(data(FIRST + 1, 300))  # the new process's second event overtook the coordinator's word
    loop.handle(data(3, 150))  # the dead process's: seq 2 never came
    loop.handle(control("restarted", {"node": "counter", "seqs": {"value": FIRST}, "values": True}))
    loop.handle(data(FIRST, 250))
    loop.handle(data(2, 120))  # the dead process's missing one, too late: ignored, not garbage
    tick_all(loop)
    assert [consumed(r) for r in loop.reports.records] == [[0], [1], [FIRST], [FIRST + 1]]
    assert [r[0][0] // MS for r in loop.reports.records] == [50, 100, 250, 300]
    # the next record says which seqs it gave up, so that a replay withholds those
    assert loop.reports.records[0][4] == {"restart_gap": {"x": [["counter", "value", 2, FIRST]]}}
    assert loop.counts["garbage"] == 0 and loop.streams.expect[STREAM] == FIRST + 2


def test_without_word_of_a_lost_producer_a_seq_that_far_ahead_is_garbage(loop):
    loop.handle(data(0, 50))
    loop.handle(data(EARLY_SEQS_MAX + 5, 300))  # a seq from the future: an insider's nonsense
    assert loop.counts["garbage"] == 1 and not loop.streams.early[STREAM]


@pytest.mark.parametrize("seqs", [{"value": 1}, {"value": 2 + RESTART_SEQ_GAP + EARLY_SEQS_MAX + 1}, ["value", 9]])
def test_a_restart_where_the_coordinator_would_not_put_it_is_refused(loop, seqs):
    """Below seqs taken, or further ahead than a dead process's unreported events reach."""
    for seq, t in ((0, 50), (1, 100)):
        loop.handle(data(seq, t))
    loop.handle(control("lost", {"node": "counter"}))
    loop.handle(control("restarted", {"node": "counter", "seqs": seqs, "values": True}))
    assert loop.counts["garbage"] == 1 and loop.streams.expect[STREAM] == 2 and "restart_gap" not in loop.notes.detail
    loop.handle(data(2, 150))  # the stream goes on
    assert loop.streams.expect[STREAM] == 3


def test_a_restart_of_a_producer_not_said_lost_is_refused(loop):
    """A forged one would cut this consumer off a live producer for the rest of the run."""
    loop.handle(data(0, 50))
    loop.handle(control("restarted", {"node": "counter", "seqs": {"value": FIRST}, "values": True}))
    loop.handle(data(1, 100))
    assert loop.counts["garbage"] == 1 and loop.streams.expect[STREAM] == 2


def test_a_restart_a_fresh_process_caught_up_with_is_ignored(loop):
    """Its inputs were taken on from the producer's own answer (it restarted too): nothing to do."""
    handover.sync_inputs(loop.streams, {"counter": Progress((400 * MS, 0), "counter", {"value": FIRST - 1})})
    loop.handle(data(FIRST, 450))
    loop.handle(control("restarted", {"node": "counter", "seqs": {"value": FIRST}, "values": True}))
    assert loop.counts["garbage"] == 0 and loop.streams.expect[STREAM] == FIRST + 1 and not loop.notes.detail


def test_word_of_another_nodes_restart_changes_nothing(loop):
    loop.handle(data(0, 50))
    loop.handle(control("lost", {"node": "where"}))
    loop.handle(control("restarted", {"node": "somebody", "seqs": {"value": FIRST}, "values": True}))
    assert loop.streams.expect[STREAM] == 1 and not loop.streams.lost_producers and loop.counts["garbage"] == 0


# ---------------------------------------------------------------------------------------------
# The new process of a flow whose process died
# ---------------------------------------------------------------------------------------------
def test_a_fresh_process_takes_each_stream_on_from_where_its_producer_stands(loop):
    handover.sync_inputs(loop.streams, {"counter": Progress((400 * MS, 0), "counter", {"value": 9})})
    assert loop.streams.frontiers[STREAM] == (400 * MS, 0)
    loop.handle(data(8, 380))  # published before the producer answered: not this process's
    loop.handle(data(10, 450))
    handover.start_fresh(loop, {"report": FIRST}, 0)
    tick_all(loop)
    (record,) = loop.reports.records
    assert consumed(record) == [10] and record[2] == (("where", "report", FIRST),)
    assert record[4] == {"restarted": {"seqs": {"report": FIRST}, "inputs": {"x": [["counter", "value", 10]]}}}
    assert loop.counts["garbage"] == 0


def test_a_fresh_process_waits_for_nothing_from_a_finished_producer(loop):
    handover.sync_inputs(loop.streams, {"counter": None})
    assert loop.streams.frontiers[STREAM] == NEVER and loop.streams.fresh_inputs == {}


# ---------------------------------------------------------------------------------------------
# What a replay reads of it, from a hostile log
# ---------------------------------------------------------------------------------------------
def step(detail: dict) -> bytes:
    return msgpack.packb(["where", 0, {}, [], "ok", detail, 0])


@pytest.mark.parametrize("detail", [
    {"restart_gap": []},
    {"restart_gap": {"x": [["counter", "value", 2]]}},
    {"restart_gap": {"x": [["counter", "value", -1, 5]]}},
    {"restart_gap": {"x": [["counter", 7, 2, 5]]}},
    {"restarted": {"seqs": {"report": 3}}},
    {"restarted": {"seqs": {"report": "3"}, "inputs": {}}},
    {"restarted": {"seqs": {}, "inputs": {"x": [["counter", "value"]]}}},
    {"restarted": ["seqs"]},
])
def test_a_malformed_restart_in_a_step_record_is_refused(detail):
    with pytest.raises(ValueError, match="its restart|its event ids"):
        fmt.decode_step(step(detail))


def test_a_well_formed_restart_in_a_step_record_is_read():
    detail = {"restart_gap": {"x": [["counter", "value", 2, FIRST]]},
              "restarted": {"seqs": {"report": FIRST}, "inputs": {"x": [["counter", "value", 10]]}}}
    assert fmt.decode_step(step(detail))[5] == detail


def _log_with_fault(path, fault: dict):
    with Pipeline("faulty_log") as pipe:
        Ticker().configure(name="counter") @ Rate(hz=20)
    writer = LogWriter(LogFile(path), pipe.compile(), backend="zenoh")
    writer.add_fault(fault)
    writer.close(pipe.trace, 0)
    return read_log(path)


def test_a_fault_record_reads_back_as_written(tmp_path):
    log = _log_with_fault(tmp_path / "run.mcap", {"kind": "process_lost", "node": "counter", "at_ns": 5,
                                                  "seqs": {"value": FIRST}, "lost_events": [["counter", "value", 3]]})
    assert log.faults == [{"kind": "process_lost", "node": "counter", "at_ns": "5", "seqs": {"value": FIRST},
                           "lost_events": [("counter", "value", 3)]}]


@pytest.mark.parametrize("fault", [
    {"node": "counter", "lost_events": "[[\"counter\", \"value\"]]"},
    {"node": "counter", "lost_events": "not json"},
    {"node": "counter", "seqs": "[1]"},
    {"lost_events": "[]"},
])
def test_a_malformed_fault_record_is_a_log_error(tmp_path, fault):
    log = _log_with_fault(tmp_path / "run.mcap", fault)
    with pytest.raises(LogError, match=r"the fault record retriever\.fault\.1 is malformed"):
        log.faults


def test_before_its_run_starts_a_loop_promises_nothing_past_the_start(session):
    """A restarted flow's process answers progress queries before run() (its end not known yet):
    with end 0 it answered NEVER, "finished", and a consumer ran on past ticks the flow still had
    to make (a trace that was not inproc's, events counted late)."""
    with Pipeline("before_run") as pipe:
        src = Ticker().configure(name="counter") @ Rate(20)
        src.then(WhereRun().configure(name="where") @ Trigger("x"), sync=Queue(maxsize=100))
    for node in ("counter", "where"):
        loop = build_loop(run_spec(pipe.compile().to_ir().doc, "before-run-test"), node, session)
        assert loop.outputs.frontier() == (0, 0), node


class _HeldPut:
    """A data publisher whose put is held while a new consumer asks the producer where its
    stream stands (Zenoh chose the put's subscribers when it began; a link to a cut-off host
    holds it for up to a lease): the answer given meanwhile, then the real put."""

    def __init__(self, session, keys, publisher):
        self.session, self.keys, self.publisher = session, keys, publisher
        self.answers: list[Progress] = []

    def put(self, message) -> None:
        from retriever.backends.zenoh.wire import decode_progress

        for reply in self.session.get(self.keys.progress("counter"), timeout=5.0):
            self.answers.append(decode_progress(reply.ok.payload.to_bytes(), expected="counter"))
        self.publisher.put(message)

    def undeclare(self) -> None:
        self.publisher.undeclare()


def test_a_seq_being_put_counts_as_sent_for_a_consumer_that_asks_meanwhile(session):
    """Issue 40: a consumer moved off a cut-off host subscribed while its producer's put was held
    by the full link to the old consumer, and was told the stream stood before that put's seq:
    it waited for a seq that had gone only to the cut-off host, every tick skipped to the end."""
    with Pipeline("held_put") as pipe:
        (Ticker().configure(name="counter") @ Rate(hz=20)).then(WhereRun().configure(name="where") @ Trigger("x"),
                                                                map={"value": "x"})
    producer = build_loop(run_spec(pipe.compile().to_ir().doc, "held-put-test"), "counter", session)
    producer.declare()
    try:
        producer.run_clock.t0, producer.run_clock.end, producer.run_clock.started = 0, 1 << 62, True
        held = producer.outputs.publishers["value"] = _HeldPut(session, producer.keys, producer.outputs.publishers["value"])
        producer.outputs.publish([((50 * MS, 0), "value", {"value": 0}, 0)])
        producer.outputs.publish([((100 * MS, 0), "value", {"value": 1}, 1)])
        assert [answer.sent.get("value") for answer in held.answers] == [0, 1]
    finally:
        producer.undeclare()
