"""Tick functions for the in-process backend, generated once per session.

``tick.run_tick`` is the reference: one generic function that asks every input's policy to
select, calls the flow through its invoker and reader, and hands the outputs to the session.
Most nodes are simpler than that — every input a ``Latest()`` port, a known calling convention,
known output ports — and for those :func:`compile_tick` writes the code of a tick that does
exactly what ``run_tick`` would do for that node with everything its plan (retriever.plan) says
inlined: ``Latest.select`` unrolled per port, the step call spelled out (``step(Num(x=v0))``),
the outputs read by attribute, each output delivered to its consumers without looking them up.
Anything else (another policy, a staleness bound, a port name that is not an identifier, a
replaced step) is not compiled; a step output of an unexpected type (a dict from a typed flow, an
untyped flow's dict of other ports, a value not of a plain type), an error, a skipped tick, leave
the compiled path for the session's generic helpers (``Host.emit``, ``failed``, ``skipped``).

The generated code reads the session through :class:`Host`, the session's surface for it, and
each node through its ``NodeRuntime`` (``rt``: its flow, buffers, consumers, counters) and that
node's plan (``rt.plan``: who feeds each input); nothing else of the session.

:func:`make_ticks` turns the code of every node into one function per node; per rate group whose
ticks run in node order, one more that runs them all, one after the other, with no call in
between, and one that runs its ticks in a loop while nothing else is due at their times, with
the chain they trigger; and per node that triggers one other node at the next microstep (a chain
of Trigger flows), one that goes on with it as long as it is the only tick due.

A compiled tick that ran records its step in the trace's tape as one compact record, expanded
into the step record and its events when the trace is read (``Trace.tape``):

    [expand, tau, wall start, wall end, one slot per input port, value and seq per output port]

An input's slot is the seq of the event it consumed (its producer is the one the port's only
edge comes from), the consumed buffer entry when several edges feed the port, None when an
optional port had nothing; an output's value and seq are None when it made no event. A chain's
link keeps a shorter record (see _TickWriter._record_line). The node's steps and step time are
counted as its records are expanded (the session expands the tape before it reads the counts).
While a log is written (``Trace.log_records``), an expander also makes the log's Message records
of the step it expands, where the record has the one common shape (see _TickWriter._step_log),
and of its event, where the value is a float or an int of up to 32 bits (_TickWriter._event_log):
a logged step then costs no msgpack of nested tuples and no writer's pass over its events
(benchmarks/reports/logging_overhead.md).

Kept in sync with ``tick.run_tick`` by tests/backends/test_inproc_ticks.py, which runs graphs with
the compiled ticks and with ``run_tick`` only and compares the traces record by record (wall-clock
fields aside).
"""

from __future__ import annotations

import functools
import keyword
import re
import struct
from bisect import insort
from collections.abc import Callable
from dataclasses import dataclass, field
from time import time_ns
from typing import Any

import msgpack

from ..flow.core import settings_of
from ..sync import Latest
from ..trace import StepStatus

_U32 = 0xFFFFFFFF
#: the data of an event's log record, msgpack ``[microstep, value]``, of a value whose bytes have a
#: byte order: a fixarray of 2, a fixint microstep, the value's type byte, the value big-endian
_EVENT_DATA = {"float": struct.Struct(">BBBd"), "uint32": struct.Struct(">BBBI")}
#: the data's formats of the others (a fixint, a uint8, a uint16 as two bytes), each packed with
#: the record's head in one call (Trace.log_records: ``record_pack``)
_WHOLE_EVENT_DATA = ("BBB", "BBBB", "BBBBB")


@dataclass(eq=False)
class Host:
    """What generated ticks read and call in the session that runs them (InprocSession)."""

    nodes: dict[str, Any]  # node id -> its NodeRuntime
    tape: list  # the trace's tape, where ticks append their records (Trace.tape)
    after: list[int]  # the node indices due at the next microstep of the tag running now
    heap: list[tuple[int, int]]  # the tags due later: a lone group stops before one at its tick's time
    max_microsteps: int
    plain_types: frozenset[type]  # output types the codec always encodes: no check before recording
    emit: Callable  # emit(rt, tau, outputs, consumed, start, end): outputs a generated tick does not take
    skipped: Callable  # skipped(rt, tau, missing)
    failed: Callable  # failed(rt, tau, consumed, exc, start, wall): a step that raised, on_error acted on
    schedule: Callable  # schedule(tag, index): a tick of node ``index`` at ``tag`` (a delayed trigger)
    keep_next: Callable  # keep_next(tag): a tick raised; what ``after`` holds goes on the heap at ``tag``
    saw_ports: Callable  # saw_ports(rt, outputs): an untyped step returned other ports than expected
    microsteps: Callable  # microsteps(tag, ran) -> (tag, ran): run ``after`` and what it triggers
    resume_group: Callable  # resume_group(g, k): rate group ``g`` goes on from its tick ``k``
    #: bound(buf, tau): a tick at ``tau`` filled ``buf`` past its ``bound_at`` (sync.fill)
    bound: Callable
    #: set by the session when the loop is to look at it (a stop, a flush asked for, ticks to
    #: generate anew): a lone group's loop stops at its next tick
    look: bool = False


def _identifier(name: object) -> bool:
    return isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)


def _own_step(flow: Any) -> bool:
    """Whether ``flow.step`` is its class's ``step`` bound to it (not one set on the instance, a
    mock or a partial, whose parameters the class's signature does not tell)."""
    bound = flow.step
    return getattr(bound, "__self__", None) is flow and getattr(bound, "__func__", None) is getattr(type(flow), "step")


def _indent(text: str, indent: str = "    ") -> str:
    return "".join(indent + line + "\n" for line in text.splitlines())


def _nonlocal(names) -> str:
    names = ", ".join(names)
    return f"    nonlocal {names}\n" if names else ""


