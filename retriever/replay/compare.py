"""One replayed step against the log: its tag a tick of its node's clock, its record (the ids it
consumed, its status, its error, the ids it produced), its outputs' tags and every value's bytes."""

from __future__ import annotations

from typing import Any

from ..codec import unpackb
from ..time import format_tag
from ..trace import STEPPED, StepStatus
from .report import Divergence


class TickCheck:
    """Whether a record's tag is a tick of its node's clock (``clock.may_tick_at``): a rate's tick
    after the one last found is known without the clock's arithmetic (a node's records come tick
    after tick). ``next[node]``: ``(the tag of its tick k, k, offset_ns, num, den)``, the rate's
    ``schedule``, tick k at ``offset_ns + k * num // den`` (StepReplay.run reads it inline)."""

    __slots__ = ("clocks", "next")

    def __init__(self, graph) -> None:
        self.clocks = {nid: node.clock for nid, node in graph.nodes.items()}
        self.next: dict[str, tuple[tuple[int, int], int, int, int, int]] = {}

    def __call__(self, node: str, tag: tuple[int, int]) -> bool:
        expected = self.next.get(node)
        if expected is not None and expected[0] == tag:
            _, k, offset, num, den = expected
        else:
            clock = self.clocks[node]
            if not clock.may_tick_at(tag):
                return False
            if clock.triggered or clock.hz is None:
                return True
            k = clock.first_tick_at_or_after(tag[0])
            offset, num, den = clock.schedule
        k += 1
        self.next[node] = ((offset + k * num // den, 0), k, offset, num, den)
        return True


def off_clock(step, on_clock: TickCheck, last: dict[str, tuple[int, int]]) -> Divergence | None:
    """The record at a tag where its node's clock has no tick, or at one it already recorded
    (``last``: the tag of each node's record last found on its clock; an instant's records run in
    (microstep, node) order, so a second record of a tick comes right after the first of them)."""
    if not on_clock(step.node, step.tag):
        return Divergence(step.node, step.tag, "tick", None, f"a record at {format_tag(step.tag)}",
                          f"no tick of {on_clock.clocks[step.node]!r} there")
    if last.get(step.node) == step.tag:
        return Divergence(step.node, step.tag, "tick", None, "a second record of this tick", "one record a tick")
    last[step.node] = step.tag
    return None


def compare_record(step, replayed: tuple) -> Divergence | None:
    """The replayed step record against the logged one: the ids it consumed, its status, its
    error, the ids it produced."""
    consumed, produced, status, detail = replayed[2:6]
    if consumed != step.consumed:
        port = next((p for p in sorted(set(consumed) | set(step.consumed)) if consumed.get(p) != step.consumed.get(p)))
        return _differs(step, "inputs (consumed event ids)", step.consumed.get(port), consumed.get(port), port)
    if status != (_OK if step.status in STEPPED else step.status):
        return _differs(step, "status", _status(step.status, step.detail), _status(status, detail))
    if status == _ERROR and (detail or {}).get("error") != (step.detail or {}).get("error"):
        return _differs(step, "error", step.detail.get("error"), detail.get("error"))
    if produced != step.produced:
        return _differs(step, "outputs (produced event ids)", list(step.produced), list(produced))
    return None


_OK, _ERROR = StepStatus.OK, StepStatus.ERROR


def _differs(step, what: str, logged_value: Any, replayed: Any, port: str | None = None) -> Divergence:
    return Divergence(step.node, step.tag, what, port, logged_value, replayed)


def compare_outputs(step, events: list, logged: dict[tuple, tuple[tuple[int, int], bytes]], encode,
                    stamped: bool) -> Divergence | None:
    """The replayed outputs of a step whose record matched, against the logged ones (``logged``:
    by id, the tag and the value's bytes of those the log holds): their tags and every value's
    msgpack bytes."""
    for ev in events:
        tag, node, port, seq, value = ev[:5]
        original = logged.get((node, port, seq))
        if original is None:
            return Divergence(step.node, step.tag, "value", port, "<not in the log: the log ends here>", value)
        logged_tag, raw = original
        if stamped:
            if logged_tag <= step.tag:
                return Divergence(step.node, step.tag, "output tag (not after its tick: causality)", port,
                                  format_tag(logged_tag), f"after {format_tag(step.tag)}")
        elif tag != logged_tag:
            return Divergence(step.node, step.tag, "output tag", port, format_tag(logged_tag), format_tag(tag))
        if encode(value) != raw:
            return Divergence(step.node, step.tag, "value", port, _logged_value(raw), value)
    return None


def _logged_value(raw: bytes) -> Any:
    """A logged value to show beside the replayed one: itself, or what it is when it does not decode."""
    try:
        return unpackb(raw, keep_unregistered=True)
    except Exception as e:  # a damaged value differs from any replayed one: say what it is
        return f"<{len(raw)} bytes that do not decode: {type(e).__name__}>"


def _status(status: str, detail: dict | None) -> str:
    return f"{status} {detail}" if detail else status
