"""InprocSession.inputs_at: what a node's tick is handed, read before it runs, consuming nothing."""

from __future__ import annotations

from dataclasses import dataclass

from retriever import Flow, Latest, LatestDistinct, Pipeline, Queue, Rate, Window, io
from retriever.backends.inproc import InprocSession


@io
@dataclass
class Count:
    n: int


class Counter(Flow[None, Count]):
    def __init__(self):
        self.n = 0

    def step(self) -> Count:
        self.n += 1
        return Count(self.n)


@io
@dataclass
class Mixed:
    newest: int
    queued: list
    distinct: int | None = None
    window: list | None = None
    unfed: int = -1


@io
@dataclass
class Plain:
    n: int
    m: int = 0


class Sink(Flow):
    def step(self, inp) -> None:
        return None


class MixedSink(Sink, Flow[Mixed, None]):
    pass


class PlainSink(Sink, Flow[Plain, None]):
    pass


def pipeline() -> Pipeline:
    with Pipeline("peek") as pipe:
        fast = Counter().named("fast") @ Rate(100)
        slow = Counter().named("slow") @ Rate(7)
        mixed = MixedSink().named("mixed") @ Rate(30)
        plain = PlainSink().named("plain") @ Rate(30, offset=0.005)  # all Latest: a compiled tick
        fast.then(mixed, map={"n": "newest"})
        fast.then(mixed, map={"n": "queued"}, sync=Queue(maxsize=2))
        slow.then(mixed, map={"n": "distinct"}, sync=LatestDistinct())
        fast.then(mixed, map={"n": "window"}, sync=Window(buffer_size=3))
        fast.then(plain, map={"n": "n"}, sync=Latest())
        slow.then(plain, map={"n": "m"}, sync=Latest())
    return pipe


def test_each_tick_consumes_what_inputs_at_read_before_it_and_reading_changes_nothing():
    plain_run = InprocSession(pipeline().compile())
    plain_run.advance(1_000_000_000)

    session = InprocSession(pipeline().compile())
    read = {"mixed": {}, "plain": {}}
    for k in range(30):
        if k == 10:
            session.stats()  # the compiled ticks hand their view of the buffers back, then go on trimming them
        for node, offset in (("mixed", 0), ("plain", 5_000_000)):
            t = offset + k * 1_000_000_000 // 30
            session.advance(t)
            values, consumed, missing = session.inputs_at(node, (t, 0))
            assert session.inputs_at(node, (t, 0)) == (values, consumed, missing)  # (nothing consumed)
            read[node][(t, 0)] = (values, consumed, missing)
    session.advance(1_000_000_000)

    assert session.trace.digest() == plain_run.trace.digest()
    values = {event.id: event.value for event in session.trace.events}
    for node, ticks in read.items():
        records = {record.tag: record for record in session.trace.steps_of(node)}
        assert sorted(records) == sorted(ticks)
        for tag, (seen, consumed, missing) in ticks.items():
            record = records[tag]
            if missing is not None:
                assert (record.status, record.detail) == ("skipped", {"missing": missing})
                continue
            assert record.status == "ok" and record.consumed == consumed
            for port, ids in consumed.items():
                got = [values[i] for i in ids]
                assert (got if isinstance(seen[port], list) else got[0]) == seen[port]
    assert read["mixed"][(0, 0)][2] == ["newest"]  # nothing yet at 0: the tick is skipped
    assert read["mixed"][(33_333_333, 0)][0] == {"newest": 4, "queued": [3, 4], "distinct": 1,
                                                  "window": [2, 3, 4], "unfed": -1}
    # slow's first count was consumed at 33 ms: LatestDistinct has nothing new (None, its fallback)
    assert read["mixed"][(100_000_000, 0)][0] == {"newest": 10, "queued": [9, 10], "distinct": None,
                                                   "window": [8, 9, 10], "unfed": -1}
