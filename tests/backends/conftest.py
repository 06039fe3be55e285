"""The backend conformance suite runs every test once per backend.

Tests take the ``backend`` fixture and pass it on: ``pipe.run(duration=..., backend=backend)``.
The in-process virtual-time backend is the reference semantics (docs/semantics.md, worked examples
§10); every other backend must produce the same traces. Add a backend here when it lands.
"""

from bisect import bisect_right

import pytest

from retriever import ActionChunking, BackendError, Exact, Latest, LatestDistinct, Pipeline, Queue, Window
from retriever.sync import chunk_rows
from retriever.time import exact_rational
from retriever.trace import STEP_STATUSES

# The virtual-time suite. Real-time backends run test_let_conformance.py instead: in real time a
# flow without latency stamps outputs when it finishes (docs/semantics.md), so only LET graphs have a
# trace fixed in advance; those must equal inproc's exactly. "zenoh" here is the Zenoh runtime in
# lockstep virtual time (virtual_time=True: one process per flow, the trace inproc's), each run
# also compared with an inproc run of the same pipeline.
# "zenoh-grouped": the same, every flow in one worker process (configure(process=): one thread
# steps them all, events by reference; one with on_error="restart" restarts in place there).
BACKENDS = ["inproc", "zenoh", "zenoh-grouped"]


@pytest.fixture(params=BACKENDS)
def backend(request, monkeypatch) -> str:
    if request.param.startswith("zenoh"):
        monkeypatch.setattr(Pipeline, "run", _in_virtual_time(Pipeline.run, grouped=request.param == "zenoh-grouped"))
        return "zenoh"
    return request.param


def _in_virtual_time(run, grouped: bool = False):
    """``Pipeline.run`` that runs ``backend="zenoh"`` in virtual time (``grouped``: its flows in
    one process), then the same pipeline on inproc (reset, its flows fresh: the zenoh run
    stepped copies in other processes), and requires the identical trace."""

    def run_virtual(pipe, duration=None, backend=None, **options):
        if backend != "zenoh":
            return run(pipe, duration, backend, **options)
        if pipe.now > 0:  # a run of its own processes, once; what goes on runs on the inproc reference
            pytest.skip("a zenoh run cannot be continued (pipe.run twice): its processes are gone")
        if grouped:
            nodes = pipe.compile().nodes.values()
            for node in nodes:
                node.flow.configure(process="all")
        try:
            trace = run(pipe, duration, "zenoh", virtual_time=True, quiet=True, **options)
            if grouped:
                processes = len(set(pipe.session.worker_pids().values()))
                assert processes == 1, processes
        except BackendError as e:  # a capability it says it lacks, before anything started
            if "cannot run the instantaneous cycle" in str(e):
                pytest.skip("zenoh in virtual time does not run instantaneous cycles")
            raise
        pipe.reset()
        reference = run(pipe, duration, "inproc", **options)
        difference = trace.first_difference(reference)
        assert difference is None, f"zenoh in virtual time differs from inproc: {difference}"
        assert trace.digest() == reference.digest()
        return trace

    return run_virtual


