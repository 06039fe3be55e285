"""After a run: the flows that a miswired port starved, and the edges that carried nothing.

A misspelled port wires nothing: the producer's events go to a port nobody reads and the consumer
skips every tick for want of its input (or, clocked by a Trigger, never ticks; or, the port
being optional, steps without it), yet the run ends with exit 0. ``starved_flows`` reads a run's
counters (no records needed, so it works for ``keep="counters"`` and on every backend) and names
each such flow and edge. ``Pipeline.run`` warns with it (:class:`~retriever.errors.StarvedFlowWarning`).

What marks a typo, rather than a sparse output that happened not to fire (an alarm), is that the
producer, one whose ports nothing could check before the run (an untyped step returning a dict
it built), made events on a port that no edge reads while an edge from it waited on a port it
never made. A flow that skipped (nearly) every one of enough ticks for another reason is named
too, with where to look; a cause upstream is named where it starts, and downstream only as
"X never stepped" when X itself was named.

Counters cannot tell a flow that stepped for a while and then lost its inputs for good (a
consumer moved to another machine that never caught up with its stream, a link lost and back
with a gap in it): it skipped most ticks, but for no cause a typo explains. During a run,
:class:`StarvationWatch` reads the step records as they come and names each input that had no
event, tick after tick, for ``STARVED_AFTER_NS`` of the run's time while a producer into it made
events there; the coordinator warns at once, marks the flow in the run's table
(``Session.starved``) and logs each such span (``retriever.starved.N``).
"""

from __future__ import annotations

from collections import Counter, deque
from typing import TYPE_CHECKING, Any, Mapping

if TYPE_CHECKING:
    from .backends.base import NodeStats
    from .graph import Edge, Graph

#: fewer ticks than this say too little to warn about a flow that skipped them (a short run's
#: first ticks may come before anything upstream produced)
MIN_TICKS = 3

#: During a run: an input that had no event for this long of the run's time (its ticks' records
#: say it was incomplete or missing) while its producers made at least STARVED_MIN_EVENTS events
#: on its edges is starved. Longer than a node moved off a lost machine takes to catch up (about
#: a lease: docs/deploy.md), shorter than a run that should have noticed.
STARVED_AFTER_NS = 3_000_000_000
STARVED_MIN_EVENTS = 3
#: how far back in the run's time StarvationWatch keeps when each producer made its events: a
#: consumer's record may arrive after its producers' later ones (reports come in batches up to a
#: second old), and the events made from its first tick without one are counted by their tags
MADE_HISTORY_NS = 10_000_000_000


def starved_flows(graph: "Graph", stats: Mapping[str, "NodeStats"],
                  produced: Mapping[tuple[str, str], int] | None) -> list[str]:
    """One line per flow a run starved and per edge that carried no event for a typo's reason.
    ``produced``: how many events each ``(node, port)`` made (None: the backend cannot say; then
    only flows that never stepped in enough ticks are named, without a cause)."""
    produced = produced or {}
    read = {(e.src, e.src_port) for e in graph.edges}
    edges_into: dict[tuple[str, str], list["Edge"]] = {}
    for e in graph.edges:
        edges_into.setdefault((e.dst, e.dst_port), []).append(e)
    # only a producer whose ports nothing could check before the run (an untyped step returning a
    # dict it built) can have misspelt one; a typed one's other ports are a sparse output's neighbours
    unread: dict[str, list[str]] = {node_id: [] for node_id in graph.nodes}
    for (node_id, port), count in sorted(produced.items()):
        if count and (node_id, port) not in read and node_id in unread and _unchecked(graph.nodes[node_id]):
            unread[node_id].append(port)
    named: set[str] = set()
    explained: set[tuple[str, str]] = set()  # (consumer, port) pairs a line already explains
    lines = []
    for node_id in _upstream_first(graph):
        node, s = graph.nodes[node_id], stats.get(node_id)
        if s is None:
            continue
        into = {port: edges_into.get((node_id, port), []) for port in node.inputs}
        if s.ticks == 0:
            clock = node.settings.clock
            watched = list(clock.trigger_ports or node.inputs) if clock is not None else []
            if clock is None or clock.hz is not None or not watched or not any(into[p] for p in watched):
                continue  # a source, a Rate clock, or nothing feeds it (build_ir warned)
            causes = [_never_had(port, into[port], stats, produced, unread, named) for port in watched if into[port]]
            if all(causes):
                lines.append(f"{node_id} never ticked: its trigger input {', and '.join(causes)}")
                named.add(node_id)
                explained.update((node_id, p) for p in watched)
            continue
        if s.ticks < MIN_TICKS or s.skips * 2 <= s.ticks:
            continue
        causes = []
        for port, spec in node.inputs.items():
            if not spec.required:
                continue
            if not into[port]:
                causes.append(f"input '{port}' has no incoming edge")
            elif (cause := _never_had(port, into[port], stats, produced, unread, named)) is not None:
                causes.append(f"input {cause}")
                explained.add((node_id, port))
        head = f"{node_id} stepped {s.steps} of {s.ticks} ticks"
        if causes:
            lines.append(f"{head}: {', and '.join(causes)}")
            named.add(node_id)
        elif s.steps == 0 and not any(_quiet(edges, produced) for edges in into.values()):
            lines.append(f"{head}: every tick was skipped, each for a missing input\n"
                         f"    hint: its step records name the port (trace.steps_of('{node_id}'), or "
                         "retriever log cat LOG --steps)")
            named.add(node_id)
    for e in graph.edges:  # an edge a typo left empty, into a port something else fed or that is optional
        if (e.dst, e.dst_port) not in explained and not produced.get((e.src, e.src_port)) and unread[e.src]:
            lines.append(f"edge {e.src} → {e.dst} carried no event: {e.src} never produced '{e.src_port}', "
                         f"and produced {_listed(unread[e.src])}, which no edge reads")
    return lines


