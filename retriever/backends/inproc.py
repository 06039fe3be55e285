"""The in-process backend: a discrete-event executor in virtual, superdense time.

This is the reference semantics every other backend is tested against (DESIGN.md §3–§4).

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
"""

from __future__ import annotations

import gc
import random
from heapq import heappop, heappush
from time import time_ns
from typing import Any

from ..errors import CausalityError, StepError
from ..flow._base import Flow, make_invoker, make_output_reader
from ..graph import Graph, Node
from ..sync import MISSING, PortBuffer
from .base import Backend, NodeStats, Session


class _NodeRuntime:
    """Everything the hot loop needs about one node, flattened into slots."""

    __slots__ = ("index", "id", "flow", "invoke", "read", "latency_ns", "on_error", "inputs",
                 "downstream", "seq", "clock", "k", "next_rate_tag", "stats", "cycle", "fallbacks")

    def __init__(self, index: int, node: Node):
        self.index = index
        self.id = node.id
        self.flow: Flow = node.flow
        self.invoke = make_invoker(node.flow, node.spec)
        self.read = make_output_reader(node.spec)
        self.latency_ns = node.settings.latency_ns
        self.on_error = node.settings.on_error
        # (port, buffer, policy, port spec) per input port
        self.inputs: list[tuple[str, PortBuffer, Any, Any]] = []
        # output port -> [(consumer index, consumer buffer, delay ns, whether it triggers the consumer)]
        self.downstream: dict[str, list[tuple[int, PortBuffer, int, bool]]] = {}
        self.seq: dict[str, int] = {}
        self.clock = node.clock
        self.k = 0
        self.next_rate_tag: tuple[int, int] | None = None
        self.stats = NodeStats()
        self.cycle: list[str] = []
        # optional input ports nothing feeds: they take their fallback on every tick
        self.fallbacks: dict[str, Any] = {}