@dataclass
class NodeCode:
    """The generated code of one node's tick, to be put together by :func:`make_ticks`. Every
    name it uses that is the node's own ends in the node's index ``k``."""

    k: int
    names: dict[str, Any]  # the objects its code refers to
    state: list[str]  # its variables: set up in make(), nonlocal in the functions that change them
    init: str  # make()'s lines that set them up
    body: str  # one tick, at tag ``tau``, outputs at ``out_tag`` (no return: it falls through)
    flush: str  # flush()'s lines: the counts to rt.stats, the seqs to rt.seq, ``visible`` to the buffers
    expand: str  # ``expand{k}(tape, i, add_event, add_step)``, the tape's record format
    helpers: str  # the functions the tick calls off its fast path: ``error{k}``, ``generic{k}``
    follower: int | None  # the one node its outputs can trigger at the next microstep, if one
    #: per input, the node whose events alone fill it, on an undelayed edge, with no latency: in a
    #: fused rate group that runs this node before that one, or where this node's tick is the
    #: only one at its tag, every event there is visible (_all_visible)
    fed_by: dict[int, int] = field(default_factory=dict)
    record: str = ""  # the line of the body that appends its compact record to the tape
    #: per node whose follower this node can be in a chain (its one edge to this node feeds an
    #: input it alone feeds): the line that appends this node's short record there in place of
    #: ``record``, and that record's expander (``link{k}_{i}``, see _TickWriter._expander)
    links: dict[int, tuple[str, str]] = field(default_factory=dict)
    #: per input, the variable of its count of visible entries (the buffer's ``visible`` is
    #: behind it until flush(); make_ticks' ``visibles`` read them, for the session's ``bound``)
    visible: list[str] = field(default_factory=list)


def compile_tick(host: Host, rt: Any) -> NodeCode | None:
    """The code of a tick that does what ``tick.run_tick`` does for ``rt`` (a NodeRuntime of the
    session ``host`` is the surface of), or None if this node needs the generic path.

    The tick counts the ticks that ran no step (``ticks{k}``), and keeps the seq of its known
    output ports and each input buffer's ``visible``, in variables of its own; the tick counts
    a step that takes the generic path and its time (``steps{k}``, ``wall{k}``), ``expand{k}``
    the others' (``xsteps{k}``, ``xwall{k}``: a trace may be read, and its tape expanded, in
    another thread than the run's, under the trace's lock, under which flush() reads them too).
    """
    if rt.replaced:
        return None
    for port, buf, policy, spec in rt.inputs:
        if type(policy) is not Latest or policy.staleness is not None:
            return None
    spec = rt.spec
    if spec.in_mode in ("io", "params") and not all(map(_identifier, [*(p for p, *_ in rt.inputs), *rt.fallbacks])):
        return None
    if spec.out_mode == "io":
        known = list(spec.outputs or ())  # output ports read by attribute
        if not all(map(_identifier, known)):
            return None
    elif spec.out_mode == "single":
        known = list(spec.outputs)
    else:  # untyped: a dict of ports; a dict of exactly the wired ones takes the compiled path, or
        known = list(rt.ports_seen or rt.downstream)  # of the ports of the first that was not
    return _TickWriter(rt, known, host.nodes).code()


