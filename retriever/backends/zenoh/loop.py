"""One node's real-time loop, inside its worker process (docs/semantics.md, docs/realtime.md).

    subscriber threads ──(key, bytes)──▶ inbox ──▶ main thread: decode, insert into PortBuffers,
            │                                     advance producer frontiers, schedule trigger ticks
            └── main thread idle, short steps, node on no cycle: do all of that, and the ticks it
                makes ready, right there (see INLINE_STEP_NS)
    main thread:  next tick τ = min(next Rate tick, pending trigger tags)
                  wait until wall ≥ τ.t and every input edge is complete up to τ (its producer's
                  frontier > τ), at most the edge's deadline → select inputs, step(), publish
                  (ASAP: stamped at completion; LET: stamped τ + latency, released then)

Tags are ``(ns since T0, microstep)``. A *frontier* is a producer's promise: every later event of
it has a tag ``≥`` the frontier. Producers send theirs on data messages, on progress messages
after ticks whose outputs do not carry it, and on demand: a consumer kept waiting by an idle or
busy producer asks its ``progress/<node>`` queryable, which answers from the producer's state.

Virtual time (``virtual=True``, ``retriever deploy --virtual-time``): the same loop with logical
time only, so that the run's trace is the in-process backend's. A tick runs once its inputs are
complete, however long that takes (no deadline), outputs are stamped as in-process ((t, m + 1),
or (t + latency, 0) published at once), nothing overruns, and the wall clock only paces waiting
and asking. The coordinator advances all nodes in lockstep: a node runs the ticks below its
*grant* (control ``grant`` {until}), then says ``reached`` {until} (a status) and waits; once every
node not done has reached it, the coordinator grants the next window (coordinator.py).
"""

from __future__ import annotations

import heapq
import queue
import sys
import threading
import time
from bisect import bisect_left, insort
from collections import Counter
from typing import Any

import zenoh

from ...errors import CausalityError, CodecError, StopRun
from ...flow._base import make_invoker, make_output_reader
from ...flow.burst import Burst
from ...graph import Node
from ...sync import PortBuffer
from ...tick import select_inputs
from .hub import weak_callback
from .reporter import Reporter
from .wire import (RELIABLE, DataMessage, KeySpace, WireEncoder, WireError, decode_control, decode_events,
                   decode_progress)

#: a frontier no event reaches: the producer is finished
NEVER = (1 << 62, 0)
#: how long a blocked tick waits for a data or progress message before asking the producer
PROBE_AFTER_NS = 500_000
#: how long published events may wait before they go to the coordinator (with the step records
#: before them), and at most how many records or bytes of events go at once. Every report wakes
#: the reporter's thread, Zenoh's and the coordinator: at 20 ms, an idle 100 Hz flow reported every
#: other tick (issue 21: idle cost). Nothing waits on a report for less: a consumer holds records
#: for HOLD_RECORDS_NS, the coordinator logs events and shows them live (--foxglove).
FLUSH_AFTER_NS = 100_000_000
#: how long step records may wait when no event waits with them (a flow that outputs nothing, or
#: not on every tick): nothing but the coordinator's counts and live view waits for those, and ten
#: reports a second cost an idle 100 Hz flow about a quarter of its CPU (issue 21: idle cost)
RECORDS_FLUSH_AFTER_NS = 1_000_000_000
FLUSH_MAX = 512
FLUSH_MAX_BYTES = 64 << 20
FLUSH_MAX_SEQS = 1 << 16  # seqs published: a flush at least this often (bursts), see RESTART_SEQ_GAP
#: published messages at least this big reach the coordinator as files in the run's shared-memory
#: directory (one copy, and none on its side) instead of inside the report
SPILL_BYTES = 64 << 10

#: What a message may claim, past which it is refused as garbage (never applied): a frontier is a
#: producer's promise, and a producer can promise no tag past the run's end plus its latency
#: (its ticks end there; LET outputs are stamped tick + latency), except NEVER once it is done and,
#: without latency, its HLC stamp at completion: at most CLOCK_AHEAD_MAX_NS past this process's
#: clock, the skew Zenoh's own HLC tolerates between sessions (500 ms). A seq may arrive ahead of
#: the next one expected (Zenoh orders per route; a message may overtake on another), by a few,
#: not by EARLY_SEQS_MAX: a message that far ahead would hold its stream's gap open forever.
CLOCK_AHEAD_MAX_NS = 500_000_000
EARLY_SEQS_MAX = 4096

#: A progress message may come far ahead of the data messages it comes after (another key; a
#: consumer that lags behind a producer of bursts may be millions of seqs behind): it waits for
#: them, whatever its seq. At most WAITING_MAX wait per stream; past that every other one is
#: forgotten (a frontier is a promise that only makes a tick run sooner: forgetting one delays a
#: tick to the next promise, it never changes what a tick sees).
WAITING_MAX = 4096

#: Consumed events reach the log through their producer's report, which may be lost with its
#: process (kill -9). So a consumer keeps the message of each event it received until the
#: coordinator says it has the event (control ``have``: per stream, the last seq its producer
#: reported), and holds back its step records that consumed an event the coordinator lacks, for
#: at most HOLD_RECORDS_NS; past that, or when the loop ends, a record goes with the messages of
#: those events, and the coordinator takes them as the producer's (each event is logged once).
HOLD_RECORDS_NS = 200_000_000

#: A flow whose process died (kill -9, a segfault) under on_error="restart" starts afresh in a
#: new process, its state lost (see "Restarting after a lost process" below). Its streams go on
#: from a seq past every one the dead process may have used: the coordinator knows the seqs it
#: reported; at most its unreported seqs were published unknown to the coordinator: fewer than
#: FLUSH_MAX_SEQS + MAX_BURST in the loop, at most MAX_PENDING_SEQS (or one report) in the
#: reporter's queue, 655,360 in all, far fewer than RESTART_SEQ_GAP. A consumer told that a
#: producer was lost takes its seqs up to that far ahead (EARLY_SEQS_MAX is for running streams).
RESTART_SEQ_GAP = 1 << 21

#: after asking a producer for its frontier, how long before asking again
ASK_EVERY_NS = 2_000_000

#: Warming up. After a sleep of ~10 ms or more, the code and data of the send and receive paths
#: are out of the CPU's caches (on this VM: encoding a 64 B event took 135 µs after a 50 ms
#: sleep, 3 µs back to back, 6 µs after 2 ms), and that cold run is most of a small message's
#: latency. So before a moment that is predictable (the next Rate tick of a node with consumers,
#: the next arrival on a periodic input stream) that follows such a sleep, the loop wakes
#: WARM_AHEAD_NS early and runs its encoder on the last event it sent, its decoder on the last
#: message it got (arrays are not copied for that), reads the HLC, and, if it publishes, puts an
#: empty message on its ``warm/<node>`` key, which no one subscribes to (Zenoh's put path, up to
#: the routing; 106 → 71 µs for the next real put here, and the HLC 28 → 6 µs). It changes only
#: how fast a tick starts, never what it reads or emits. Sleeps shorter than WARM_AFTER_IDLE_NS
#: leave the caches warm.
WARM_AHEAD_NS = 1_000_000
WARM_AFTER_IDLE_NS = 4_000_000

#: Running on the receiving thread. A data message that arrives while the main thread sleeps is
#: handled on Zenoh's thread that received it: decoded, delivered, and the ticks it makes ready
#: run there too, as a plain subscriber callback would. Handing it to the main thread instead
#: costs a thread wake-up: on this VM (an idle vCPU woken by an IPI) 20–40 µs of a 64 B
#: message's ~500 µs, and 0.05–0.1× of the ratio to raw Zenoh (benchmarks/reports/latency.md,
#: with and without). Only steps known to be short run there (the node's last step took under
#: INLINE_STEP_NS): meanwhile that link receives nothing more. And only on nodes on no cycle of
#: the graph, so that a put blocked by a congested link can never wait, around a cycle, on a
#: receiving thread that is itself blocked in a put. Nor on nodes whose flow has a ``setup()``: what
#: it acquired may belong to its thread (an EGL context, a CUDA stream), so such a flow steps, sets
#: up and tears down on the main thread only. Either way the same ticks run with the same inputs:
#: where a tick runs changes how soon, never what.
INLINE_STEP_NS = 1_000_000

#: virtual time: how long a loop at its grant, or with no tick known below it, waits before
#: looking again (any message wakes it sooner: the next grant, a frontier)
VIRTUAL_IDLE_NS = 100_000_000

#: while its flow is being restarted, how often a loop with a tick due looks again (it also
#: wakes for every message, the coordinator's handover among them)
RESTART_POLL_NS = 50_000_000

_DATA, _PROGRESS, _CONTROL, _NUDGE = 0, 1, 2, 3
#: put in the inbox after work done on a receiving thread: the main thread looks again
_NUDGED = (_NUDGE, None, None)
_TICKED, _DONE = "ticked", "done"


