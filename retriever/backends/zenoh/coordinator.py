"""The coordinator of a real-time run on Zenoh: the embedded default (docs/realtime.md).

    pipe.run(duration=10, backend="zenoh")
        │ open the hub (tcp/127.0.0.1:7447, else a free port), write SPEC.json (IR + python path)
        │ start one worker process per node ──▶ each says `ready` on status/node/<node>
        │ put `start` {T0 = HLC now + margin, end} on ctl/run
        │ collect status/report/* (the events each worker published, its step records) into the
        │ trace and the log: the coordinator is not on the events' path
        ▼ every worker says `done` (or one fails: `stop` the rest) → processes reaped, sessions closed

Tags in the trace and the log are ns since ``T0``, so a run's trace compares with the in-process
backend's directly. Workers are started and stopped by PID; none outlives the run (each also asks
the kernel for SIGTERM when its parent dies).
"""

from __future__ import annotations

import atexit
import json
import mmap
import os
import queue
import secrets
import shutil
import signal
import subprocess
import sys
import threading
import time
import warnings
import weakref
from pathlib import Path

import zenoh

from ...errors import (BackendError, CausalityError, RemoteError, RestartLimitError, RetrieverWarning, SetupError,
                       StepError)
from ...graph import Graph
from ...starved import StarvationWatch
from ...trace import NOT_KEPT, STEPPED
from ..base import NodeStats, RestartBudget, Session
from .access import AccessError, RunAccess, secret_bytes, write_private
from .command import mode_args
from .folders import RUN_FOLDER, private_folder
from .hub import new_zid, open_hub, weak_callback
from .loop import RESTART_SEQ_GAP
from .origin import Senders, new_key
from .host import Host, LocalHost, WorkerProcess
from .seen import EventIds, RecentTicks
from .wire import RELIABLE, KeySpace, WireEncoder, WireError, decode_events, decode_report, decode_status
from .worker import EXIT_FAILED, EXIT_HANDED_OVER


#: after `stop`, how long workers have to send their last reports and exit; one still running is
#: stuck in a step (a loop looks at `stop` between steps only): its stacks are printed, it is killed
STOP_GRACE_S = 1.5
#: how long, at most, a worker's stack dump (SIGUSR1, written at once by a C handler) takes to read
STACKS_WAIT_S = 0.5

#: how long after a worker process ended by itself (exit code 0, 1 or 3) the coordinator waits for
#: the status that says why (Zenoh may deliver it after the exit is seen): none by then, it died
EXIT_GRACE_S = 2.0

#: how often, at most, the coordinator tells the consumers which events it has (control `have`)
HAVE_EVERY_S = 0.02

#: where in its life each state a worker process says of itself puts it: a process says a state
#: only after those below it (`ready` again and again while it waits for the start), and says a
#: last one (done, failed, handed_over) once. Anything else is an insider's replay of a status of
#: the process (its signature holds): a second `done` added its counts and reports again, a `ready`
#: after its `done` moved the node back; refused (may_say)
PROCESS_STAGES = {"ready": 0, "restart": 1, "done": 2, "failed": 2, "handed_over": 2}


def may_say(last: str | None, state: str) -> bool:
    """Whether a process whose last state was ``last`` (None: none yet) may now say ``state``."""
    return last is None or PROCESS_STAGES[state] > PROCESS_STAGES[last] or state == last == "ready"


#: sessions not closed yet
_OPEN: weakref.WeakSet = weakref.WeakSet()


def _close_open_sessions() -> None:
    """Close what a program left open (an error before its run, a forgotten pipe.reset()): its
    workers are stopped and its hub closed. At exit Python joins the threads Zenoh started before
    it runs atexit hooks, and an open session's threads never end: the process hung there."""
    for session in list(_OPEN):
        session.close()


try:  # threading's own exit hooks run before that join (concurrent.futures uses them too)
    threading._register_atexit(_close_open_sessions)
except (AttributeError, RuntimeError):  # another Python: atexit, which may come too late
    atexit.register(_close_open_sessions)