class _TickWriter:
    """Writes the code of one node's compiled tick (:func:`compile_tick`), piece by piece."""

    def __init__(self, rt: Any, known: list[str], nodes: dict[str, Any]):
        self.rt, self.known, self.nodes = rt, known, nodes
        #: per input, the ``(node, port)`` of each edge that feeds it (its plan's)
        self.sources = [rt.plan.sources(port) for port, *_ in rt.inputs]
        self.k = k = rt.index
        spec = rt.spec
        self.names: dict[str, Any] = {
            f"stats{k}": rt.stats, f"node{k}": rt.id, f"step{k}": rt.flow.step, f"seqs{k}": rt.seq,
            f"read{k}": rt.read, f"rt{k}": rt, f"in_type{k}": spec.in_type, f"out_type{k}": spec.out_type,
            f"known{k}": tuple(known),
            # what the step said of its tick (Flow.add_step_detail): a record with detail, which
            # only the generic path writes (the one dict, emptied in place when it is taken)
            f"detail{k}": settings_of(rt.flow).step_detail,
        }
        self.ports = [port for port, *_ in rt.inputs]
        self.required = [port_spec.required for *_, port_spec in rt.inputs]
        self.seq = [f"seq{k}_{j}" for j in range(len(known))]
        self.visible = [f"visible{k}_{i}" for i in range(len(self.ports))]
        self.values = [f"v{j}" for j in range(len(known))]

    def code(self) -> NodeCode:
        k, rt = self.k, self.rt
        init = (f"ticks{k} = steps{k} = wall{k} = xsteps{k} = xwall{k} = 0\n"
                f"logged{k} = step_fixed{k} = event_heads{k} = event_packs{k} = None\n")
        init += "".join(f"{s} = seqs{k}.get({port!r}, 0)\n" for port, s in zip(self.known, self.seq))
        init += "".join(f"{v} = buf{k}_{i}.visible\n" for i, v in enumerate(self.visible))
        flush = (f"stats{k}.ticks += ticks{k} + steps{k} + xsteps{k}\nstats{k}.steps += steps{k} + xsteps{k}\n"
                 f"stats{k}.step_ns += wall{k} + xwall{k}\nticks{k} = steps{k} = wall{k} = xsteps{k} = xwall{k} = 0\n"
                 f"{self._to_seqs()}")
        flush += "".join(f"buf{k}_{i}.visible = {v}\n" for i, v in enumerate(self.visible))
        for i, (_, buf, _, port_spec) in enumerate(rt.inputs):
            self.names.update({f"buf{k}_{i}": buf, f"entries{k}_{i}": buf.entries,
                               f"fallback{k}_{i}": port_spec.fallback})
        state = [f"ticks{k}", f"steps{k}", f"wall{k}", f"xsteps{k}", f"xwall{k}", *self.seq, *self.visible]
        followers = {consumer for port in self.known for consumer, _, delay_ns, triggers in rt.downstream.get(port, ())
                     if triggers and not delay_ns and not rt.latency_ns}
        follower = followers.pop() if len(followers) == 1 else None
        # the output whose event a follower in a chain consumes: its one edge to it
        to_follower = [j for j, port in enumerate(self.known) for consumer, *_ in rt.downstream.get(port, ())
                       if consumer == follower]
        self.passes = to_follower[0] if len(to_follower) == 1 else None
        fed_by = self._fed_by()
        links = {}
        feeds = [node for sources in self.sources for node, _ in sources]
        for i, producer in fed_by.items():
            if feeds.count(self.sources[i][0][0]) == 1:  # its one edge to this node
                links[producer] = (self._record_line(link=i), self._expander(link=i))
        return NodeCode(k, self.names, state, init, self._body(), flush, self._expander(), self._helpers(), follower,
                        fed_by, self._record_line(), links, self.visible)

    def _fed_by(self) -> dict[int, int]:
        """NodeCode.fed_by: input ``i`` -> the index of the node that alone feeds it, where that
        node stamps its events at the next microstep of its tick (no latency, no delay)."""
        fed = {}
        for i, (port, *_) in enumerate(self.rt.inputs):
            feeds = [feed for feed in self.rt.plan.feeds if feed.port == port]
            if len(feeds) == 1 and not feeds[0].src_latency_ns and not feeds[0].delay_ns:
                fed[i] = self.nodes[feeds[0].src].index
        return fed

    # -- the tick --------------------------------------------------------------------------
    def _body(self) -> str:
        """Select every input; skip the tick if a required port has nothing, else run it."""
        k, ports, required = self.k, self.ports, self.required
        if required == [True]:  # one port, required: the step runs in the branch that found a value
            return (f"{self._select(0)}{_indent(self._run())}"
                    f"else:\n    ticks{k} += 1\n    skipped(rt{k}, tau, [{ports[0]!r}])\n")
        body = ""
        for i, port in enumerate(ports):
            on_missing = (f"arg{i} = fallback{k}_{i}()" if not required[i]
                          else f"missing = missing or []\n    missing.append({port!r})")
            body += f"{self._select(i)}else:\n    entry{i} = None\n    {on_missing}\n"
        if not any(required):
            return body + self._run()
        return (f"missing = None\n{body}if missing is None:\n{_indent(self._run())}"
                f"else:\n    ticks{k} += 1\n    skipped(rt{k}, tau, missing)\n")

    def _select(self, i: int) -> str:
        """``Latest.select`` on input ``i``: PortBuffer.advance and trim inlined, on the buffer's
        entries and a copy of its ``visible`` of the tick's own. If ``H`` is not empty, ``n`` is
        true and the newest is in ``entry{i}``, its value in ``arg{i}``; the code that follows at
        this indent runs only then, and an ``else:`` after it, only if not."""
        k = self.k
        return f"""\
entries = entries{k}_{i}
{_visibility(k, i)}if n:
    entry{i} = entries[n - 1]
    arg{i} = entry{i}[4]
    if n > {self.rt.inputs[i][1].trim_batch}:
        del entries[:n - 1]
        n = 1
    visible{k}_{i} = n
"""

    def _run(self) -> str:
        """Call the step between two clock readings; an error goes to ``failed``, outputs that
        the compiled path does not take to ``emit``, the rest to :meth:`_record`."""
        k = self.k
        # a step output of another type leaves in v0 (or in outputs, with no known port) what
        # read() makes of it, a list: not of a plain type, so it takes the generic path below
        got = self.values[0] if self.values else "outputs"
        expected, reads = self._reads()
        read_lines = "".join(f"{v} = {expr}\n" for v, expr in zip(self.values, reads)) or "outputs = None\n"
        if self.rt.spec.out_mode == "dict" and len(self.known) == 1:  # a dict of one key: that one, or
            read_lines = (f"try:\n    {read_lines}"
                          f"except KeyError:  # another: read() says what, the generic path takes it\n"
                          f"    {got} = read{k}(raw)\n")
        no_events = f"{' = '.join(self.values or ['outputs'])} = None\n"
        entries = "".join(f", entry{i}" for i in range(len(self.ports)))
        return f"""\
start = time_ns()
try:
    raw = {self._call()}
    if {expected}:
{_indent(read_lines, "        ")}    elif raw is None:
{_indent(no_events, "        ")}    else:
        {got} = read{k}(raw)
except KeyboardInterrupt:
    ticks{k} += 1  # (as run_tick counts it)
    raise
except BaseException as exc:  # SystemExit too, as in run_tick
    error{k}(tau, exc, start, (now := time_ns()) - start{entries})
else:
    now = time_ns()
    if {" or ".join(self._generic())}:
        generic{k}(tau, raw, start, now{entries})
    else:
{_indent(self._record(), "        ")}"""

    def _helpers(self) -> str:
        """``error{k}``, for a step that raised, and ``generic{k}``, for outputs the compiled path
        does not take: what they need of the tick, its consumed ids, to the session's generic helpers."""
        k = self.k
        entries = "".join(f", entry{i}" for i in range(len(self.ports)))
        seen = (f"if type(raw) is dict and tuple(raw) != known{k}:\n    saw_ports(rt{k}, raw)\n"
                if self.rt.spec.out_mode == "dict" and self.rt.ports_seen is None else "")
        from_seqs = "".join(f"{s} = seqs{k}[{port!r}]\n" for port, s in zip(self.known, self.seq))
        consumed = self._consumed("entry")
        return f"""\
def error{k}(tau, exc, start, wall{entries}):
    nonlocal ticks{k}, wall{k}
    wall{k} += wall
    ticks{k} += 1
{_indent(consumed)}    failed(rt{k}, tau, consumed, exc, start, wall)
def generic{k}(tau, raw, start, now{entries}):
{_nonlocal([f"steps{k}", f"wall{k}", *self.seq])}    wall{k} += now - start
    steps{k} += 1
{_indent(consumed + self._to_seqs() + seen)}    try:  # emit() may raise after it counted events
        emit(rt{k}, tau, read{k}(raw), consumed, start, now)
    finally:
{_indent(from_seqs or "pass", "        ")}"""

    def _call(self) -> str:
        """The step call: make_invoker, spelled out; optional ports nothing feeds get their fallback."""
        k, rt, mode = self.k, self.rt, self.rt.spec.in_mode
        args = [f"arg{i}" for i in range(len(self.ports))]
        for u, port_spec in enumerate(rt.fallbacks.values()):
            self.names[f"unfed{k}_{u}"] = port_spec.fallback
            args.append(f"unfed{k}_{u}()")
        names = [*self.ports, *rt.fallbacks]
        keywords = ", ".join(f"{p}={a}" for p, a in zip(names, args))
        if mode == "params" and rt.spec.positional is not None and sorted(rt.spec.positional) == sorted(names) \
                and _own_step(rt.flow):
            by_name = dict(zip(names, args))  # the same call, by position (a little faster)
            return f"step{k}({', '.join(by_name[p] for p in rt.spec.positional)})"
        if mode == "io":
            return f"step{k}(in_type{k}({keywords}))"
        if mode == "single":
            return f"step{k}({args[0]})"
        if mode == "params":
            return f"step{k}({keywords})"
        return f"step{k}(None)" if rt.spec.source_takes_arg else f"step{k}()"

    def _reads(self) -> tuple[str, list[str]]:
        """The test that the step returned what make_output_reader expects, and how to read each
        known port from it (a None output: no events, read by the caller)."""
        k, known, mode = self.k, self.known, self.rt.spec.out_mode
        if mode == "io":
            return f"type(raw) is out_type{k}", [f"raw.{p}" for p in known]
        if mode == "single":
            return "raw is not None", ["raw"]
        keys = ("not raw" if not known else "len(raw) == 1" if len(known) == 1 else f"tuple(raw) == known{k}")
        return f"type(raw) is dict and {keys}", [f"raw[{p!r}]" for p in known]

    def _generic(self) -> list[str]:
        """When the generic path takes the outputs: another type, values the codec must look at,
        a trigger past max_microsteps (an error, raised as _emit does, after the outputs before it),
        a step that said something of its tick (Flow.add_step_detail: its record has detail)."""
        rt = self.rt
        conditions = [f"type({v}) not in plain" for v in self.values] or ["outputs is not None"]
        if not rt.latency_ns and any(triggers and not delay_ns for port in self.known
                                     for _, _, delay_ns, triggers in rt.downstream.get(port, ())):
            conditions.append("out_tag[1] > max_microsteps")
        conditions.append(f"detail{self.k}")  # the step said something of its tick: a record with detail
        return conditions

    def _record(self) -> str:
        """Count each output's seq, deliver its event, and append the compact record to the tape."""
        k, rt = self.k, self.rt
        out_tag = f"(tau[0] + {rt.latency_ns}, 0)" if rt.latency_ns else "out_tag"
        # a rate tick's tau is its group's, shared; a trigger tick's is its own: kept as two ints
        # (of which the time is its instant's, shared), it goes with the tick's events
        src = []
        for j, port in enumerate(self.known):
            emits = f"s{j} = {self.seq[j]}\n{self.seq[j]} = s{j} + 1\n"
            if rt.downstream.get(port):
                emits += f"ev = ({out_tag}, node{k}, {port!r}, s{j}, v{j}, now)\n" + self._deliver(j, port)
            src.append(f"if v{j} is not None:\n{_indent(emits)}else:\n    s{j} = None\n")
        src.append(self._record_line())
        return "".join(src)

    def _record_line(self, link: int | None = None) -> str:
        """The line that appends the tick's compact record to the tape: ``[expand{k}, tau (one
        field or two), start, end, a slot per input, value and seq per output]``; or, as a chain's
        link whose input ``link`` its predecessor in the chain alone feeds, ``[link{k}_{link},
        end, a slot per other input, value and seq per output]``: its tag, start and that slot
        are the predecessor's (the record just before it in the tape; see _expander)."""
        k, rt = self.k, self.rt
        slots = self._slots()
        if link is None:
            tau = ["tau"] if rt.clock.hz is not None else ["tau[0]", "tau[1]"]
            record = [f"expand{k}", *tau, "start", "now", *slots]
        else:
            record = [f"link{k}_{link}", "now", *(slot for i, slot in enumerate(slots) if i != link)]
        record += [f"{x}{j}" for j in range(len(self.known)) for x in ("v", "s")]
        return f"tape_extend(({', '.join(record)},))\n"

    def _deliver(self, j: int, port: str) -> str:
        """Deliver output ``j``'s event ``ev`` to each consumer (``sync.fill`` inlined: the
        session's ``bound`` when a buffer is due, with the consumer's count of entries it saw).

        A buffer that only this port feeds gets its entries in order (a node's ticks run in tag
        order, and its output tags and an edge's delay keep that order), so it is appended to. The
        event itself is the entry of every undelayed edge; a delayed one gets an entry at its
        arrival tag."""
        k, rt, out = self.k, self.rt, []
        edges = zip(rt.downstream.get(port, ()), rt.plan.consumers.get(port, ()), strict=True)
        for c, ((consumer, buf, delay_ns, triggers), edge) in enumerate(edges):
            dbuf = f"dbuf{k}_{j}_{c}"
            self.names[dbuf], self.names[f"consumer{k}_{j}_{c}"] = buf.entries, consumer
            self.names[f"dbo{k}_{j}_{c}"] = buf
            if delay_ns:
                out.append(f"entry = ((ev[0][0] + {delay_ns}, 0), *ev[1:])\n")
            entry = "entry" if delay_ns else "ev"
            if len(self.nodes[edge.dst].plan.sources(edge.dst_port)) == 1:
                out.append(f"{dbuf}.append({entry})\n")
            else:
                out.append(f"if not {dbuf} or {dbuf}[-1] < {entry}:\n    {dbuf}.append({entry})\n"
                           f"else:\n    insort({dbuf}, {entry})\n")
            if not (triggers or self._keeps_pace(self.nodes[edge.dst])):
                # sync.fill's bound, inlined: what the consumer's policy can no longer select goes
                out.append(f"if len({dbuf}) >= dbo{k}_{j}_{c}.bound_at:\n    bound(dbo{k}_{j}_{c}, tau)\n")
            if triggers:  # a tick of the consumer at the event's arrival: the next microstep, if undelayed
                out.append(f"schedule({entry}[0], consumer{k}_{j}_{c})\n" if delay_ns or rt.latency_ns
                           else f"next_add(consumer{k}_{j}_{c})\n")
        return "".join(out)

    def _keeps_pace(self, consumer: Any) -> bool:
        """Whether ``consumer`` ticks at least as often as this node, a Rate flow, emits: its own
        ticks trim its buffer of this node's events (its selects do, skipped or not), so the
        bound need not be looked at on this edge (nor paid for; a consumer this edge triggers
        ticks on each of its events)."""
        mine, theirs = self.rt.clock, consumer.clock
        return (not mine.triggered and mine.hz is not None and theirs.hz is not None
                and theirs.hz >= mine.hz)

    def _to_seqs(self) -> str:
        return "".join(f"seqs{self.k}[{port!r}] = {s}\n" for port, s in zip(self.known, self.seq))

    # -- what an input consumed: in the tick, from its entry; in expand, from its slot ----------
    def _single_source(self, i: int) -> bool:
        """Whether one edge feeds input ``i`` (then its slot is the consumed event's seq)."""
        feeds = self.sources[i]
        if len(feeds) == 1:
            self.names[f"src{self.k}_{i}"], self.names[f"srcport{self.k}_{i}"] = feeds[0]
        return len(feeds) == 1

    def _slots(self) -> list[str]:
        slots = [f"entry{i}[3]" if self._single_source(i) else f"entry{i}" for i in range(len(self.ports))]
        return [s if r else f"None if entry{i} is None else {s}" for i, (s, r) in enumerate(zip(slots, self.required))]

    def _consumed(self, held: str) -> str:
        """Lines that make the step record's ``consumed``, the ids of what each input consumed:
        ``entry{i}``, the buffer entry (in the tick), or ``c{i}``, the slot (in expand)."""
        k, ids = self.k, []
        for i in range(len(self.ports)):
            if not self._single_source(i):
                ids.append(f"(({held}{i}[1], {held}{i}[2], {held}{i}[3]),)")
            else:
                ids.append(f"((src{k}_{i}, srcport{k}_{i}, {held}{i}{'[3]' if held == 'entry' else ''}),)")
        pairs = list(zip(self.ports, ids, self.required))
        return ("consumed = {" + ", ".join(f"{p!r}: {x}" for p, x, r in pairs if r) + "}\n"
                + "".join(f"if {held}{i} is not None:\n    consumed[{p!r}] = {x}\n"
                          for i, (p, x, r) in enumerate(pairs) if not r))

    # -- the record format -----------------------------------------------------------------
    def _expander(self, link: int | None = None) -> str:
        """``expand{k}(tape, i, add_event, add_step)``: the events and the step record of the
        compact record at ``tape[i]``, as ``_emit`` records them; counts the step and its time.
        With ``link``, ``link{k}_{link}``, the same for a chain link's short record: its tag is
        the microstep after the record before it, its start that record's end, the slot of input
        ``link`` that record's seq of the output to this node (``chain_tau``, ``chain_end``,
        ``chain_s``: what each expander of a node that has a follower leaves for it)."""
        k, rt, known = self.k, self.rt, self.known
        slots = [f"c{i}" for i in range(len(self.ports)) if i != link]
        outs = [f"{x}{j}" for j in range(len(known)) for x in ("v", "s")]
        if link is None:
            fields = ["_", *(["tau"] if rt.clock.hz is not None else ["t", "m"]), "start", "end", *slots, *outs]
            head = "" if rt.clock.hz is not None else "tau = (t, m)\n"
        else:
            fields = ["_", "end", *slots, *outs]
            head = f"tau = (chain_tau[0], chain_tau[1] + 1)\nstart = chain_end\nc{link} = chain_s\n"
        leave = "" if self.passes is None else f"chain_tau, chain_end, chain_s = tau, end, s{self.passes}\n"
        if rt.latency_ns:
            out_tag = f"out_tag = (tau[0] + {rt.latency_ns}, 0)\n"
        else:  # the ticks of a rate group share their tau: their events share one out_tag, as in the run
            out_tag = ("if tau is not last_tau:\n    last_tau, last_out = tau, (tau[0], tau[1] + 1)\n"
                       "out_tag = last_out\n")
        if len(known) == 1:  # the common case, without a list
            events = f"""\
if v0 is None:
    produced = ()
else:
    add_event((out_tag, node{k}, {known[0]!r}, s0, v0, end))
    produced = ((node{k}, {known[0]!r}, s0),)
"""
        else:
            events = "produced = []\n" + "".join(f"""\
if v{j} is not None:
    add_event((out_tag, node{k}, {port!r}, s{j}, v{j}, end))
    produced.append((node{k}, {port!r}, s{j}))
""" for j, port in enumerate(known)) + "produced = tuple(produced)\n"
        return f"""\
def {"expand" if link is None else "link"}{k}{"" if link is None else f"_{link}"}(tape, i, add_event, add_step, log=None, seq=0):
    nonlocal xsteps{k}, xwall{k}, last_tau, last_out, chain_tau, chain_end, chain_s, logged{k}, step_fixed{k}, event_heads{k}, event_packs{k}
    {", ".join(fields)}, = tape[i:i + {len(fields)}]
{_indent(head)}    wall = end - start
    xsteps{k} += 1
    xwall{k} += wall
{_indent(self._consumed("c") + (out_tag if known else "") + events)}\
    add_step((node{k}, tau, consumed, produced, OK, None, start, wall))
    if log is not None:
{_indent(self._log_records(), "        ")}{_indent(leave)}    return i + {len(fields)}
"""

    def _log_records(self) -> str:
        """An expander's lines that add the log's records of the step it expanded and of its
        events (Trace.log_records): first, what this node's records are made with (the fixed
        bytes of their heads, the packs of whole records), once per hand-over of the log
        (``logged{k}``, the ``log`` they were read for), then _step_log's lines and _event_log's."""
        k, known = self.k, self.known
        step, size = self._step_log()
        event = self._event_log()
        heads = "".join([f"step_fixed{k} = log[3]({size})\n" if size else "",
                         f"event_heads{k} = log[4](node{k}, {known[0]!r})\n"
                         f"event_packs{k} = ({', '.join(f'log[5]({f!r})' for f in _WHOLE_EVENT_DATA)})\n"
                         if len(known) == 1 else ""])
        return (f"if log is not logged{k}:\n    logged{k} = log\n{_indent(heads)}" if heads else "") + step + event

    def _event_log(self) -> str:
        """An expander's lines that add the log's record of each event of the step it expanded,
        in the order the events were added: of a float or an int from 0 to 2**32 - 1 (one output),
        the Message record, its data the msgpack ``[microstep, value]`` (a fixarray, a fixint
        microstep, the value as msgpack writes it: a float 64, the shortest uint), its head's
        fixed bytes ``event_heads{k}[len(data)]``: a value of one to three bytes in one
        ``struct.pack`` of the whole record (its bytes have no byte order: ``event_packs{k}``), a
        float or uint32 in a pack of the head and one of the data (``event_float``,
        ``event_uint32``: _EVENT_DATA, big-endian);
        None, for the log writer to make, for any other event (another type, a microstep of 128
        or more, a port the log has no channel for yet)."""
        k, known = self.k, self.known
        if len(known) != 1:
            return "".join(f"if v{j} is not None:\n    log[1](None)\n" for j in range(len(known)))
        self.names.update({f"event_{kind}": data.pack for kind, data in _EVENT_DATA.items()})
        head = f"event_heads{k}[{{size}}], s0 & {_U32}, out_tag[0], end"
        whole = f"log[1](event_packs{k}[{{i}}]({head}, 0x92, out_tag[1], {{value}}))\n"
        made = {kind: whole.format(i=i, size=2 + len(data_format), value=value)
                for i, (kind, data_format, value) in enumerate([("fixint", "B", "v0"), ("uint8", "BB", "0xCC, v0"),
                                                                  ("uint16", "BBB", "0xCD, v0 >> 8, v0 & 255")])}
        for kind, value in (("float", "0xCB, v0"), ("uint32", "0xCE, v0")):
            made[kind] = (f"log[1](log[2]({head.format(size=_EVENT_DATA[kind].size)}) + "
                          f"event_{kind}(0x92, out_tag[1], {value}))\n")
        return f"""\
if v0 is not None:
    if out_tag[1] >= 128 or event_heads{k} is None:
        log[1](None)
    elif type(v0) is float:
        {made["float"]}\
    elif type(v0) is not int or v0 < 0 or v0 > {_U32}:
        log[1](None)
    elif v0 < 128:
        {made["fixint"]}\
    elif v0 < 256:
        {made["uint8"]}\
    elif v0 < 65536:
        {made["uint16"]}\
    else:
        {made["uint32"]}\
"""

    def _step_log(self) -> tuple[str, int]:
        """An expander's lines that add the log's record of the step it expanded (Trace.log_records),
        and the size of its data (0: none made): the Message record, its data the step's msgpack
        ``(node, microstep, consumed, produced, status, detail, wall)`` in one ``struct.pack`` of
        the bytes that stay the same from step to step and the ints that change, each int in a
        fixed width (uint32 seqs, uint64 wall time: as valid msgpack as the shortest, and read
        back the same); None, for the log writer to encode from the record, where the record is
        not of the one shape written here (an output that made no event, an optional or
        many-edged input, a microstep of 128 or more, ...)."""
        k, rt, known = self.k, self.rt, self.known
        none = "log[0](None)\n"
        # the inputs in its consumed ids: each fed by one edge (an optional one consumed something:
        # c{i} is not None); an optional input nothing feeds is never in them
        fed = [i for i, feeds in enumerate(self.sources) if feeds or self.required[i]]
        if (len(known) != 1 or len(fed) > 15 or not all(len(self.sources[i]) == 1 for i in fed)):
            return none, 0
        pack = functools.partial(msgpack.packb, use_bin_type=True)
        parts: list[bytes | tuple[str, str]] = [b"\x97" + pack(rt.id), ("B", "tau[1]"), bytes((0x80 | len(fed),))]
        for i in fed:
            (src, src_port), = self.sources[i]
            parts += [pack(self.ports[i]) + b"\x91\x93" + pack(src) + pack(src_port) + b"\xce", ("I", f"c{i}")]
        parts += [b"\x91\x93" + pack(rt.id) + pack(known[0]) + b"\xce", ("I", "s0"),
                  pack(StepStatus.OK.value) + b"\xc0\xcf", ("Q", "wall")]
        merged: list[bytes | tuple[str, str]] = []  # neighbouring bytes as one
        for part in parts:
            if type(part) is bytes and merged and type(merged[-1]) is bytes:
                merged[-1] += part
            else:
                merged.append(part)
        data = struct.Struct(">" + "".join(f"{len(p)}s" if type(p) is bytes else p[0] for p in merged))
        self.names[f"step_data{k}"] = data.pack
        args = ", ".join(repr(p) if type(p) is bytes else p[1] for p in merged)
        ints = " and ".join([*(f"c{i} is None" for i in range(len(self.ports)) if i not in fed),
                             *(f"c{i} is not None" for i in fed if not self.required[i]),
                             *(f"c{i} <= {_U32}" for i in fed), f"s0 <= {_U32}", "wall >= 0"])
        return (f"if v0 is not None and tau[1] < 128 and {ints}:\n"
                f"    log[0](log[2](step_fixed{k}, seq, tau[0], start) + step_data{k}({args}))\n"
                f"else:\n    {none}"), data.size


