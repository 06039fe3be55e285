"""The node loop: one node in real time, in its worker process; it only dispatches (the package
docstring draws it). Each concern is a module of this package, each state an object of it."""

from __future__ import annotations

import queue
import threading
import time

import zenoh

from ....flow._base import make_invoker, make_output_reader
from ....graph import Node
from ..hub import weak_callback
from ..protocol import ControlOpener
from ..reporter import Reporter
from ..wire import KeySpace, WireEncoder, WireError, decode_events, decode_progress
from . import handover
from .clock import RunClock
from .control import obey
from .frontiers import NEVER, InEdge, Streams
from .inbox import CONTROL, DATA, NUDGE, NUDGED, PROGRESS
from .notes import Notes
from .outputs import Outputs
from .reports import SPILL_BYTES, Reports
from .schedule import DONE, TICKED, Schedule
from .source import is_plain_source, quiet_source, source_pass
from .steps import Steps
from .timing import WARM_AHEAD_NS, Warmup
from .transport import Transport, ZenohTransport
from .waiting import Waiting

#: Running on the receiving thread. A data message that arrives while the main thread sleeps is
#: handled on the transport's thread that received it: decoded, delivered, and the ticks it
#: makes ready run there too, as a plain subscriber callback would. Handing it to the main thread
#: instead costs a thread wake-up, a good part of a small message's latency
#: (benchmarks/reports/latency.md, with and without). Only steps known to be short run there (the
#: node's last step took under INLINE_STEP_NS): meanwhile that link receives nothing more. And
#: only on nodes on no cycle of the graph, so that a put blocked by a congested link can never
#: wait, around a cycle, on a receiving thread that is itself blocked in a put. Nor on nodes whose
#: flow has a ``setup()``: what it acquired may belong to its thread (an EGL context, a CUDA
#: stream), so such a flow steps, sets up and tears down on the main thread only. Either way the
#: same ticks run with the same inputs: where a tick runs changes how soon, never what.
INLINE_STEP_NS = 1_000_000

#: while its flow is being restarted, how often a loop with a tick due looks again (it also
#: wakes for every message, the coordinator's handover among them)
RESTART_POLL_NS = 50_000_000


