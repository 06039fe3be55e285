"""The in-process backend: a discrete-event executor in virtual, superdense time.

This is the reference semantics every other backend is tested against (docs/semantics.md). Its
nodes are wired by the graph's plan (retriever.plan) and tick by the reference tick
(retriever.tick.run_tick), but where a generated tick is faster (below).

    pending ticks (heap of tags)                   one tick of node v at tag τ
    ┌──────────────────────────┐                   ┌───────────────────────────────────────┐
    │ (0,0): {cam, pol}        │  pop smallest τ   │ each input port: policy.select(H≤τ)   │
    │ (0,1): {ctrl}            │ ────────────────▶ │ MISSING on a required port → skipped  │
    │ (5000000,0): {ctrl}      │                   │ else commit, step(), emit outputs at  │
    └──────────────────────────┘                   │ (t+latency,0) or (t,m+1); schedule    │
                ▲                                  │ the trigger ticks they cause          │
                └──────────────────────────────────┴───────────────────────────────────────┘

Why ticks at one tag may run in any order: every output of a tick at τ carries a tag > τ, and a
tick reads only events with tag ≤ τ, so no tick at τ can see another's outputs. The trace is
compared in canonical order, so ``tie_break_seed`` (shuffling same-tag ticks) must not change it;
the property tests check exactly that.

What keeps the loop near the cost of the step calls (benchmarks/step_overhead.py):

- nodes whose clocks share one Rate schedule are one ``_RateGroup``, with one heap entry per tick;
  while nothing else is due at its ticks' times (one schedule in the graph, or between the ticks
  of a slower one), a group's ticks run back to back in one generated loop, off the heap, with
  the chain of Trigger flows they trigger inline;
- a tag's ticks run consumers first (each node before the nodes that feed it, where edges allow):
  then a rate group's tick finds every event a producer of the group sent it visible (the
  producer's tick at the same tag, whose outputs are not, comes later), and skips that test;
- ticks at ``(t, m + 1)`` are made only by ticks at ``(t, m)`` (zero-latency outputs on undelayed
  edges), so they wait in a list the loop runs microstep by microstep, never on the heap;
- nodes whose inputs are all ``Latest()`` run tick code generated for them (``inproc_ticks``),
  which does what ``tick.run_tick`` does with the node's ports, calling convention and consumers
  inlined: a rate group's in one function, a chain of Trigger flows' in one function; a tick
  known to be the only one at its tag (a chain's) skips the test of what is visible on inputs
  that one producer alone feeds;
- those ticks record each step as one compact record in the trace's tape, made into the
  step record and events when the trace is read.

``tick.run_tick`` is the reference; tests/backends/test_inproc_ticks.py holds the two to the same
trace. The session's parts: ``_Agenda``, the ticks due; ``_Recorder``, what became of each tick
(records, delivered events, the on_error decision acted on); the loop (``_advance``); and the
tick functions (``CompiledTicks``, backends/inproc_compiled.py): the generated ticks, which read
the session through one public surface, ``inproc_ticks.Host``, and the reference elsewhere.
"""

from __future__ import annotations

import atexit
import dataclasses
import random
import threading
import warnings
import weakref
from heapq import heappop, heappush
from time import time_ns
from typing import Any, Callable

import numpy as np

from ..codec import packb
from ..errors import BackendError, CausalityError, CodecError, ReplayedError, RetrieverWarning, RunEnded, SetupError
from ..flow.core import Flow, make_invoker, make_output_reader, set_up, tear_down, with_step_detail
from ..flow.read_only import make_read_only
from ..flow.burst import Burst
from ..graph import Graph, Node
from ..plan import NodePlan, bind_inputs, plan_graph, tie_order
from ..sync import PortBuffer
from ..tick import (Decision, RestartBudget, decide, ending, error_outcome, error_text, exit_outcome, run_tick,
                    select_inputs, skipped_outcome)
from ..time import format_tag
from ..trace import StepStatus, holding_full_collections
from .base import Backend, NodeStats, Session
from .inproc_compiled import CompiledTicks

#: sessions whose flows are set up: torn down at the program's exit at the latest
_OPEN: weakref.WeakSet = weakref.WeakSet()


@atexit.register
def _tear_down_open_sessions() -> None:
    for session in list(_OPEN):
        session.close()


#: the types of output values the codec always encodes (None: no event). An output of another type
#: is checked before it is recorded, so that a step returning what the trace cannot hold fails at
#: that step, as it does on a real-time backend, and not at the end in ``trace.digest()``; these
#: need no check, which keeps it off the hot path (benchmarks/step_overhead.py)
PLAIN_TYPES = frozenset({int, float, str, bytes, bool, type(None)})
_OK = StepStatus.OK


def _encodes_surely(value: Any) -> bool:
    """Whether the codec is sure to encode ``value``, seen without encoding it: plain values and
    arrays of a non-object dtype, inside lists, tuples and dicts. False means: ask the codec."""
    kind = type(value)
    if kind in PLAIN_TYPES:
        return True
    if kind is np.ndarray:
        return not value.dtype.hasobject
    if kind is list or kind is tuple:
        return all(map(_encodes_surely, value))
    if kind is dict:
        return all(map(_encodes_surely, value)) and all(map(_encodes_surely, value.values()))
    return False