#: the most ticks one chain function runs before the loop takes over again (bounds its code)
CHAIN_MAX = 32


Schedule = tuple[int, int, int]  # a rate group's (offset_ns, step_num, step_den)


def make_ticks(host: Host, parts: list[NodeCode | Callable], groups: list[tuple[tuple[int, ...], Schedule]],
               fuse: bool) -> tuple:
    """``(ticks, chains, fused, alone, flush, peek, visibles)`` of every node: ``parts[i]`` is node ``i``'s code, or
    its generic tick; ``groups`` are the rate groups' nodes and schedules ``(offset_ns, step_num,
    step_den)``. Each function ``f(tau, out_tag)`` runs at ``tau`` with ``out_tag`` the next
    microstep, and returns the ``out_tag`` of the last tick it ran:

    - ``ticks[i]`` runs one tick of node ``i``;
    - ``chains[i]`` too, when it is the only tick due at ``tau``, and if node ``i`` heads a chain
      of Trigger flows (what a rate group's node triggers; each link the one node its
      predecessor can trigger), goes on with the next, at the next microstep, as long as it is
      the only tick due (``after``, the session's list of them, holds just it), and so on;
    - ``fused[g]`` (with ``fuse``) runs one tick of each node of ``groups[g]``, in turn;
    - ``alone[g](k, until_ns, ran, log_at)`` (with ``fuse``) runs the group's ticks ``k, k + 1,
      …`` with the ticks they trigger (the chain the group triggers inline, the rest through
      ``host.microsteps``), as long as nothing else is due at their time: it stops before a
      tick when the heap holds a tag at or before its time, the tick is at or past ``until_ns``,
      ``ran`` (the ticks run, counted on) reaches ``log_at`` or the session asks to look
      (``host.look``: ticks to compile anew, a flush asked for); then, or when a tick
      raises, it hands the group the index of its next tick (``host.resume_group``).
      Returns ``ran``;
    - ``flush()`` hands the counts to each ``rt.stats``, the seqs to ``rt.seq`` and each input's
      ``visible`` to its buffer (the session calls it, after expanding the tape, before it reads them);
    - ``peek()``, per compiled node, ``(index, ticks, steps, step ns)`` counted and not handed
      over yet, changing nothing (for counts read where flushing is not safe: InprocSession.stats);
    - ``visibles``, per input buffer of a compiled node (by ``id``), a function that reads its
      visible count now (for the session's ``bound``, which must not move what a tick counted as seen).
    """
    names: dict[str, Any] = {
        "time_ns": time_ns, "insort": insort, "OK": StepStatus.OK, "tape_extend": host.tape.extend, "emit": host.emit,
        "skipped": host.skipped, "failed": host.failed, "schedule": host.schedule,
        "after": host.after, "next_add": host.after.append, "keep_next": host.keep_next,
        "saw_ports": host.saw_ports, "max_microsteps": host.max_microsteps, "plain": host.plain_types,
        "host": host, "heap": host.heap, "microsteps": host.microsteps, "resume": host.resume_group,
        "bound": host.bound,
    }
    codes = {i: part for i, part in enumerate(parts) if isinstance(part, NodeCode)}
    everyone = set(range(len(parts)))
    short: set[tuple[int, int]] = set()  # (link, predecessor) pairs whose short records _links wrote
    src = ["last_tau = last_out = chain_tau = chain_end = chain_s = None\n", *(code.init for code in codes.values())]
    bodies = []
    for i, part in enumerate(parts):
        if i in codes:
            names.update(part.names)
            src.append(f"def tick{i}(tau, out_tag):\n{_nonlocal(part.state)}{_indent(part.body)}    return out_tag\n")
            bodies.append(part.body)
        else:
            names[f"tick{i}"] = part
            bodies.append(f"tick{i}(tau, out_tag)\nnow = time_ns()\n")  # (the next step starts after it)
    chains = {}
    for head, chain in _chains(codes, groups):
        src.append(_chain_function(head, chain, codes, names, everyone, short))
        chains[head] = f"chain{head}"
    groups = groups if fuse else []
    for g, (group, schedule) in enumerate(groups):
        state = _nonlocal(s for i in group if i in codes for s in codes[i].state)
        body = _one_reading("".join(_without_visible_tests(codes, group, bodies)))
        src.append(f"def fused{g}(tau, out_tag):\n{state}    now = time_ns()\n{_indent(body)}    return out_tag\n")
        src.append(_alone(g, group, schedule, codes, bodies, names, everyone, short))
    state = _nonlocal(s for code in codes.values() for s in code.state)
    src.append(f"def flush():\n{state}{_indent(''.join(code.flush for code in codes.values()))}    pass\n")
    src.append("visibles = {" + "".join(
        f"id(buf{k}_{i}): lambda: {v}, " for k, code in codes.items() for i, v in enumerate(code.visible)) + "}\n")
    src.append("def peek():\n    return (" + "".join(
        f"({k}, ticks{k} + steps{k} + xsteps{k}, steps{k} + xsteps{k}, wall{k} + xwall{k}), " for k in codes) + ")\n")
    src += [code.expand + code.helpers for code in codes.values()]
    src += [expander for i, j in sorted(short) for expander in [codes[j].links[i][1]]]
    chain_of = [chains.get(i, f"tick{i}") for i in range(len(parts))]
    source = (f"def make():\n{_indent(''.join(src))}"
              f"    return ([{', '.join(f'tick{i}' for i in range(len(parts)))}], "
              f"[{', '.join(chain_of)}], [{', '.join(f'fused{g}' for g in range(len(groups)))}], "
              f"[{', '.join(f'alone{g}' for g in range(len(groups)))}], flush, peek, visibles)\n")
    exec(_compiled(source), names)  # noqa: S102
    ticks, chain_ticks, fused, alone, flush, peek, visibles = names["make"]()
    for f in [*(ticks[i] for i in codes), *(chain_ticks[i] for i in chains), *fused, *alone]:
        f.source = source
    return ticks, chain_ticks, fused, alone, flush, peek, visibles


