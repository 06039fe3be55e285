"""Per-node tick functions for the in-process backend, generated once per session.

``InprocSession._tick`` is the reference: one generic function that asks every input's policy to
select, calls the flow through its invoker and reader, and emits. Most nodes are simpler than
that — every input a required ``Latest()`` port, a known calling convention, known output ports
— and for those :func:`compile_tick` writes a function that does exactly what ``_tick`` would do
for that node with everything known at wiring time inlined: ``Latest.select`` unrolled per port,
the step call spelled out (``step(Num(x=v0))``), the outputs read by attribute, each output
delivered to its consumers without looking them up. Anything else (another policy, a
staleness bound, a port name that is not an identifier, a replaced step) is not compiled; a
step output of an unexpected type (None, a dict from a typed flow, an error) leaves the
compiled path for the session's generic helpers (``_emit``, ``_failed``, ``_skipped``).

Kept in sync with ``_tick`` by tests/backends/test_inproc_ticks.py, which runs graphs with the
compiled ticks and with ``_tick`` only and compares the traces record by record (wall-clock
fields aside).
"""

from __future__ import annotations

import keyword
from bisect import insort
from collections.abc import Callable
from time import time_ns
from typing import Any

from ..errors import CausalityError
from ..sync import Latest


def _identifier(name: object) -> bool:
    return isinstance(name, str) and name.isidentifier() and not keyword.iskeyword(name)


def _select(i: int, port: str, required: bool, only: bool, trim_batch: int) -> str:
    """``Latest.select`` on input ``i`` (PortBuffer.advance inlined), leaving the entry in ``entry{i}``
    (None if MISSING) and the step's argument in ``arg{i}``."""
    if not required:
        on_missing = f"entry{i} = None\n        arg{i} = fallback{i}()"
    elif only:
        on_missing = f"ticks_n += 1\n        return skipped(rt, tau, [{port!r}])"
    else:
        on_missing = f"entry{i} = None\n        missing = missing or []\n        missing.append({port!r})"
    return f"""\
    entries = buf{i}.entries
    n = buf{i}.visible
    end = len(entries)
    while n < end and entries[n][0] <= tau:
        n += 1
    buf{i}.visible = n
    if not n:
        {on_missing}
    else:
        entry{i} = entries[n - 1]
        arg{i} = entry{i}[4]
        if n > {trim_batch}:
            buf{i}.trim(n - 1)
"""


def _deliver(rt: Any, port: Any, names: dict, port_expr: str, feeds: dict) -> str:
    """Deliver the event just recorded on ``port`` to each consumer (``PortBuffer.insert`` inlined).

    A buffer that only this port feeds gets its entries in order (a node's ticks run in tag order,
    and its output tags and an edge's delay keep that order), so it is appended to."""
    out = []
    for consumer, buf, delay_ns, triggers in rt.downstream.get(port, ()):
        c = len(names)
        names[f"dbuf{c}"], names[f"consumer{c}"] = buf.entries, consumer
        arrival = f"(out_tag[0] + {delay_ns}, 0)" if delay_ns else "out_tag"
        if feeds[id(buf)] == 1:
            out.append(f"dbuf{c}.append(({arrival}, node_id, {port_expr}, seq, value, ids))\n")
            if triggers:
                out.append(f"arrival = {arrival}\n")
        else:
            out.append(f"""\
arrival = {arrival}
entry = (arrival, node_id, {port_expr}, seq, value, ids)
if not dbuf{c} or dbuf{c}[-1] < entry:
    dbuf{c}.append(entry)
else:
    insort(dbuf{c}, entry)
""")
        if triggers:
            out.append(f"""\
if arrival[1] > max_microsteps:
    raise CausalityError(rt.cycle or nodes[consumer{c}].cycle, tau, max_microsteps)
schedule(arrival, consumer{c})
""")
    return "".join(out)


# one event on a port whose seq counter lives in the generated code ({seq}), or in rt.seq ({seq} None),
# after the events in {produced}; a value not of a plain type goes to session.check_output first
def _record(port_expr: str, seq: str | None, produced: str) -> str:
    check = (f"if type(value) not in plain:\n"
             f"    check_output(rt, tau, {port_expr}, value, consumed, start, {produced})\n")
    if seq is None:
        count = f"seq = seqs.get({port_expr}, 0)\nseqs[{port_expr}] = seq + 1\n"
    else:
        count = f"seq = {seq}\n{seq} = seq + 1\n"
    return check + count + f"""\
ids = (eid := (node_id, {port_expr}, seq),)
events_append((out_tag, node_id, {port_expr}, seq, value, end))
"""