def _never_had(port: str, edges: list["Edge"], stats, produced: Mapping[tuple[str, str], int],
               unread: dict[str, list[str]], named: set[str]) -> str | None:
    """Why ``port`` never had an event, if every edge into it is explained by a typo upstream or
    by a producer that was itself named as starved; else None."""
    whys = []
    for e in edges:
        upstream = stats.get(e.src)
        if upstream is not None and upstream.steps == 0 and e.src in named:
            whys.append(f"edge {e.src} → {e.dst}, {e.src} never stepped")
        elif unread[e.src] and not produced.get((e.src, e.src_port)):  # made it: no typo explains the edge
            whys.append(f"edge {e.src} → {e.dst}, output '{e.src_port}' was never produced; {e.src} produced "
                        f"{_listed(unread[e.src])}, which no edge reads")
        else:
            return None
    return f"'{port}' never had an event ({'; '.join(whys)})"


def _unchecked(node) -> bool:
    """Whether a flow's output ports could not be known before the run: an untyped step whose
    returned keys were not read from its source (a dict built in a variable, a decorator)."""
    return node.spec.outputs is None and node.spec.returned_keys is None


def _quiet(edges: list["Edge"], produced: Mapping[tuple[str, str], int]) -> bool:
    """Whether the producers into one port made no event there (a sparse output that did not
    fire, or one that only a typo explains: either way not a reason to guess)."""
    return bool(edges) and not any(produced.get((e.src, e.src_port)) for e in edges)


def _listed(ports: list[str]) -> str:
    return ", ".join(repr(p) for p in ports)


def _upstream_first(graph: "Graph") -> list[str]:
    """The nodes, each after the nodes that feed it where a cycle does not forbid it: a starved
    producer is named before its consumers, which then say it never stepped."""
    feeds: dict[str, list[str]] = {node: [] for node in graph.nodes}
    for e in graph.edges:
        feeds[e.dst].append(e.src)
    order: list[str] = []
    placed: set[str] = set()
    for root in graph.nodes:
        stack, entered = [(root, iter(feeds[root]))], {root}
        while stack:
            node, producers = stack[-1]
            producer = next(producers, None)
            if producer is None:
                stack.pop()
                if node not in placed:
                    placed.add(node)
                    order.append(node)
            elif producer not in placed and producer not in entered:
                entered.add(producer)
                stack.append((producer, iter(feeds[producer])))
    return order