def _chains(codes: dict, groups: list[tuple[tuple[int, ...], Schedule]]) -> list[tuple[int, list[int]]]:
    """``(head, chain)`` of each chain of two or more compiled Trigger flows: headed by what a
    rate group's node triggers, or by a node nothing compiled triggers alone."""
    grouped = {i for group, _ in groups for i in group}
    followed = {code.follower for code in codes.values()}
    heads = {codes[i].follower for i in grouped if i in codes} | {i for i in codes if i not in followed | grouped}
    return [(head, chain) for head in sorted(heads & codes.keys()) if len(chain := _chain(codes, head)) > 1]


def _chain_function(head: int, chain: list[int], codes: dict, names: dict, everyone: set[int],
                    short: set[tuple[int, int]]) -> str:
    """``chain{head}`` (make_ticks). A chain runs only when its head is the only tick due, and
    each link only when it is (so every event an input got from a producer that alone feeds it is
    visible: _all_visible)."""
    links = _links(codes, chain, names, everyone, short)
    return f"""\
def chain{head}(tau, out_tag):
{_nonlocal(s for i in chain for s in codes[i].state)}    now = time_ns()
    pass_on = None
    try:
{_indent(_one_reading(links[0] + _chain_steps(links[1:], "return out_tag")), "        ")}    except BaseException:
        if pass_on is not None:
            next_add(pass_on)
        keep_next(out_tag)
        raise
    return out_tag
"""