class NodeRuntime:
    """Everything the hot loop needs about one node, flattened into slots: what the generic tick
    (tick.run_tick) and the generated ones (inproc_ticks) read of a node."""

    __slots__ = ("index", "id", "flow", "spec", "invoke", "read", "latency_ns", "on_error", "inputs", "plan",
                 "downstream", "seq", "clock", "stats", "cycle", "fallbacks", "replaced", "restarts", "ports_seen")

    def __init__(self, index: int, node: Node, plan: NodePlan):
        self.index = index
        self.id = node.id
        self.plan = plan  # its wiring
        self.flow: Flow = node.flow
        self.spec = node.spec
        self.replaced = False  # replace_step() swapped step() for logged outputs
        self.invoke = make_invoker(node.flow, node.spec)
        self.read = make_output_reader(node.spec)
        self.latency_ns = node.settings.latency_ns
        self.on_error = node.settings.on_error
        self.restarts = RestartBudget(node.settings.max_restarts, node.settings.restart_window)
        # (port, buffer, policy, port spec) per input port, and the optional input ports nothing
        # feeds, which take their fallback on every tick
        self.inputs, self.fallbacks = bind_inputs(plan, node.inputs)
        # output port -> [(consumer index, consumer buffer, delay ns, whether it triggers the consumer)]
        self.downstream: dict[str, list[tuple[int, PortBuffer, int, bool]]] = {}
        self.seq: dict[str, int] = {}
        self.clock = node.clock
        self.stats = NodeStats()
        self.cycle: list[str] = plan.cycle or []
        # an untyped step's output ports, in order, the first time they were not the wired ones
        # (a port nothing consumes still makes events): the compiled tick expects them from then on
        self.ports_seen: tuple[str, ...] | None = None


def _wire(nodes: list[NodeRuntime], by_id: dict[str, NodeRuntime]) -> None:
    """Point each node's outputs at its consumers' input buffers, as its plan says."""
    buffers = {(rt.id, port): buf for rt in nodes for port, buf, _, _ in rt.inputs}
    for rt in nodes:
        for port, consumers in rt.plan.consumers.items():
            rt.downstream[port] = [(by_id[c.dst].index, buffers[(c.dst, c.dst_port)], c.delay_ns, c.triggers)
                                   for c in consumers]


class _RateGroup:
    """The Rate/Hybrid nodes whose clocks have one schedule: their rate ticks at ``(t_k, 0)``
    always come due together, so they share one heap entry per tick instead of one per node."""

    __slots__ = ("order", "ticks", "alone", "k", "next_tag", "offset_ns", "step_num", "step_den")

    def __init__(self, schedule: tuple[int, int, int], order: tuple[int, ...]):
        self.order = order  # node indices, consumers first (plan.tie_order): the tick order
        # their tick functions, in that order, or the one that runs them all (CompiledTicks.functions)
        self.ticks: tuple = ()
        # the function that runs its ticks while nothing else is due, if compiled (inproc_ticks.make_ticks)
        self.alone = None
        self.k = 0
        # the clocks' tick_time(k) is offset_ns + k * step_num // step_den (inlined in the loop)
        self.offset_ns, self.step_num, self.step_den = schedule
        self.next_tag = (self.offset_ns, 0)

    def advance(self) -> tuple[int, int]:
        """Move to the next tick; return its tag."""
        return self.move_to(self.k + 1)

    def move_to(self, k: int) -> tuple[int, int]:
        """Make tick ``k`` the next; return its tag."""
        self.k = k
        self.next_tag = (self.time_of(k), 0)
        return self.next_tag

    def time_of(self, k: int) -> int:
        """The time of tick ``k`` (the clocks' tick_time(k))."""
        return self.offset_ns + k * self.step_num // self.step_den