class NodeLoop:
    """Runs one node in real time from ``T0`` until ``end`` (both HLC Unix ns). Its events go
    through ``transport`` (Zenoh on ``session`` when none is given); its control plane (the
    run's control, progress queries, reports) is on ``session`` whatever the transport."""

    def __init__(self, session: zenoh.Session, keys: KeySpace, node: Node, edges: list[InEdge],
                 inputs: list[tuple], fallbacks: dict, *, realtime: str,
                 ports: list[str] | None = None, consumed: bool = True, spill_dir: str | None = None,
                 inline: bool = False, cycle: list[str] | None = None, instant_ports: frozenset = frozenset(),
                 max_microsteps: int = 1000, virtual: bool = False, transport: Transport | None = None):
        self.session, self.keys, self.node, self.id = session, keys, node, node.id
        self.flow, self.virtual = node.flow, virtual
        self.ports = list(ports if ports is not None else node.outputs)  # untyped flows: the IR knows
        self.transport = transport if transport is not None else ZenohTransport(session, keys, self.id)
        self.lock = threading.Lock()  # guards what the progress queryable reads
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        # The loop's state belongs to whoever holds `turn`: the thread that built the loop (the
        # worker's main thread), except while it waits for a message in wait(). A receiving
        # thread that takes it then does the main thread's work itself (INLINE_STEP_NS).
        self.turn = threading.Lock()
        self.turn.acquire()
        self.inline = inline  # whether this node may run ticks on a receiving thread at all
        self.last_wall: int | None = None  # how long the last step took; None before the first
        self.failure: BaseException | None = None  # raised on a receiving thread, for run() to raise

        self.run_clock = RunClock(session)
        self.notes = Notes(self.id)
        self.schedule = Schedule(node.clock, self.lock)
        self.streams = Streams(self.id, edges, self.schedule, self.run_clock, self.notes, self.lock)
        # the coordinator's directory on this host, if it shares one, takes the big messages
        reporter = Reporter(session, keys.report(self.id), self.id, spill_dir=spill_dir, spill_bytes=SPILL_BYTES)
        self.reports = Reports(reporter, self.id, self.run_clock, self.notes, set(self.streams.frontiers))
        self.outputs = Outputs(self.id, self.ports, consumed=consumed, latency_ns=node.settings.latency_ns,
                               virtual=virtual, cycle=cycle, instant_ports=instant_ports,
                               max_microsteps=max_microsteps, lock=self.lock, clock=self.run_clock,
                               schedule=self.schedule, streams=self.streams, reports=self.reports,
                               transport=self.transport)
        self.warmup = Warmup(self.outputs, self.schedule, self.run_clock)
        self.steps = Steps(self, inputs, fallbacks, make_invoker(node.flow, node.spec), make_output_reader(node.spec),
                           realtime=realtime)
        self.waiting = Waiting(self)
        self.spin_ns = 0 if virtual else node.settings.spin_ns  # (virtual time: nothing to be on time for)
        # what the worker reads and sets: the same objects as the parts'
        self.counts, self.sent, self.reporter = self.notes.counts, self.outputs.sent, reporter

        # the loop's lifecycle, set by its parts, its control, and the worker
        self.granted = 0  # virtual time: ticks below this (ns since T0) may run (waiting.py)
        self.on_reached = None  # virtual time: on_reached(until) says the node reached a grant
        # opens the run's control with this process's key (protocol/seal.py); the worker gives
        # it the key: without one, no control message is taken
        self.opener = ControlOpener(None)
        self.stopping = False
        self.abandoned = False  # its process's parent died: it stops without finishing (worker.py)
        # on_error="restart" (handover.py): after a failed step, ticks wait for the new process,
        # which takes this loop's state over once the coordinator says so
        self.restarting = False
        self.handing_over = False
        self.told_to_stop = False  # a `stop` (control, or SIGTERM) ended it, not the run's end
        self.on_exit = None  # called with the tick whose step called sys.exit(0): the run ends
        self.on_restart = None  # called with (tag, error) when a step's failure starts a restart
        self.declared: list = []  # the control plane's subscriber and queryable on `session`

    # ---------------------------------------------------------------------------------------
    # Wiring: the transport for events, the run's session for control
    # ---------------------------------------------------------------------------------------
    def declare(self) -> None:
        """Hear the inputs, the producers' progress and the run's control; speak on the outputs
        and answer progress queries. Call before announcing readiness."""
        self.declare_inputs()
        self.declare_outputs()

    def declare_inputs(self) -> None:
        """What this node listens to: its input streams, their producers' progress, the run's control."""
        put = self.inbox.put
        self.transport.declare_inputs(sorted(self.streams.frontiers), self.streams.sources,
                                      self.receive if self.inline else None, put)
        self.declared.append(self._declare_control())

    def _declare_control(self) -> zenoh.Subscriber:
        return self.session.declare_subscriber(self.keys.run_control(), weak_callback(self._control_in))

    def _control_in(self, sample) -> None:
        """A put on ctl/run (on Zenoh's thread): queued opened and decoded (a record of
        protocol.RUN_CONTROL), or, when it does not open with this process's key (forged, replayed,
        another run's) or does not decode, as the WireError saying so (garbage)."""
        try:
            record = self.opener.control(str(sample.key_expr), sample.payload.to_bytes(), sample.attachment)
        except WireError as e:
            self.inbox.put((CONTROL, None, e))
            return
        self.inbox.put((CONTROL, None, record))

    def declare_outputs(self) -> None:
        """What this node speaks on: its data and progress keys, and the answer to progress queries."""
        self.declared.append(self._declare_queryable())
        outputs = self.outputs
        outputs.publishers, outputs.progress_publisher, outputs.warm_publisher = self.transport.declare_outputs(
            self.ports, outputs.consumed)

    def _declare_queryable(self) -> zenoh.Queryable:
        return self.session.declare_queryable(self.keys.progress(self.id), weak_callback(self._answer_progress))

    def redeclare(self) -> None:
        """Declare the subscriptions and the progress queryable again, then drop the old ones
        (before the start only: no event flows yet). Zenoh then tells every linked peer of them
        anew. Under load, with many peers linking at once, a peer was seen linked to this node
        and never told of its queryable (nor, maybe, its subscriptions): see worker.py,
        REDECLARE_AFTER_S."""
        if not self.declared:
            return
        old = self.declared
        self.declared = []
        self.transport.redeclare_inputs()
        for d in old:
            if isinstance(d, zenoh.Queryable):
                self.declared.append(self._declare_queryable())
            else:
                self.declared.append(self._declare_control())
        for d in old:
            d.undeclare()
        self.counts["redeclared"] += 1

    def await_routes(self, timeout: float) -> None:
        """Before the node says ready: wait until its events' routes carry (the transport's)."""
        self.transport.await_routes(timeout, lambda: self.stopping)

    def undeclare(self) -> None:
        self.transport.undeclare()
        for d in self.declared:
            d.undeclare()
        self.declared = []
        self.outputs.publishers = {}

    def _answer_progress(self, query: zenoh.Query) -> None:
        frontier = self.outputs.frontier()  # first: the seqs read after it can only be later ones
        query.reply(self.keys.progress(self.id), WireEncoder().progress(frontier, self.id, dict(self.sent)))

    # ---------------------------------------------------------------------------------------
    # Messages
    # ---------------------------------------------------------------------------------------
    def receive(self, item: tuple) -> None:
        """A data message, on the transport's thread that received it: handled right here if the
        main thread is waiting for one (and the loop's work done, see INLINE_STEP_NS), else queued."""
        if self.failure is None and self.turn.acquire(blocking=False):
            try:
                self._serve(item)
            except BaseException as exc:  # StopRun, or a bug: the main thread raises it
                self.failure = exc
            finally:
                self.turn.release()
                self.inbox.put(NUDGED)  # the main thread's wake-up time may have changed
        else:
            self.inbox.put(item)

    def _serve(self, item: tuple) -> None:
        """The main thread's work for one message: what was queued before it, the message, held
        outputs now due, then the ticks now ready, while steps stay short."""
        if self.inbox.qsize():
            self.drain()
        self.handle(item)
        if self.stopping:
            return
        now = self.run_clock.now()
        self.outputs.release(now)
        while (self.last_wall is not None and self.last_wall < INLINE_STEP_NS
               and self.try_tick(now) is TICKED):
            now = self.run_clock.now()

    def handle(self, item: tuple) -> None:
        """One inbox item (inbox.py), on whichever thread holds ``turn``."""
        kind, key, data = item
        streams = self.streams
        if kind == DATA:
            try:
                events = decode_events(data, expected=key)
                streams.check_claims(key, events[0].seq, events[-1].frontier)
            except WireError as e:
                self.notes.garbage(key, e)
                return
            arrival = time.time_ns()
            # (a burst is not warmed for)
            self.warmup.arrived(key, data if len(events) == 1 else None, arrival - self.run_clock.t0)
            reports = self.reports
            if reports.values:
                have, kept = reports.have.get(key, -1), (arrival, data)  # one for a burst's events: sent once
                for msg in events:
                    if msg.seq > have:
                        reports.kept[(msg.producer, msg.port, msg.seq)] = kept
            for msg in events:
                streams.in_order(key, msg)
        elif kind == NUDGE:
            return
        elif kind == PROGRESS:
            if data is None:
                return  # the query timed out
            try:
                progress = decode_progress(data, expected=key)
                mine = [s for s in streams.frontiers if s[0] == progress.producer]
                for stream in mine:  # (its seqs may be far ahead: see frontiers.WAITING_MAX)
                    streams.check_claims(stream, None, progress.frontier)
            except WireError as e:
                self.notes.garbage(key, e)
                return
            for stream in mine:
                streams.progress(stream, progress.sent.get(stream[1], -1), progress.frontier)
        else:
            obey(self, data)

    def wait(self, ns: int) -> bool:
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
        self.handle(item)
        return True

    def drain(self) -> None:
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
            self.handle(item)

    # ---------------------------------------------------------------------------------------
    # The loop
    # ---------------------------------------------------------------------------------------
    def run(self, t0: int, end: int, resume: bool = False) -> None:
        """Tick from T0 (HLC Unix ns) while ``t < end`` (ns since T0), then finish. ``resume``:
        join a run in progress (a restarted flow) at its next Rate tick."""
        clock, outputs, reports = self.run_clock, self.outputs, self.reports
        with self.lock:
            clock.start(t0, end)
        if resume and not self.virtual:  # (in virtual time no tick came due meanwhile: time waited)
            self.steps.skip_missed_ticks(clock.now(), "restart_skipped", "restart_skipped")
        else:
            self.schedule.start()
        outputs.publish_progress()
        plain_source = is_plain_source(self)
        while not self.stopping:
            quiet = plain_source and not (self.schedule.pending or outputs.held or self.restarting
                                          or self.inbox.qsize())
            if quiet and not self.notes.detail:
                quiet_source(self)  # its ticks for as long as they are quiet
                if self.stopping:
                    break
                quiet = not (self.schedule.pending or outputs.held or self.restarting or self.inbox.qsize())
            if quiet:
                now = clock.now()
                wake = source_pass(self, now)
            else:
                self.drain()
                if self.stopping:
                    break
                now = clock.now()
                outputs.release(now)
                wake = self.try_tick(now)
            if wake is TICKED:
                if reports.flush_due is not None and now >= reports.flush_due:  # (now: before that tick)
                    reports.flush()  # also when ticks run back to back: a late node still reports
                continue  # look again at once
            if wake is DONE:
                break
            if reports.flush_due is not None and reports.flush_due <= wake:
                # before waiting, not after: a tick that came due is not held up by it, and the
                # reporter thread does its work while this one waits (a 200 Hz tick's p99
                # lateness grew when the report went out just as the tick was due)
                reports.flush()
                if reports.flush_due is not None:
                    wake = min(wake, reports.flush_due)
            if outputs.held:
                wake = min(wake, outputs.held[0][0][0])
            self._sleep(now, wake)
        if not self.handing_over and not self.abandoned:
            self._finish()

    def _sleep(self, now: int, wake: int) -> None:
        """Until ``wake`` (ns since T0), or a message: warmed up for the moment it foresees
        (timing.py), or spinning to a Rate tick (configure(spin=))."""
        target, message = self.warmup.target(now, wake)
        if target is not None:
            early = target - WARM_AHEAD_NS
            # nothing came meanwhile, and the wait (at most 100 ms) lasted to the moment
            if not self.wait(early - now) and self.run_clock.now() >= early:
                self.warmup.warm(message)
                self.warmup.warmed_for = target
            return
        next_rate = self.schedule.next_rate
        if self.spin_ns and next_rate is not None and wake == next_rate[0]:
            self._spin_to(wake)
        else:
            self.wait(wake - self.run_clock.now())

    def _spin_to(self, wake: int) -> None:
        """Wait for the Rate tick at ``wake`` (configure(spin=)): sleep until ``spin_ns`` before
        it, then busy-wait to it, unless a message comes (the loop then looks again)."""
        now = self.run_clock.now
        while (left := wake - self.spin_ns - now()) > 0:  # (one wait sleeps at most 100 ms)
            if self.wait(left):
                return
        inbox = self.inbox
        began = now()
        while now() < wake and not inbox.qsize():
            pass
        self.counts["spin_ns"] += now() - began

    def try_tick(self, now: int) -> int | str:
        """Run the next tick if it is due and its inputs are complete (or past deadline):
        ``TICKED``. Else the wall time (ns since T0) to look again, or ``DONE``."""
        schedule, end = self.schedule, self.run_clock.end
        with self.lock:  # the next Rate tick or the lowest pending trigger tag
            tau = schedule.next_rate
            if schedule.pending and (tau is None or schedule.pending[0] < tau):
                tau = schedule.pending[0]
        if self.virtual:
            bound = self.streams.tick_bound()
            if bound >= (end, 0) or bound >= (self.granted, 0):
                return self.waiting.done_waiting(now) if bound >= (end, 0) else self.waiting.at_grant(now)
            if tau is None or tau >= (self.granted, 0):  # a tick below the grant may still be triggered
                return self.waiting.ask_triggers(now)
        elif tau is None or tau[0] >= end:
            return self.waiting.done_waiting(now)
        elif tau[0] > now:
            return tau[0]
        if self.restarting:  # due, but the flow is being restarted: the new process will run it
            return now + RESTART_POLL_NS
        incomplete, wake = self.waiting.incomplete(tau, now)
        if wake is not None:
            return wake
        schedule.take(tau)
        self.steps.tick(tau, incomplete)
        return self.after_tick()

    def after_tick(self) -> int | str:
        """Right after a tick: ``TICKED`` (look again at once) unless the next tick is a Rate
        tick not due yet and nothing else is waiting, in which case its time, as the next pass of
        the loop would find it (an idle flow then makes one pass per tick, not two)."""
        schedule = self.schedule
        if (self.virtual or self.stopping or self.restarting or schedule.pending or self.outputs.held
                or self.inbox.qsize()):
            return TICKED
        tau = schedule.next_rate
        if tau is None or tau[0] >= self.run_clock.end or self.streams.triggering:
            return TICKED
        return tau[0] if tau[0] > self.run_clock.now() else TICKED

    # ---------------------------------------------------------------------------------------
    # The end, and a restart's hand-over (handover.py: take_over, sync_inputs, start_fresh)
    # ---------------------------------------------------------------------------------------
    def _finish(self) -> None:
        """Release what is held (tags past the end still belong to the run), promise nothing more."""
        self.drain()
        unrun = self.schedule.stop(self.run_clock.end)
        if unrun:  # triggered before the end, but their inputs never completed in time
            self.counts["unrun_ticks"] += unrun
        self.outputs.release_held()
        self.outputs.publish_progress(NEVER)
        self.reports.finish()

    def handover_state(self) -> dict:
        """This loop's state, for the process that takes over (call after ``undeclare``: the
        messages already queued are taken in first, and no more come)."""
        self.drain()
        return handover.handover_state(self)