def _chain(codes: dict, head: int) -> list[int]:
    """The chain of Trigger flows ``head`` heads: each link the one node the one before can
    trigger (NodeCode.follower), compiled, not yet in it; at most CHAIN_MAX."""
    chain, j = [head], codes[head].follower
    while j in codes and j not in chain and len(chain) < CHAIN_MAX:
        chain.append(j)
        j = codes[j].follower
    return chain


def _links(codes: dict, chain: list[int], names: dict, everyone: set[int], short: set[tuple[int, int]],
           first_after: int | None = None) -> list[str]:
    """The bodies of a chain's ticks, each run as the only tick due at its tag: what a link
    triggers (only ever its follower: NodeCode.follower) goes in ``pass_on`` instead of the
    session's ``after``; no input that one producer alone feeds is tested for visibility (every
    producer's ticks were at earlier tags); and a link after the first (and the first, if
    ``first_after`` is the node whose compact record is always the one before it) records a
    short record where it can (NodeCode.links: the record before it in the tape is its
    predecessor's), noted in ``short``."""
    links = [_passing_on(codes[i].body, j, names) for i, j in zip(chain, chain[1:])] + [codes[chain[-1]].body]
    links = [_all_visible(codes[i], body, everyone) for i, body in zip(chain, links)]
    for at, (before, link) in enumerate(zip([first_after, *chain], chain)):
        code = codes[link]
        if before in code.links:
            assert codes[before].follower == link  # (so its expander leaves the state this record reads)
            assert links[at].count(code.record) == 1
            links[at] = links[at].replace(code.record, code.links[before][0])
            short.add((before, link))
    return links