class _Agenda:
    """The ticks due: a heap of the tags due later, and per tag the nodes due there; and the nodes
    due at the next microstep of the tag running now (``after``). Only a tick at ``(t, m)`` makes
    ticks at ``(t, m + 1)`` (a zero-latency output on an undelayed edge), so those need no heap."""

    def __init__(self, groups: list[_RateGroup]):
        self.heap: list[tuple[int, int]] = []
        # tag -> the nodes due: a rate group alone (the common case), or a set of node indices,
        # and then the rate groups due at that tag are in rate_due
        self.pending: dict[tuple[int, int], _RateGroup | set[int]] = {}
        self.rate_due: dict[tuple[int, int], list[_RateGroup]] = {}
        self.after: list[int] = []  # (a node triggered twice is in it twice)
        self.groups = groups
        for group in groups:
            self.schedule_group(group)

    def schedule(self, tag: tuple[int, int], index: int) -> None:
        """A tick of node ``index`` at ``tag``, the arrival of an event that triggers it: at the next
        microstep of the tag running now (a zero-latency output on an undelayed edge), or later,
        at microstep 0 (latency, delay)."""
        if tag[1]:
            self.after.append(index)
        else:
            self.schedule_later(tag, index)

    def schedule_later(self, tag: tuple[int, int], index: int) -> None:
        waiting = self.pending.get(tag)
        if waiting is None:
            self.pending[tag] = {index}
            heappush(self.heap, tag)
        elif type(waiting) is set:
            waiting.add(index)
        else:  # a rate group is due there: share the tag
            self.rate_due[tag] = [waiting]
            self.pending[tag] = {*waiting.order, index}

    def schedule_group(self, group: _RateGroup) -> None:
        tag = group.next_tag
        waiting = self.pending.get(tag)
        if waiting is None:
            self.pending[tag] = group
            heappush(self.heap, tag)
            return
        if type(waiting) is not set:
            self.rate_due[tag] = [waiting]
            self.pending[tag] = waiting = set(waiting.order)
        else:
            self.rate_due.setdefault(tag, [])
        waiting.update(group.order)
        self.rate_due[tag].append(group)

    def resume_group(self, g: int, k: int) -> None:
        """Rate group ``g`` ran alone up to its tick ``k`` (exclusive): schedule that one."""
        group = self.groups[g]
        group.move_to(k)
        self.schedule_group(group)

    def keep_next(self, tag: tuple[int, int]) -> None:
        """A tick at the microstep before ``tag`` raised: the ticks already triggered for ``tag``
        go on the heap, for a later advance()."""
        for index in set(self.after):
            self.schedule_later(tag, index)
        self.after.clear()


