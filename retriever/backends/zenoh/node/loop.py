"""The node loop: one node in real time, in its worker process; it only dispatches (the package
docstring draws it). Each concern is a module of this package, each state an object of it."""

from __future__ import annotations

import queue
import threading
import time

import zenoh

from ....flow.core import make_invoker, make_output_reader
from ....graph import Node
from ..protocol import ControlOpener
from ..wire import KeySpace, WireError, decode_events, decode_progress
from . import handover
from .clock import RunClock
from .control import obey
from .ending import Ending
from .frontiers import NEVER, InEdge, Streams
from .inbox import DATA, EVENTS, FAILED, NUDGE, NUDGED, PROGRESS
from .notes import Notes
from .outputs import Outputs
from .plane import ControlPlane
from .reporter import Reporter
from .reports import REPORT_DEFER_MAX_NS, SPILL_BYTES, Reports
from .schedule import DONE, TICKED, Schedule
from .source import PlainSource
from .steps import Steps
from .timing import Pacer, Rehearsal, Warmup
from .transport import Transport, ZenohTransport
from .waiting import Waiting

#: Running on the receiving thread. A data message that arrives while the main thread sleeps is
#: handled on the transport's thread that received it: decoded, delivered, and the ticks it
#: makes ready run there too, as a plain subscriber callback would. Handing it to the main thread
#: instead costs a thread wake-up, a good part of a small message's latency
#: (benchmarks/reports/latency.md, with and without). With Zenoh, that thread is Zenoh's own
#: receiving thread (node/transport.py). Only steps known to be short run there (the node's last
#: step took under INLINE_STEP_NS): meanwhile that thread receives nothing more. And
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
        self.virtual = virtual
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
        self.warmup = Warmup(self.outputs, self.schedule, self.run_clock,
                             Rehearsal(self.id, node.clock, edges, inputs, self.run_clock))
        self.spin_ns = 0 if virtual else node.settings.spin_ns  # (virtual time: nothing to be on time for)
        self.pacer = Pacer(self, warmup=self.warmup, schedule=self.schedule, clock=self.run_clock, spin_ns=self.spin_ns,
                           counts=self.notes.counts)
        self.steps = Steps(self, node, inputs, fallbacks, make_invoker(node.flow, node.spec),
                           make_output_reader(node.spec), realtime=realtime, virtual=virtual, notes=self.notes,
                           schedule=self.schedule, outputs=self.outputs, reports=self.reports, streams=self.streams,
                           clock=self.run_clock, lock=self.lock)
        self.waiting = Waiting(self, virtual=virtual, session=session, keys=keys, streams=self.streams,
                               clock=self.run_clock, outputs=self.outputs, reports=self.reports)
        self.source = PlainSource(self, steps=self.steps, waiting=self.waiting, schedule=self.schedule,
                                  notes=self.notes, outputs=self.outputs, reports=self.reports, warmup=self.warmup,
                                  clock=self.run_clock, lock=self.lock)
        self.plain_source = False  # whether it takes the short way of a plain source (source.py), from begin()
        # whether a GroupLoop runs its passes among others' (group.py): none may wait, and the
        # group hears the run's control for all of them (GroupLoop.hear_control)
        self.grouped = False
        # what the worker reads and sets: the same objects as the parts'
        self.counts, self.sent, self.reporter = self.notes.counts, self.outputs.sent, reporter

        # the loop's lifecycle, set by its parts, its control, and the worker
        self.granted = 0  # virtual time: ticks below this (ns since T0) may run (waiting.py)
        self.on_reached = None  # virtual time: on_reached(until) says the node reached a grant
        # opens the run's control with this process's key (protocol/seal.py); the worker gives
        # it the key: without one, no control message is taken
        self.opener = ControlOpener(None)
        self.endings: set[Ending] = set()  # every way it was told to end (stop): read as `ending`
        self.stopping = False  # whether it has an `ending` (set by stop only): what its waits look at, cheaply
        # on_error="restart" (handover.py): after a failed step, ticks wait for the new process,
        # which takes this loop's state over once the coordinator says so (Ending.HANDING_OVER);
        # not an ending itself: until then the loop runs on
        self.restarting = False
        self.on_exit = None  # called with the tick whose step called sys.exit(0): the run ends
        self.on_restart = None  # called with (tag, error) when a step's failure starts a restart
        # on_error="restart" where it runs (a group's member: in_place.py); None: in a new process
        self.in_place = None
        self.plane = ControlPlane(self)  # the run's control, progress queries: on `session`
        self.declared = self.plane.declared  # its subscriber and queryable

    @property
    def flow(self):
        """The flow it steps now (a restart in place puts a fresh one: in_place.py)."""
        return self.steps.flow

    # ---------------------------------------------------------------------------------------
    # How the loop ends early (ending.py)
    # ---------------------------------------------------------------------------------------
    def stop(self, ending: Ending) -> None:
        """End the loop ``ending``'s way: it leaves its run at its next pass (before the start,
        the wait it is in), and its process then acts on :attr:`ending`. Called by the run's
        control, a failed step and the worker's signal handlers, maybe from a signal handler
        while the main thread is in here: adding to a set cannot be torn, so an ending never
        overwrites another that came meanwhile, and the graver wins whatever the order."""
        self.endings.add(ending)
        self.stopping = True

    @property
    def ending(self) -> Ending | None:
        """How the loop ends: None while nothing told it to end before the run's end. When two
        endings came, the graver wins, whichever came first: ABANDONED over HANDING_OVER over
        TOLD_TO_STOP. Abandoned: another process now runs the node, or the parent that would
        hear this one is gone; anything it still said or promised (``done``, a hand-over, its
        frontier past the end) would contradict that. Handing over rather than told to stop:
        the flow's new process waits for this one's state, and the stop reaches it too;
        finishing here would promise the consumers nothing more while the new process goes on."""
        return max(self.endings, default=None)

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
        # a grouped loop never waits on its own (the group does, GroupLoop.run): it never lends
        # its turn to a receiving thread, which then only queues, off Zenoh's thread
        # (transport.py: a receiving thread that may step is Zenoh's own)
        self.transport.declare_inputs(sorted(self.streams.frontiers), self.streams.sources,
                                      self.receive if self.inline and not self.grouped else None, put)
        if self.inline and not self.grouped:
            self.transport.declare_warm(self.streams.sources, self.warmed)
        if not self.grouped:  # (a group hears the run's control once for all: GroupLoop.hear_control)
            self.plane.listen()

    def declare_outputs(self) -> None:
        """What this node speaks on: its data and progress keys, and the answer to progress queries."""
        self.plane.answer()
        outputs = self.outputs
        outputs.publishers, outputs.progress_publisher, outputs.warm_publisher = self.transport.declare_outputs(
            self.ports, outputs.consumed)

    def redeclare(self) -> None:
        """Declare the subscriptions and the progress queryable again, then drop the old ones
        (before the start only: no event flows yet). Zenoh then tells every linked peer of them
        anew. Under load, with many peers linking at once, a peer was seen linked to this node
        and never told of its queryable (nor, maybe, its subscriptions): see worker/starts.py,
        REDECLARE_AFTER_S."""
        if not self.declared:
            return
        self.transport.redeclare_inputs()
        self.plane.redeclare()
        self.counts["redeclared"] += 1

    def await_routes(self, timeout: float) -> None:
        """Before the node says ready: wait until its events' routes carry (the transport's)."""
        self.transport.await_routes(timeout, lambda: self.stopping)

    def undeclare(self) -> None:
        self.transport.undeclare()
        self.plane.undeclare()
        self.outputs.publishers = {}

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

    def warmed(self, producer: str) -> None:
        """``producer`` warms up for its next tick (its message is on its way in about
        timing.WARM_AHEAD_NS): on the thread that will receive it, if the main thread is
        waiting, rehearse the arrival of its streams' last messages (timing.Rehearsal); nothing
        of the loop's changes. The main thread no longer wakes to rehearse a stream so heralded
        (Warmup.arrived): two rehearsals at once, one would wait for the other's ``turn``."""
        clock = self.run_clock
        if clock.started:  # (before, its arrivals' times are not since T0: nothing to herald)
            self.warmup.herald(producer, time.time_ns() - clock.t0)
        if self.failure is None and self.turn.acquire(blocking=False):
            try:
                self.warmup.rehearse(producer)
            finally:
                self.turn.release()

    def _serve(self, item: tuple) -> None:
        """The main thread's work for one message: what was queued before it, the message, held
        outputs now due, then the ticks now ready, while steps stay short."""
        if self.inbox.qsize():
            self.drain()
        self.handle(item)
        if self.stopping:
            return
        clock = self.run_clock  # (RunClock.now, inline: a call saved per message, and per tick)
        now = time.time_ns() - clock.t0
        if self.outputs.held:  # (a call saved per message when nothing is: the usual case)
            self.outputs.release(now)
        while (self.last_wall is not None and self.last_wall < INLINE_STEP_NS
               and self.try_tick(now) is TICKED):
            now = time.time_ns() - clock.t0

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
                for _, seq, _, producer, port, _ in events:  # (unpacked: a NamedTuple's fields are slow reads in 3.11)
                    if seq > have:
                        reports.kept[(producer, port, seq)] = kept
            for msg in events:
                streams.in_order(key, msg)
        elif kind == EVENTS:  # from a producer of this process (group.py): trusted, by reference
            for msg in data:
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
        elif kind == FAILED:
            raise data
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
        self.begin(t0, end, resume)
        while not self.stopping:
            now, wake = self.one_pass()
            if wake is TICKED:
                continue  # look again at once
            if wake is DONE:
                break
            self.pacer.sleep(now, wake)
        self.end()

    def begin(self, t0: int, end: int, resume: bool = False) -> None:
        """The run's clock starts: the first tick is scheduled (``resume``: the next Rate tick
        of a run in progress) and the consumers told where this node stands."""
        clock = self.run_clock
        with self.lock:
            clock.start(t0, end)
        if resume and not self.virtual:  # (in virtual time no tick came due meanwhile: time waited)
            self.steps.skip_missed_ticks(clock.now(), "restart_skipped", "restart_skipped")
        else:
            self.schedule.start()
        self.outputs.publish_progress()
        self.plain_source = (self.source.fits(virtual=self.virtual, edges=self.streams.edges, spin_ns=self.spin_ns)
                             and not self.grouped)

    def one_pass(self) -> tuple[int, int | str]:
        """One pass of the loop: what came is handled, held outputs now due released, the next
        tick run if it is due and ready. ``(now, TICKED)`` to look again at once, ``(now,
        DONE)``, or ``(now, wake)``: nothing to do before ``wake`` (ns since T0) unless a
        message comes."""
        clock, outputs, reports = self.run_clock, self.outputs, self.reports
        quiet = self.plain_source and not (self.schedule.pending or outputs.held or self.restarting
                                           or self.inbox.qsize())
        if quiet and not self.notes.detail:
            self.source.run_quiet()  # its ticks for as long as they are quiet
            if self.stopping:
                return clock.now(), DONE
            quiet = not (self.schedule.pending or outputs.held or self.restarting or self.inbox.qsize())
        if quiet:
            now = clock.now()
            wake = self.source.one_pass(now)
        else:
            self.drain()
            now = clock.now()
            if self.stopping:
                return now, DONE
            outputs.release(now)
            wake = self.try_tick(now)
        if wake is TICKED:
            if reports.flush_due is not None and now >= reports.flush_due:  # (now: before that tick)
                reports.flush()  # also when ticks run back to back: a late node still reports
            return now, wake
        if wake is DONE:
            return now, wake
        if reports.flush_due is not None and reports.flush_due <= wake:
            # before waiting, not after: a tick that came due is not held up by it, and the
            # reporter thread does its work while this one waits (a report that went out just
            # as a tick came due made that tick late: control_jitter.py shows it); halfway into
            # the wait, not at its start, when the messages of the tick just run are on their way
            # (reporter.py)
            reports.flush(defer_ns=min(REPORT_DEFER_MAX_NS, (wake - now) // 2))
            if reports.flush_due is not None:
                wake = min(wake, reports.flush_due)
        if outputs.held:
            wake = min(wake, outputs.held[0][0][0])
        return now, wake

    def end(self) -> None:
        """After the last pass: finish, unless the loop hands over to a new process or was abandoned."""
        if self.ending not in (Ending.HANDING_OVER, Ending.ABANDONED):
            self._finish()

    def try_tick(self, now: int) -> int | str:
        """Run the next tick if it is due and its inputs are complete (or past deadline):
        ``TICKED``. Else the wall time (ns since T0) to look again, or ``DONE``."""
        schedule, end = self.schedule, self.run_clock.end
        # the next Rate tick or the lowest pending trigger tag, read without the lock: the lock
        # keeps the progress queryable from reading a schedule half written, and whoever holds
        # `turn` (this thread) is the schedule's only writer
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
        self.transport.end_of_stream()
        self.reports.finish()

    def handover_state(self) -> dict:
        """This loop's state, for the process that takes over (call after ``undeclare``: the
        messages already queued are taken in first, and no more come)."""
        self.drain()
        return handover.handover_state(self)