class StarvationWatch:
    """During a run, from its step records as they come (each node's in tick order, the nodes'
    interleaved as their reports arrive): each input port of a flow that had no event at tick
    after tick (its records name it ``incomplete`` or ``missing``) for ``STARVED_AFTER_NS`` while
    its producers made events there. Each such span is an episode, a dict: ``node``,
    ``port``, ``producers`` ("node.port" each), ``since_ns`` (its first tick without an event),
    ``until_ns`` (the first tick with one again; None while it lasts), ``ticks`` (without one)
    and ``produced`` (the events its producers made at its ticks' tags from ``since_ns`` on, as
    reported by its last tick: a producer's records may come up to a second after it). ``news`` lists what
    happened since it was last emptied: ``("starved", episode)`` and ``("fed", episode)``. The
    time counts from the first tick without an event that saw its producers make some: a sparse
    output that was quiet for long before it fired is not a starved consumer."""

    def __init__(self, graph: "Graph"):
        self._into: dict[tuple[str, str], list[tuple[str, str]]] = {}
        for e in graph.edges:
            self._into.setdefault((e.dst, e.dst_port), []).append((e.src, e.src_port))
        self._ports: dict[str, list[str]] = {}
        for node, port in sorted(self._into):
            self._ports.setdefault(node, []).append(port)
        self._fed = {stream for streams in self._into.values() for stream in streams}
        self._made: Counter = Counter()  # events made per stream into a port (_fed), as reported so far
        # per stream: (tag_ns, events made up to and with that step) of its last MADE_HISTORY_NS, and
        # how many it made before the oldest of them
        self._history: dict[tuple[str, str], deque] = {}
        self._older: Counter = Counter()
        # (node, port) -> [since_ns, ticks, events made by then, the first tick that saw more made]
        self._without: dict[tuple[str, str], list] = {}
        self._open: dict[tuple[str, str], dict[str, Any]] = {}
        self.episodes: list[dict[str, Any]] = []
        self.news: list[tuple[str, dict[str, Any]]] = []

    def step(self, node: str, tag: tuple[int, int], produced, detail) -> None:
        """One step record of ``node`` (its fields as reported: ``produced`` event ids, ``detail``)."""
        made = Counter((event_id[0], event_id[1]) for event_id in produced
                       if (event_id[0], event_id[1]) in self._fed) if produced else {}
        for stream, n in made.items():
            self._made[stream] += n
            history = self._history.setdefault(stream, deque())
            history.append((tag[0], self._made[stream]))
            while history[0][0] < tag[0] - MADE_HISTORY_NS:
                self._older[stream] = history.popleft()[1]
        ports = self._ports.get(node)
        if not ports:
            return
        short = _named(detail, "incomplete") | _named(detail, "missing")
        for port in ports:
            key = (node, port)
            if port not in short:
                if self._without.pop(key, None) is not None and key in self._open:
                    episode = self._open.pop(key)
                    episode["until_ns"] = tag[0]
                    self.news.append(("fed", episode))
                continue
            without = self._without.get(key)
            if without is None:
                self._without[key] = [tag[0], 1, self._producers_made_before(key, tag[0]), None]
                continue
            without[1] += 1
            made = self._producers_made(key) - without[2]
            if made and without[3] is None:  # its producers began to make events it does not get
                without[3] = tag[0]
            episode = self._open.get(key)
            if episode is not None:
                episode["ticks"], episode["produced"] = without[1], made
            elif made >= STARVED_MIN_EVENTS and tag[0] - without[3] >= STARVED_AFTER_NS:
                episode = {"node": node, "port": port, "producers": [f"{s}.{p}" for s, p in self._into[key]],
                           "since_ns": without[0], "until_ns": None, "ticks": without[1], "produced": made}
                self._open[key] = episode
                self.episodes.append(episode)
                self.news.append(("starved", episode))

    def _producers_made(self, key: tuple[str, str]) -> int:
        return sum(self._made[stream] for stream in self._into[key])

    def _producers_made_before(self, key: tuple[str, str], tag_ns: int) -> int:
        """How many events the producers into ``key`` made at tags before ``tag_ns`` (as far back
        as MADE_HISTORY_NS; before that, as reported)."""
        total = 0
        for stream in self._into[key]:
            before = self._older[stream]
            for at, made in reversed(self._history.get(stream, ())):
                if at < tag_ns:
                    before = made
                    break
            total += before
        return total


def _named(detail, key: str) -> set[str]:
    """The ports a record's ``detail`` names under ``key`` (what a worker sent: anything else, none)."""
    ports = detail.get(key) if type(detail) is dict else None
    return {p for p in ports if type(p) is str} if type(ports) is list else set()


def describe_starved(episode: Mapping[str, Any]) -> str:
    """``viewer: input 'pixels' had no event from t=3.9 s to the end (805 ticks), while
    camera.pixels made 805``: one episode of :class:`StarvationWatch`, in words."""
    until = episode.get("until_ns")
    span = (f"from t={episode['since_ns'] / 1e9:.3g} s " +
            ("to the end" if until is None else f"to t={until / 1e9:.3g} s"))
    return (f"{episode['node']}: input '{episode['port']}' had no event {span} ({episode['ticks']} ticks), while "
            f"{' and '.join(episode['producers'])} made {episode['produced']}")