class _Recorder:
    """What became of each tick, in the trace's tape: a step's events, delivered to its consumers'
    buffers (the ticks they trigger scheduled), and its step record; a skipped tick's record; a
    failed step's, then what ``on_error`` decides (tick.decide). The reference tick and the
    generated ones hand their outcomes here."""

    def __init__(self, tape: list, nodes: list[NodeRuntime], max_microsteps: int, schedule):
        self.tape, self.nodes, self.max_microsteps, self.schedule = tape, nodes, max_microsteps, schedule
        self.bound: Callable | None = None  # bound(buf, tau): CompiledTicks.bound, set by the session

    def emit(self, rt: NodeRuntime, tau: tuple[int, int], outputs, consumed: dict, start: int, end: int,
             dropped: dict | None = None) -> None:
        """Record and deliver the outputs of a tick that ran, and its step record."""
        out_tag = (tau[0] + rt.latency_ns, 0) if rt.latency_ns else (tau[0], tau[1] + 1)
        produced = []
        if outputs:
            event = self._event
            for port, value in outputs:
                if value is None:  # sparse output: no event
                    continue
                if type(value) not in PLAIN_TYPES:
                    if type(value) is Burst:  # an event per value, in order; none if one cannot be recorded
                        self._check_burst(rt, tau, port, value, consumed, start, produced)
                        for item in value.values:
                            event(rt, tau, port, item, out_tag, end, produced)
                        continue
                    self._check_output(rt, tau, port, value, consumed, start, produced)
                    make_read_only(value)  # an emitted value is immutable: its consumers share it
                event(rt, tau, port, value, out_tag, end, produced)
        self.tape.append((rt.id, tau, consumed, tuple(produced), StepStatus.OK, with_step_detail(rt.flow, dropped),
                          start, end - start))

    def emit_undelivered(self, rt: NodeRuntime, tau: tuple[int, int], outputs, consumed: dict, start: int, end: int,
                         dropped: dict | None = None) -> None:
        """:meth:`emit` for a session whose routes were taken (InprocSession.take_routes: a
        replay), which delivers nothing: each event recorded without ``_event``'s call, an array of
        a plain dtype made read-only without ``_check_output``'s and ``make_read_only``'s (whose
        verdicts on it these are); any other value as :meth:`emit` does."""
        produced = []
        if outputs:
            out_tag = (tau[0] + rt.latency_ns, 0) if rt.latency_ns else (tau[0], tau[1] + 1)
            tape, seqs, node_id = self.tape, rt.seq, rt.id
            for port, value in outputs:
                if value is None:  # sparse output: no event
                    continue
                kind = type(value)
                if kind is np.ndarray and not value.dtype.hasobject:
                    value.flags.writeable = False  # an emitted value is immutable (make_read_only)
                elif kind not in PLAIN_TYPES:
                    if kind is Burst:
                        self._check_burst(rt, tau, port, value, consumed, start, produced)
                        for item in value.values:
                            self._event(rt, tau, port, item, out_tag, end, produced)
                        continue
                    self._check_output(rt, tau, port, value, consumed, start, produced)
                    make_read_only(value)
                seq = seqs.get(port, 0)
                seqs[port] = seq + 1
                tape.append((out_tag, node_id, port, seq, value, end))
                produced.append((node_id, port, seq))
        self.tape.append((rt.id, tau, consumed, tuple(produced), _OK, with_step_detail(rt.flow, dropped),
                          start, end - start))

    def _check_burst(self, rt: NodeRuntime, tau: tuple[int, int], port: str, burst: Burst, consumed: dict,
                     start: int, produced: list) -> None:
        """Before a Burst's events are recorded: each value checked (_check_output: the run stops
        at one that cannot be recorded, before any is), then made read-only."""
        if burst.rows is None or burst.rows.dtype.hasobject:
            for i, item in enumerate(burst.values):
                if type(item) not in PLAIN_TYPES:
                    self._check_output(rt, tau, port, item, consumed, start, produced, i)
        make_read_only(burst)

    def _event(self, rt: NodeRuntime, tau: tuple[int, int], port: str, value: Any, out_tag: tuple[int, int],
               end: int, produced: list) -> None:
        """Record one event of a tick and deliver it to its consumers."""
        seqs, node_id = rt.seq, rt.id
        seq = seqs.get(port, 0)
        seqs[port] = seq + 1
        event = (out_tag, node_id, port, seq, value, end)
        self.tape.append(event)
        produced.append((node_id, port, seq))
        # the event is the buffer entry of an undelayed edge
        for consumer, buf, delay_ns, triggers in rt.downstream.get(port, ()):
            entry = ((out_tag[0] + delay_ns, 0), node_id, port, seq, value, end) if delay_ns else event
            buf.insert(entry)  # (sync.fill, with the session's bound: a generated tick keeps its own count)
            if len(buf.entries) >= buf.bound_at:
                self.bound(buf, tau)
            if triggers:
                if entry[0][1] > self.max_microsteps:
                    raise CausalityError(rt.cycle or self.nodes[consumer].cycle, tau, self.max_microsteps)
                self.schedule(entry[0], consumer)

    def _check_output(self, rt: NodeRuntime, tau: tuple[int, int], port: str, value: Any, consumed: dict,
                      start: int, produced: list | tuple, in_burst: int | None = None) -> None:
        """Before an output not of a plain type is recorded: stop the run (CodecError naming the
        node, port, tick and type) if the codec cannot encode it, as a real-time backend, which
        cannot send it, does; whatever ``on_error`` says, since this is a bug in the flow, not a
        failure of one tick. The error record lists the events of the tick already ``produced``."""
        try:
            if rt.replaced or _encodes_surely(value):  # a replayed step emits logged values
                return
        except RecursionError:  # a value that contains itself: the codec says so
            pass
        try:
            packb(value)
        except CodecError as e:
            what = "a value" if in_burst is None else f"a Burst whose value {in_burst} is one"
            error = CodecError(f"{rt.id}.{port}: the step at {format_tag(tau)} returned {what} the run cannot "
                               f"record: {e}")
            rt.stats.errors += 1
            first_line = str(error).split("\n", 1)[0]
            status, detail = error_outcome(f"CodecError: {first_line}", "stop")
            self.tape.append((rt.id, tau, consumed, tuple(produced), status, detail, start, time_ns() - start))
            raise error from None

    def skipped(self, rt: NodeRuntime, tau: tuple[int, int], missing: list[str]) -> None:
        rt.stats.skips += 1
        self.tape.append((rt.id, tau, {}, (), *skipped_outcome(missing), 0, 0))

    def failed(self, rt: NodeRuntime, tau: tuple[int, int], consumed: dict, exc: BaseException,
               start: int, wall: int) -> None:
        """Record a step that raised ``exc``, then act on ``on_error`` (tick.decide)."""
        decision = decide(rt.on_error, exc, rt.restarts, tau[0])
        if decision is Decision.END_RUN:  # (the seed paper's benchmark ends so)
            rt.stats.steps += 1
            self.tape.append((rt.id, tau, consumed, (), *exit_outcome(), start, wall))
            raise ending(decision, rt.id, tau, exc)
        rt.stats.errors += 1
        self.tape.append((rt.id, tau, consumed, (), *error_outcome(error_text(exc), rt.on_error), start, wall))
        if decision is Decision.RESTART:
            rt.stats.counts["restarts"] = rt.stats.counts.get("restarts", 0) + 1
            if not rt.replaced:  # (a replayed step was never set up: its flow is not run)
                rt.flow.reset()
        elif decision is not Decision.SKIP:
            raise ending(decision, rt.id, tau, exc, rt.restarts) from exc