class InprocSession(Session):
    backend_name = "inproc"
    steppable = True

    def __init__(self, graph: Graph, tie_break_seed: int | None = None):
        super().__init__(graph)
        self.max_microsteps = graph.max_microsteps
        self._tie_break_seed = tie_break_seed
        self._rng = random.Random(tie_break_seed) if tie_break_seed is not None else None
        self._heap: list[tuple[int, int]] = []
        self._pending: dict[tuple[int, int], set[int]] = {}
        self._nodes = [_NodeRuntime(i, node) for i, node in enumerate(sorted(graph.nodes.values(), key=lambda n: n.id))]
        self._by_id = by_id = {rt.id: rt for rt in self._nodes}
        self._wire(graph, by_id)
        for rt in self._nodes:
            if type(rt.flow).reset is not Flow.reset:
                rt.flow.reset()  # the paper's flows initialise their state in reset()
            if rt.clock.hz is not None:
                rt.next_rate_tag = (rt.clock.tick_time(0), 0)
                self._schedule(rt.next_rate_tag, rt.index)

    # ---------------------------------------------------------------------------------------
    # Wiring
    # ---------------------------------------------------------------------------------------
    def _wire(self, graph: Graph, by_id: dict[str, _NodeRuntime]) -> None:
        buffers: dict[tuple[str, str], PortBuffer] = {}
        policies: dict[tuple[str, str], Any] = {}
        for e in graph.edges:
            key = (e.dst, e.dst_port)
            buf = buffers.setdefault(key, PortBuffer())
            policies[key] = e.sync
            dst = graph.nodes[e.dst]
            by_id[e.src].downstream.setdefault(e.src_port, []).append(
                (by_id[e.dst].index, buf, e.delay_ns, dst.triggers_on(e.dst_port)))
        for node in graph.nodes.values():
            rt = by_id[node.id]
            for port, spec in node.inputs.items():
                key = (node.id, port)
                if key in buffers:
                    rt.inputs.append((port, buffers[key], policies[key], spec))
                elif spec.required:
                    rt.inputs.append((port, PortBuffer(), _AlwaysMissing, spec))
                else:
                    rt.fallbacks[port] = spec
            for cycle in graph.instantaneous_cycles:
                if node.id in cycle:
                    rt.cycle = cycle
                    break

    def _schedule(self, tag: tuple[int, int], index: int) -> None:
        waiting = self._pending.get(tag)
        if waiting is None:
            self._pending[tag] = {index}
            heappush(self._heap, tag)
        else:
            waiting.add(index)

    # ---------------------------------------------------------------------------------------
    # The loop
    # ---------------------------------------------------------------------------------------
    def advance(self, until_ns: int) -> None:
        # Every step appends trace records that live as long as the run, so each automatic *full*
        # collection re-walks the whole trace: about half the loop's time on long runs (measured,
        # benchmarks/README.md). Hold off full collections while the loop runs; young collections,
        # which reclaim the cyclic garbage flows make, go on as usual.
        thresholds = gc.get_threshold()
        gc.set_threshold(thresholds[0], thresholds[1], 1 << 30)
        try:
            self._advance(until_ns)
        finally:
            gc.set_threshold(*thresholds)

    def _advance(self, until_ns: int) -> None:
        heap, pending, nodes, rng = self._heap, self._pending, self._nodes, self._rng
        log, steps = self.log, self.trace.raw_steps
        log_at = len(steps) + 1 if log is not None else float("inf")
        while heap and heap[0][0] < until_ns:
            if len(steps) >= log_at:
                log_at = len(steps) + self.write_log()
            tag = heappop(heap)
            indices = pending.pop(tag)
            if len(indices) == 1:
                order = indices
            elif rng is None:
                order = sorted(indices)
            else:
                order = list(indices)
                order.sort()
                rng.shuffle(order)
            for index in order:
                rt = nodes[index]
                if tag == rt.next_rate_tag:
                    rt.k += 1
                    rt.next_rate_tag = (rt.clock.tick_time(rt.k), 0)
                    self._schedule(rt.next_rate_tag, index)
                self._tick(rt, tag)
        self.now_ns = max(self.now_ns, until_ns)

    def _tick(self, rt: _NodeRuntime, tau: tuple[int, int]) -> None:
        stats = rt.stats
        stats.ticks += 1
        # sync.select_inputs, inlined: the call alone cost 10% of the steps/s of this loop (measured
        # with benchmarks/step_overhead.py); keep the two identical
        values: dict[str, Any] = {}
        consumed: dict[str, tuple] = {}
        missing: list[str] | None = None
        commits: list | None = None
        dropped: dict[str, int] | None = None
        for port, buf, policy, spec in rt.inputs:
            value, ids, n_dropped, commit = policy.select(buf, tau)
            if value is MISSING:
                if spec.required:
                    (missing := missing or []).append(port)
                else:
                    values[port] = spec.fallback()
                continue
            values[port] = value
            consumed[port] = ids
            if commit is not None:
                (commits := commits or []).append((policy, buf, commit))
            if n_dropped:
                (dropped := dropped or {})[port] = n_dropped
        if missing is not None:
            stats.skips += 1
            self.trace.raw_steps.append((rt.id, tau, {}, (), "skipped", {"missing": missing}, 0, 0))
            return
        if commits is not None:
            for policy, buf, commit in commits:
                policy.commit_to(buf, commit)
        fallbacks = rt.fallbacks
        if fallbacks:
            for port, spec in fallbacks.items():
                values[port] = spec.fallback()

        start = time_ns()
        try:
            outputs = rt.read(rt.invoke(values))
        except Exception as exc:
            wall = time_ns() - start
            stats.step_ns += wall
            self._failed(rt, tau, consumed, exc, start, wall)
            return
        end = time_ns()
        stats.step_ns += end - start
        stats.steps += 1

        out_tag = (tau[0] + rt.latency_ns, 0) if rt.latency_ns else (tau[0], tau[1] + 1)
        produced = []
        if outputs:
            events, seqs, node_id = self.trace.raw_events, rt.seq, rt.id
            for port, value in outputs:
                if value is None:  # sparse output: no event
                    continue
                seq = seqs.get(port, 0)
                seqs[port] = seq + 1
                events.append((out_tag, node_id, port, seq, value, end))
                produced.append((node_id, port, seq))
                for consumer, buf, delay_ns, triggers in rt.downstream.get(port, ()):
                    arrival = (out_tag[0] + delay_ns, 0) if delay_ns else out_tag
                    buf.insert((arrival, node_id, port, seq, value))
                    if triggers:
                        if arrival[1] > self.max_microsteps:
                            raise CausalityError(rt.cycle or self._nodes[consumer].cycle, tau, self.max_microsteps)
                        self._schedule(arrival, consumer)
        self.trace.raw_steps.append((rt.id, tau, consumed, tuple(produced), "ok", dropped, start, end - start))

    def _failed(self, rt: _NodeRuntime, tau: tuple[int, int], consumed: dict, exc: Exception,
                start: int, wall: int) -> None:
        rt.stats.errors += 1
        detail = {"error": f"{type(exc).__name__}: {exc}", "on_error": rt.on_error}
        self.trace.raw_steps.append((rt.id, tau, consumed, (), "error", detail, start, wall))
        if rt.on_error == "stop":
            raise StepError(rt.id, tau, exc) from exc
        if rt.on_error == "restart":
            rt.flow.reset()

    def stats(self) -> dict[str, NodeStats]:
        return {rt.id: rt.stats for rt in self._nodes}

    def seeds(self) -> dict:
        return {} if self._rng is None else {"tie_break_seed": self._tie_break_seed}

    # ---------------------------------------------------------------------------------------
    # Hooks for replay (retriever.log.replay): drive ticks from a log instead of the clocks
    # ---------------------------------------------------------------------------------------
    def take_routes(self) -> dict[tuple[str, str], list[tuple[PortBuffer, int]]]:
        """Stop delivering outputs; return where each ``(node, port)`` delivered, with its delay,
        so the caller can deliver logged events instead."""
        routes: dict[tuple[str, str], list[tuple[PortBuffer, int]]] = {}
        for rt in self._nodes:
            for port, consumers in rt.downstream.items():
                routes[(rt.id, port)] = [(buf, delay_ns) for _, buf, delay_ns, _ in consumers]
            rt.downstream = {}
        return routes

    def tick(self, node: str, tau: tuple[int, int]) -> None:
        """Run one tick of ``node`` at ``tau`` now, as the loop would (records land in the trace)."""
        self._tick(self._by_id[node], tau)

    def replace_step(self, node: str, outputs: Any) -> None:
        """Make ``node``'s ticks emit ``next(outputs)`` (an iterable of ``(port, value)``) instead
        of calling its ``step()``: replayed sources."""
        rt = self._by_id[node]
        rt.invoke = lambda values: next(outputs)
        rt.read = lambda raw: raw


class _AlwaysMissingPolicy:
    """Stands in for the policy of a required port nothing feeds: every tick is skipped."""

    def select(self, buf, tau):
        return MISSING, None, 0, None


_AlwaysMissing = _AlwaysMissingPolicy()


class InprocBackend(Backend):
    name = "inproc"

    def open(self, graph: Graph, tie_break_seed: int | None = None, **options: object) -> InprocSession:
        if options:
            from ..errors import BackendError

            raise BackendError(f"the inproc backend takes no options {sorted(options)} "
                               "(it accepts tie_break_seed=)")
        return InprocSession(graph, tie_break_seed=tie_break_seed)
