"""coordinator/exits.py: in virtual time, the records a zenoh run reports wait until no step's
sys.exit(0) can cut them off, and the earliest exit cuts what ran past it, as in-process."""

from __future__ import annotations

from collections import Counter
from types import SimpleNamespace

from retriever import Pipeline, Rate
from retriever.backends.base import output_ports
from retriever.backends.zenoh.coordinator import Hosting, RunBook, RunControl, assemble
from retriever.backends.zenoh.coordinator.exits import ExitCut
from retriever.backends.zenoh.protocol import End, Exit
from retriever.backends.zenoh.wire import KeySpace
from retriever.trace import Trace

from .semantics_flows import EndsAt

MS = 1_000_000
RANK = {"watcher": 0, "ender": 1, "feeder": 2}  # a tag's ticks: the watcher's, the ender's, the feeder's


def record(node: str, t_ms: int, m: int = 0, produced: tuple = ()) -> tuple:
    return (node, (t_ms * MS, m), {}, produced, "ok", None, 0, 0)


def event(node: str, seq: int, t_ms: int, m: int = 1) -> tuple:
    return ((t_ms * MS, m), node, "value", seq, seq, 0)


def cut_taking() -> tuple[ExitCut, list, list]:
    steps, events = [], []
    cut = ExitCut(RANK)
    cut.hand_to(steps.append, events.append)
    return cut, steps, events


def test_the_earliest_exit_is_by_tag_then_by_tie_order():
    cut = ExitCut(RANK)
    assert cut.earliest({}) is None
    exits = {"feeder": ((700 * MS, 0), None), "ender": ((700 * MS, 0), None), "watcher": ((800 * MS, 0), None)}
    assert cut.earliest(exits) == ((700 * MS, 0), "ender")
    assert cut.earliest({**exits, "watcher": ((700 * MS, 0), None)}) == ((700 * MS, 0), "watcher")


def test_records_wait_until_every_node_passed_them_then_go_on_as_they_came():
    cut, steps, events = cut_taking()
    cut.step(record("feeder", 0, produced=(("feeder", "value", 0),)))
    cut.event(event("feeder", 0, 0))
    cut.event(((200 * MS, 0), "feeder", "value", 1, 1, 0))  # a LET output, due later
    assert steps == events == []
    cut.final_below(50 * MS)
    assert steps == [record("feeder", 0, produced=(("feeder", "value", 0),))]
    assert events == [event("feeder", 0, 0)]
    cut.step(record("feeder", 10))  # below the barrier passed: at once
    assert steps[-1] == record("feeder", 10)
    cut.final_below(250 * MS)
    assert events[-1][0] == (200 * MS, 0)


def test_the_exit_cuts_the_ticks_after_it_and_their_events_but_not_those_before_it():
    cut, steps, events = cut_taking()
    for r in [record("watcher", 700, produced=(("watcher", "value", 7),)), record("ender", 700),
              record("feeder", 700, produced=(("feeder", "value", 7),)), record("watcher", 700, 1),
              record("feeder", 650, produced=(("feeder", "value", 6),)), record("watcher", 750)]:
        cut.step(r)
    # the feeder's tick at 650 ms made its event past the exit (as a flow with latency does)
    for e in [event("watcher", 7, 700), event("feeder", 7, 700), ((900 * MS, 0), "feeder", "value", 6, 6, 0)]:
        cut.event(e)
    cut.settle(((700 * MS, 0), "ender"))
    assert sorted((node, tag[0] // MS, tag[1]) for node, tag, *_ in steps) == [
        ("ender", 700, 0), ("feeder", 650, 0), ("watcher", 700, 0)]
    assert sorted(e[1:4] for e in events) == [("feeder", "value", 6), ("watcher", "value", 7)]
    cut.step(record("feeder", 800))  # the run is over: whatever still comes is taken
    assert steps[-1] == record("feeder", 800)


def test_a_run_without_an_exit_takes_all_that_is_held_at_its_end():
    cut, steps, events = cut_taking()
    cut.step(record("feeder", 950))
    cut.event(event("feeder", 9, 950))
    cut.settle(None)
    assert (len(steps), len(events)) == (1, 1)


class SeenControl(RunControl):
    """The coordinator's puts, kept (no hub)."""

    def __init__(self):
        super().__init__(None, KeySpace("exits"))
        self.records = []

    def put(self, record) -> None:
        self.records.append(record)


def test_in_virtual_time_the_run_ends_at_the_earliest_exit_whichever_is_heard_first(tmp_path):
    """Two nodes exit in one window; the coordinator hears of the later one first: End at its
    time (+ 1 ns: its tag's ticks still run), then at the earlier one's, which ended the run."""
    with Pipeline("two_exits") as pipe:
        EndsAt(at=9).configure(name="late") @ Rate(10)
        EndsAt(at=3).configure(name="early") @ Rate(10)
    graph = pipe.compile()
    trace = Trace(keep="trace")
    trace.ports = output_ports(graph)
    book = RunBook(graph, Counter())
    processes = {"late": SimpleNamespace(pid=40_001), "early": SimpleNamespace(pid=40_002)}
    book.processes.workers, book.processes.state, book.t0 = dict(processes), {n: "ready" for n in processes}, 0
    control = SeenControl()
    parts = assemble(book, trace, tmp_path, control, Hosting(), virtual_time=True)
    for node, t_ms in (("late", 800), ("early", 200)):
        process, tag = processes[node], (t_ms * MS, 0)
        book.ending.exit_recorded[node] = (tag, process)  # (its step record came first)
        parts.inbox.handle((control.keys.node_status(node), Exit(node=node, pid=process.pid, tag=tag).encode(),
                            process))
    assert [r.at for r in control.records if isinstance(r, End)] == [800 * MS + 1, 200 * MS + 1]
    assert book.ending.ended_by == "early"