class Coordinator(Session):
    backend_name = "zenoh"
    holds_processes = True

    def __init__(self, graph: Graph, *, namespace: str | None = None, startup_timeout: float = 60.0,
                 start_margin: float = 0.3, hub_port: int = 7447, quiet: bool = False,
                 secret: str | os.PathLike | bytes | None = None, virtual_time: bool = False,
                 keep: str = "trace", foxglove: int | None = None):
        super().__init__(graph, keep)
        #: the port of a Foxglove live view (its WebSocket server, in this process), if asked for
        self._foxglove_port = foxglove
        self._print_endpoint = not quiet
        #: lockstep virtual time (loop.py): the trace is the in-process backend's, however long it takes
        self.virtual_time = bool(virtual_time)
        self._granted = 0  # virtual time: the ticks below this (ns since T0) may run
        self._reached: dict[str, int] = {}  # per node, the last grant it said it reached
        self._last_grant = (0.0, 0.0)  # (when granted, when put last), monotonic s
        if self.virtual_time and graph.instantaneous_cycles:
            cycle = graph.instantaneous_cycles[0]
            raise BackendError(
                f"zenoh in virtual time cannot run the instantaneous cycle {' → '.join([*cycle, cycle[0]])} (yet): "
                "each of its flows waits for the other's promise of what comes next, one microstep at a time\n"
                "    hint: give an edge of the cycle a delay= or a flow on it a latency=, or run it on inproc "
                "(virtual time too) or on zenoh in real time")
        _refuse_in_a_worker(graph)
        self._check_deployable()
        self.namespace = namespace or f"run-{os.getpid()}-{secrets.token_hex(3)}"
        self.keys = KeySpace(self.namespace)
        self._access = self._run_access(secret)
        self.startup_timeout = startup_timeout
        self.start_margin_ns = round(start_margin * 1e9)
        self.t0: int | None = None  # HLC Unix ns of the run's start
        self.end_ns = 0  # the run's end, ns since T0
        self._init_records(graph)
        self._workers: dict[str, WorkerProcess] = {}  # each node's process
        self._retiring: dict[str, WorkerProcess] = {}  # a restarting node's old process, until it hands over
        self._retired: list[WorkerProcess] = []  # old processes that handed over, to reap
        self._said: dict[WorkerProcess, str] = {}  # each process's last state (PROCESS_STAGES)
        self._state: dict[str, str] = {}
        self._exited: dict[int, float] = {}  # pid -> when that worker process was first seen gone
        self._ran = False
        self._closed = False
        self._inbox: queue.SimpleQueue = queue.SimpleQueue()
        self._dir = _run_dir()
        self._hosts: dict[str, Host] = {}  # where each node's processes run
        self._encoder = WireEncoder()
        self._hub = None
        self._subscribers: list = []
        _OPEN.add(self)  # closed at the interpreter's exit at the latest (see _close_open_sessions)
        try:
            access = self._access
            dictionary = access.write_dictionary(self._dir) if access else None
            self._open_hub(hub_port, access.session_config(dictionary) if access else None)
            #: a Zenoh config file with which a client joins the run as a read-only watcher
            self.watch_config = (access.write_watcher_config(self._dir / "watch.json5", self.endpoint)
                                 if access else None)
            if not quiet:
                print(f"retriever: {self._where()} (namespace '{self.namespace}'); {self._how_to_watch()}",
                      file=sys.stderr, flush=True)
            self._listen()
            self._spec = {"ir": graph.to_ir().doc, "namespace": self.namespace, "hub": self.endpoint,
                          "python_path": _python_path(), "main_file": _main_file(graph), "argv": list(sys.argv),
                          "spill_dir": str(self._dir), "access": access.to_spec(dictionary) if access else None,
                          "startup_timeout": self.startup_timeout,
                          # each first process's session id, and the hub's: a worker says ready once
                          # linked to its neighbours and the hub, whatever other peers it has
                          "zids": {nid: new_zid() for nid in graph.nodes}, "hub_zid": str(self._hub.zid()),
                          "virtual_time": self.virtual_time}
            self._hosts = self._place()
            for nid in graph.nodes:
                self._spawn(nid)
        except BaseException:
            self.close()
            raise

    def _start_live_view(self) -> None:
        from ...log.foxglove import LiveView

        self.live = LiveView(self._foxglove_port, self.graph.to_ir())
        if self._print_endpoint:
            print(f"retriever: Foxglove live view on ws://127.0.0.1:{self.live.port} (in the Foxglove app: Open "
                  "connection, Foxglove WebSocket)", file=sys.stderr, flush=True)

    def _check_deployable(self) -> None:
        """Every flow must be rebuildable from the IR in another process (_check_deployable)."""
        _check_deployable(self.graph)

    def _run_access(self, secret) -> RunAccess | None:
        """The run's credentials: random, or derived from the deployment secret (access.py)."""
        try:
            return RunAccess.create(self.namespace, secret_bytes(secret))
        except AccessError as e:
            raise BackendError(str(e)) from None

    def _open_hub(self, port: int, access: dict[str, str] | None) -> None:
        """Open the run's own session (``self._hub``), which the workers join at ``self.endpoint``."""
        self._hub, self.endpoint = open_hub(port, access=access, keys=self.keys)

    def _where(self) -> str:
        """Where the run's hub is, for the line that says how to watch it."""
        return f"Zenoh hub listening on {self.endpoint}"

    def _how_to_watch(self) -> str:
        """How a plain Zenoh client sees the run's events, for the line that says where it is."""
        if self.watch_config is None:
            return f"anyone on its network may join it (insecure); watch it with a subscriber on {self.keys.all_data()}"
        return (f"watch it read-only with zenoh.Config.from_file('{self.watch_config}') and a subscriber on "
                f"{self.keys.all_data()}")

    def _listen(self) -> None:
        """Take the workers' statuses and reports, answer their questions (what is finished, the start)."""
        put, senders = self._inbox.put, self._senders

        def take(sample) -> None:  # on Zenoh's thread: what no process of the node signed is held nowhere
            key, data, mac = str(sample.key_expr), sample.payload.to_bytes(), sample.attachment
            sender = senders.sender(key.rsplit("/", 1)[1], key, data, None if mac is None else mac.to_bytes())
            if sender is not None:
                put((key, data, sender))

        self._subscribers += [
            self._hub.declare_subscriber(self.keys.status("**"), take),
            self._hub.declare_queryable(self.keys.finished(), weak_callback(self._answer_finished)),
            self._hub.declare_queryable(self.keys.start(), weak_callback(self._answer_start))]

    def _place(self) -> dict[str, Host]:
        """Every node on this machine: the spec in the run directory, the workers its children."""
        write_private(self._dir / "spec.json", json.dumps(self._spec))  # it holds the run's password
        host = LocalHost(self._dir / "spec.json")
        return {nid: host for nid in self.graph.nodes}

    def _init_records(self, graph: Graph) -> None:
        """What the coordinator keeps of the run's reports and statuses (no Zenoh, no process:
        benchmarks/fuzz.py feeds forged reports to ``_handle`` on just this)."""
        self._stats = {nid: NodeStats() for nid in graph.nodes}
        self._restarts = {nid: RestartBudget(node.settings.max_restarts, node.settings.restart_window)
                          for nid, node in graph.nodes.items()}
        self._event_ids = EventIds()  # every event id seen (as runs of seqs: bounded memory)
        # events a consumer's report carried for its producer (loop.HOLD_RECORDS_NS), and per
        # stream the last seq the coordinator has, told to the consumers (control `have`)
        self._carried: set[tuple[str, str, int]] = set()
        self._have: dict[tuple[str, str], int] = {}
        self._have_told: dict[tuple[str, str], int] = {}
        self._feeds = {(e.src, e.src_port, e.dst) for e in graph.edges}
        # reports handled, and reports sent as the node's processes said when they ended: Zenoh
        # orders messages per key only, so a last report may come after the `done` status
        self._reports = {nid: 0 for nid in graph.nodes}
        self._reports_sent = {nid: 0 for nid in graph.nodes}
        self._ticks = RecentTicks()  # (node, tag) of the step records seen (the recent ones, then a floor)
        self._failure: tuple[str, dict] | None = None
        # who sent what (origin.py): the keys of each node's processes, the first ones made
        # ahead (a dora run's, in its spec), and what was refused as forged
        self._senders = Senders()
        self._first_keys: dict[str, bytes] = {}
        self._forged_told = 0
        # a step's sys.exit(0): its `exit` status ends the run once its process's record of
        # that step (status ok, detail {"exit": 0}) is in; per node, the (tag, process) of each
        self._exit_said: dict[str, tuple[tuple[int, int], object]] = {}
        self._exit_recorded: dict[str, tuple[tuple[int, int], object]] = {}
        self._done_info: dict[str, dict] = {}  # what each node's worker said of its run when done
        self._stackless: dict[str, float] = {}  # nodes asked for their stacks that printed none, and how long waited
        self._limit: RestartLimitError | None = None  # a flow ran out of restarts (on_error="restart")
        # a lost process (see "Restarting after a lost process" in loop.py): the nodes starting
        # afresh, by what became of the old process; per stream, the highest seq known (events
        # and records); event ids that records produced and no report carried yet
        self._fresh: dict[str, dict] = {}
        self._values = True  # whether the workers report their events' values (set at the start)
        self._stop_sent = False  # whether this coordinator told the workers to stop
        self.ended_by: str | None = None  # the node whose step called sys.exit(0), ending the run
        self.live = None  # a Foxglove live view, fed with what the reports bring (log/foxglove.py)
        #: bytes of the workers' reports (step records and events) received, spilled ones included
        self.reported_bytes = 0
        #: nodes whose process is a restarted flow's, not yet in the run (before resume or restarted)
        self._joining: set[str] = set()
        self._restarted: dict[str, dict[str, int]] = {}  # a node started afresh: its seqs, till its next status
        self._unrecovered: list[dict] = []  # faults of processes not started afresh, logged at the end
        self._max_seq: dict[tuple[str, str], int] = {}
        self._unseen: set[tuple[str, str, int]] = set()
        #: what went wrong with the run's processes, as the log's fault records have it
        self.faults: list[dict] = []
        #: inputs that had no event for long while their producers made events (starved.py)
        self.starvation = StarvationWatch(graph)
        self._streams = {(nid, port) for nid, node in graph.nodes.items() for port in node.outputs}
        # untyped flows may emit on ports no edge names (a dict step's extra keys)
        self._open_outputs = {nid for nid, node in graph.nodes.items() if node.spec.out_mode == "dict"}

    # ---------------------------------------------------------------------------------------
    # Processes
    # ---------------------------------------------------------------------------------------
    def _spawn(self, nid: str, join: tuple[int, int] | None = None, fresh: bool = False) -> None:
        """Start the worker process of ``nid``; ``join``: (T0, end) of the run it joins, taking
        over the state of the process it replaces, or, ``fresh``, starting afresh (that one died)."""
        mode = mode_args(join, fresh)
        self._workers[nid], key = self._hosts[nid].spawn(nid, mode, self._first_keys.pop(nid, None) or new_key())
        self._senders.add(nid, key, self._workers[nid])
        if join is not None:
            self._joining.add(nid)
        self._state[nid] = "starting"

    def _processes(self) -> list[WorkerProcess]:
        """Every worker process this run started."""
        return [*self._workers.values(), *self._retiring.values(), *self._retired]

    def worker_pids(self) -> dict[str, int]:
        """PIDs of the worker processes, by node (for tests and tools)."""
        return {nid: p.pid for nid, p in self._workers.items()}

    def _dump_stacks(self, nodes: list[str], wait: float = STACKS_WAIT_S, show: bool = True) -> None:
        """Have these workers print every thread's Python stack to their stderr (SIGUSR1): on
        the coordinator's stderr (``show``), or only kept for an error message that shows them."""
        before = {}
        for nid in nodes:
            proc = self._workers.get(nid)
            if proc is not None and proc.poll() is None:
                output = self._hosts[nid].output(nid)
                before[nid] = output.stderr_lines
                output.forwarding = show
                proc.send_signal(signal.SIGUSR1)
        give_up = time.monotonic() + wait  # a bound: the dump is written at once by a C handler
        for nid, lines in before.items():
            output = self._hosts[nid].output(nid)
            output.settle(lines, max(0.0, give_up - time.monotonic()))
            if output.stderr_lines == lines:  # asked, and nothing came: the error says so (_unfinished)
                self._stackless[nid] = wait

    def _unfinished(self, nid: str) -> str:
        """What the error of a run that did not finish says of node ``nid``: the stacks its process
        printed (on its stderr, last), or why there are none; and, done but short of reports, the
        events it sent that never reached the coordinator (lost with those reports)."""
        said = ""
        missing = self._reports_sent[nid] - self._reports[nid]
        if self._state.get(nid) == "done" and missing > 0:
            lost = [f"{nid}.{port} {seqs}" for port, last in sorted(self._done_info.get(nid, {}).get("sent", {}).items())
                    if (seqs := self._unseen_seqs(nid, port, last))]
            said = (f"    {nid} said done after {self._reports_sent[nid]} report(s), of which {missing} never reached "
                    f"the coordinator" + (f"; it never got the event(s) {', '.join(lost)}" if lost else "") + "\n")
        proc = self._workers.get(nid)
        code = proc.poll() if proc is not None else None
        tail = self._stderr_tail(nid, 60)
        if code is None and nid not in self._stackless:
            return f"{said}    {nid} stderr (its stacks last):\n{tail}\n"
        if code is not None:
            why = f"its process had ended ({_exit_text(code)})"
        else:
            stopped = isinstance(self._hosts[nid], LocalHost) and _is_stopped(proc.pid)
            why = (f"its process (pid {proc.pid}) printed none within {self._stackless[nid]:g} s of SIGUSR1: "
                   + ("it is stopped (SIGSTOP, or a debugger)" if stopped else
                      "stopped, or stuck in code that holds Python's lock"))
        return f"{said}    {nid}: no stacks: {why}" + (f"; its stderr last:\n{tail}\n" if tail.strip() else "\n")

    def _unseen_seqs(self, nid: str, port: str, last: int, most: int = 8) -> str:
        """The seqs up to ``last`` of stream ``nid.port`` that never reached the coordinator, as
        ``seqs 3, 5-7`` (the first ``most`` runs of them, of the last 100,000 seqs at most)."""
        runs: list[list[int]] = []
        for seq in range(max(self._have.get((nid, port), -1) + 1, last - 99_999), last + 1):
            if (nid, port, seq) in self._event_ids:
                continue
            if runs and runs[-1][1] == seq - 1:
                runs[-1][1] = seq
            elif len(runs) < most:
                runs.append([seq, seq])
            else:
                break
        if not runs:
            return ""
        spelled = ", ".join(str(a) if a == b else f"{a}-{b}" for a, b in runs)
        return f"seq{'s' if len(runs) > 1 or runs[0][0] != runs[0][1] else ''} {spelled}"

    def _stderr_tail(self, nid: str, lines: int = 15) -> str:
        host = self._hosts.get(nid)
        return host.output(nid).tail(lines) if host is not None else ""

    # ---------------------------------------------------------------------------------------
    # Running
    # ---------------------------------------------------------------------------------------
    def advance(self, until_ns: int) -> None:
        if self._ran:
            raise BackendError("a real-time run on the zenoh backend cannot be continued: wall time went on\n"
                               "    hint: give the whole duration to one pipe.run(duration=...), or pipe.reset()")
        self._ran = True
        try:
            self._await(lambda: all(s == "ready" for s in self._state.values()),
                        time.monotonic() + self.startup_timeout, "start")
            self.t0 = self._hub.new_timestamp().get_time_as_ntp64().as_nanos() + self.start_margin_ns
            self.end_ns = until_ns
            if self._foxglove_port is not None:
                self._start_live_view()
            # values come to the coordinator only for the trace (keep="trace"), the log, or a live view
            self._values = self.keep == "trace" or self.log is not None or self.live is not None

            def finished() -> bool:
                return (all(s == "done" for s in self._state.values())
                        and all(self._reports[n] >= self._reports_sent[n] for n in self._reports))

            if self.virtual_time:
                self._granted = min(self.LOCKSTEP_WINDOW_NS, until_ns)
                self._last_grant = (time.monotonic(), time.monotonic())
                self._control("start", {"t0": self.t0, "end": until_ns, "values": self._values,
                                        "grant": self._granted})
                self._await(lambda: self._lockstep() and finished(), float("inf"), "finish")
            else:
                self._control("start", {"t0": self.t0, "end": until_ns, "values": self._values})
                slack = max(self._deadlines(), 1.0) + 10.0
                # a coordinator behind on its reports (a logged run of many events) finishes late,
                # not in error: the wait goes on while they come
                self._await(finished, time.monotonic() + (self.t0 + until_ns - time.time_ns()) / 1e9 + slack, "finish",
                            patience=slack)
        except BaseException:
            self._stop_workers()  # their last reports, then: which outputs died with a process
            self._tell_forged()
            self._record_faults_left()
            self._record_starved()
            self.close()
            raise
        self.now_ns = until_ns
        self._record_faults_left()
        self._record_starved()
        self.close()  # a real-time run is over when its time is: workers reaped, hub closed
        self._warn_forged()
        self._check_exit_recorded()
        self._check_every_flow_ticked()
        self._warn_starved_by_late_events()

    def _warn_forged(self) -> None:
        """Messages and records refused as forged (origin.py): the run stands, and says so."""
        self._tell_forged()
        if self.own_counts["forged"]:
            warnings.warn(f"{self.own_counts['forged']} message(s) or record(s) on the run's key space were refused: "
                          f"no process of the run's node made them ({'; '.join(self._senders.reasons)})\n"
                          "    hint: a process holding the run's secret or password put them; none reached the "
                          "trace or the log (pipe.counts()['forged'])", RetrieverWarning, stacklevel=4)

    def _check_exit_recorded(self) -> None:
        """A node whose process said its step called sys.exit(0) and never sent that step's
        record did not end the run: the run went on, and fails saying so."""
        node = self._exit_unrecorded()
        if node is not None:
            raise BackendError(f"{self.backend_name} run: the process of '{node}' said its step called sys.exit(0) "
                               f"at {self._exit_said[node][0]}, and never sent the record of that step: the run "
                               "went on without it")

    def _check_every_flow_ticked(self) -> None:
        """A flow with a rate that had ticks due in the run's window, and ran none, fails the
        run (issue 17: a run of 50 flows exited 0 with 47 at 0 ticks): a run that looks fine
        with flows missing is worse than none. Its worker's ``done`` says what it saw."""
        if self.ended_by is not None:  # a step's sys.exit(0) ended the run before its end
            return
        idle = []
        for nid, node in self.graph.nodes.items():
            due = _ticks_due(node.clock, self.end_ns)
            if due == 0 or self._stats[nid].ticks > 0:
                continue
            said = self._done_info.get(nid, {})
            if said.get("ticks"):
                why = f"its worker ran {said['ticks']} ticks, whose step records never reached the coordinator"
            elif "started_ns" in said:
                why = f"its worker ran none; the run's start reached it {said['started_ns'] / 1e9:.2f} s after T0"
            else:
                why = "its worker stopped before the run's start reached it"
            idle.append(f"    {nid} ({node.clock!r}): 0 of {due} ticks; {why}")
        if idle:
            raise BackendError(f"{self.backend_name} run: {len(idle)} flow(s) never ticked in the run's "
                               f"{self.end_ns / 1e9:g} s, though their clocks had ticks due:\n" + "\n".join(idle)
                               + "\n    hint: a machine too loaded to start the run's processes in time needs a "
                               f"later start: pipe.run(..., start_margin=seconds) (now {self.start_margin_ns / 1e9:g})")

    @property
    def starved(self) -> list[dict]:
        """Each span in which an input had no event while its producers made some (starved.py)."""
        return self.starvation.episodes

    def _say_starved(self) -> None:
        """Say at once which input starves (its node skips tick after tick while its producer makes
        events), and when one that did has an event again."""
        news, self.starvation.news = self.starvation.news, []
        for what, episode in news:
            node, port = episode["node"], episode["port"]
            if what == "starved":
                print(f"retriever: warning: node '{node}' is starved: its input '{port}' has had no event since "
                      f"t={episode['since_ns'] / 1e9:.3f} s ({episode['ticks']} ticks), while "
                      f"{' and '.join(episode['producers'])} made {episode['produced']} events there"
                      "\n    hint: its step records say why each tick went without (retriever log cat LOG "
                      f"--steps); `retriever status` shows whether it recovers", file=sys.stderr, flush=True)
            else:
                print(f"retriever: node '{node}' has events on its input '{port}' again at "
                      f"t={episode['until_ns'] / 1e9:.3f} s, after {episode['ticks']} ticks without",
                      file=sys.stderr, flush=True)

    def _record_starved(self) -> None:
        """Log each starved span (the run ends: one still starved lasted to its end)."""
        if self.starvation.news:
            self._say_starved()
        if self.log is not None:
            for episode in self.starvation.episodes:
                self.log.add_starved(episode)

    def _warn_starved_by_late_events(self) -> None:
        """A flow that never stepped though events came on its inputs, late (after the ticks they
        were for): say which edge, and the fix. The run stands (it did what its policies say)."""
        for nid, stats in sorted(self._stats.items()):
            if stats.steps or not stats.counts.get("late"):
                continue
            ports = sorted({port for node, _, _, _, _, detail, *_ in self.trace.raw_steps
                            if node == nid and detail for port in (detail.get("late") or {})})
            # the edges into the ports the step records name (none are kept under keep="counters"),
            # whose producer made any event: another into the same port may have been silent
            into = [e for e in self.graph.edges if e.dst == nid and (e.src, e.src_port) in self._max_seq]
            edges = [e for e in into if e.dst_port in ports] or into
            names = ", ".join(f"{e.src}.{e.src_port} → {nid}.{e.dst_port}" for e in edges)
            e = edges[0] if edges else None
            stale = [x for x in edges if getattr(x.sync, "staleness", None) is not None]
            hint = ("give the producer a latency= that covers its step (a LET flow: its outputs are due at tick + "
                    "latency)" + (f", or the edge a longer deadline: {e.src}.then({nid}, deadline=seconds)"
                                  if e is not None else ""))
            if stale:  # the late events came, and were too old for the policy by then
                hint = (f"{stale[0].sync!r} on {stale[0].src} → {nid} takes no event older than its staleness, and "
                        "late ones are: allow more staleness, or " + hint)
            warnings.warn(
                f"flow '{nid}' never stepped in this run: its inputs were late, {stats.counts['late']} event(s) "
                f"on {names} arrived after the ticks they were for, and its policies took none later\n"
                f"    hint: {hint}", RetrieverWarning, stacklevel=4)

    # ---------------------------------------------------------------------------------------
    # Lockstep virtual time (see loop.py's docstring)
    # ---------------------------------------------------------------------------------------
    #: how far each grant reaches past the last, in virtual ns: the nodes run that much of the
    #: run between two barriers (a source never runs further ahead of its slowest consumer)
    LOCKSTEP_WINDOW_NS = 50_000_000
    #: how long (wall) without a grant reached before it is put again (a put may be missed), and
    #: before the run fails naming the nodes that did not reach it
    REGRANT_S = 0.5
    LOCKSTEP_STALL_S = 120.0

    def log_metadata(self) -> dict[str, str]:
        """``time``: a run in lockstep virtual time says so (its wall times mean nothing)."""
        return {"time": "virtual"} if self.virtual_time else {}

    def _lockstep(self) -> bool:
        """Grant the next window once every node not done has reached this one; whether the
        last grant (the run's end) is out. Fails the run when nothing moved for LOCKSTEP_STALL_S."""
        now = time.monotonic()
        behind = sorted(n for n, s in self._state.items() if s != "done" and self._reached.get(n, -1) < self._granted)
        if not behind and self._granted < self.end_ns:
            self._granted = min(self._granted + self.LOCKSTEP_WINDOW_NS, self.end_ns)
            self._last_grant = (now, now)
            self._control("grant", {"until": self._granted})
            return False
        if behind and now - self._last_grant[1] > self.REGRANT_S:  # a put may be missed: again
            self._last_grant = (self._last_grant[0], now)
            self._control("grant", {"until": self._granted})
        if now - self._last_grant[0] > self.LOCKSTEP_STALL_S:
            waiting = behind or sorted(n for n, s in self._state.items()
                                       if s != "done" or self._reports[n] < self._reports_sent[n])
            self._dump_stacks(waiting, show=False)
            raise BackendError(
                f"zenoh run (virtual time): worker(s) {', '.join(waiting)} did not "
                + (f"reach t={self._granted / 1e9:g} s" if behind else "finish")
                + f" within {self.LOCKSTEP_STALL_S:g} s of wall time\n"
                + "".join(self._unfinished(n) for n in waiting)
                + "    hint: the stacks show where a step that did not return is")
        return self._granted >= self.end_ns

    def _deadlines(self) -> float:
        deadlines = [e.deadline for e in self.graph.edges if e.deadline is not None]
        return max([self.graph.deadline, *deadlines])

    def _await(self, condition, give_up: float, what: str, patience: float | None = None) -> None:
        """Collect messages until ``condition()``; fail on a failed or dead worker or at ``give_up``
        (with ``patience``, at the latest that long after the last report came)."""
        next_write = next_have = time.monotonic()
        reports = sum(self._reports.values())
        while not condition():
            if self.stop_requested:  # asked from afar (retriever stop): as Ctrl-C here would
                raise KeyboardInterrupt
            try:
                item = self._inbox.get(timeout=0.02)
                self._handle(item)
                while True:
                    self._handle(self._inbox.get_nowait())
            except queue.Empty:
                pass
            self._tell_forged()
            if self._failure is not None:
                self._raise_failure()
            if self.starvation.news:
                self._say_starved()
            self._check_processes()
            now = time.monotonic()
            if now >= next_write:
                if self.log is not None:
                    self.write_log()
                    # while this thread waited for the log's disk no report was taken: that time
                    # is the coordinator's, not a late worker's
                    give_up += time.monotonic() - now
                else:
                    self.drop_records()
                next_write = now + self.LOG_HANDOVER_S
            if now >= next_have:
                self._tell_have()
                next_have = now + HAVE_EVERY_S
            if patience is not None and sum(self._reports.values()) != reports:
                reports = sum(self._reports.values())
                give_up = max(give_up, now + patience)
            if now > give_up:
                waiting = sorted(n for n, s in self._state.items() if s != ("ready" if what == "start" else "done")
                                 or self._reports[n] < self._reports_sent[n])
                self._dump_stacks(waiting, show=False)  # the error below shows them
                said = "".join(self._unfinished(n) for n in waiting)  # (before the kill: how each was found)
                if what == "finish":  # stuck in a step (SIGTERM only asks the loop to stop): no use waiting
                    for nid in waiting:
                        self._workers[nid].kill()
                raise BackendError(f"{self.backend_name} run: worker(s) {', '.join(waiting)} did not {what} in time\n"
                                   + said
                                   + ("    hint: a flow that takes longer to load needs pipe.run(..., startup_timeout="
                                      f"seconds) (now {self.startup_timeout:g})" if what == "start" else
                                      "    hint: the stacks show where a step that did not return is"))
        if self.log is not None:
            self.write_log()

    def _handle(self, item: tuple) -> None:
        """A status or report, with the process of its node that signed it (origin.py)."""
        key, data, sender = item
        if key.startswith(self.keys.status("report") + "/"):
            self.reported_bytes += len(data)
            try:
                report = decode_report(data, expected=key.rsplit("/", 1)[1])
            except WireError as e:
                self._garbage(key, e)
                return
            stats = self._stats.get(report.node)
            if stats is None:
                self._garbage(key, WireError(f"a report of an unknown node '{report.node}'"))
                return
            self._reports[report.node] += 1
            for wall, message in report.events:
                self._event(key, report.node, wall, message)
            steps = self.trace.raw_steps
            clock = self.graph.nodes[report.node].clock
            end = self.end_ns if self.t0 is not None else None
            for tag, consumed, produced, status, detail, start, wall in report.records:
                if (report.node, tag) in self._ticks:
                    self._garbage(key, WireError(f"a second step record of {report.node} at {tag}"))
                    continue
                if not clock.may_tick_at(tag, end):
                    self._senders.refuse(f"a step record of {report.node} at {tag}, which is no tick of its {clock!r}")
                    continue
                self._ticks.add((report.node, tag))
                exit_code = detail.get("exit") if detail is not None else None
                if status == "ok" and type(exit_code) is int and exit_code == 0:  # its step's sys.exit(0)
                    self._exit_recorded[report.node] = (tag, sender)
                    self._end_by_exit(report.node)
                steps.append((report.node, tag, consumed, produced, status, detail, start, wall))
                if self.live is not None:
                    self.live.step(report.node, tag, consumed, produced, status, detail, start, wall)
                self.starvation.step(report.node, tag, produced, detail)
                for event_id in produced:  # a LET output is published after its record went
                    if event_id not in self._event_ids:
                        self._unseen.add(event_id)
                    if event_id[2] > self._max_seq.get(event_id[:2], -1):
                        self._max_seq[event_id[:2]] = event_id[2]
                stats.ticks += 1
                if status in STEPPED:
                    stats.steps += 1
                    stats.step_ns += wall
                elif status == "skipped":
                    stats.skips += 1
                else:
                    stats.errors += 1
                    stats.step_ns += wall
            return
        try:
            node, state, info = decode_status(data)
        except WireError as e:
            self._garbage(key, e)
            return
        if node not in self._state:
            self._garbage(key, WireError(f"status of an unknown node '{node}'"))
            return
        # Only the node's own process speaks for it: its running one (a restart spawns a process,
        # so only it may ask for one), or, while it restarts, the old one (which alone says it
        # handed over). A status signed by another of its processes (one that already handed
        # over or was replaced) is garbage; an insider's (a `failed` stopped the run, a `done`
        # added its counts, an `exit` ended it) is signed by none and never got here.
        current, retiring = self._workers.get(node), self._retiring.get(node)
        sayers = {"handed_over": (retiring,), "done": (current, retiring), "failed": (current, retiring)}
        if sender is None or not any(sender is p for p in sayers.get(state, (current,))):
            self._garbage(key, WireError(f"a '{state}' status of {node} from pid {info.get('pid')!r:.20}, "
                                         f"which is not the process of {node} that could say it"))
            return
        if state in PROCESS_STAGES:
            if not may_say(self._said.get(sender), state):
                self._garbage(key, WireError(f"a '{state}' status of {node} after its process said "
                                             f"'{self._said[sender]}' (a replay)"))
                return
            self._said[sender] = state
        if state == "reached":  # virtual time: from the node's own process
            until = info.get("until")
            if not self.virtual_time or type(until) is not int:
                self._garbage(key, WireError(f"a 'reached' status of {node} with until {until!r:.30}"
                                             f"{'' if self.virtual_time else ' in a run not in virtual time'}"))
                return
            # past the grant (one it was told by someone else): it reached this one on the way
            self._reached[node] = max(self._reached.get(node, -1), min(until, self._granted))
            return
        if state == "exit":  # its step called sys.exit(0): the run ends there, once its record is in
            tag = info.get("tag")
            if not _is_tag(tag):
                self._garbage(key, WireError(f"an 'exit' status of {node} with tag {tag!r:.30}"))
                return
            self._exit_said[node] = (tuple(tag), sender)
            self._end_by_exit(node)
            return
        if state == "unanswered":  # before the start: its neighbours declare themselves again
            nodes = info.get("nodes")
            if type(nodes) is not list or not nodes or not all(type(n) is str and n in self._state for n in nodes):
                self._garbage(key, WireError(f"an 'unanswered' status of {node} that names no nodes of the run"))
            elif self.t0 is not None:  # no worker asks once the run started
                self._garbage(key, WireError(f"an 'unanswered' status of {node} after the run's start"))
            else:
                self._control("redeclare", {"nodes": sorted(set(nodes))})
            return
        counts = info.get("counts", {})
        if type(counts) is not dict or not all(type(k) is str and type(v) is int for k, v in counts.items()):
            self._garbage(key, WireError(f"status of {node} with counts that are not names and integers"))
            counts = {}
        node_counts = self._stats[node].counts
        for name, n in counts.items():
            node_counts[name] = node_counts.get(name, 0) + n
        if state in ("done", "handed_over") and type(info.get("reports")) is int:
            self._reports_sent[node] += info["reports"]
        if state != "ready":
            self._restarted.pop(node, None)
        if state == "failed":
            self._failure = (node, info)
        elif state == "restart":  # its old process keeps listening until the new one takes over
            tag = info.get("tag")
            budget = self._restarts[node]
            tag = tuple(tag) if _is_tag(tag) else (self._run_time(), 0)
            if not budget.take(tag[0]):
                self._limit = RestartLimitError(node, tag, str(info.get("error", "")), budget.max_restarts,
                                                budget.window_s)
                self._failure = (node, {"error": str(self._limit)})
                return
            node_counts["restarts"] = node_counts.get("restarts", 0) + 1
            self._retiring[node] = self._workers[node]
            self._spawn(node, join=(self.t0, self.end_ns))
            return
        elif state == "ready" and info.get("linked") is False and self._failure is None:
            # peers do not route for each other: a worker without a link to another would never
            # get that one's events, nor it this one's
            unlinked = info.get("unlinked")
            unlinked = (", ".join(f"'{n:.60}'" for n in unlinked[:8] if type(n) is str)
                        if type(unlinked) is list else "some of its neighbours")
            self._failure = (node, {"error": (
                f"the worker of '{node}' has no direct link to {unlinked} after {self.startup_timeout:g} s\n"
                f"    hint: on a loaded machine, give it longer: pipe.run(..., startup_timeout=seconds); across "
                f"machines, each must reach the others at the address it listens on (retriever-worker --listen)")})
            return
        elif state == "ready" and node in self._fresh:
            self._restart_afresh(node)
        elif state == "ready" and node in self._restarted:
            # said again: it has not seen `restarted` yet (worker.START_ASK_S), nor, maybe, its consumers
            self._control("restarted", {"node": node, "seqs": self._restarted[node], "values": self._values})
        elif state == "ready" and node in self._retiring:
            if self._state[node] == "done":  # the run ended while it restarted: stopped at close
                return
            self._control("handover", {"node": node})
        elif state == "handed_over":
            self._retired.append(self._retiring.pop(node))
            self._control("resume", {"node": node})
            self._joining.discard(node)
            return
        elif state == "done":
            if (info.get("stopped") is True and not self._stop_sent and self.t0 is not None and self._failure is None
                    and node not in self._exit_said):  # (an exit's record may come after its `done`)
                # it ended before the run's end on a stop this coordinator never sent: a run cut
                # short must not look finished (an insider's `stop` on ctl/run, or a SIGTERM to it)
                self._failure = (node, {"error": (
                    f"{node} stopped before the run's end: told to stop, and not by this coordinator (a process "
                    "holding the run's secret put a stop on its control key, or someone sent its worker SIGTERM)")})
            self._done_info[node] = {k: info[k] for k in ("started_ns", "ticks") if type(info.get(k)) is int}
            sent = info.get("sent")  # {port: last seq put}: which events its reports held (_unfinished)
            if type(sent) is dict and all(type(p) is str and p in self.graph.nodes[node].outputs and type(q) is int
                                          for p, q in sent.items()):
                self._done_info[node]["sent"] = sent
            old = self._retiring.pop(node, None)
            if old is not None:
                self._retired.append(old)
        self._state[node] = state

    def _end_by_exit(self, node: str) -> None:
        """End the run as a step of ``node`` asked (sys.exit(0)), once its process both said so
        (status ``exit``) and recorded that step (status ok, detail ``{"exit": 0}``) at that tag."""
        said = self._exit_said.get(node)
        if said is None or self._exit_recorded.get(node) != said or self.t0 is None or self._stop_sent:
            return
        self._stop_sent = True
        self.ended_by = node
        # as if the run ended now: no tick at or past the exit, but every event sent before
        # it (each stamped before now, the exit's tag may be earlier on a late node) still
        # reaches the ticks it triggers, within their deadline, as at any run's end
        self._control("end", {"at": max(said[0][0], self._run_time())})

    def _exit_unrecorded(self) -> str | None:
        """A node whose process said its step called sys.exit(0), and never sent the record of that step."""
        return next((node for node, said in sorted(self._exit_said.items(), key=lambda item: item[0])
                     if self._exit_recorded.get(node) != said), None)

    def _tell_forged(self) -> None:
        """Count what was refused as forged (``forged``), and say so on stderr when more came."""
        refused = self._senders.refused
        if refused == self._forged_told:
            return
        self.own_counts["forged"] = refused
        if self._forged_told == 0:
            print(f"retriever: refused a message or record that no process of the run's node made: "
                  f"{self._senders.reasons[0]} (counted as 'forged'; a process holding the run's secret?)",
                  file=sys.stderr, flush=True)
        self._forged_told = refused

    def _run_time(self) -> int:
        """Now, in ns since T0 (0 before the start)."""
        return max(0, time.time_ns() - self.t0) if self.t0 is not None else 0

    def _answer_finished(self, query) -> None:
        """Which nodes are done, which of them have every report in, and which start afresh
        after their process died (a restarted flow's process waits for answers from the others,
        but from these)."""
        states = list(self._state.items())
        done = sorted(node for node, state in states if state == "done")
        # and whose every report is in: their processes may now close their sessions (worker.py,
        # REPORTS_TAKEN_S)
        complete = sorted(node for node, state in states if state in ("done", "handed_over")
                          and self._reports.get(node, 0) >= self._reports_sent.get(node, 0))
        query.reply(self.keys.finished(), WireEncoder().control("finished", {"nodes": done, "complete": complete,
                                                                             "restarting": sorted(self._fresh)}))

    def _answer_start(self, query) -> None:
        """T0 and the end, to a worker that said ready and has not seen ``start`` (a put it may
        have missed: see START_ASK_S in worker.py); nothing before the run has a start."""
        t0 = self.t0
        if t0 is not None:
            query.reply(self.keys.start(), WireEncoder().control("start", {"t0": t0, "end": self.end_ns,
                                                                           "values": self._values}))

    def _control(self, op: str, args: dict) -> None:
        self._hub.put(self.keys.run_control(), self._encoder.control(op, args), congestion_control=RELIABLE)

    def _event(self, key: str, node: str, wall: int, message: bytes | str) -> None:
        try:
            events = decode_events(message if type(message) is bytes else self._unspill(node, message), blank_ok=True)
        except WireError as e:
            self._garbage(key, e)
            return
        for msg in events:
            self._one_event(key, node, wall, msg)

    def _one_event(self, key: str, node: str, wall: int, msg) -> None:
        stream = (msg.producer, msg.port)
        event_id = (msg.producer, msg.port, msg.seq)
        if msg.producer != node:  # carried by a consumer, for a producer whose report may be lost
            if (msg.producer, msg.port, node) not in self._feeds:
                self._garbage(key, WireError(f"{node} reported an event of {msg.producer}.{msg.port}, "
                                             "which is no output port of it nor one it consumes"))
            elif event_id not in self._event_ids:
                self._carried.add(event_id)
                self._take_event(event_id, msg, wall)
            return
        if stream not in self._streams and node not in self._open_outputs:
            self._garbage(key, WireError(f"{node} reported an event of {msg.producer}.{msg.port}, "
                                         "which is no output port of it"))
            return
        if event_id in self._carried:  # its producer's report came after all
            self._carried.discard(event_id)
            return
        if event_id in self._event_ids:
            self._garbage(key, WireError(f"event {event_id} arrived twice"))
            return
        self._take_event(event_id, msg, wall)

    def _take_event(self, event_id: tuple[str, str, int], msg, wall: int) -> None:
        self._event_ids.add(event_id)
        self._unseen.discard(event_id)
        producer, port, seq = event_id
        if seq > self._max_seq.get((producer, port), -1):
            self._max_seq[(producer, port)] = seq
        have = self._have.get((producer, port), -1)
        while (producer, port, have + 1) in self._event_ids:  # every seq up to it (carried ones may skip)
            have += 1
        self._have[(producer, port)] = have
        self.trace.raw_events.append((msg.tag, msg.producer, msg.port, msg.seq,
                                      msg.value if self._values else NOT_KEPT, wall))
        if self.live is not None:
            self.live.event(msg.producer, msg.port, msg.tag, msg.seq, msg.value if self._values else NOT_KEPT, wall)

    def _tell_have(self) -> None:
        """Tell the consumers which events the coordinator has (the last seq of each stream that
        moved on since last told): they forget those messages and report the records that wait."""
        moved = [[src, port, seq] for (src, port), seq in self._have.items() if self._have_told.get((src, port)) != seq]
        if moved:
            self._control("have", {"streams": moved})
            self._have_told.update(((src, port), seq) for src, port, seq in moved)

    def _unspill(self, node: str, name: str) -> mmap.mmap:
        """A message a worker wrote to a file of the run directory: mapped (its arrays are views
        of the mapping), and the file removed (the mapping keeps its pages)."""
        if not name.startswith(f"{node}.") or not name.endswith(".msg") or "/" in name:
            raise WireError(f"{node} reported an event in the file {name!r:.80}, which is not one of its files")
        path = self._dir / name
        try:
            fd = os.open(path, os.O_RDONLY)
        except OSError as e:
            raise WireError(f"{node} reported an event in {path}, which cannot be opened: {e.strerror}") from None
        try:
            path.unlink()
            mapped = mmap.mmap(fd, 0, access=mmap.ACCESS_READ)
            self.reported_bytes += len(mapped)
            return mapped
        except (OSError, ValueError) as e:  # ValueError: an empty file
            raise WireError(f"{node} reported an event in {path}, which cannot be mapped: {e}") from None
        finally:
            os.close(fd)

    def _garbage(self, key: str, error: WireError) -> None:
        self.own_counts["garbage"] += 1
        if self.own_counts["garbage"] <= 3:
            print(f"retriever: dropped a message on {key}: {error}", file=sys.stderr, flush=True)

    def _check_processes(self) -> None:
        for host in {id(h): h for h in self._hosts.values()}.values():
            if not host.alive and self._failure is None:  # its flows stopped with it, whatever they said
                self._host_lost(host, sorted(n for n, h in self._hosts.items() if h is host))
                if self._failure is not None:
                    self._raise_failure()
        for nid, proc in [*self._workers.items(), *self._retiring.items()]:
            code = proc.poll()
            if code is None or self._state[nid] == "done" or not self._hosts[nid].alive:
                continue  # running, finished, or gone with its host (above)
            if code in (0, EXIT_HANDED_OVER, EXIT_FAILED):
                # a worker's own exit: its last status may still be on the way (it says why it ended)
                exited = self._exited.setdefault(proc.pid, time.monotonic())
                if time.monotonic() - exited < EXIT_GRACE_S:
                    continue
            # it died, or ended without a word (os._exit in a step): its state is lost
            if self._failure is not None:
                self._raise_failure()
            if self.t0 is not None and self.graph.nodes[nid].settings.on_error == "restart":
                self._lost(nid, proc, code)
                return  # the processes of the node changed: look again next time
            self._hosts[nid].output(nid).drain()
            if self.t0 is not None:  # the log says what died, and which of its outputs with it
                self._unrecovered.append({"node": nid, "at_ns": self._run_time(), "pid": proc.pid,
                                          "exit": _exit_text(code)})
            self._failure = (nid, {"error": f"worker process of '{nid}' (pid {proc.pid}) {_exit_text(code)} "
                                            f"before it finished\n{self._stderr_tail(nid)}"})
            self._raise_failure()

    def _host_lost(self, host: Host, nodes: list[str]) -> None:
        """A host went with the nodes on it: the run stops (a deployment may move them instead),
        and the log says which processes went with it (their faults, once their last reports are in)."""
        if self.t0 is not None:
            self._unrecovered += [{"node": nid, "at_ns": self._run_time(), "pid": self._workers[nid].pid,
                                   "exit": f"was lost with its worker '{host.name}'"} for nid in nodes]
        self._failure = (nodes[0], {"error": f"worker '{host.name}' was lost (its liveliness token went): its node(s) "
                                             f"{', '.join(nodes)} stopped\n    hint: is the machine up, and on the "
                                             "network? `retriever workers` lists the workers up"})

    # ---------------------------------------------------------------------------------------
    # A lost process (on_error="restart"; see "Restarting after a lost process" in loop.py)
    # ---------------------------------------------------------------------------------------
    def _lost(self, nid: str, proc: WorkerProcess, code: int) -> None:
        """A worker process of ``nid`` died after the start: within the restart budget, start the
        flow afresh in a new process (a hand-over in progress dies with it); else fail the run."""
        at = self._run_time()
        why = f"its worker process (pid {proc.pid}) {_exit_text(code)} at t={at / 1e9:.3f} s"
        if nid in self._fresh:  # the last one died before it was ready: that fault stands on its own
            self._record_fault(self._fresh.pop(nid), None)
        budget = self._restarts[nid]
        if not budget.take(at):
            self._limit = RestartLimitError(nid, None, why, budget.max_restarts, budget.window_s)
            self._unrecovered.append({"node": nid, "at_ns": at, "pid": proc.pid, "exit": _exit_text(code)})
            self._failure = (nid, {"error": str(self._limit)})
            return
        counts = self._stats[nid].counts
        for name in ("restarts", "crash_restarts"):
            counts[name] = counts.get(name, 0) + 1
        print(f"retriever: flow '{nid}': {why}; starting it afresh (on_error='restart')",
              file=sys.stderr, flush=True)
        self._start_afresh(nid, {"node": nid, "at_ns": at, "pid": proc.pid, "exit": _exit_text(code)})

    def _start_afresh(self, nid: str, fault: dict) -> None:
        """Start ``nid`` afresh in a new process on its host (see "Restarting after a lost process"
        in loop.py); ``fault``: what became of the old one, logged once the new one is ready."""
        for other in (self._workers.get(nid), self._retiring.pop(nid, None)):
            if other is not None:
                if other.poll() is None:
                    other.kill()
                self._retired.append(other)
        self._control("lost", {"node": nid})
        self._restarted.pop(nid, None)
        self._fresh[nid] = fault
        self._spawn(nid, join=(self.t0, self.end_ns), fresh=True)

    def _restart_afresh(self, nid: str) -> None:
        """The new process of ``nid`` is ready: its streams go on past every seq the dead one may
        have used; the consumers and it are told (control ``restarted``), the log gets the fault."""
        ports = {port for node, port in self._max_seq if node == nid} | set(self.graph.nodes[nid].outputs)
        seqs = {port: self._max_seq.get((nid, port), -1) + 1 + RESTART_SEQ_GAP for port in sorted(ports)}
        for port, first in seqs.items():  # the consumers give up the seqs below: nothing to wait for
            self._have[(nid, port)] = max(self._have.get((nid, port), -1), first - 1)
        self._record_fault(self._fresh.pop(nid), seqs)
        self._restarted[nid] = seqs
        self._control("restarted", {"node": nid, "seqs": seqs, "values": self._values})
        self._joining.discard(nid)

    def _record_fault(self, fault: dict, seqs: dict[str, int] | None) -> None:
        """Keep a lost process's fault, and log it: the outputs its step records claimed and no
        report carried (LET outputs it still held) are lost, which a replay must know."""
        nid = fault["node"]
        lost = sorted(event_id for event_id in self._unseen if event_id[0] == nid)
        self._unseen.difference_update(lost)
        fault = {"kind": "process_lost", **fault, "restarted": seqs is not None, "seqs": seqs or {},
                 "lost_events": [list(event_id) for event_id in lost]}
        self.faults.append(fault)
        if self.log is not None:
            self.log.add_fault(fault)

    def _record_faults_left(self) -> None:
        """Log the faults of processes that died and were not started afresh (not allowed, out
        of budget, or the run ended first), once their last reports are in."""
        for fault in [*self._fresh.values(), *self._unrecovered]:
            self._record_fault(fault, None)
        self._fresh.clear()
        self._unrecovered.clear()

    def _raise_failure(self) -> None:
        node, info = self._failure
        error = info.get("error", "failed")
        tb = info.get("traceback")
        where = "\n    worker traceback:\n" + "\n".join("        " + line for line in tb.strip().splitlines()) if tb else ""
        tag = info.get("tag")
        settings = self.graph.nodes[node].settings if node in self.graph.nodes else None
        if self._limit is not None:
            raise self._limit
        cycle = next((c for c in self.graph.instantaneous_cycles if node in c), None)
        if info.get("zeno") is True and cycle is not None and _is_tag(tag):
            raise CausalityError(cycle, tuple(tag), self.graph.max_microsteps)
        if info.get("setup") is True and settings is not None:
            failure = SetupError(node, str(error))
            failure.args = (failure.args[0] + where,)
            raise failure
        if tag is not None and settings is not None and ".step() raised " in error:
            failure = StepError(node, tuple(tag), RemoteError(error.split(".step() raised ", 1)[1]))
            failure.args = (failure.args[0] + where,)
            raise failure
        raise BackendError(f"{self.backend_name} run stopped: {error}{where}")

    # ---------------------------------------------------------------------------------------
    # Stopping
    # ---------------------------------------------------------------------------------------
    def _stop_workers(self, grace: float = STOP_GRACE_S) -> None:
        """Ask every live worker to stop, collect what they send, then make sure they are gone:
        one still running after ``grace`` is stuck in a step, so its stacks are printed and it is
        killed. Before the run's start they have nothing to send, and may not listen yet: SIGTERM them."""
        if self._hub is None:
            return
        if self.t0 is None:
            for p in self._processes():
                if p.poll() is None:
                    p.send_signal(signal.SIGTERM)
            self._reap()
            return
        self._stop_sent = True
        try:
            self._control("stop", {})
        except Exception:
            pass
        # a process not in the run yet (a restarted flow's, before it took over or was told its
        # seqs) has nothing to send, and may be waiting for its neighbours, not reading control
        for nid in self._joining:
            p = self._workers.get(nid)
            if p is not None and p.poll() is None:
                p.send_signal(signal.SIGTERM)
        give_up = time.monotonic() + grace
        while time.monotonic() < give_up and any(p.poll() is None for p in self._processes()):
            try:
                self._handle(self._inbox.get(timeout=0.02))
            except queue.Empty:
                pass
        while True:
            try:
                self._handle(self._inbox.get_nowait())
            except queue.Empty:
                break
        stuck = sorted(nid for nid, p in [*self._workers.items(), *self._retiring.items()] if p.poll() is None)
        if stuck:  # they had their grace: where are they? (once, on our stderr, prefixed with the node)
            print(f"retriever: worker(s) {', '.join(stuck)} did not stop within {grace:g} s; their stacks, "
                  "then SIGKILL:", file=sys.stderr, flush=True)
            self._dump_stacks(stuck)
            for p in self._processes():
                if p.poll() is None:
                    p.kill()
        self._reap(grace=0.5)

    def _reap(self, grace: float = 5.0) -> None:
        """Wait for every worker to exit; SIGTERM, then SIGKILL, the ones that do not."""
        procs = self._processes()
        deadline = time.monotonic() + grace
        for p in procs:
            try:
                p.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=2.0)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        if any(p.poll() is None for p in self._processes()):
            self._stop_workers()
        if self.live is not None:
            self.live.close()
        give_up = time.monotonic() + 1.0  # their last lines, before the run returns
        for output in {id(o): o for host in self._hosts.values() for o in host.outputs()}.values():
            output.drain(max(0.0, give_up - time.monotonic()))
        if self._hub is not None:
            self._release_hosts()
            for sub in self._subscribers:
                sub.undeclare()
            try:
                self._hub.close()
            except zenoh.ZError as e:
                # a link whose peer stopped reading (a watcher suspended with SIGSTOP, its
                # socket full) holds the close 10 s: Zenoh sets SO_LINGER 10 s on its TCP
                # sockets, and close() waits that long for unsent bytes (strace: the main thread
                # in close() 10.2 s), as long as the session's close timeout (10 s). The run is
                # over and recorded all the same; the hub's session goes with this process
                print(f"retriever: the run's hub did not close in time: a peer connected to it stopped reading "
                      f"(a suspended watcher?) ({e})", file=sys.stderr, flush=True)
            self._hub = None
        shutil.rmtree(self._dir, ignore_errors=True)
        _OPEN.discard(self)

    def _release_hosts(self) -> None:
        """Let go of the hosts, the run over (a worker daemon forgets it); on this machine, nothing."""

    def stats(self) -> dict[str, NodeStats]:
        return self._stats

    def produced_counts(self) -> dict[tuple[str, str], int]:
        # from the step records' produced ids, which every run reports whatever it keeps
        return {key: seq + 1 for key, seq in self._max_seq.items()}