def _check_trace(pipe, trace) -> None:
    """Invariants every trace must satisfy (docs/semantics.md), whatever the pipeline:

    - event ids (node, port, seq) are unique; per port, seq runs 0, 1, 2, … in tag order;
    - a step's produced events carry (t, m + 1), or (t + latency, 0) for a flow with latency;
    - sampling rule: every consumed event exists and has tag ≤ τ (time + delay ≤ τ's time on a
      delayed edge);
    - one step record per node and tag (several triggers at one tag make one tick);
    - a skipped step consumed and produced nothing;
    - clocks: the node ticked at exactly its Rate ticks (t < now) and the tags of the events on
      its trigger ports (§3);
    - sampling (§4): each step consumed exactly what a brute-force model of its ports' policies
      selects from the events with tag ≤ τ; skipped exactly when a required port is MISSING.
    """
    graph = pipe.compile()
    by_id = {}
    for ev in trace.events:
        assert ev.id not in by_id, f"duplicate event id {ev.id}"
        by_id[ev.id] = ev
    ports = {}
    for ev in trace.canonical()[0]:
        ports.setdefault((ev.node, ev.port), []).append(ev.seq)
    for key, seqs in ports.items():
        assert seqs == list(range(len(seqs))), f"{key}: seqs {seqs[:10]}… are not 0, 1, 2, … in tag order"
    delays = {(e.src, e.src_port, e.dst, e.dst_port): e.delay_ns for e in graph.edges}
    seen = set()
    for rec in trace.steps:
        assert (rec.node, rec.tag) not in seen, f"two step records for {rec.node} at {rec.tag}"
        seen.add((rec.node, rec.tag))
        assert rec.status in STEP_STATUSES, rec  # real time adds incomplete, late, overrun
        if rec.status == "skipped":
            assert rec.consumed == {} and rec.produced == (), rec
        latency = graph.nodes[rec.node].settings.latency_ns
        expected = (rec.tag[0] + latency, 0) if latency else (rec.tag[0], rec.tag[1] + 1)
        for eid in rec.produced:
            assert eid in by_id, f"{rec}: produced {eid} is not in the trace"
            assert by_id[eid].tag == expected, f"{rec}: produced {eid} at {by_id[eid].tag}, expected {expected}"
        for port, ids in rec.consumed.items():
            for eid in ids:
                assert eid in by_id, f"{rec}: consumed {eid} is not in the trace"
                ev = by_id[eid]
                delay = delays[(ev.node, ev.port, rec.node, port)]
                if delay:  # DESIGN shifts a delayed stream in time; its microstep there is not pinned
                    assert ev.tag[0] + delay <= rec.tag[0], f"{rec}: consumed {eid} from {ev.tag} (+{delay} ns)"
                else:
                    assert ev.tag <= rec.tag, f"{rec}: consumed {eid} from {ev.tag}, after τ"
    _check_clocks(pipe, trace, graph)
    _check_sampling(pipe, trace, graph)


def _expected_ticks(pipe, trace, graph, now_ns):
    """Rate ticks with t < now, plus the arrival tag of every event on a trigger port."""
    exact, delayed = set(), set()
    for node in graph.nodes.values():
        clock = node.clock
        if clock.hz is not None:
            k = 0
            while (t := clock.tick_time(k)) < now_ns:
                exact.add((node.id, (t, 0)))
                k += 1
    for e in graph.edges:
        if not graph.nodes[e.dst].triggers_on(e.dst_port):
            continue
        for ev in trace.events:
            if ev.node == e.src and ev.port == e.src_port and ev.tag[0] + e.delay_ns < now_ns:
                if e.delay_ns:
                    delayed.add((e.dst, ev.tag[0] + e.delay_ns))
                else:
                    exact.add((e.dst, ev.tag))
    return exact, delayed


def _check_clocks(pipe, trace, graph) -> None:
    now_ns = round(pipe.now * 1e9)
    exact, delayed = _expected_ticks(pipe, trace, graph, now_ns)
    actual = {(s.node, s.tag) for s in trace.steps}
    missing = exact - actual
    assert not missing, f"ticks that should have happened: {sorted(missing)[:5]}"
    extra = {(n, tag) for n, tag in actual - exact if (n, tag[0]) not in delayed}
    assert not extra, f"ticks no clock or trigger event explains: {sorted(extra)[:5]}"
    ticked_at = {(n, tag[0]) for n, tag in actual}
    assert delayed <= ticked_at, f"delayed trigger events with no tick: {sorted(delayed - ticked_at)[:5]}"