class InEdge:
    """One incoming edge: where its events go and how long a tick waits for it."""

    __slots__ = ("src", "src_port", "port", "buf", "delay_ns", "triggers", "deadline_ns", "src_latency_ns")

    def __init__(self, src: str, src_port: str, port: str, buf: PortBuffer, delay_ns: int, triggers: bool,
                 deadline_ns: int, src_latency_ns: int = 0):
        self.src, self.src_port, self.port, self.buf = src, src_port, port, buf
        self.delay_ns, self.triggers, self.deadline_ns = delay_ns, triggers, deadline_ns
        self.src_latency_ns = src_latency_ns  # the producer's declared latency: how far past the end it stamps


class NodeLoop:
    """Runs one node in real time from ``T0`` until ``end`` (both HLC Unix ns)."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, node: Node, edges: list[InEdge],
                 inputs: list[tuple], fallbacks: dict, *, realtime: str,
                 ports: list[str] | None = None, consumed: bool = True, spill_dir: str | None = None,
                 inline: bool = False, cycle: list[str] | None = None, instant_ports: frozenset = frozenset(),
                 max_microsteps: int = 1000, virtual: bool = False):
        self.session, self.keys, self.node, self.id = session, keys, node, node.id
        self.edges = edges
        self.triggered = any(e.triggers for e in edges)  # some input may bring a tick
        self.inputs = inputs  # (port, buffer, policy, port spec), as in the in-process backend
        self.fallbacks = fallbacks
        self.realtime = realtime
        # virtual time (see the module docstring): ticks below `granted` (ns since T0) may run;
        # `reached`, the last grant this node said it reached; on_reached(until) says so
        self.virtual = virtual
        self.granted = 0
        self.reached = -1
        self.on_reached = None
        self.blocked: tuple[tuple[int, int], int] | None = None  # (tick, since when: wall ns) waiting for inputs
        settings = node.settings
        self.latency_ns = settings.latency_ns
        self.on_error, self.on_overrun, self.on_deadline_miss = (
            settings.on_error, settings.on_overrun, settings.on_deadline_miss)
        if realtime == "best_effort":  # misses are counted and logged, never fatal
            self.on_overrun = "skip" if self.on_overrun == "error" else self.on_overrun
            self.on_deadline_miss = "publish_late" if self.on_deadline_miss == "error" else self.on_deadline_miss
        self.clock = node.clock
        self.flow = node.flow
        self.invoke = make_invoker(node.flow, node.spec)
        self.read = make_output_reader(node.spec)
        self.encoder = WireEncoder()
        self.seqs: dict[str, int] = {}  # per output port, the next event's seq
        self.ports = list(ports if ports is not None else node.outputs)  # untyped flows: the IR knows
        self.single_port = len(self.ports) == 1
        self.consumed = consumed  # whether any flow consumes this one (else no progress messages)
        # the coordinator's directory on this host, if it shares one, takes the big messages
        self.reporter = Reporter(session, keys.report(self.id), self.id, spill_dir=spill_dir, spill_bytes=SPILL_BYTES)

        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        self.lock = threading.Lock()  # guards what the progress queryable reads
        # The loop's state belongs to whoever holds `turn`: the thread that built the loop (the
        # worker's main thread), except while it waits for a message in _wait. A receiving thread
        # that takes it then does the main thread's work itself (INLINE_STEP_NS).
        self.turn = threading.Lock()
        self.turn.acquire()
        self.inline = inline  # whether this node may run ticks on a receiving thread at all
        self.last_wall: int | None = None  # how long the last step took; None before the first
        self.failure: BaseException | None = None  # raised on a receiving thread, for run() to raise
        # per input stream (producer, port): its frontier, the next seq to take in order,
        # out-of-order arrivals, and progress messages waiting for the seqs they come after
        streams = {(e.src, e.src_port) for e in edges}
        self.frontiers: dict[tuple[str, str], tuple[int, int]] = {k: (0, 0) for k in streams}
        self.expect: dict[tuple[str, str], int] = {k: 0 for k in streams}
        self.early: dict[tuple[str, str], dict[int, Any]] = {k: {} for k in streams}
        self.waiting: dict[tuple[str, str], list[tuple[int, tuple[int, int]]]] = {k: [] for k in streams}
        self.src_latency_ns = {(e.src, e.src_port): e.src_latency_ns for e in edges}
        self.sources = sorted({e.src for e in edges})
        self.sent: dict[str, int] = {port: seq - 1 for port, seq in self.seqs.items()}  # last seq put
        self.pending: list[tuple[int, int]] = []  # trigger tick tags (a heap, deduplicated below)
        self.pending_set: set[tuple[int, int]] = set()
        self.k = 0
        self.next_rate: tuple[int, int] | None = None
        self.running: tuple[int, int] | None = None  # the tag of the tick in progress
        self.last_tick: tuple[int, int] = (-1, 0)
        self.held: list[tuple] = []  # LET outputs waiting for release: (tag, port, value, seq)
        self.sending: tuple[int, int] | None = None  # lowest tag of outputs being put right now
        self.t0 = 0
        self.end = 0
        self.promised_end = 0
        # run() began: before, the end is not known, and a frontier past (0, 0) no promise it can
        # keep (with end 0 it said NEVER: "finished", and a consumer ran on without it)
        self.started = False
        self.stopping = False
        self.abandoned = False  # its process's parent died: it stops without finishing (worker.py)
        # on_error="restart" (see "Restarting" below): after a failed step, ticks wait for the
        # new process, which takes this loop's state over once the coordinator says so
        self.restarting = False
        self.handing_over = False
        self.told_to_stop = False  # a `stop` (control, or SIGTERM) ended it, not the run's end
        self.on_exit = None  # called with the tick whose step called sys.exit(0): the run ends
        self.on_restart = None  # called with (tag, error) when a step's failure starts a restart
        self.taken_over: dict[tuple[str, str], int] = {}  # per stream, the seqs the old process took
        self.lost_producers: set[str] = set()  # producers whose process died, until they restart
        self.fresh_inputs: dict[str, list] = {}  # a fresh process: per input port, where its streams began

        self.records: list = []  # step records not yet reported to the coordinator
        self.recorded = 0  # step records made in all (the coordinator checks it got every tick)
        self.held_records: list[tuple[int, tuple]] = []  # (held since, record): see HOLD_RECORDS_NS
        self.kept: dict[tuple[str, str, int], tuple[int, bytes]] = {}  # event id -> (arrival wall ns, message)
        #: whether the coordinator wants the events' values (for the trace or the log; the start
        #: says): without, reports carry each event without its value, and consumers keep nothing
        self.values = True
        self.have: dict[tuple[str, str], int] = {}  # per input stream, the last seq the coordinator has
        self.published: list[tuple[int, bytes]] = []  # (wall ns, data message) not yet reported
        self.published_bytes = 0
        self.published_seqs = 0  # the seqs of the events in it (a burst's are many)
        self.flush_due: int | None = None  # when the oldest unreported record or event must go
        self.pending_detail: dict[str, Any] = {}  # late events and skipped ticks, told on the next record
        self.counts = Counter()  # garbage, late, incomplete, overrun, deadline_miss, report_waits, ...
        self.ask_after: dict[str, int] = {}  # producer -> when it may be asked for its frontier again
        self.last_stamp = 0  # ASAP: the last tick's output tag; each tick's is later
        # On an instantaneous cycle (docs/semantics.md, Causality) an ASAP output of a tick at (t, m) is
        # stamped (HLC, m + 1): time moves on at every hop in real time, so the microstep is what
        # counts the hops of one instant, and past max_microsteps an output that would trigger
        # another tick (on one of instant_ports) stops the run, as in-process (a Zeno loop).
        self.cycle = cycle
        self.instant_ports = instant_ports if cycle else frozenset()
        self.max_microsteps = max_microsteps
        self.period_ns = round(1e9 / float(self.clock.hz)) if self.clock.hz is not None else 0
        self.spin_ns = 0 if virtual else node.settings.spin_ns  # (virtual time: nothing to be on time for)
        self._declared: list = []
        # warming up (WARM_AHEAD_NS): the last event published, as encoder arguments; per input
        # stream, its last arrival (ns since T0), the gap before it, and its last message
        self.warm_publish: tuple | None = None
        self.warm_publisher: zenoh.Publisher | None = None  # on warm/<node>, declared with the rest
        self.arrivals: dict[tuple[str, str], tuple[int, int, bytes]] = {}
        self.warmed_for: int | None = None

    # ---------------------------------------------------------------------------------------
    # Wiring to Zenoh
    # ---------------------------------------------------------------------------------------
    def declare(self) -> None:
        """Subscribe to the inputs, the producers' progress and the run's control; answer
        progress queries. Call before announcing readiness."""
        self.declare_inputs()
        self.declare_outputs()

    def declare_inputs(self) -> None:
        """What this node listens to: its input streams, their producers' progress, the run's control."""
        put = self.inbox.put
        receive = weak_callback(self._receive) if self.inline else put
        s, keys = self.session, self.keys
        for src, src_port in sorted({(e.src, e.src_port) for e in self.edges}):
            self._declared.append(s.declare_subscriber(
                keys.data(src, src_port),
                lambda sample, k=(src, src_port): receive((_DATA, k, sample.payload.to_bytes()))))
        for src in self.sources:
            self._declared.append(s.declare_subscriber(
                keys.progress(src), lambda sample, k=src: put((_PROGRESS, k, sample.payload.to_bytes()))))
        self._declared.append(s.declare_subscriber(
            keys.run_control(), lambda sample: put((_CONTROL, None, sample.payload.to_bytes()))))

    def declare_outputs(self) -> None:
        """What this node speaks on: its data and progress keys, and the answer to progress queries."""
        s, keys = self.session, self.keys
        self._declared.append(s.declare_queryable(keys.progress(self.id), weak_callback(self._answer_progress)))
        self.publishers = {port: self._publisher(keys.data(self.id, port)) for port in self.ports}
        self.progress_publisher = self._publisher(keys.progress(self.id))
        self.warm_publisher = s.declare_publisher(keys.warm(self.id), express=True)
        # every declaration undeclared at the end: one left holds the session, and with it its
        # shared memory, which then outlives the process in /dev/shm (Zenoh's exit() skips it)
        self._declared += [self.progress_publisher, self.warm_publisher]

    def _publisher(self, key: str) -> zenoh.Publisher:
        # BLOCK, not Zenoh's default DROP: a dropped event would leave a gap in its stream's seqs
        # that no frontier can cross (a slow consumer backs its producer up instead)
        return self.session.declare_publisher(key, express=True, congestion_control=RELIABLE)

    def redeclare(self) -> None:
        """Declare the subscriptions and the progress queryable again, then drop the old ones
        (before the start only: no event flows yet). Zenoh then tells every linked peer of them
        anew. Under load, with many peers linking at once, a peer was seen linked to this node
        and never told of its queryable (nor, maybe, its subscriptions): see worker.py,
        REDECLARE_AFTER_S."""
        queryables = [d for d in self._declared if isinstance(d, zenoh.Queryable)]
        subscribers = [d for d in self._declared if isinstance(d, zenoh.Subscriber)]
        if not queryables and not subscribers:
            return
        kept = [d for d in self._declared if not isinstance(d, (zenoh.Queryable, zenoh.Subscriber))]
        self._declared = []
        self.declare_inputs()
        if queryables:
            self._declared.append(self.session.declare_queryable(self.keys.progress(self.id),
                                                                  weak_callback(self._answer_progress)))
        for d in [*queryables, *subscribers]:
            d.undeclare()
        self._declared += kept
        self.counts["redeclared"] += 1

    def await_routes(self, timeout: float) -> None:
        """Before the node says ready: wait until its events' routes carry (Zenoh's do once linked
        and answered, which the worker waited for; backends/dora/link.py has its own)."""

    def undeclare(self) -> None:
        for d in [*self._declared, *getattr(self, "publishers", {}).values()]:
            d.undeclare()
        self._declared = []
        self.publishers = {}

    def _answer_progress(self, query: zenoh.Query) -> None:
        frontier = self.frontier()  # first: the seqs read after it can only be later ones
        query.reply(self.keys.progress(self.id), WireEncoder().progress(frontier, self.id, dict(self.sent)))

    def _receive(self, item: tuple) -> None:
        """A data message, on the Zenoh thread that received it: handled right here if the main
        thread is waiting for one (and the loop's work done, see INLINE_STEP_NS), else queued."""
        if self.failure is None and self.turn.acquire(blocking=False):
            try:
                self._serve(item)
            except BaseException as exc:  # StopRun, RestartFlow, or a bug: the main thread raises it
                self.failure = exc
            finally:
                self.turn.release()
                self.inbox.put(_NUDGED)  # the main thread's wake-up time may have changed
        else:
            self.inbox.put(item)

    def _serve(self, item: tuple) -> None:
        """The main thread's work for one message: what was queued before it, the message, held
        outputs now due, then the ticks now ready, while steps stay short."""
        if self.inbox.qsize():
            self._drain()
        self._handle(item)
        if self.stopping:
            return
        now = self.now()
        self._release(now)
        while (self.last_wall is not None and self.last_wall < INLINE_STEP_NS
               and self._try_tick(now) is _TICKED):
            now = self.now()

    # ---------------------------------------------------------------------------------------
    # Time
    # ---------------------------------------------------------------------------------------
    def now(self) -> int:
        """Wall time since T0, ns."""
        return time.time_ns() - self.t0

    def hlc(self) -> int:
        """HLC time since T0, ns: what ASAP outputs are stamped with."""
        return self.session.new_timestamp().get_time_as_ntp64().as_nanos() - self.t0

    def frontier(self, sent: bool = False) -> tuple[int, int]:
        """Every later output of this node will have a tag ≥ this (thread-safe). ``sent``: as
        if the outputs being put now were out already (the frontier they carry); the main
        thread, which just stamped them, then skips reading the HLC again."""
        with self.lock:
            if not self.started:  # its end not known yet: nothing promised past the run's start
                return (0, 0)
            lower = self.running or self._next_tick_bound()
            if lower >= (self.end, 0) and self.running is None:
                own = NEVER
            elif self.latency_ns:
                own = (lower[0] + self.latency_ns, 0)
            elif self.virtual:
                own = (lower[0], lower[1] + 1)
            else:
                # the tick in progress, or the next, is stamped past the last stamp and the HLC now
                stamp = self.last_stamp + 1 if sent else max(self.hlc(), self.last_stamp + 1)
                own = (max(stamp, lower[0] + 1), 0)
            if self.held:
                own = min(own, self.held[0][0])
            if self.sending is not None and not sent:
                own = min(own, self.sending)
            return own

    def _next_tick_bound(self) -> tuple[int, int]:
        """No future tick of this node has a tag below this."""
        bound = self.next_rate if self.next_rate is not None else NEVER
        if self.pending:
            bound = min(bound, self.pending[0])
        for e in self.edges:
            if e.triggers:
                bound = min(bound, self._edge_frontier(e))
        return bound

    def _edge_frontier(self, e: InEdge) -> tuple[int, int]:
        """The producer's frontier as this edge delivers it (a delay shifts it, microstep 0)."""
        f = self.frontiers[(e.src, e.src_port)]
        return (f[0] + e.delay_ns, 0) if e.delay_ns else f

    # ---------------------------------------------------------------------------------------
    # The loop
    # ---------------------------------------------------------------------------------------
    def run(self, t0: int, end: int, resume: bool = False) -> None:
        """Tick from T0 (HLC Unix ns) while ``t < end`` (ns since T0), then finish. ``resume``:
        join a run in progress (a restarted flow) at its next Rate tick."""
        self.t0, self.end = t0, end
        self.promised_end = end  # what producers' frontiers are checked against (an `end` may come sooner)
        self.started = True
        if resume and not self.virtual:  # (in virtual time no tick came due meanwhile: time waited)
            self._skip_missed_ticks(self.now(), "restart_skipped", "restart_skipped")
        elif self.clock.hz is not None:
            with self.lock:
                self.next_rate = (self.clock.tick_time(self.k), 0)
        self._publish_progress()
        # a source on a Rate clock, in real time, its outputs not delayed: an idle pass of the
        # loop takes the short way (issue 21: an idle 100 Hz flow's CPU)
        plain_source = (not self.virtual and not self.edges and not self.inputs and not self.fallbacks
                        and self.clock.hz is not None and not self.latency_ns and not self.spin_ns)
        while not self.stopping:
            quiet = plain_source and not (self.pending or self.held or self.restarting or self.inbox.qsize())
            if quiet and not self.pending_detail:
                self._quiet_source()  # its ticks for as long as they are quiet
                if self.stopping:
                    break
                quiet = not (self.pending or self.held or self.restarting or self.inbox.qsize())
            if quiet:
                now = self.now()
                wake = self._source_pass(now)
            else:
                self._drain()
                if self.stopping:
                    break
                now = self.now()
                self._release(now)
                wake = self._try_tick(now)
            if wake is _TICKED:
                if self.flush_due is not None and now >= self.flush_due:  # (now: before that tick)
                    self.flush()  # also when ticks run back to back: a late node still reports
                continue  # look again at once
            if wake is _DONE:
                break
            if self.flush_due is not None and self.flush_due <= wake:
                # before waiting, not after: a tick that came due is not held up by it, and the
                # reporter thread does its work while this one waits (a 200 Hz tick's p99
                # lateness grew when the report went out just as the tick was due)
                self.flush()
                if self.flush_due is not None:
                    wake = min(wake, self.flush_due)
            if self.held:
                wake = min(wake, self.held[0][0][0])
            target, message = self._warm_target(now, wake)
            if target is not None:
                early = target - WARM_AHEAD_NS
                # nothing came meanwhile, and the wait (at most 100 ms) lasted to the moment
                if not self._wait(early - now) and self.now() >= early:
                    self._warm(message)
                    self.warmed_for = target
                continue
            if self.spin_ns and self.next_rate is not None and wake == self.next_rate[0]:
                self._spin_to(wake)
            else:
                self._wait(wake - self.now())
        if not self.handing_over and not self.abandoned:
            self._finish()

    def _warm_target(self, now: int, wake: int) -> tuple[int | None, bytes | None]:
        """The predictable moment before ``wake`` to warm up for, after a long enough sleep, and
        the received message to decode then; ``(None, None)`` if there is none."""
        target, message = None, None
        if self.warm_publish is not None and self.next_rate is not None:
            target = self.next_rate[0]
        for last, gap, data in self.arrivals.values():
            expected = last + gap
            if now < expected and (target is None or expected < target):
                target, message = expected, data
        if target is None or target > wake or target - now < WARM_AFTER_IDLE_NS or target == self.warmed_for:
            return None, None
        return target, message

    def _warm(self, message: bytes | None) -> None:
        """Run the encoder and the decoder once, results unused (see WARM_AHEAD_NS). Both did
        this work before; should it fail now (a flow changed a value it had emitted), the
        warm-up is simply skipped: it never stops a run."""
        try:
            if self.warm_publish is not None:
                self.encoder.data_parts(*self.warm_publish)
                self.hlc()
                if self.warm_publisher is not None:
                    self.warm_publisher.put(b"")
            if message is not None:
                decode_events(message)
        except Exception:
            self.warm_publish = None

    def _wait(self, ns: int) -> bool:
        """Wait at most ``ns`` for a message and handle it; whether one came."""
        if ns <= 0:
            return False
        self.turn.release()  # a receiving thread may do the work meanwhile
        try:
            item = self.inbox.get(timeout=min(ns, 100_000_000) / 1e9)
        except queue.Empty:
            item = None
        finally:
            self.turn.acquire()
        if self.failure is not None:
            raise self.failure
        if item is None:
            return False
        self._handle(item)
        return True

    def _spin_to(self, wake: int) -> None:
        """Wait for the Rate tick at ``wake`` (configure(spin=)): sleep until ``spin_ns`` before
        it, then busy-wait to it, unless a message comes (the loop then looks again)."""
        while (left := wake - self.spin_ns - self.now()) > 0:  # (one _wait sleeps at most 100 ms)
            if self._wait(left):
                return
        inbox, now = self.inbox, self.now
        began = now()
        while now() < wake and not inbox.qsize():
            pass
        self.counts["spin_ns"] += now() - began

    def _drain(self) -> None:
        """Handle what is queued now, not what arrives meanwhile: a consumer with a backlog
        still gets to tick between batches."""
        waiting = self.inbox.qsize()
        if not waiting:  # (most passes: no exception raised to learn it)
            return
        get = self.inbox.get_nowait
        for _ in range(waiting):
            try:
                item = get()
            except queue.Empty:
                return
            self._handle(item)

    def _try_tick(self, now: int) -> int | str:
        """Run the next tick if it is due and its inputs are complete (or past deadline):
        ``_TICKED``. Else the wall time (ns since T0) to look again, or ``_DONE``."""
        with self.lock:
            tau = self.next_rate
            if self.pending and (tau is None or self.pending[0] < tau):
                tau = self.pending[0]
        if self.virtual:
            bound = self._next_tick_bound()
            if bound >= (self.end, 0) or bound >= (self.granted, 0):
                return self._done_waiting(now) if bound >= (self.end, 0) else self._at_grant(now)
            if tau is None or tau >= (self.granted, 0):  # a tick below the grant may still be triggered
                return self._ask_triggers(now)
        elif tau is None or tau[0] >= self.end:
            return self._done_waiting(now)
        elif tau[0] > now:
            return tau[0]
        if self.restarting:  # due, but the flow is being restarted: the new process will run it
            return now + RESTART_POLL_NS
        incomplete, wake = self._incomplete(tau, now)
        if wake is not None:
            return wake
        with self.lock:
            self.running = tau
            if tau == self.next_rate:
                self.k += 1
                self.next_rate = (self.clock.tick_time(self.k), 0)
            if self.pending and self.pending[0] == tau:
                heapq.heappop(self.pending)
                self.pending_set.discard(tau)
        self._tick(tau, incomplete)
        return self._after_tick()

    def _source_pass(self, now: int) -> int | str:
        """``_try_tick`` for a plain source (see ``run``) with nothing pending, held, queued or
        restarting: its next Rate tick, run as ``_tick`` would (no inputs to select or wait for)."""
        tau = self.next_rate
        if tau is None or tau[0] >= self.end:
            return self._done_waiting(now)
        if tau[0] > now:
            return tau[0]
        with self.lock:
            self.running = tau
            self.k += 1
            self.next_rate = (self.clock.tick_time(self.k), 0)
        self.last_tick = tau
        detail: dict[str, Any] | None = self.pending_detail or None
        self.pending_detail = {}
        start = time.time_ns()
        try:
            outputs = list(self.read(self.invoke({})))
        except KeyboardInterrupt:
            raise
        except BaseException as exc:
            self._step_failed(tau, {}, detail, exc, start)
            return self._after_tick()
        wall = time.time_ns() - start
        self.last_wall = wall
        self._source_stepped(tau, outputs, detail, start, wall)
        return self._after_tick()

    def _source_stepped(self, tau, outputs: list, detail, start: int, wall: int) -> None:
        """A plain source's step returned ``outputs``: publish them and keep the record, as
        ``_tick`` would, then handle an overrun."""
        overran = self.period_ns and wall > self.period_ns
        status = "overrun" if overran else "ok"
        if outputs:
            self._emit(tau, {}, outputs, detail, start, wall, status)
        else:  # as _emit with no event: no stamp, nothing to publish but progress
            self._finish_tick(tau, {}, (), status, detail, start, wall)
        if overran:
            self._overran(tau, wall, start + wall - self.t0)

    def _quiet_source(self) -> None:
        """Run a plain source's ticks (see ``run``) for as long as they are quiet: nothing
        pending, held, queued or restarting, and steps that return no event, on time. Each such
        tick takes about as few operations as a hand-written loop that waits on an inbox (issue
        21: an idle 100 Hz flow's CPU; right after a wake-up the interpreter runs cold, and the
        general pass cost about 45 µs a tick more than such a loop, measured in the worker). A
        source that has published still warms up before each tick, as in the general loop.
        Anything else returns to the general loop: a message (handled first), a step's events,
        error or overrun (its tick finished first), a flush due, the end."""
        lock, time_ns, t0, end = self.lock, time.time_ns, self.t0, self.end
        invoke, tick_time, period, queued = self.invoke, self.clock.tick_time, self.period_ns, self.inbox.qsize
        while not (self.stopping or self.restarting or queued()):  # (what came during a step: handled first)
            tau = self.next_rate
            if tau is None or tau[0] >= end:
                return
            wait = tau[0] - (time_ns() - t0)
            if wait > 0:
                if self.flush_due is not None and self.flush_due <= tau[0]:
                    return  # the general loop flushes before it waits
                # a node with consumers that has published warms up just before the tick, by the
                # general loop's rule (_warm_target; a source has no arrivals to warm for)
                warm_at = None
                if self.warm_publish is not None:
                    target, _ = self._warm_target(tau[0] - wait, tau[0])
                    warm_at = None if target is None else target - WARM_AHEAD_NS
                if self._wait(wait if warm_at is None else warm_at - (tau[0] - wait)):
                    return  # a message came, and was handled
                if warm_at is not None and time_ns() - t0 >= warm_at:
                    self._warm(None)
                    self.warmed_for = tau[0]
                continue
            with lock:
                self.running = tau
                self.k = k = self.k + 1
                self.next_rate = (tick_time(k), 0)
            self.last_tick = tau
            start = time_ns()
            try:
                raw = invoke({})
            except KeyboardInterrupt:
                raise
            except BaseException as exc:
                self._step_failed(tau, {}, None, exc, start)
                return
            wall = self.last_wall = time_ns() - start
            outputs = ()
            if raw is not None:  # (an empty dict, an output object of Nones: quiet too)
                try:
                    outputs = list(self.read(raw))
                except KeyboardInterrupt:
                    raise
                except BaseException as exc:
                    self._step_failed(tau, {}, None, exc, start)
                    return
            if outputs or (period and wall > period):
                self._source_stepped(tau, outputs, None, start, wall)
                return
            with lock:
                self.running = None
            if self.consumed:
                self._publish(())  # the frontier, for its consumers
            self.records.append((tau, {}, (), "ok", None, start, wall))  # as _record, inline
            self.recorded += 1
            if self.flush_due is None:
                self.flush_due = time_ns() - t0 + RECORDS_FLUSH_AFTER_NS
            elif len(self.records) >= FLUSH_MAX:
                self.flush()

    def _after_tick(self) -> int | str:
        """Right after a tick: ``_TICKED`` (look again at once) unless the next tick is a Rate
        tick not due yet and nothing else is waiting, in which case its time, as the next pass of
        the loop would find it (an idle flow then makes one pass per tick, not two)."""
        if self.virtual or self.stopping or self.restarting or self.pending or self.held or self.inbox.qsize():
            return _TICKED
        tau = self.next_rate
        if tau is None or tau[0] >= self.end or self.triggered:
            return _TICKED
        return tau[0] if tau[0] > self.now() else _TICKED

    def _incomplete(self, tau: tuple[int, int], now: int) -> tuple[list[str], int | None]:
        """Ports whose edge is not complete up to ``tau`` and past deadline; or the wall time to
        look again if some edge may still complete in time."""
        late_ports, wake = [], None
        for e in self.edges:
            f = self._edge_frontier(e)
            if f > tau:
                continue
            if self.virtual:  # no deadline: wait for it, asking its producer now and then
                since = self._blocked_since(tau, now)
                again = self._ask(e.src, now, since)
                wake = again if wake is None else min(wake, again)
                continue
            if now >= tau[0] + e.deadline_ns:
                late_ports.append(e.port)
                continue
            wake = min(tau[0] + e.deadline_ns, wake if wake is not None else tau[0] + e.deadline_ns,
                       self._ask(e.src, now, tau[0]))
        return sorted(set(late_ports)), wake

    def _had_below(self, ports: list[str]) -> dict[str, list[list]]:
        """For a tick run incomplete: per port, each of its producers' streams and the seq it
        expects next. The tick saw that stream's events below it and none from it on (a stream
        is taken in order), so a replay can withhold the later ones with an earlier tag that came
        after this tick: those its next record names late, and those that never came (its
        process died, or the run ended first), which no record names."""
        return {port: [[e.src, e.src_port, self.expect[(e.src, e.src_port)]] for e in self.edges if e.port == port]
                for port in ports}

    def _blocked_since(self, tau: tuple[int, int], now: int) -> int:
        """Virtual time: since when (wall, ns since T0) the tick ``tau`` waits for its inputs."""
        if self.blocked is None or self.blocked[0] != tau:
            self.blocked = (tau, now)
        return self.blocked[1]

    def _ask_triggers(self, now: int) -> int:
        """Virtual time: no tick below the grant is known, but a trigger edge may still bring one:
        ask its producer for its frontier now and then; when to look again."""
        wake = now + VIRTUAL_IDLE_NS
        since = self._blocked_since((self.granted, -1), now)
        for e in self.edges:
            if e.triggers and self._edge_frontier(e) < (self.granted, 0):
                wake = min(wake, self._ask(e.src, now, since))
        return wake

    def _at_grant(self, now: int) -> int:
        """Virtual time: every tick below the grant has run; say so once (with this node's
        frontier to its consumers first), then wait for the next grant."""
        if self.reached < self.granted and not self.restarting:  # (the new process will say it)
            self.reached = self.granted
            if self.consumed:
                self._publish_progress()
            self.flush()
            if self.on_reached is not None:
                self.on_reached(self.granted)
        return now + VIRTUAL_IDLE_NS

    def _ask(self, src: str, now: int, since: int) -> int:
        """Ask a producer for its frontier once a wait has lasted ``PROBE_AFTER_NS`` past
        ``since``, then at most every ``ASK_EVERY_NS``; returns when to look again."""
        if now < since + PROBE_AFTER_NS:
            return since + PROBE_AFTER_NS
        after = self.ask_after.get(src, 0)
        if now < after:
            return after
        self.ask_after[src] = now + ASK_EVERY_NS
        put = self.inbox.put

        def on_reply(reply: zenoh.Reply, src: str = src) -> None:
            if reply.ok is not None:
                put((_PROGRESS, src, reply.ok.payload.to_bytes()))
            else:
                put((_PROGRESS, src, None))

        self.session.get(self.keys.progress(src), handler=on_reply, timeout=1.0)
        return now + ASK_EVERY_NS

    def _done_waiting(self, now: int) -> int | str:
        """No tick below ``end`` is known: finished once no edge can still trigger one."""
        if self.held:
            return self.held[0][0][0]
        wake: int | None = None
        end_tag = (self.end, 0)
        for e in self.edges:
            if not e.triggers:
                continue
            f = self._edge_frontier(e)
            if f >= end_tag or (now >= self.end + e.deadline_ns and not self.virtual):
                continue
            again = min(self.end + e.deadline_ns, self._ask(e.src, now, self.end))
            wake = again if wake is None else min(wake, again)
        return _DONE if wake is None else wake

    def _overran(self, tau: tuple[int, int], wall: int, done: int) -> None:
        """After a Rate tick's step outlasted the period: skip the ticks that came due meanwhile
        but the newest (on_overrun="skip"), run every one of them, late, in order
        (on_overrun="catch_up": none is lost, so a LET flow's trace stays the virtual-time one),
        or stop (on_overrun="error", realtime="hard")."""
        if self.on_overrun == "catch_up" and self.realtime != "hard":
            self.counts["overrun"] += 1
            return
        missed = self._skip_missed_ticks(done, "overrun", "overrun_skipped")
        if missed and (self.realtime == "hard" or self.on_overrun == "error"):
            raise StopRun(f"{self.id} overran its period: the step at t={tau[0] / 1e9:.6f} s took "
                          f"{wall / 1e6:.3f} ms, {missed} tick(s) missed\n    hint: make step() faster, lower the "
                          f"rate, or set on_overrun='skip' (realtime='{self.realtime}')", tau)

    def _skip_missed_ticks(self, now: int, counter: str, detail_key: str) -> int:
        """Skip the Rate ticks that came due before ``now`` but the newest, which runs next;
        count them under ``counter`` and tell the next record under ``detail_key``."""
        if self.clock.hz is None:
            return 0
        clock = self.clock
        missed = 0
        with self.lock:
            while clock.tick_time(self.k + 1) <= now and clock.tick_time(self.k) < self.end:
                self.k += 1
                missed += 1
            self.next_rate = (clock.tick_time(self.k), 0)
        if missed:
            self.counts[counter] += missed
            self.pending_detail[detail_key] = self.pending_detail.get(detail_key, 0) + missed
        return missed

    # ---------------------------------------------------------------------------------------
    # Messages
    # ---------------------------------------------------------------------------------------
    def _handle(self, item: tuple) -> None:
        kind, key, data = item
        if kind == _DATA:
            try:
                events = decode_events(data, expected=key)
                self._check_claims(key, events[0].seq, events[-1].frontier)
            except WireError as e:
                self._garbage(key, e)
                return
            arrival = time.time_ns()
            self._arrived(key, data if len(events) == 1 else None, arrival - self.t0)  # (a burst is not warmed)
            if self.values:
                have, kept = self.have.get(key, -1), (arrival, data)  # one for a burst's events: sent once
                for msg in events:
                    if msg.seq > have:
                        self.kept[(msg.producer, msg.port, msg.seq)] = kept
            for msg in events:
                self._in_order(key, msg)
        elif kind == _NUDGE:
            return
        elif kind == _PROGRESS:
            if data is None:
                return  # the query timed out
            try:
                progress = decode_progress(data, expected=key)
                streams = [s for s in self.frontiers if s[0] == progress.producer]
                for stream in streams:  # (its seqs may be far ahead: see WAITING_MAX)
                    self._check_claims(stream, None, progress.frontier)
            except WireError as e:
                self._garbage(key, e)
                return
            for stream in streams:
                self._progress(stream, progress.sent.get(stream[1], -1), progress.frontier)
        else:
            try:
                op, args = decode_control(data)
            except WireError as e:
                self._garbage("ctl/run", e)
                return
            if op == "stop":
                self.stopping = self.told_to_stop = True
            elif op == "end":  # a step's sys.exit(0) ended the run there: the ticks before it still run
                at = args.get("at")
                if type(at) is int and at >= 0:
                    with self.lock:
                        self.end = min(self.end, at)
                else:
                    self._garbage("ctl/run", WireError(f"an 'end' control message with at {at!r:.30}"))
            elif op == "redeclare":  # only for a node not started yet (worker._await_control)
                self._garbage("ctl/run", WireError("a 'redeclare' control message during the run"))
            elif op == "handover" and args.get("node") == self.id and self.restarting:
                self.stopping = self.handing_over = True
            elif op == "have":
                self._coordinator_has(args)
            elif op == "grant" and self.virtual:
                until = args.get("until")
                if type(until) is int and until >= 0:
                    self.granted = max(self.granted, min(until, self.end))
                    if until <= self.reached and self.on_reached is not None:  # our word was missed: again
                        self.on_reached(self.reached)
                else:
                    self._garbage("ctl/run", WireError(f"a 'grant' control message with until {until!r:.30}"))
            elif op == "lost" and args.get("node") == self.id:
                # the coordinator counts this process dead (its worker daemon hung or was cut off)
                # and starts another: this one must not run on beside it, nor promise anything
                self.abandoned = self.stopping = True
            elif op == "lost" and args.get("node") in self.sources:
                self.lost_producers.add(args["node"])
            elif op == "restarted" and args.get("node") in self.sources:
                self._producer_restarted(args["node"], args.get("seqs"))

    def _check_claims(self, stream: tuple[str, str], seq: int | None, frontier: tuple[int, int]) -> None:
        """Refuse a data message's seq from the future or a frontier its producer cannot promise
        (see CLOCK_AHEAD_MAX_NS): applied, one would hold the stream back, or make every later
        event of it late, for the rest of the run."""
        expect = self.expect[stream]
        ahead = EARLY_SEQS_MAX + (RESTART_SEQ_GAP if stream[0] in self.lost_producers else 0)
        if seq is not None and seq > expect + ahead:
            raise WireError(f"seq {seq} of {stream[0]}.{stream[1]} is {seq - expect} past the next one expected "
                            f"({expect}): a seq from the future")
        if frontier == NEVER:
            return
        if frontier > NEVER:
            raise WireError(f"frontier {frontier} of {stream[0]} is past every tag a run has")
        end = self.promised_end
        if end and frontier[0] > end + self.src_latency_ns[stream] + 1:  # the run started: end known
            # past the run's end plus the producer's latency only an ASAP stamp can be, near the clock
            limit = self.now() + CLOCK_AHEAD_MAX_NS
            if frontier[0] > limit:
                raise WireError(f"frontier {frontier} of {stream[0]} is past what it can promise now (t <= "
                                f"{end + self.src_latency_ns[stream] + 1} ns, the run's end plus its latency, "
                                f"or {limit} ns, its clock)")

    def _arrived(self, stream: tuple[str, str], data: bytes, now: int) -> None:
        """Note when a stream's message came, to foresee its next one (see WARM_AHEAD_NS)."""
        last = self.arrivals.get(stream)
        gap = now - last[0] if last is not None else 0
        self.arrivals[stream] = (now, gap, data)

    def _in_order(self, stream: tuple[str, str], msg) -> None:
        """Take a stream's events in seq order (Zenoh may reorder across routes); a frontier
        holds once every seq before it has been taken."""
        expect = self.expect[stream]
        if msg.seq < expect or msg.seq in self.early[stream]:
            # a duplicate; below taken_over it is one the process this one took over from had
            # too (both listened meanwhile): expected, not garbage
            if msg.seq >= self.taken_over.get(stream, 0):
                self._garbage(stream, WireError(f"seq {msg.seq} of {stream[0]}.{stream[1]} arrived twice"))
            return
        if msg.seq > expect:
            self.early[stream][msg.seq] = msg
            return
        early = self.early[stream]
        while msg is not None:
            self._advance_frontier(stream, msg.frontier)
            for e in self.edges:
                if e.src == msg.producer and e.src_port == msg.port:
                    self._deliver(e, msg)
            expect += 1
            msg = early.pop(expect, None)
        self.expect[stream] = expect
        waiting = self.waiting[stream]
        if waiting and waiting[0][0] < expect:  # (sorted by seq)
            ready = bisect_left(waiting, (expect,))
            self._advance_frontier(stream, max(f for _, f in waiting[:ready]))
            del waiting[:ready]

    def _progress(self, stream: tuple[str, str], after_seq: int, frontier: tuple[int, int]) -> None:
        if after_seq < self.expect[stream]:
            self._advance_frontier(stream, frontier)
            return
        waiting = self.waiting[stream]
        insort(waiting, (after_seq, frontier))
        if len(waiting) > WAITING_MAX:  # every other one goes, the last one stays: a later one promises as much
            del waiting[-2::-2]

    def _advance_frontier(self, stream: tuple[str, str], frontier: tuple[int, int]) -> None:
        if frontier > self.frontiers[stream]:
            with self.lock:
                self.frontiers[stream] = frontier

    def _deliver(self, e: InEdge, msg) -> None:
        arrival = (msg.tag[0] + e.delay_ns, 0) if e.delay_ns else msg.tag
        entry = (arrival, msg.producer, msg.port, msg.seq, msg.value)
        if arrival <= self.last_tick:
            # A tick at or after this tag already ran without it: never applied to that past tick,
            # but in the buffer, by its tag, for every tick from the next one on (a slow policy's
            # chunk still reaches its controller). Its next record names it, by id: a replay puts
            # it in the buffer at exactly that point (retriever/replay.py). It triggers no past tick.
            self.counts["late"] += 1
            self.pending_detail.setdefault("late", {}).setdefault(e.port, []).append(
                (msg.producer, msg.port, msg.seq))
            e.buf.insert(entry)
            return
        e.buf.insert(entry)
        if e.triggers and arrival[0] < self.end and arrival not in self.pending_set:
            with self.lock:
                self.pending_set.add(arrival)
                heapq.heappush(self.pending, arrival)

    def _garbage(self, key: Any, error: WireError) -> None:
        self.counts["garbage"] += 1
        if self.counts["garbage"] <= 3:
            print(f"retriever worker {self.id}: dropped a message on {key}: {error}", file=sys.stderr, flush=True)

    # ---------------------------------------------------------------------------------------
    # A tick
    # ---------------------------------------------------------------------------------------
    def _tick(self, tau: tuple[int, int], incomplete: list[str]) -> None:
        self.last_tick = tau
        detail: dict[str, Any] | None = self.pending_detail or None
        self.pending_detail = {}
        if incomplete:
            self.counts["incomplete"] += 1
            detail = {**(detail or {}), "incomplete": incomplete, "had_below": self._had_below(incomplete)}
            if self.realtime == "hard":  # the tick does not step: skipped, and the run stops
                self._record(tau, {}, (), "skipped", detail, time.time_ns(), 0)
                raise StopRun(f"{self.id}: input(s) {', '.join(incomplete)} not complete up to the tick at "
                              f"t={tau[0] / 1e9:.6f} s within the deadline (realtime='hard')\n"
                              "    hint: raise the edge's deadline= or the Pipeline's, or use realtime='soft'", tau)
        values, consumed, missing, commits, dropped = select_inputs(self.inputs, tau)
        if dropped:
            detail = {**(detail or {}), **dropped}
        if missing is not None:
            self._finish_tick(tau, {}, (), "skipped", {**(detail or {}), "missing": missing}, time.time_ns(), 0)
            return
        for policy, buf, commit in commits or ():
            policy.commit_to(buf, commit)
        for port, spec in self.fallbacks.items():
            values[port] = spec.fallback()

        start = time.time_ns()
        try:
            outputs = list(self.read(self.invoke(values)))
        except KeyboardInterrupt:
            raise
        except BaseException as exc:  # SystemExit too: sys.exit(1) in a step is that step's error, as in-process
            self._step_failed(tau, consumed, detail, exc, start)
            return
        wall = time.time_ns() - start
        self.last_wall = wall
        overran = self.period_ns and wall > self.period_ns and not self.virtual
        self._emit(tau, consumed, outputs, detail, start, wall,
                   "overrun" if overran else "incomplete" if incomplete else "ok")
        if overran:
            self._overran(tau, wall, start + wall - self.t0)

    def _step_failed(self, tau, consumed, detail, exc: BaseException, start: int) -> None:
        """The step raised ``exc`` (not KeyboardInterrupt): record it, then stop the run, restart
        the flow or go on, as ``on_error`` says; ``sys.exit(0)`` ends the whole run cleanly."""
        wall = self.last_wall = time.time_ns() - start
        if isinstance(exc, SystemExit) and exc.code in (None, 0):
            # sys.exit(0): the whole run ends here, cleanly. The coordinator is told first
            # (it stops every node), then this loop ends as if told to stop.
            self._finish_tick(tau, consumed, (), "ok", {**(detail or {}), "exit": 0}, start, wall)
            if self.on_exit is not None:
                self.on_exit(tau)
            self.stopping = self.told_to_stop = True
            return
        error = f"{type(exc).__name__}: {exc}"
        self._finish_tick(tau, consumed, (), "error", {**(detail or {}), "error": error, "on_error": self.on_error},
                          start, wall)
        if self.on_error == "stop":
            raise StopRun(f"{self.id}.step() raised {error}", tau) from exc
        if self.on_error == "restart":
            self.restarting = True
            if self.on_restart is not None:
                self.on_restart(tau, error)

    def _emit(self, tau, consumed, outputs, detail, start, wall, status) -> None:
        """Publish a step's outputs (or hold them, LET) and record it with ``status``: ``ok``,
        ``incomplete`` or ``overrun``, or ``late`` when it misses its LET deadline."""
        events = [(port, value) for port, value in outputs  # None, or an empty burst: no event
                  if value is not None and not (type(value) is Burst and not value.values)]
        produced = []
        seqs = self.seqs
        if self.latency_ns:
            tag = (tau[0] + self.latency_ns, 0)
        elif self.virtual:  # as in-process: one microstep later
            if tau[1] + 1 > self.max_microsteps and any(port in self.instant_ports for port, _ in events):
                self._zeno(tau)
            tag = (tau[0], tau[1] + 1)
        elif events:
            microstep = tau[1] + 1 if self.instant_ports else 0
            if microstep > self.max_microsteps and any(port in self.instant_ports for port, _ in events):
                self._zeno(tau)
            # strictly increasing, so the frontier right after a publish is its tag + 1 ns even
            # when the node runs late (the tag then passes the next tick's time)
            self.last_stamp = max(self.hlc(), tau[0] + 1, self.last_stamp + 1)
            tag = (self.last_stamp, microstep)
        else:  # nothing to stamp: no clock read (a later stamp is past this one's all the same)
            tag = None
        batch = []
        for port, value in events:
            seq = seqs.get(port, 0)
            if type(value) is Burst:  # its events go as one message: one batch item
                seqs[port] = seq + len(value.values)
                produced.extend((self.id, port, s) for s in range(seq, seq + len(value.values)))
            else:
                seqs[port] = seq + 1
                produced.append((self.id, port, seq))
            batch.append((tag, port, value, seq))
        if self.latency_ns and not self.virtual:  # (in virtual time, LET outputs go at once: the tag says when)
            finished = start + wall - self.t0
            if finished > tag[0]:  # the step outlasted its logical execution time
                self.counts["deadline_miss"] += 1
                stop = self.realtime == "hard" or self.on_deadline_miss == "error"
                # what was done with the outputs: published late, or dropped (and the run stopped)
                detail = {**(detail or {}), "deadline_miss_ns": finished - tag[0],
                          "on_deadline_miss": "error" if stop else self.on_deadline_miss}
                if stop or self.on_deadline_miss == "drop":
                    for _, port, _, seq in batch:  # (a burst's first seq)
                        seqs[port] = min(seqs[port], seq)
                    self._finish_tick(tau, consumed, (), "late", detail, start, wall)
                    if stop:
                        hint = ("raise latency=, or run the pipeline with realtime='soft', where on_deadline_miss "
                                f"(now '{self.on_deadline_miss}') decides" if self.realtime == "hard" else
                                "raise latency=, or set on_deadline_miss='publish_late' or 'drop'")
                        raise StopRun(f"{self.id} missed its LET deadline: the step at t={tau[0] / 1e9:.6f} s "
                                      f"finished {(finished - tag[0]) / 1e6:.3f} ms after t+latency\n    hint: {hint}",
                                      tau)
                    return
                self._release(finished)  # earlier ticks' held outputs go first
                self._finish_tick(tau, consumed, tuple(produced), "late", detail, start, wall, publish=batch)
                return
            with self.lock:
                for item in batch:
                    heapq.heappush(self.held, item)
            self._finish_tick(tau, consumed, tuple(produced), status, detail, start, wall)
            return
        self._finish_tick(tau, consumed, tuple(produced), status, detail, start, wall, publish=batch)

    def _zeno(self, tau: tuple[int, int]) -> None:
        """Stop the run: the instant of ``tau`` ran past max_microsteps. The tick's outputs are
        not published and it has no record, as in-process (the run's end record says why)."""
        with self.lock:
            self.running = None
        raise StopRun(str(CausalityError(self.cycle, tau, self.max_microsteps)), tau, zeno=True)

    def _finish_tick(self, tau, consumed, produced, status, detail, start, wall, publish=()) -> None:
        with self.lock:
            self.running = None
            if publish:
                self.sending = publish[0][0]
        self._publish(publish)  # first: the record is for the coordinator, and can wait
        self._record(tau, consumed, produced, status, detail, start, wall)

    def _record(self, tau, consumed, produced, status, detail, start, wall) -> None:
        self.records.append((tau, consumed, produced, status, detail, start, wall))
        self.recorded += 1
        if self.flush_due is None:
            self.flush_due = self.now() + RECORDS_FLUSH_AFTER_NS
        elif len(self.records) >= FLUSH_MAX:
            self.flush()

    def _release(self, now: int) -> None:
        """Publish held LET outputs whose tag time has come."""
        if not self.held or self.held[0][0][0] > now:
            return
        batch = []
        with self.lock:
            while self.held and self.held[0][0][0] <= now:
                batch.append(heapq.heappop(self.held))
            self.sending = batch[0][0]
        self._publish(batch)

    def _publish(self, batch: list) -> None:
        """Send events (each but the last carries its own tag as frontier, the last the node's
        frontier), then a progress message if some consumer's port did not get the frontier."""
        if not batch and not self.consumed:  # (an idle tick of a flow no one consumes: nothing to say)
            return
        frontier = self.frontier(sent=True)
        data, publishers = self.encoder.data, self.publishers
        last = len(batch) - 1
        for i, (tag, port, value, seq) in enumerate(batch):
            publisher = publishers.get(port)
            if publisher is None:  # an output port no edge uses (an untyped flow's extra key)
                publisher = publishers[port] = self._publisher(self.keys.data(self.id, port))
            try:
                message = data(tag, seq, frontier if i == last else tag, self.id, port, value)
            except CodecError as e:  # the step returned it; in-process it would have gone by reference
                what = "the Burst (value[i]: its value i)" if type(value) is Burst else "the event"
                raise StopRun(f"{self.id}.{port}: {what} at t={tag[0] / 1e9:.6f} s cannot be sent to another "
                              f"process: {e}", tag) from None
            burst = type(value) is Burst
            # counted as sent before the put, not after: a consumer that subscribes meanwhile and
            # asks where the stream stands (a node started afresh: sync_inputs) must not be told
            # to wait for this seq. Zenoh chose the put's subscribers when it began, and a put held
            # by a congested link (a consumer's host cut off, BLOCK) began long before it returns:
            # told 'sent up to seq - 1', the new consumer waited for a seq that never came to it,
            # every tick incomplete, for the rest of the run (issue 40)
            self.sent[port] = seq + len(value.values) - 1 if burst else seq
            publisher.put(message)
            if self.consumed and not burst:  # someone waits for this node's next event: warm its path first
                self.warm_publish = (tag, seq, frontier, self.id, port, value)
            if not self.values:  # the coordinator records that it was sent, not what
                blank = Burst._of((None,) * len(value.values)) if burst else None  # sent as nil
                message = data(tag, seq, frontier if i == last else tag, self.id, port, blank)
            self.published.append((time.time_ns(), message))
            self.published_bytes += len(message)
            self.published_seqs += len(value.values) if burst else 1
        if batch:
            if self.published_bytes >= FLUSH_MAX_BYTES or self.published_seqs >= FLUSH_MAX_SEQS:
                self.flush()
            else:  # (held LET outputs are released after their record went)
                due = self.now() + FLUSH_AFTER_NS
                if self.flush_due is None or self.flush_due > due:  # (records alone may wait longer)
                    self.flush_due = due
        if self.sending is not None:
            with self.lock:
                self.sending = None  # only now may a progress query promise past these tags
        if self.consumed and not (batch and self.single_port):
            self._publish_progress(frontier)

    def _publish_progress(self, frontier: tuple[int, int] | None = None) -> None:
        self.progress_publisher.put(self.encoder.progress(frontier or self.frontier(), self.id, self.sent))

    # ---------------------------------------------------------------------------------------
    # Restarting (on_error="restart")
    # ---------------------------------------------------------------------------------------
    # A step raised. This process runs no more ticks, but keeps receiving (its input buffers
    # stay whole) and answering for its frontier (it stays at the tick due), releases held LET
    # outputs on time, and says `restart`. The coordinator starts a new process, which listens
    # to the same inputs and says `ready`; then it tells this one to hand over: this loop stops,
    # and its state goes to the new process in a file. The new loop goes on from that state
    # with a fresh flow, so what it consumes is what one process would have consumed: a log
    # replays, the replay resetting the flow at the error record as the in-process backend does.
    # Rate ticks that came due meanwhile are skipped but the newest (like an overrun), and
    # triggered ticks run late.

    def handover_state(self) -> dict:
        """This loop's state, for the process that takes over (call after ``undeclare``: the
        messages already queued are taken in first, and no more come)."""
        self._drain()
        streams = sorted(self.frontiers)
        return {
            "buffers": [[port, buf.entries, buf.visible, buf.cursor, buf.last_id] for port, buf, *_ in self.inputs],
            "streams": [[src, port, self.frontiers[(src, port)], self.expect[(src, port)],
                         [tuple(m) for m in self.early[(src, port)].values()], self.waiting[(src, port)]]
                        for src, port in streams],
            "pending": self.pending, "k": self.k, "next_rate": self.next_rate, "last_tick": self.last_tick,
            "last_stamp": self.last_stamp, "seqs": self.seqs, "sent": self.sent,
            # a held burst goes as its values, marked (the codec encodes values, not bursts)
            "held": [(tag, port, value.values, seq, "burst") if type(value) is Burst else (tag, port, value, seq)
                     for tag, port, value, seq in self.held],
            "pending_detail": self.pending_detail, "values": self.values,
        }

    def take_over(self, state: dict) -> None:
        """Go on from the state of the process this one replaces (see :meth:`handover_state`)."""
        buffers = {port: buf for port, buf, *_ in self.inputs}
        for port, entries, visible, cursor, last_id in state["buffers"]:
            buf = buffers[port]
            buf.entries, buf.visible, buf.cursor, buf.last_id = [tuple(e) for e in entries], visible, cursor, last_id
        for src, port, frontier, expect, early, waiting in state["streams"]:
            stream = (src, port)
            self.frontiers[stream], self.expect[stream] = tuple(frontier), expect
            self.early[stream] = {m[1]: DataMessage(*m) for m in early}
            self.waiting[stream] = sorted((seq, tuple(f)) for seq, f in waiting)
            self.taken_over[stream] = max([expect, *(seq + 1 for seq in self.early[stream])])
        self.pending = [tuple(t) for t in state["pending"]]
        heapq.heapify(self.pending)
        self.pending_set = set(self.pending)
        self.k, self.last_stamp = state["k"], state["last_stamp"]
        self.next_rate = tuple(state["next_rate"]) if state["next_rate"] is not None else None
        self.last_tick = tuple(state["last_tick"])
        self.held = [(h[0], h[1], Burst._of(tuple(h[2])), h[3]) if len(h) == 5 else tuple(h) for h in state["held"]]
        heapq.heapify(self.held)
        self.values = state.get("values") is not False
        self.seqs, self.sent = dict(state["seqs"]), dict(state["sent"])
        self.pending_detail = dict(state["pending_detail"])

    # ---------------------------------------------------------------------------------------
    # Restarting after a lost process (on_error="restart", the process died: kill -9, segfault)
    # ---------------------------------------------------------------------------------------
    # Nothing can be handed over: the flow starts afresh in a new process, with empty input
    # buffers. The coordinator says `lost` {node} at once; the new process subscribes to its
    # inputs and learns from each producer's progress answer the seq its streams go on from
    # (older ones it ignores), links to its consumers and says `ready`. The coordinator then
    # puts `restarted` {node, seqs}: the new process's first seq per output port, past every one
    # the dead process may have used (RESTART_SEQ_GAP). Each consumer of it gives up the seqs it
    # still missed from the dead process, tells its next record which (``restart_gap``, so a
    # replay withholds exactly those), and takes the stream on from there. The new process's
    # first record says where its inputs began (``restarted``): a replay resets the flow and
    # empties its buffers there, as the run did.

    def sync_inputs(self, answers: dict[str, Any]) -> None:
        """Take each input stream on from where its producer stands now (a fresh process):
        ``answers`` maps a producer to its progress answer, or to None when it is finished."""
        first: dict[str, list] = {}
        for e in self.edges:
            stream = (e.src, e.src_port)
            if e.src not in answers:  # it never answered: its events are taken from seq 0
                continue
            answer = answers[e.src]
            if answer is None:
                self.frontiers[stream] = NEVER
                self.taken_over[stream] = self.expect[stream] = 1 << 62
                continue
            expect = answer.sent.get(e.src_port, -1) + 1
            self.frontiers[stream] = max(self.frontiers[stream], answer.frontier)
            self.expect[stream] = self.taken_over[stream] = expect  # older ones may still arrive: ignored
            first.setdefault(e.port, []).append([e.src, e.src_port, expect])
        self.fresh_inputs = {port: sorted(ids) for port, ids in first.items()}

    def start_fresh(self, seqs: dict[str, int], t0: int) -> None:
        """Go on from the coordinator's ``restarted``: each output port's first seq, Rate ticks from now."""
        self.seqs = {port: seq for port, seq in seqs.items()}
        self.sent = {port: seq - 1 for port, seq in seqs.items()}
        for e in self.edges:  # a feedback edge to itself: its inputs are its new outputs
            if e.src == self.id and e.src_port in seqs:
                stream = (e.src, e.src_port)
                self.expect[stream] = self.taken_over[stream] = seqs[e.src_port]
                self.fresh_inputs.setdefault(e.port, []).append([e.src, e.src_port, seqs[e.src_port]])
        self.pending_detail["restarted"] = {"seqs": dict(sorted(seqs.items())), "inputs": self.fresh_inputs}
        if self.clock.hz is not None:  # run() starts at this tick
            self.k = self.clock.first_tick_at_or_after(time.time_ns() - t0)

    def _producer_restarted(self, producer: str, seqs: Any) -> None:
        """Control ``restarted`` {node: producer, seqs: {port: first seq}}: see above. Checked for
        sense first (a forged one would cut this consumer off a live producer): the producer was
        said ``lost``, and each first seq lies where the coordinator puts it, past every seq taken
        by at most RESTART_SEQ_GAP + EARLY_SEQS_MAX. A process that took its inputs on afresh from
        the producer's own answer (sync_inputs) needs no word of it: one it has caught up is ignored."""
        streams = [s for s in self.frontiers if s[0] == producer]
        if type(seqs) is not dict or not all(type(k) is str and type(v) is int and v >= 0 for k, v in seqs.items()):
            self._garbage("ctl/run", WireError(f"a 'restarted' control message of {producer} without its seqs"))
            return
        if producer not in self.lost_producers:
            if any(seqs.get(s[1], -1) > self.expect[s] for s in streams):
                self._garbage("ctl/run", WireError(f"a 'restarted' control message of {producer}, which was not "
                                                   "said lost: refused"))
            return
        wild = [s for s in streams if s[1] in seqs and not 0 <= seqs[s[1]] - self.expect[s] <= RESTART_SEQ_GAP
                + EARLY_SEQS_MAX]
        if wild:
            self._garbage("ctl/run", WireError(f"a 'restarted' control message of {producer} puts "
                                               f"{producer}.{wild[0][1]} at seq {seqs[wild[0][1]]}, where its stream "
                                               f"is at {self.expect[wild[0]]}: refused"))
            return
        self.lost_producers.discard(producer)
        # records that consumed an event of the dead process the coordinator lacks go now, with
        # it: the coordinator's next `have` jumps over the seqs this one gives up
        self.flush(final=True)
        for stream in streams:
            first = seqs.get(stream[1])
            if first is None:
                continue
            expect = self.expect[stream]
            for e in self.edges:
                if (e.src, e.src_port) == stream:
                    gaps = self.pending_detail.setdefault("restart_gap", {}).setdefault(e.port, [])
                    gaps.append([producer, stream[1], expect, first])
            later = {seq: msg for seq, msg in self.early[stream].items() if seq >= first}
            waiting = self.waiting[stream]
            promised = [f for seq, f in waiting if seq < first]  # the dead process's, and the new one's start
            self.waiting[stream] = [(seq, f) for seq, f in waiting if seq >= first]
            self.expect[stream], self.early[stream] = first, {}
            self.taken_over[stream] = first  # what the dead process sent and arrives now is ignored
            if promised:
                self._advance_frontier(stream, max(promised))
            for seq in sorted(later):
                self._in_order(stream, later[seq])

    # ---------------------------------------------------------------------------------------
    # The end
    # ---------------------------------------------------------------------------------------
    def _finish(self) -> None:
        """Release what is held (tags past the end still belong to the run), promise nothing more."""
        self._drain()
        with self.lock:
            self.next_rate = None
            unrun = sum(1 for tag in self.pending if tag[0] < self.end)
            if unrun:  # triggered before the end, but their inputs never completed in time
                self.counts["unrun_ticks"] += unrun
            self.pending, self.pending_set = [], set()
        self.release_held()
        self._publish_progress(NEVER)
        self.finish_reports()

    def release_held(self) -> None:
        """Publish every held LET output now, before its time: this loop ends (the run's end, or
        its process restarts or stops). Their seqs are in step records already, and consumers
        take events by tag, not by arrival: early, they change no tick; missing, they would
        leave a gap in their stream that no consumer's edge completes past."""
        with self.lock:
            batch = sorted(self.held)
            self.held = []
            self.sending = batch[0][0] if batch else None
        self._publish(batch)

    def _coordinator_has(self, args: dict) -> None:
        """Control ``have`` {streams: [[producer, port, last seq], …]}: forget those messages."""
        streams = args.get("streams")
        if type(streams) is not list:
            self._garbage("ctl/run", WireError("a 'have' control message without a list of streams"))
            return
        for item in streams:
            if (type(item) is list and len(item) == 3 and type(item[0]) is str and type(item[1]) is str
                    and type(item[2]) is int and (item[0], item[1]) in self.frontiers):
                stream = (item[0], item[1])
                self.have[stream] = max(self.have.get(stream, -1), item[2])
        if self.kept:
            self.kept = {eid: kept for eid, kept in self.kept.items() if eid[2] > self.have.get(eid[:2], -1)}

    def _unlogged(self, record: tuple) -> list[tuple[str, str, int]]:
        """The events a step record consumed that the coordinator may not have (and wants)."""
        if not self.values:
            return []
        have, me = self.have, self.id  # its own events go in its own reports, before its records
        return [eid for ids in record[1].values() for eid in ids if eid[0] != me and eid[2] > have.get(eid[:2], -1)]

    def flush(self, final: bool = False) -> None:
        """Hand step records and published events to the reporter, for the coordinator: records
        that consumed an event it may lack wait (HOLD_RECORDS_NS), in order; past that, or when
        ``final``, they go with the messages of those events."""
        held = self.held_records
        if self.records:
            since = time.monotonic_ns()
            held.extend((since, record) for record in self.records)
            self.records = []
        ready = 0
        if held:
            give_up = time.monotonic_ns() - HOLD_RECORDS_NS
            while ready < len(held) and (final or held[ready][0] <= give_up or not self._unlogged(held[ready][1])):
                ready += 1
        records = [record for _, record in held[:ready]]
        del held[:ready]
        events = self.published
        carried = {eid for record in records for eid in self._unlogged(record)}
        if carried:
            kept = (self.kept[eid] for eid in sorted(carried) if eid in self.kept)
            events = events + list({id(k): k for k in kept}.values())  # a burst's events share a message
        if records or events:
            self.reporter.send(records, events, self.published_seqs)
        self.published, self.published_bytes, self.published_seqs = [], 0, 0
        self.flush_due = self.now() + FLUSH_AFTER_NS if held else None

    def finish_reports(self) -> None:
        """Report what is left and return once every report is out (before a last status), and
        count how often and how long the loop waited for the reporter (it then ran late)."""
        self.flush(final=True)
        self.reporter.close()
        if self.reporter.waits:
            self.counts["report_waits"] = self.reporter.waits
            self.counts["report_wait_ns"] = self.reporter.waited_ns