def _chain_steps(links: list[str], leave: str) -> str:
    """The ticks of chain links, one a microstep, each run if the tick before passed it on and
    nothing else is due (else what was passed on goes to ``after``, and ``leave``)."""
    return "".join(f"""\
if after or pass_on is None:
    if pass_on is not None:
        next_add(pass_on)
    {leave}
pass_on = None
tau = out_tag
out_tag = (tau[0], tau[1] + 1)
{body}""" for body in links)


def _alone(g: int, group: tuple[int, ...], schedule: Schedule, codes: dict, bodies: list[str],
           names: dict, everyone: set[int], short: set[tuple[int, int]]) -> str:
    """``alone{g}`` (make_ticks): the group's ticks in a loop, each with nothing else due at its
    time ``t``, so that at ``(t, 0)`` every event from a producer outside the group, or of the
    group but placed after the consumer, is visible (_all_visible); the chain the group
    triggers, if one, inline."""
    place = {node: at for at, node in enumerate(group)}
    followers = {codes[i].follower for i in group if i in codes} - {None}
    head = followers.pop() if len(followers) == 1 else None
    if head not in codes or head in place:
        head = None
    ticks = []
    for node in group:
        body = bodies[node]
        if node in codes:
            before = {p for p in group if place[p] < place[node]}
            body = _all_visible(codes[node], body, everyone - before)
            if head is not None:
                body = _passing_on(body, head, names, only=True)
        ticks.append(body)
    chain = _chain(codes, head) if head is not None else []
    # the group's last node, if it alone passes the chain on: its record is the one before the chain's
    passing = [node for node, body in zip(group, ticks) if "pass_on = " in body]
    last = group[-1] if passing == [group[-1]] else None
    offset_ns, step_num, step_den = schedule
    inline = "" if head is None else f"""\
while True:  # the chain the group triggers: as chain{head} does
{_indent(_one_reading(_chain_steps(_links(codes, chain, names, everyone, short, last), "break")))}    break
pass_on = None  # (left set when the chain left what it passed on in after)
ran += out_tag[1] - 1
"""
    return f"""\
def alone{g}(k, until_ns, ran, log_at):
{_nonlocal(s for i in {*group, *chain} if i in codes for s in codes[i].state)}    out_tag = pass_on = None
    try:
        while True:
            t = {offset_ns} + k * {step_num} // {step_den}
            if t >= until_ns or heap and heap[0][0] <= t or ran >= log_at or host.look:
                return ran
            tau = (t, 0)
            out_tag = (t, 1)
            pass_on = None
            now = time_ns()
{_indent(_one_reading("".join(ticks)), " " * 12)}            ran += {len(group)}
{_indent(inline, " " * 12)}            if after:
                out_tag, ran = microsteps(out_tag, ran)
            k += 1
    except BaseException:
        if pass_on is not None:
            next_add(pass_on)
        keep_next(out_tag)
        k += 1
        raise
    finally:
        resume({g}, k)
"""