def _indent(text: str, indent: str) -> str:
    return "".join(indent + line + "\n" for line in text.splitlines())


def compile_tick(session: Any, rt: Any, feeds: dict) -> tuple[Callable, Callable] | None:
    """``(tick, flush)``, or None if this node needs the generic path.

    ``tick(tau, next_microstep)`` does what ``session._tick(rt, tau)`` does (``next_microstep`` is
    ``(tau[0], tau[1] + 1)``, shared by the ticks at ``tau``). It counts ticks (``ticks_n`` only
    those that ran no step: every tick that runs one counts in ``steps_n``), steps and step time,
    and the seq of its known output ports, in variables of its own: ``flush()`` adds the counts to
    ``rt.stats`` and writes the seqs to ``rt.seq`` (the session calls it whenever it leaves the loop).
    """
    if rt.replaced:
        return None
    ports, required = [], []
    for port, buf, policy, spec in rt.inputs:
        if type(policy) is not Latest or policy._staleness_ns is not None:
            return None
        ports.append(port)
        required.append(spec.required)
    spec = rt.spec
    if spec.in_mode in ("io", "params") and not all(map(_identifier, [*ports, *rt.fallbacks])):
        return None
    if spec.out_mode == "io":
        known = list(spec.outputs or ())  # output ports read by attribute
        if not all(map(_identifier, known)):
            return None
    elif spec.out_mode == "single":
        known = list(spec.outputs)
    else:  # untyped: a dict of ports; the wired ones get their own seq counters
        known = list(rt.downstream)
    seq_of = {port: f"seq_{j}" for j, port in enumerate(known)}
    names: dict[str, Any] = {
        "stats": rt.stats, "node_id": rt.id, "step": rt.flow.step, "time_ns": time_ns, "insort": insort,
        "events_append": session.trace.raw_events.append, "steps_append": session.trace.raw_steps.append,
        "seqs": rt.seq, "read": rt.read, "emit": session._emit, "skipped": session._skipped,
        "failed": session._failed, "rt": rt, "schedule": session._schedule,
        "max_microsteps": session.max_microsteps, "CausalityError": CausalityError,
        "nodes": session._nodes, "in_type": spec.in_type, "out_type": spec.out_type,
        "plain": type(session).plain_types, "check_output": session.check_output,
    }
    seqs = ", ".join(seq_of.values())
    src = ["ticks_n = steps_n = step_ns = 0\n"]
    src += [f"{seq} = seqs.get({port!r}, 0)\n" for port, seq in seq_of.items()]
    src.append(f"def tick(tau, out_tag):\n    nonlocal ticks_n, steps_n, step_ns{', ' if seqs else ''}{seqs}\n"
               )
    only = len(ports) == 1
    if not only and any(required):
        src.append("    missing = None\n")
    for i, (port, buf, _, port_spec) in enumerate(rt.inputs):
        names[f"buf{i}"], names[f"fallback{i}"] = buf, port_spec.fallback
        src.append(_select(i, port, required[i], only, buf.trim_batch))
    if not only and any(required):
        src.append("    if missing is not None:\n        ticks_n += 1\n        return skipped(rt, tau, missing)\n")
    # buffer entries carry, as entry[5], the consumed-ids tuple of a Latest() selection
    if all(required):
        src.append("    consumed = {" + ", ".join(f"{p!r}: entry{i}[5]" for i, p in enumerate(ports)) + "}\n")
    else:
        src.append("    consumed = {}\n")
        for i, p in enumerate(ports):
            src.append(f"    if entry{i} is not None:\n        consumed[{p!r}] = entry{i}[5]\n")
    # optional ports nothing feeds: their fallback, on every tick that runs
    args = [f"arg{i}" for i in range(len(ports))]
    for k, (port, port_spec) in enumerate(rt.fallbacks.items()):
        names[f"unfed{k}"] = port_spec.fallback
        ports.append(port)
        args.append(f"unfed{k}()")

    # the call: make_invoker, spelled out
    if spec.in_mode == "io":
        call = "step(in_type(" + ", ".join(f"{p}={a}" for p, a in zip(ports, args)) + "))"
    elif spec.in_mode == "single":
        call = f"step({args[0]})"
    elif spec.in_mode == "params":
        call = "step(" + ", ".join(f"{p}={a}" for p, a in zip(ports, args)) + ")"
    else:
        call = "step(None)" if spec.source_takes_arg else "step()"

    # reading the outputs: make_output_reader, for the expected output type
    if spec.out_mode == "io":
        expected, reads = "type(raw) is out_type", [f"raw.{p}" for p in known]
    elif spec.out_mode == "single":
        expected, reads = "raw is not None", ["raw"]
    else:
        expected, reads = "type(raw) is dict", None
    read_lines = "".join(f"            v{j} = {expr}\n" for j, expr in enumerate(reads or ()))
    to_seqs = "".join(f"        seqs[{port!r}] = {seq}\n" for port, seq in seq_of.items())
    from_seqs = "".join(f"        {seq} = seqs[{port!r}]\n" for port, seq in seq_of.items())
    src.append(f"""\
    start = time_ns()
    try:
        raw = {call}
        if {expected}:
{read_lines}            outputs = None
        else:
            outputs = read(raw)
    except KeyboardInterrupt:
        raise
    except BaseException as exc:  # SystemExit too, as in _tick
        wall = time_ns() - start
        step_ns += wall
        ticks_n += 1
        return failed(rt, tau, consumed, exc, start, wall)
    end = time_ns()
    wall = end - start
    step_ns += wall
    steps_n += 1
    if outputs is not None:  # an output of another type: the generic path, with the seqs
{to_seqs}        emit(rt, tau, outputs, consumed, start, end)
{from_seqs}        return
""")
    if rt.latency_ns:
        src.append(f"    out_tag = (tau[0] + {rt.latency_ns}, 0)\n")
    record = "steps_append((node_id, tau, consumed, {}, 'ok', None, start, wall))\n"
    if reads is None:  # untyped: the ports are the dict's keys; wired ones are counted and delivered inline
        src.append("    produced = []\n    for port, value in raw.items():\n"
                   "        if value is None:\n            continue\n")
        for j, port in enumerate(known):
            body = _record("port", seq_of[port], "produced") + "produced.append(eid)\n"
            body += _deliver(rt, port, names, "port", feeds)
            src.append(f"        {'if' if j == 0 else 'elif'} port == {port!r}:\n" + _indent(body, "            "))
        body = _record("port", None, "produced") + "produced.append(eid)\n"
        src.append(("        else:\n" + _indent(body, "            ")) if known else _indent(body, "        "))
        src.append("    " + record.format("ids if len(produced) == 1 else tuple(produced)"))
    elif len(reads) == 1:  # one output port: its ids tuple is the step's produced tuple
        port = known[0]
        body = _record(repr(port), seq_of[port], "()") + _deliver(rt, port, names, repr(port), feeds)
        src.append("    value = v0\n    if value is not None:\n" + _indent(body, "        "))
        src.append("        " + record.format("ids"))
        src.append("    else:\n        " + record.format("()"))
    else:
        src.append("    produced = []\n")
        for j, port in enumerate(known):
            body = _record(repr(port), seq_of[port], "produced") + "produced.append(eid)\n"
            body += _deliver(rt, port, names, repr(port), feeds)
            src.append(f"    value = v{j}\n    if value is not None:\n" + _indent(body, "        "))
        src.append("    " + record.format("tuple(produced)"))
    src.append(f"""\
def flush():
    nonlocal ticks_n, steps_n, step_ns
    stats.ticks += ticks_n + steps_n
    stats.steps += steps_n
    stats.step_ns += step_ns
    ticks_n = steps_n = step_ns = 0
{to_seqs.replace("        ", "    ")}""")
    source = "def make():\n" + _indent("".join(src), "    ") + "    return tick, flush\n"
    # the source is ours, built from identifiers checked above and repr() of port names
    exec(compile(source, f"<inproc tick {rt.id}>", "exec"), names)  # noqa: S102
    tick, flush = names["make"]()
    tick.source = source
    return tick, flush