def _ticks_due(clock, end_ns: int) -> int:
    """How many ticks of a rate clock fall in [0, end_ns): the first at or after the end counts
    them; 0 for a clock without a rate (a Trigger ticks only on what arrives)."""
    first_at_or_after = getattr(clock, "first_tick_at_or_after", None)
    return first_at_or_after(end_ns) if first_at_or_after is not None else 0


def _exit_text(code: int) -> str:
    """How a process ended, from its exit status: ``killed by SIGKILL``, ``exited with code 7``."""
    if code < 0:
        try:
            return f"was killed by {signal.Signals(-code).name}"
        except ValueError:
            return f"was killed by signal {-code}"
    return f"exited with code {code}"


def _is_tag(value: object) -> bool:
    return type(value) is list and len(value) == 2 and all(type(x) is int for x in value)


def _refuse_in_a_worker(graph: Graph) -> None:
    from . import worker

    if worker.serving is not None:
        raise BackendError(f"pipeline '{graph.name}' was started in the worker process of node '{worker.serving}', "
                           "while it imported its flow: a module of the run starts a pipeline when it is imported "
                           "(workers import the modules of their flows, the main script as __mp_main__)\n"
                           "    hint: start the run under `if __name__ == \"__main__\":`")


def _is_stopped(pid: int) -> bool:
    """Whether process ``pid`` of this machine is stopped (Linux /proc: state T or t)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat[stat.rindex(")") + 2:][:1] in ("T", "t")


def _check_deployable(graph: Graph) -> None:
    """Every flow must be rebuildable from the IR; a class in ``__main__`` is, when the main
    script is a file (workers import it as ``__mp_main__``, like multiprocessing)."""
    main_file = getattr(sys.modules.get("__main__"), "__file__", None)
    problems = [f"  {nid}: {node.rebuild_problem}" for nid, node in graph.nodes.items()
                if node.rebuild_problem is not None and not (main_file and node.rebuild_needs_main)]
    if problems:
        raise BackendError("the zenoh backend runs each flow in its own process, rebuilt from the IR (type + "
                           "params), and these flows cannot be rebuilt that way:\n" + "\n".join(problems)
                           + "\n    hint: define flow classes at a module's top level and give them "
                           "msgpack-serializable constructor arguments, or run in-process: backend=\"inproc\"")


def _run_dir() -> Path:
    """The run's directory: the spec and big events on their way to the
    coordinator. In shared memory when the host has it (no disk I/O for those events)."""
    shm = Path("/dev/shm")
    base = str(shm) if shm.is_dir() and os.access(shm, os.W_OK | os.X_OK) else None
    return private_folder(RUN_FOLDER, base)  # named by pid: a SIGKILLed run's is reaped by the next


def _python_path() -> list[str]:
    """The import path the flows came from, for the workers (absolute directories only)."""
    out = []
    for entry in sys.path:
        path = os.path.abspath(entry or ".")
        if os.path.isdir(path) and path not in out:
            out.append(path)
    return out


def _main_file(graph: Graph) -> str | None:
    """The ``__main__`` script, when some flow class is defined in it."""
    if not any(type(n.flow).__module__ == "__main__" for n in graph.nodes.values()):
        return None
    path = getattr(sys.modules.get("__main__"), "__file__", None)
    if path is None:
        raise BackendError("a flow class is defined in an interactive __main__, which worker processes cannot "
                           "import\n    hint: move the flow classes to a module or a script file")
    return os.path.abspath(path)