class _PortModel:
    """A brute-force model of one input port: what its policy must hand each tick (DESIGN §4)."""

    def __init__(self, edges, events):
        self.policy = edges[0].sync
        self.delayed = any(e.delay_ns for e in edges)
        delay = {(e.src, e.src_port): e.delay_ns for e in edges}
        entries = []
        for ev in events:
            d = delay.get((ev.node, ev.port))
            if d is not None:
                arrival = (ev.tag[0] + d, ev.tag[1])  # order of a merged, shifted stream
                entries.append((arrival, ev.node, ev.port, ev.seq, ev))
        entries.sort(key=lambda x: x[:4])
        self.entries = entries
        self.keys = [x[0] for x in entries]
        self.consumed = set()  # Queue: ids consumed (or dropped) by earlier ticks
        self.last = None  # LatestDistinct: id consumed last

    def ambiguous(self, tau):
        """On a delayed edge, DESIGN does not pin the microstep of a shifted event at τ's time."""
        return self.delayed and any(k[0] == tau[0] for k in self.keys)

    def select(self, tau):
        """(ids or None for MISSING, dropped)."""
        h = self.entries[:bisect_right(self.keys, tau)]
        p = self.policy
        if isinstance(p, Latest):
            if not h or (p.staleness is not None and tau[0] - h[-1][0][0] > round(p.staleness * 1e9)):
                return None, 0
            return (h[-1][4].id,), 0
        if isinstance(p, LatestDistinct):
            if not h or h[-1][4].id == self.last:
                return None, 0
            return (h[-1][4].id,), 0
        if isinstance(p, Window):
            if p.duration is not None:
                h = [x for x in h if x[0][0] >= tau[0] - round(p.duration * 1e9)]
            if p.buffer_size is not None:
                h = h[-p.buffer_size:]
            return tuple(x[4].id for x in h), 0
        if isinstance(p, Queue):
            new = [x[4].id for x in h if x[4].id not in self.consumed]
            dropped = 0
            if p.maxsize is not None and len(new) > p.maxsize:
                dropped = len(new) - p.maxsize
            return tuple(new), dropped
        if isinstance(p, Exact):
            if not h or tau[0] - h[-1][0][0] > round(p.tolerance * 1e9):
                return None, 0
            best = [x for x in h if x[0][0] == h[-1][0][0]]
            return (best[0][4].id,), 0
        if isinstance(p, ActionChunking):
            for x in reversed(h):
                rows, t0 = chunk_rows(x[4].value, x[0][0])
                if t0 <= tau[0]:
                    break
            else:
                return None, 0
            length = len(rows) if p.chunk_steps is None else min(p.chunk_steps, len(rows))
            hz = exact_rational(p.control_hz)
            row = (tau[0] - t0) * hz.numerator // (1_000_000_000 * hz.denominator)
            if length == 0 or (row >= length and p.on_exhausted == "missing"):
                return None, 0
            return (x[4].id,), 0
        raise AssertionError(f"no model for {p!r}")

    def commit(self, ids):
        if isinstance(self.policy, Queue):
            self.consumed.update(ids)
        elif isinstance(self.policy, LatestDistinct) and ids:
            self.last = ids[-1]


def _check_sampling(pipe, trace, graph) -> None:
    """Every step consumed exactly what its ports' policies select from the events with tag ≤ τ;
    a tick is skipped exactly when a required port is MISSING; Queue drops are counted."""
    by_port = {}
    for e in graph.edges:
        by_port.setdefault((e.dst, e.dst_port), []).append(e)
    models = {key: _PortModel(edges, trace.events) for key, edges in by_port.items()}
    for rec in trace.canonical()[1]:
        node = graph.nodes[rec.node]
        selected, missing_required, unsure = {}, set(), set()
        for port, spec in node.inputs.items():
            model = models.get((rec.node, port))
            if model is None:
                if spec.required:
                    missing_required.add(port)
                continue
            ids, dropped = model.select(rec.tag)
            selected[port] = (model, ids, dropped)
            if spec.required and model.ambiguous(rec.tag):
                unsure.add(port)
            elif ids is None and spec.required:
                missing_required.add(port)
        if rec.status == "skipped":
            missing = set(rec.detail["missing"])
            assert missing and missing_required <= missing <= missing_required | unsure, rec
            continue
        assert not missing_required, f"{rec}: should have been skipped, missing {sorted(missing_required)}"
        for port, (model, ids, dropped) in selected.items():
            if model.ambiguous(rec.tag):
                model.commit(rec.consumed.get(port, ()))
                continue
            if isinstance(model.policy, Queue) and dropped:
                kept = ids[dropped:]
                got = rec.consumed.get(port)
                assert got == kept, f"{rec}: {port} consumed {got}, expected {kept}"
                assert (rec.detail or {}).get(port) == dropped, f"{rec}: {port} should count {dropped} dropped"
            else:
                assert rec.consumed.get(port, None if ids is None else ()) == ids, \
                    f"{rec}: {port} consumed {rec.consumed.get(port)}, expected {ids}"
            model.commit(ids or ())


@pytest.fixture
def check_trace():
    """``check_trace(pipe, trace)`` asserts the invariants every trace satisfies."""
    return _check_trace
