"""After a run: the flows that skipped every tick, or most of them, and the input that starved them.

A misspelled port wires nothing: the producer's events go to a port nobody reads and the consumer
skips every tick for want of its input, yet the run ends with exit 0. ``starved_flows`` reads a
run's counters (no records needed, so it works for ``keep="counters"`` and on every backend) and
says, for each such flow, which required input never had an event and which edge should have
brought it. ``Pipeline.run`` warns with it (:class:`~retriever.errors.StarvedFlowWarning`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Mapping

if TYPE_CHECKING:
    from .backends.base import NodeStats
    from .graph import Graph


def starved_flows(graph: "Graph", stats: Mapping[str, "NodeStats"],
                  produced: Mapping[tuple[str, str], int] | None) -> list[str]:
    """One line per flow that skipped more than half of its ticks because a required input never
    had an event, or that skipped every tick for any reason. ``produced``: how many events each
    ``(node, port)`` produced in the run (None: the backend cannot say; then only flows that
    never stepped are named, without a cause)."""
    lines = []
    for node_id, node in graph.nodes.items():
        s = stats.get(node_id)
        if s is None or s.ticks == 0 or s.skips * 2 <= s.ticks:
            continue
        causes = []
        for port, spec in node.inputs.items():
            if not spec.required:
                continue
            edges = [e for e in graph.edges if e.dst == node_id and e.dst_port == port]
            if not edges:
                causes.append(f"input '{port}' has no incoming edge")
            elif produced is not None and not any(produced.get((e.src, e.src_port), 0) for e in edges):
                why = "; ".join(_why(e, graph, stats, produced) for e in edges)
                causes.append(f"input '{port}' never had an event ({why})")
        head = f"{node_id} stepped {s.steps} of {s.ticks} ticks"
        if causes:
            lines.append(f"{head}: {', and '.join(causes)}")
        elif s.steps == 0:
            lines.append(f"{head}: every tick was skipped, each for a missing input\n"
                         f"    hint: its step records name the port (trace.steps_of('{node_id}'), or "
                         "retriever log cat LOG --steps)")
    return lines


def _why(edge, graph: "Graph", stats: Mapping[str, "NodeStats"], produced: Mapping[tuple[str, str], int]) -> str:
    upstream = stats.get(edge.src)
    if upstream is not None and upstream.steps == 0:
        return f"edge {edge.src} → {edge.dst}, {edge.src} never stepped"
    read = {e.src_port for e in graph.edges if e.src == edge.src}
    unread = sorted(port for (node, port), n in produced.items() if node == edge.src and n and port not in read)
    also = f"; {edge.src} produced {', '.join(repr(p) for p in unread)}, which no edge reads" if unread else ""
    return f"edge {edge.src} → {edge.dst}, output '{edge.src_port}' was never produced{also}"