def _visibility(k: int, i: int) -> str:
    """The part of node ``k``'s select on input ``i`` that finds how many entries are visible at
    ``tau`` (``n``, of ``end``): its ``visible`` of the tick before, and as many as came since
    whose tags are not past ``tau``."""
    return f"""\
n = visible{k}_{i}
end = len(entries)
if n < end:  # entries came: all of them are visible, or those up to the first past tau ({k}_{i})
    if entries[-1][0] <= tau:
        n = end
    else:
        while entries[n][0] <= tau:
            n += 1
"""


def _without_visible_tests(codes: dict, group: tuple[int, ...], bodies: list[str]) -> list[str]:
    """The bodies of a fused rate group's ticks, where a node runs before the node that alone
    feeds one of its inputs (NodeCode.fed_by) with that input's visibility test left out: the
    group runs alone at ``tau = (t, 0)``, so that producer's events there came from its ticks
    before ``t`` (its tick at ``t`` comes later), each stamped at the next microstep of its tick
    (no latency, no delay), so not past ``tau``: every entry is visible."""
    place = {node: at for at, node in enumerate(group)}
    return [_all_visible(codes[node], bodies[node], {p for p in group if place[p] > place[node]})
            if node in codes else bodies[node] for node in group]


def _all_visible(code: NodeCode, body: str, producers: set[int]) -> str:
    """``body``, node ``code.k``'s tick, without the visibility test of each input that one of
    ``producers`` alone feeds (NodeCode.fed_by): where the tick runs, every event of such a
    producer in that input is known to be visible (in a fused group, see _without_visible_tests;
    in a chain, the link before runs at the microstep before, and the link runs only if it
    sent an event, stamped at the link's tick, after its earlier ones)."""
    for i, producer in code.fed_by.items():
        if producer in producers:
            test = _visibility(code.k, i)
            assert test in body
            body = body.replace(test, "n = len(entries)\n")
    return body


def _passing_on(body: str, follower: int, names: dict, only: bool = False) -> str:
    """A tick's code in a chain: what it triggers (only ever its follower: NodeCode.follower) goes
    in ``pass_on`` instead of the session's ``after``; with ``only``, its triggers of ``follower``
    go there, its others to ``after``."""
    passed = re.sub(r"next_add\((consumer\d+_\d+_\d+)\)",
                    lambda m: f"pass_on = {follower}" if names[m[1]] == follower else m[0], body)
    assert only or "next_add(" not in passed
    return passed


def _one_reading(bodies: str) -> str:
    """Ticks run one after the other (a fused rate group, a chain) with one clock reading per
    step: each step starts when the one before it ended (``now``, read once at the start), so its
    wall time includes the framework's work since (its inputs' select, the events before it)."""
    return bodies.replace("start = time_ns()\n", "start = now\n")


@functools.lru_cache(maxsize=256)
def _compiled(source: str):
    """The code of one source: graphs of one shape share it (compiling is most of a session's
    start). The source is ours, built from identifiers checked in compile_tick and repr() of port names."""
    return compile(source, "<inproc ticks>", "exec")


def clear_compiled_ticks() -> None:
    """Forget the code compiled for the graphs of earlier sessions, so that the next session
    compiles its ticks from their source as the first one in a process does (a cold start is
    what benchmarks/step_overhead.py times as a session's open)."""
    _compiled.cache_clear()