class InprocSession(Session):
    backend_name = "inproc"
    steppable = True

    def __init__(self, graph: Graph, tie_break_seed: int | None = None, keep: str = "trace",
                 generate_ticks: bool = True):
        """``generate_ticks=False``: every node ticks through the reference ``tick.run_tick``, none
        through generated code (to debug a flow's step, or to compare the two paths)."""
        super().__init__(graph, keep)
        self._records = self.trace  # where the ticks record (pipe.trace may later read a log)
        self.max_microsteps = graph.max_microsteps
        self._tie_break_seed = tie_break_seed
        self._rng = random.Random(tie_break_seed) if tie_break_seed is not None else None
        plan = plan_graph(graph)
        self._nodes = [NodeRuntime(i, node, plan.nodes[node.id])
                       for i, node in enumerate(sorted(graph.nodes.values(), key=lambda n: n.id))]
        self._by_id = {rt.id: rt for rt in self._nodes}
        _wire(self._nodes, self._by_id)
        groups: dict[tuple[int, int, int], list[int]] = {}
        for rt in self._nodes:
            if type(rt.flow).reset is not Flow.reset:
                rt.flow.reset()  # the paper's flows initialise their state in reset()
            if rt.clock.hz is not None:
                groups.setdefault(rt.clock.schedule, []).append(rt.index)
        # consumers first: a fused rate group's ticks then skip the test of what is visible on the
        # edges within it (inproc_ticks._without_visible_tests)
        tie = tie_order(plan)
        self._rank = rank = [tie[rt.id] for rt in self._nodes]
        self._groups = [_RateGroup(schedule, tuple(sorted(indices, key=rank.__getitem__)))
                        for schedule, indices in groups.items()]
        self._agenda = agenda = _Agenda(self._groups)
        self._recorder = recorder = _Recorder(self._records.tape, self._nodes, self.max_microsteps, agenda.schedule)
        # the tick functions, generated or the reference, built on the first advance()
        self._compiled = CompiledTicks(self._records, self._nodes, self._groups, agenda, recorder,
                                       max_microsteps=self.max_microsteps, plain_types=PLAIN_TYPES,
                                       microsteps=self._microsteps, fuse=self._rng is None,
                                       generate=generate_ticks)
        recorder.bound = self._compiled.bound
        self._emit = recorder.emit  # what a tick() hands its outputs to (take_routes: emit_undelivered)
        # the counts and seqs the generated ticks keep go to the nodes (CompiledTicks.flush) in the
        # thread that runs them: held by advance(); another thread asks for it (stats()), and the
        # loop does it between two instants
        self._advancing = threading.Lock()
        self._runner: int | None = None  # the thread in advance()
        self._flushes_asked: list[threading.Event] = []
        self._set_up = False  # whether the flows' setup() ran and their teardown() has not

    def _microsteps(self, next_microstep: tuple[int, int], ran: int) -> tuple[tuple[int, int], int]:
        """Run the ticks in the agenda's ``after`` (what the ticks at the microstep before
        ``next_microstep`` triggered) and what they trigger, microstep by microstep, until none is
        left. Returns the microstep after the last and ``ran``, counted on."""
        compiled = self._compiled
        after, chains, ticks, rank, rng = self._agenda.after, compiled.chains, compiled.ticks, self._rank, self._rng
        t = next_microstep[0]
        try:
            while after:
                tag = next_microstep
                next_microstep = (t, tag[1] + 1)
                if len(after) == 1:  # the only one: it may go on along a chain, one tick a microstep
                    next_microstep = chains[after.pop()](tag, next_microstep)
                    ran += next_microstep[1] - tag[1]
                    continue
                indices = sorted(set(after), key=rank.__getitem__)
                after.clear()
                if rng is not None:
                    rng.shuffle(indices)
                for i in indices:
                    ticks[i](tag, next_microstep)
                ran += len(indices)
        except BaseException:
            self._agenda.keep_next(next_microstep)
            raise
        return next_microstep, ran

    def _answer_flushes(self) -> None:
        """Flush for the threads that asked (stats()), between two instants of a run."""
        self._compiled.flush()
        asked, self._flushes_asked = self._flushes_asked, []
        for done in asked:
            done.set()

    #: how long stats() from another thread waits for a run's loop to flush between two instants
    #: (a step may take long): past that, it reads the counts where they are (_counted_so_far)
    FLUSH_WAIT_S = 1.0

    def tick_order(self) -> list[tuple[str, ...]]:
        """Per rate group (the nodes of one Rate schedule), its nodes' ids in the order they tick at an instant."""
        return [tuple(self._nodes[i].id for i in group.order) for group in self._groups]

    def generated_ticks(self) -> frozenset[str]:
        """The nodes whose ticks were generated code in this session's runs so far (others run ``tick.run_tick``)."""
        return frozenset(self._compiled.generated)

    def look_between_ticks(self) -> None:
        self._compiled.host.look = True

    # ---------------------------------------------------------------------------------------
    # Lifecycle: every flow's setup() before the first tick, teardown() when the session closes
    # (pipe.reset(), another backend, the program's exit): a run in virtual time may go on
    # ---------------------------------------------------------------------------------------
    def set_up(self, skip: frozenset[str] = frozenset()) -> None:
        """Call each flow's ``setup()`` once, in node order (a failure: SetupError, and the
        flows already set up are torn down), but for the nodes in ``skip``, which will not step
        (a replay's sources and flows replayed from the log)."""
        if self._set_up:
            return
        self._set_up = True
        _OPEN.add(self)
        for rt in self._nodes:
            if rt.id in skip:
                continue
            try:
                set_up(rt.flow)
            except Exception as exc:
                self.close()
                raise SetupError(rt.id, exc) from exc

    def close(self) -> None:
        """Call ``teardown()`` of each flow set up, in reverse node order; a failure is a warning."""
        if not self._set_up:
            return
        self._set_up = False
        _OPEN.discard(self)
        for rt in reversed(self._nodes):
            try:
                tear_down(rt.flow)
            except Exception as exc:
                warnings.warn(f"{rt.id}.teardown() raised {type(exc).__name__}: {exc}", RetrieverWarning,
                              stacklevel=2)

    # ---------------------------------------------------------------------------------------
    # The loop
    # ---------------------------------------------------------------------------------------
    def advance(self, until_ns: int) -> None:
        # every step appends records that live as long as the trace (young collections, which
        # reclaim the cyclic garbage flows make, go on as usual)
        self.set_up()
        try:
            if self._runner == threading.get_ident():
                raise BackendError("pipe.run() or pipe.step() called while this pipeline runs, in this thread "
                                   "(from a step?)\n    hint: a step cannot run its own pipeline; run another "
                                   "Pipeline, or call the function the step needs directly")
            with self._advancing, holding_full_collections():
                runner, self._runner = self._runner, threading.get_ident()
                try:
                    self._advance(until_ns)
                except RunEnded:
                    raise
                except BaseException as exc:  # a step's error, a stop: now is the instant it got to
                    self.now_ns = max(self.now_ns, min(self._reached_ns(exc), until_ns))
                    raise
                finally:
                    self._runner = runner
                    if self._flushes_asked:
                        self._answer_flushes()
        except RunEnded as ended:  # a step's sys.exit(0): the run is over at its tick
            self.now_ns = ended.tag[0]
            self.ended = ended

    def _reached_ns(self, exc: BaseException) -> int:
        """The time of the instant a run that raised ``exc`` got to: the tick it names (a step's
        error, a causality error), else the latest rate tick that ran (a stop, Ctrl-C)."""
        tag = getattr(exc, "tag", None)
        if type(tag) is tuple and len(tag) == 2 and type(tag[0]) is int:
            return tag[0]
        ran = [g.time_of(g.k - 1) for g in self._groups if g.k > 0]
        return max(ran, default=self.now_ns)

    def _advance(self, until_ns: int) -> None:
        agenda, host, rng = self._agenda, self._compiled.host, self._rng
        heap, pending, rate_due, after, schedule_group = (agenda.heap, agenda.pending, agenda.rate_due, agenda.after,
                                                          agenda.schedule_group)
        ticks = self._compiled.functions()
        log = self.log
        # every so many steps (ticks: each leaves one step record), between two instants: the log's
        # hand-over, or a look at whether a stop was asked for (a run in the background,
        # pipe.run(..., blocking=False), stopped by its handle)
        ran = 0
        log_at = 1 if log is not None else self.LOG_BATCH
        while heap and heap[0][0] < until_ns:
            if host.look:  # (between two instants)
                host.look = False
                log_at, ticks = self._look(ran, log_at, ticks)
            if ran >= log_at:
                log_at = ran + self._hand_over()
            tag = heappop(heap)
            due = pending.pop(tag)
            if type(due) is _RateGroup:  # one rate group's tick, nothing else: its nodes in order
                if due.alone is not None and (not heap or heap[0][0] > tag[0]):
                    # nothing else due at its time: its ticks back to back, up to the next that is
                    ran = due.alone(due.k, until_ns, ran, log_at)
                    continue
                due.k = k = due.k + 1  # due.advance(), inlined
                due.next_tag = next_tag = (due.offset_ns + k * due.step_num // due.step_den, 0)
                if next_tag in pending:
                    schedule_group(due)
                else:  # schedule_group, inlined for the common case
                    pending[next_tag] = due
                    heappush(heap, next_tag)
                ran += len(due.order)
                if rng is None or len(due.order) == 1:
                    order = due.ticks  # one fused tick, or one per node
                else:
                    indices = list(due.order)
                    rng.shuffle(indices)
                    order = [ticks[i] for i in indices]
            else:
                groups = rate_due.pop(tag, None)
                if groups is not None:  # rate ticks: schedule each group's next one
                    for group in groups:
                        group.advance()
                        schedule_group(group)
                ran += len(due)
                order = [ticks[i] for i in due] if len(due) == 1 else self._ordered(due, ticks)
            next_microstep = (tag[0], tag[1] + 1)
            try:
                for tick in order:
                    tick(tag, next_microstep)
            except BaseException:
                agenda.keep_next(next_microstep)
                raise
            if after:
                _, ran = self._microsteps(next_microstep, ran)
        self.now_ns = max(self.now_ns, until_ns)

    def _look(self, ran: int, log_at: int, ticks: list) -> tuple[int, list]:
        """What the loop does between two instants when asked to look (``host.look``): a stop
        (RunHandle.stop; a logged run stops at its hand-over, now), a recompile, the flushes of
        counts other threads wait for. The hand-over's new step count and the tick functions."""
        if self.stop_requested:
            if self.log is None:
                raise KeyboardInterrupt
            log_at = ran
        compiled = self._compiled
        if compiled.recompile:
            compiled.recompile = False
            compiled.drop()
            ticks = compiled.functions()
        if self._flushes_asked:
            self._answer_flushes()
        return log_at, ticks

    def _hand_over(self) -> int:
        """Between two instants, every so many steps: the log's hand-over (first: with
        keep="counters" it empties the trace), or without a log a look at whether a stop was asked
        for and the records dropped. How many steps until the next one."""
        if self.log is not None:
            return self.write_log()
        if self.stop_requested:
            raise KeyboardInterrupt
        self.drop_records()
        return self.LOG_BATCH

    def _ordered(self, due: set[int], ticks: list) -> list:
        """The ticks of the nodes ``due`` at one tag, by rank, or shuffled (tie_break_seed)."""
        indices = sorted(due, key=self._rank.__getitem__)
        if self._rng is not None:
            self._rng.shuffle(indices)
        return [ticks[i] for i in indices]

    def stats(self) -> dict[str, NodeStats]:
        """The nodes' counts, with what the compiled ticks counted since they last handed it
        over. Those are handed over (CompiledTicks.flush) only where that is safe: in a thread when no
        run goes on, or by a run's loop between two instants, which a thread other than the
        run's asks for and waits up to FLUSH_WAIT_S; in the run's own thread (a step, a signal
        handler) or when the loop does not come round in time (a long step), the counts are read
        where they are, as of now, into copies."""
        me = threading.get_ident()
        if self._runner != me:
            if self._advancing.acquire(blocking=False):  # no run goes on
                try:
                    self._compiled.flush()
                finally:
                    self._advancing.release()
                return {rt.id: rt.stats for rt in self._nodes}
            done = threading.Event()
            self._flushes_asked.append(done)
            self._compiled.host.look = True
            if done.wait(self.FLUSH_WAIT_S):
                return {rt.id: rt.stats for rt in self._nodes}
        return self._counted_so_far()

    def produced_counts(self) -> dict[tuple[str, str], int]:
        self.stats()  # hands the compiled ticks' seqs to the nodes
        return {(rt.id, port): seq for rt in self._nodes for port, seq in rt.seq.items()}

    def _counted_so_far(self) -> dict[str, NodeStats]:
        """Copies of the nodes' counts with what the compiled ticks counted and did not hand over
        yet (the tape expanded first, unless a thread is expanding it: then this may be a signal
        handler of that thread, and the records still in the tape are not counted yet)."""
        self._records.expand(wait=False)
        pending = self._compiled.not_handed_over()
        out = {}
        for rt in self._nodes:
            ticks, steps, step_ns = pending.get(rt.index, (0, 0, 0))
            s = rt.stats
            out[rt.id] = dataclasses.replace(s, ticks=s.ticks + ticks, steps=s.steps + steps,
                                             step_ns=s.step_ns + step_ns, counts=dict(s.counts))
        return out

    def seeds(self) -> dict:
        return {} if self._rng is None else {"tie_break_seed": self._tie_break_seed}

    # ---------------------------------------------------------------------------------------
    # Hooks for replay (retriever.replay): drive ticks from a log instead of the clocks;
    # and for a driver that supplies one node's outputs from outside (retriever.gym)
    # ---------------------------------------------------------------------------------------
    def take_routes(self) -> dict[tuple[str, str], list[tuple[tuple[str, str], PortBuffer, int]]]:
        """Stop delivering outputs; return where each ``(node, port)`` delivered: the consuming
        ``(node, port)``, its buffer and the edge's delay, so the caller can deliver logged
        events instead."""
        owners = {id(buf): (rt.id, port) for rt in self._nodes for port, buf, _, _ in rt.inputs}
        routes: dict[tuple[str, str], list[tuple[tuple[str, str], PortBuffer, int]]] = {}
        for rt in self._nodes:
            for port, consumers in rt.downstream.items():
                routes[(rt.id, port)] = [(owners[id(buf)], buf, delay_ns) for _, buf, delay_ns, _ in consumers]
            rt.downstream = {}
        self._emit = self._recorder.emit_undelivered
        self._compiled.drop()
        self._compiled.generic_only = True  # generated ticks deliver, and expect inproc entries
        return routes

    def prepare_inputs(self, node: str, prepare: Callable[[dict], None]) -> None:
        """Have ``prepare(values)`` make, in place, the input values that ``node``'s ticks selected
        into what its step takes, before each step: a replay's logged values, decoded only once a
        tick takes one. Only after :meth:`take_routes` (generated ticks call the step themselves)."""
        if not self._compiled.generic_only:
            raise RuntimeError("prepare_inputs() needs take_routes() first")
        rt = self._by_id[node]
        invoke = rt.invoke

        def prepared(values: dict) -> Any:
            prepare(values)
            return invoke(values)

        rt.invoke = prepared

    def tick(self, node: str, tau: tuple[int, int]) -> None:
        """Run one tick of ``node`` at ``tau`` now, as the loop would (records land in the trace)."""
        compiled = self._compiled
        if compiled.ticks is not None or compiled.flushes:  # generated ticks keep their own seq counters
            compiled.drop()
        recorder = self._recorder
        run_tick(self._by_id[node], tau, recorder.skipped, recorder.failed, self._emit)

    def retract(self, node: str) -> None:
        """Take back the outputs of ``node``'s last recorded tick, as a real-time LET step that
        missed its deadline drops them: out of the trace, its record's ``produced`` emptied,
        their seqs used again. Only after :meth:`take_routes` (nothing was delivered): replay."""
        if not self._compiled.generic_only:
            raise RuntimeError("retract() needs take_routes() first: outputs were delivered")
        steps, events = self.trace.raw_steps, self.trace.raw_events
        i = max(i for i, s in enumerate(steps) if s[0] == node)
        produced = set(steps[i][3])
        steps[i] = (*steps[i][:3], (), *steps[i][4:])
        events[:] = [e for e in events if (e[1], e[2], e[3]) not in produced]
        seqs = self._by_id[node].seq
        for _, port, seq in produced:
            seqs[port] = min(seqs[port], seq)

    def restart_afresh(self, node: str, seqs: dict[str, int]) -> list[tuple[PortBuffer, list[tuple]]]:
        """Start ``node`` afresh, as a real-time run did after its process died: the flow reset,
        its input buffers emptied, its ports' next seqs from ``seqs``. Returns each buffer with
        the entries it held. Only after :meth:`take_routes`: replay."""
        if not self._compiled.generic_only:
            raise RuntimeError("restart_afresh() needs take_routes() first: outputs were delivered")
        rt = self._by_id[node]
        rt.flow.reset()
        held = []
        for _, buf, _, _ in rt.inputs:
            held.append((buf, buf.entries))
            buf.entries, buf.visible, buf.cursor, buf.last_id = [], 0, 0, None
        rt.seq.update(seqs)
        return held

    def replace_step(self, node: str, outputs: Any) -> None:
        """Make ``node``'s ticks emit ``next(outputs)`` (each a list of ``(port, value)``, or a
        ``ReplayedError`` to raise: a tick logged as an error) instead of calling its ``step()``:
        replayed sources, and an agent whose actions come from outside (retriever.gym). A tick
        whose required input has nothing is skipped as before, and takes nothing from ``outputs``."""
        rt = self._by_id[node]
        self._compiled.drop()
        rt.replaced = True

        def invoke(values: dict) -> Any:
            out = next(outputs)
            if type(out) is ReplayedError:
                raise out
            return out

        rt.invoke = invoke
        rt.read = lambda raw: raw

    def held(self, node: str) -> dict[str, int]:
        """Per input port of ``node``, how many events its buffer holds now: what its policy may
        still select at a tick to come, and a few more (sync.fill bounds it as events come)."""
        return {port: len(buf.entries) for port, buf, _, _ in self._by_id[node].inputs}

    def inputs_at(self, node: str, tau: tuple[int, int]) -> tuple[dict[str, Any], dict[str, tuple], list[str] | None]:
        """What ``node``'s tick at ``tau`` is handed if it runs next: its input values (an optional
        port with nothing gets its fallback), the ids of the events each port's policy selects,
        and the required ports that have nothing (None if none; else the tick will be skipped).
        Selected by the node's own policies (``tick.select_inputs``) on copies of its buffers, so
        nothing is consumed. It is what the tick gets once every tick before ``tau`` has run
        (``advance(tau[0])`` for a tick at microstep 0): no event with a tag ``≤ tau`` can come later."""
        self._compiled.flush()  # the generated ticks hand back how far they have looked into the buffers
        rt = self._by_id[node]
        values, consumed, missing, _, _ = select_inputs(
            [(port, buf.copy(), policy, spec) for port, buf, policy, spec in rt.inputs], tau)
        for port, spec in rt.fallbacks.items():
            values[port] = spec.fallback()
        return values, consumed, missing


class InprocBackend(Backend):
    name = "inproc"

    def open(self, graph: Graph, tie_break_seed: int | None = None, keep: str = "trace",
             generate_ticks: bool = True, **options: object) -> InprocSession:
        if options:
            from ..errors import BackendError

            hint = ""
            if "virtual_time" in options:
                hint = ("\n    hint: inproc always runs in virtual time; virtual_time=True is for backend='zenoh' "
                        "(one process per flow, the same trace)")
            elif "rerun" in options:
                hint = ("\n    hint: a live view needs backend='zenoh' or 'dora'; for an in-process run, write a log "
                        "(log='run.mcap') and export it: retriever log export run.mcap --format rerun -o run.rrd")
            raise BackendError(f"the inproc backend takes no options {sorted(options)} "
                               f"(it accepts tie_break_seed=, keep=, generate_ticks=){hint}")
        return InprocSession(graph, tie_break_seed=tie_break_seed, keep=keep, generate_ticks=generate_ticks)
